"""Atomic writers: what they leave behind, and with which permissions."""

from __future__ import annotations

import os
import stat

import pytest

from trmd_cli.write import atomic_dir, atomic_path


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_output_folders_follow_the_umask_like_mkdir(tmp_path, umask_022):
    """mkdtemp makes private folders; a finished output folder is as mkdir would make it."""
    reference = tmp_path / "made_by_mkdir"
    reference.mkdir()
    with atomic_dir(tmp_path / "out") as tmp:
        (tmp / "a.txt").write_text("x")
    mode = stat.S_IMODE((tmp_path / "out").stat().st_mode)
    assert mode == stat.S_IMODE(reference.stat().st_mode) == 0o755
    assert sorted(p.name for p in tmp_path.iterdir()) == ["made_by_mkdir", "out"]


def test_a_failed_folder_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError), atomic_dir(tmp_path / "out") as tmp:
        (tmp / "a.txt").write_text("x")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_file_appears_only_when_complete(tmp_path):
    target = tmp_path / "f.bin"
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"123")
        assert not target.exists()
    assert target.read_bytes() == b"123"


# -- frames to integers, and the result folder ------------------------------------------------

def test_to_uint_clips_rounds_and_maps_nan_to_black():
    import numpy as np

    from trmd_cli.write import to_uint

    x = np.array([np.nan, -np.inf, np.inf, -0.5, 0.0, 0.5, 1.0 / 255, 0.999, 1.0, 7.0],
                 np.float32)
    # round(v · 255) with halves up, after clipping to [0, 1]; NaN and −∞ black, +∞ white
    assert to_uint(x).tolist() == [0, 0, 255, 0, 0, 128, 1, 255, 255, 255]
    assert to_uint(x.astype(np.float64), 16).tolist() == [0, 0, 65535, 0, 0, 32768, 257, 65469,
                                                          65535, 65535]


def test_to_uint_of_half_floats_at_16_bits_does_not_overflow():
    """65535 · x does not fit a half float: the scaling happens in single precision."""
    import warnings

    import numpy as np

    from trmd_cli.write import to_uint

    x = np.array([0.25, 0.5, 1.0, 2.0], np.float16)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = to_uint(x, 16)
    assert out.dtype == np.uint16 and out.tolist() == [16384, 32768, 65535, 65535]
    assert to_uint(x).tolist() == [64, 128, 255, 255]


def _result(k: int = 5, h: int = 6, w: int = 8):
    import numpy as np

    from trmd_cli.deblur import FrameResult
    from trmd_cli.events import Exposure
    from trmd_cli.methods import Estimate

    frames = np.linspace(0.0, 1.2, k * h * w, dtype=np.float32).reshape(k, h, w)
    exposure = Exposure(1_000, 2_000)
    instants = np.linspace(1_000, 2_000, k)
    return FrameResult(3, "000003", frames[k // 2], exposure,
                       Estimate(frames, instants, 0.3), num_events=42)


def test_result_folder_holds_each_frame_and_the_middle_one(tmp_path, umask_022):
    import json

    import cv2
    import numpy as np

    from trmd_cli.write import to_uint, write_result_folder

    res = _result()
    info = write_result_folder(tmp_path, res, meta={"method": "edi"})
    names = [f"frame_{k:03d}.png" for k in range(5)]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [*names, "sharp.png", "timestamps.txt", "meta.json"])
    for name, frame in zip(names, res.frames, strict=True):
        assert np.array_equal(cv2.imread(str(tmp_path / name), cv2.IMREAD_UNCHANGED),
                              to_uint(frame))
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644
    assert (tmp_path / "sharp.png").read_bytes() == (tmp_path / names[2]).read_bytes()
    lines = (tmp_path / "timestamps.txt").read_text().splitlines()
    assert lines[1:] == [f"{n} {t}" for n, t in zip(names, (1000, 1250, 1500, 1750, 2000),
                                                      strict=True)]
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["method"] == "edi" and meta["events"] == 42
    assert meta["contrast"] == 0.3 and "fallback_contrast" not in meta
    # values above 1: the frames' top sixth (1.0 … 1.2 of a ramp up to 1.2)
    above = int((res.frames > 1.0).sum())
    assert info["clipped_fraction"] == pytest.approx(above / res.frames.size)
    assert 0.15 < info["clipped_fraction"] < 0.18


def test_instants_are_written_exactly_on_an_epoch_clock():
    """Near 1.5e15 µs a float64 resolves a quarter of a microsecond: the instants are written
    from whole numbers, to the thousandth (the float would give …498.25 for …498.333)."""
    from trmd_cli.events import Exposure
    from trmd_cli.write import instant_texts

    e = Exposure(1_468_941_032_229_165, 1_468_941_032_233_165)
    assert instant_texts(e, 7) == [
        "1468941032229165", "1468941032229831.667", "1468941032230498.333",
        "1468941032231165", "1468941032231831.667", "1468941032232498.333",
        "1468941032233165"]
    assert float(e.instants_us(3)[5]) == 1468941032232498.25  # what the float would say
    assert instant_texts(Exposure(0, 40_001), 1) == ["20000.5"]
    assert instant_texts(Exposure(10, 20), 3) == ["10", "15", "20"]


def test_result_folder_says_the_motion_methods_refitted_threshold(tmp_path):
    import dataclasses
    import json

    from trmd_cli.write import write_result_folder

    res = _result()
    res = dataclasses.replace(res, estimate=dataclasses.replace(res.estimate,
                                                                fallback_contrast=0.2625))
    write_result_folder(tmp_path, res, meta={"method": "motion"})
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["contrast"] == 0.3 and meta["fallback_contrast"] == 0.2625


def test_a_full_disk_in_a_result_folder_is_one_line(tmp_path, monkeypatch):
    import errno

    from trmd_cli import write
    from trmd_cli.errors import WriteError

    def full(fd, data, offset):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(write.os, "pwrite", full)
    with pytest.raises(WriteError, match="No space left") as caught:
        write.write_result_folder(tmp_path, _result())
    assert caught.value.path == str(tmp_path)


def test_a_failed_frame_leaves_no_file_behind_it(tmp_path, monkeypatch):
    """One frame's write fails while the others are still being written on the encoder
    threads: the failure is raised only once they all ended, so the caller's folder, removed
    then, is not written into afterwards."""
    import threading
    import time

    from trmd_cli import write

    real = write._write_in_place
    ended: list[str] = []

    def slow_or_full(path, data):
        if path.name == "frame_000.png":
            raise OSError(28, os.strerror(28))  # ENOSPC
        if threading.current_thread() is not threading.main_thread():
            time.sleep(0.02)
        real(path, data)
        ended.append(path.name)

    monkeypatch.setattr(write, "_write_in_place", slow_or_full)
    with pytest.raises(OSError):
        write.write_result_folder(tmp_path, _result())
    names = sorted(p.name for p in tmp_path.iterdir())
    # whatever was started is complete: every frame but the failed one, and nothing after
    assert "frame_000.png" not in names
    assert sorted(n for n in ended if n.startswith("frame_")) == [
        n for n in names if n.startswith("frame_")]
    time.sleep(0.1)
    assert sorted(p.name for p in tmp_path.iterdir()) == names
