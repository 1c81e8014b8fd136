"""Frame sources: image folders with exposure files, paired per-frame event files, stored frames."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.helpers.data import SHARED, needs_shared
from trmd_cli.errors import InputError
from trmd_cli.events import Exposure
from trmd_cli.read import ReadOptions, open_events
from trmd_cli.read import chunked as chunked_mod
from trmd_cli.read.folders import (
    frame_number,
    frames_from_recording,
    list_images,
    open_frame_folder,
    pair_folders,
    read_exposure_file,
)

W, H = 24, 16


def write_dat(path: Path, t, x, y, p, width=W, height=H) -> None:
    """Prophesee .dat: '%' header, type 0x0C, size 8, then (uint32 t, uint32 x|y<<14|p<<28)."""
    body = b"".join(struct.pack("<II", int(a), int(b) | (int(c) << 14) | (int(d > 0) << 28))
                    for a, b, c, d in zip(t, x, y, p, strict=True))
    path.write_bytes(f"% Width {width}\n% Height {height}\n".encode() + b"\x0c\x08" + body)


def evdi_sequence(root: Path, rng, n_frames=4, period=10_000, exposure=6_000, rgb=False,
                  depth=np.uint8):
    """EVDI layout: root/Blur/00000k.png, root/Exposure_{start,end}.txt (µs), root/events.dat."""
    blur = root / "Blur"
    blur.mkdir(parents=True)
    images = []
    for k in range(n_frames):
        top = np.iinfo(depth).max
        img = rng.integers(0, top, (H, W, 3) if rgb else (H, W)).astype(depth)
        # written out of order and with a non-padded name to test numeric ordering
        cv2.imwrite(str(blur / f"{k * 5:06d}.png"), img)
        images.append(img)
    starts = 1_000 + period * np.arange(n_frames)
    (root / "Exposure_start.txt").write_text("".join(f"{s}\n" for s in starts))
    (root / "Exposure_end.txt").write_text("".join(f"{s + exposure}\n" for s in starts))
    n = 4000
    t = np.sort(rng.integers(0, 1_000 + period * n_frames, n))
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    p = np.where(rng.integers(0, 2, n) == 1, 1, -1)
    write_dat(root / "events.dat", t, x, y, p)
    return images, starts, (t, x, y, p)


def test_frame_numbers_and_listing(tmp_path):
    for name in ("10.png", "9.png", "frame_2.jpg", "notes.txt", "x.tif"):
        (tmp_path / name).write_bytes(b"")
    assert frame_number("event000014.mat") == 14 and frame_number("blur") is None
    assert [p.name for p in list_images(tmp_path)] == ["frame_2.jpg", "9.png", "10.png", "x.tif"]


def test_exposure_file_units(tmp_path):
    f = tmp_path / "e.txt"
    f.write_text("# exposure starts\n1615008142416409\n\n1615008142538749 extra\n")
    np.testing.assert_array_equal(read_exposure_file(f), [1615008142416409, 1615008142538749])
    f.write_text("1.5\n2.25\n")  # numbers with a fraction: seconds
    np.testing.assert_array_equal(read_exposure_file(f), [1_500_000, 2_250_000])
    np.testing.assert_array_equal(read_exposure_file(f, "ms"), [1_500, 2_250])
    f.write_text("12\n3O\n")
    with pytest.raises(InputError, match="line 2"):
        read_exposure_file(f)


@pytest.mark.parametrize("rgb, depth", [(False, np.uint8), (True, np.uint8), (False, np.uint16)])
def test_evdi_folder_frames_and_windows(tmp_path, rng, rgb, depth):
    images, starts, (t, x, y, p) = evdi_sequence(tmp_path, rng, rgb=rgb, depth=depth)
    src = open_frame_folder(tmp_path / "Blur", tmp_path / "events.dat")
    assert len(src) == 4 and (src.width, src.height) == (W, H)
    assert src.exposures() == [Exposure(int(s), int(s) + 6_000) for s in starts]
    got = list(src)
    assert [w.frame.index for w in got] == [0, 5, 10, 15]
    for k, fw in enumerate(got):
        img = images[k].astype(np.float32) / np.iinfo(depth).max
        if rgb:
            img = img[..., ::-1]  # written BGR by OpenCV, read back as RGB
        np.testing.assert_allclose(fw.frame.image, img, atol=1e-6)
        assert fw.frame.image.dtype == np.float32
        m = (t >= fw.exposure.start_us) & (t <= fw.exposure.end_us)
        np.testing.assert_array_equal(fw.events.t, t[m])
        np.testing.assert_array_equal(fw.events.x, x[m])
        np.testing.assert_array_equal(fw.events.p, p[m])


def test_margin_offset_subset_and_streaming(tmp_path, rng, monkeypatch):
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)
    _, starts, (t, *_rest) = evdi_sequence(tmp_path, rng)
    src = open_frame_folder(tmp_path / "Blur", tmp_path / "events.dat", time_offset_us=-500)
    assert src.recording is not None and src.recording._cache is None
    assert src.exposures()[0] == Exposure(int(starts[0]) - 500, int(starts[0]) + 5_500)
    sub = src.subset([1, 3])
    wins = list(sub.iter_windows(margin_us=200))
    assert [w.frame.index for w in wins] == [5, 15]
    for w in wins:
        lo, hi = w.exposure.start_us - 200, w.exposure.end_us + 200
        np.testing.assert_array_equal(w.events.t, t[(t >= lo) & (t <= hi)])


def test_exposure_files_must_fit_the_frames(tmp_path, rng):
    evdi_sequence(tmp_path, rng)
    (tmp_path / "Exposure_end.txt").write_text("1\n2\n3\n")
    with pytest.raises(InputError, match="3 exposure times for 4 frames"):
        open_frame_folder(tmp_path / "Blur", tmp_path / "events.dat")
    (tmp_path / "Exposure_end.txt").write_text("1\n2\n3\n4\n")
    with pytest.raises(InputError, match="not after start"):
        open_frame_folder(tmp_path / "Blur", tmp_path / "events.dat")


def test_missing_exposures_and_wrong_size(tmp_path, rng):
    evdi_sequence(tmp_path, rng)
    for f in ("Exposure_start.txt", "Exposure_end.txt"):
        (tmp_path / f).unlink()
    with pytest.raises(InputError, match="Exposure_start.txt"):
        open_frame_folder(tmp_path / "Blur", tmp_path / "events.dat")
    explicit = [Exposure(1000 + 10_000 * k, 7000 + 10_000 * k) for k in range(4)]
    src = open_frame_folder(tmp_path / "Blur", tmp_path / "events.dat", exposures=explicit)
    assert src.exposures() == explicit
    write_dat(tmp_path / "wide.dat", [1, 2], [0, 1], [0, 1], [1, -1], width=W + 1)
    with pytest.raises(InputError, match="sensor"):
        open_frame_folder(tmp_path / "Blur", tmp_path / "wide.dat", exposures=explicit)


def test_exposures_far_from_events_warn(tmp_path, rng):
    evdi_sequence(tmp_path, rng)
    (tmp_path / "Exposure_start.txt").write_text("1.0\n2.0\n3.0\n4.0\n")  # seconds: far away
    (tmp_path / "Exposure_end.txt").write_text("1.5\n2.5\n3.5\n4.5\n")
    src = open_frame_folder(tmp_path / "Blur", tmp_path / "events.dat")
    assert any("outside the events' time range" in w for w in src.warnings)
    assert all(len(w.events) == 0 for w in src)


def _esl_pair(root: Path, rng, numbers=(14, 15, 16), size=(W, H)):
    sio = pytest.importorskip("scipy.io")
    (root / "images").mkdir()
    (root / "mat").mkdir()
    truth = {}
    for k, n in enumerate(numbers):
        cv2.imwrite(str(root / "images" / f"{n:06d}.png"), rng.integers(0, 255, size[::-1],
                                                                          dtype=np.uint8))
        start = 1_615_007_563_000_000 + 122_340 * k
        t = np.sort(rng.integers(start, start + 104_000, 300))
        # small coordinates: the sensor size must come from the image, not from max+1
        x, y, pol = rng.integers(0, 5, 300), rng.integers(0, 5, 300), rng.integers(0, 2, 300)
        sio.savemat(root / "mat" / f"event{n:06d}.mat", {
            "section_event_timestamp": (t / 1e6)[None], "section_event_x": x[None],
            "section_event_y": y[None], "section_event_polarity": pol[None],
            "start_timestamp": np.array([[start / 1e6]]),
            "end_timestamp": np.array([[(start + 104_000) / 1e6]])})
        truth[n] = (start, t, x, y, np.where(pol == 1, 1, -1))
    return truth


def test_paired_esl_layout(tmp_path, rng):
    truth = _esl_pair(tmp_path, rng)
    assert [n for *_, n in pair_folders(tmp_path / "images", tmp_path / "mat")] == [14, 15, 16]
    src = open_frame_folder(tmp_path / "images")  # finds the sibling mat/ folder
    assert (src.width, src.height) == (W, H) and src.warnings == []
    for fw in src:
        start, t, x, y, p = truth[fw.frame.index]
        assert fw.exposure == Exposure(start, start + 104_000)
        assert (fw.events.width, fw.events.height) == (W, H)
        np.testing.assert_array_equal(fw.events.t, t)
        np.testing.assert_array_equal(fw.events.x, x)
        np.testing.assert_array_equal(fw.events.p, p)


def test_paired_unmatched_and_duplicates(tmp_path, rng):
    _esl_pair(tmp_path, rng)
    cv2.imwrite(str(tmp_path / "images" / "000099.png"), np.zeros((H, W), np.uint8))
    src = open_frame_folder(tmp_path / "images", tmp_path / "mat")
    assert len(src) == 3 and any("no event file" in w for w in src.warnings)
    (tmp_path / "mat" / "event_14_copy.mat").write_bytes(
        (tmp_path / "mat" / "event000014.mat").read_bytes())
    with pytest.raises(InputError, match="number 14"):
        pair_folders(tmp_path / "images", tmp_path / "mat")


def test_no_events_given(tmp_path, rng):
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "0.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(InputError, match="no events"):
        open_frame_folder(tmp_path / "frames")
    with pytest.raises(InputError, match="no images"):
        open_frame_folder(tmp_path, tmp_path)


@needs_shared
def test_esl_cups_folder():
    pytest.importorskip("scipy.io")
    src = open_frame_folder(SHARED / "real" / "esl-cups" / "images")
    assert len(src) == 8 and (src.width, src.height) == (346, 260) and src.warnings == []
    gaps = np.diff([e.start_us for e in src.exposures()])
    assert np.all(np.abs(gaps - 122_340) < 5)  # frames 122.34 ms apart
    fw = next(iter(src))
    assert fw.frame.name == "000014" and fw.frame.image.shape == (260, 346)
    assert len(fw.events) == open_events(SHARED / "real/esl-cups/mat/event000014.mat",
                                         ReadOptions(sensor=(346, 260))).num_events()


@needs_shared
def test_aedat4_stored_frames_source():
    rec = open_events(SHARED / "recordings" / "davis346.aedat4")
    src = frames_from_recording(rec)
    assert len(src) == 59
    total = 0
    for fw in src:
        e = fw.exposure
        assert fw.frame.image.shape == (260, 346)
        ref = rec.events(e.start_us, e.end_us + 1)
        np.testing.assert_array_equal(fw.events.t, ref.t)
        total += len(fw.events)
    assert total > 0


def test_recording_without_frames_is_input_error(tmp_path):
    write_dat(tmp_path / "e.dat", [1, 2], [0, 1], [0, 1], [1, -1])
    with pytest.raises(InputError, match="no frames"):
        frames_from_recording(open_events(tmp_path / "e.dat"))


def test_single_image_with_event_file_or_folder(tmp_path, rng):
    _, starts, (t, *_rest) = evdi_sequence(tmp_path, rng)
    img = tmp_path / "Blur" / "000005.png"
    win = [Exposure(int(starts[1]), int(starts[1]) + 6_000)]
    src = open_frame_folder(img, tmp_path / "events.dat", exposures=win)
    (fw,) = list(src)
    assert fw.frame.index == 5
    np.testing.assert_array_equal(fw.events.t, t[(t >= win[0].start_us) & (t <= win[0].end_us)])
    (tmp_path / "esl").mkdir()
    truth = _esl_pair(tmp_path / "esl", rng, numbers=(7, 8))
    one = open_frame_folder(tmp_path / "esl" / "images" / "000008.png", tmp_path / "esl" / "mat")
    (fw,) = list(one)
    np.testing.assert_array_equal(fw.events.t, truth[8][1])


def test_windows_read_ahead_by_a_subset_are_not_read_again(tmp_path, rng, monkeypatch):
    from trmd_cli.read import folders

    truth = _esl_pair(tmp_path, rng, numbers=(14, 15, 16, 17))
    # past the budget nothing is kept, and every window is read by the pass itself
    with monkeypatch.context() as m:
        m.setattr(folders, "KEEP_EVENTS", 100)
        small = open_frame_folder(tmp_path / "images")
        assert len(list(small.subset([0, 2], keep=True))) == 2 and small._kept == {}
    src = open_frame_folder(tmp_path / "images")
    ahead = list(src.subset([1, 3], keep=True))
    # the kept files are gone: the source's own pass can only give them from memory
    for n in (15, 17):
        (tmp_path / "mat" / f"event{n:06d}.mat").unlink()
    got = list(src)
    assert [fw.frame.index for fw in got] == [14, 15, 16, 17]
    assert got[1] is ahead[0] and got[3] is ahead[1]
    for fw in got:
        np.testing.assert_array_equal(fw.events.t, truth[fw.frame.index][1])
    # taken once: a second pass reads the files again (and finds them gone)
    with pytest.raises((OSError, InputError)):
        list(src)


def test_a_frames_folder_gives_its_size_to_a_text_file_that_states_none(tmp_path, rng):
    """Events that never fire in the last column or row: the frames' size is the sensor's,
    not max + 1 of the coordinates (the file holds no size of its own)."""
    _, starts, (t, x, y, p) = evdi_sequence(tmp_path, rng)
    keep = (x < W - 3) & (y < H - 2)
    (tmp_path / "events.txt").write_text("".join(
        f"{a} {b} {c} {int(d > 0)}\n" for a, b, c, d in zip(t[keep], x[keep], y[keep], p[keep],
                                                             strict=True)))
    src = open_frame_folder(tmp_path / "Blur", tmp_path / "events.txt")
    assert (src.width, src.height) == (W, H)
    assert not any("max+1" in w for w in src.warnings)
    ev = next(iter(src)).events
    assert (ev.width, ev.height) == (W, H)


def test_a_frames_folder_alone_finds_its_events_beside_it(tmp_path, rng):
    from trmd_cli.read.inputs import open_inputs

    _esl_pair(tmp_path, rng)
    with open_inputs([tmp_path / "images"]) as ins:
        assert len(ins.source) == 3 and ins.source.exposures()[0].duration_us == 104_000
    (tmp_path / "mat").rename(tmp_path / "elsewhere")
    with pytest.raises(InputError, match="got a frames folder but no events"):
        open_inputs([tmp_path / "images"])


def test_trmd_h5_counts_that_disagree_are_refused(tmp_path, rng):
    import h5py

    from tests.helpers.data import random_stream
    from trmd_cli.errors import FormatError
    from trmd_cli.read.dataset import open_dataset
    from trmd_cli.write import write_h5

    s = random_stream(rng, width=W, height=H)
    frames = np.full((3, H, W), 0.5, np.float32)
    wins = [Exposure(1_000 + 30_000 * k, 21_000 + 30_000 * k) for k in range(3)]
    write_h5(tmp_path / "ok.h5", s, blurry=frames, exposures=wins,
             sharp=np.repeat(frames[:, None], 7, axis=1))
    with h5py.File(tmp_path / "ok.h5") as f, h5py.File(tmp_path / "short.h5", "w") as g:
        for name in ("events", "frames"):
            f.copy(name, g)
        del g["frames/sharp"]
        g["frames/sharp"] = f["frames/sharp"][:2]
        g.attrs.update(f.attrs)
    with pytest.raises(FormatError, match="frames/sharp holds 2 .* for 3 frames"):
        open_dataset(tmp_path / "short.h5", 3)
    with h5py.File(tmp_path / "ok.h5") as f, h5py.File(tmp_path / "more.h5", "w") as g:
        for name in ("events", "frames"):
            f.copy(name, g)
        del g["frames/blurry"]
        g["frames/blurry"] = np.concatenate([frames, frames[:1]])
        g.attrs.update(f.attrs)
    with pytest.raises(FormatError, match="holds 3 exposure windows for 4 frames"):
        with open_events(tmp_path / "more.h5") as rec:
            rec.frame_exposures()
