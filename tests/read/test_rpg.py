"""The RPG event-camera layout (events.txt, images.txt, images/): folders written here read
back exactly, time digit by time digit; bad lines are one clear error naming the line."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.cli import assert_one_error_line
from tests.helpers.data import assert_events
from trmd_cli.cli.app import app
from trmd_cli.errors import FormatError, InputError
from trmd_cli.events import Exposure
from trmd_cli.read import ReadOptions, detect_format, open_events
from trmd_cli.read import chunked as chunked_mod
from trmd_cli.read import rpg as rpg_mod
from trmd_cli.read.inputs import open_inputs

runner = CliRunner()
W, H = 40, 30
S0 = 1_468_941_032  # seconds since the epoch, as the dataset's bags have them


def seconds(ns: int, decimals: int = 9) -> str:
    """A time of ``ns`` nanoseconds written in seconds with ``decimals`` digits (truncated)."""
    whole, frac = divmod(int(ns), 1_000_000_000)
    return f"{whole}.{frac:09d}"[: len(str(whole)) + 1 + decimals] if decimals else str(whole)


def rpg_folder(root: Path, rng, n=2000, frames=3, decimals=9, phase=123, name="seq"):
    """t in ns (whole µs plus one shared sub-µs remainder), written as the dataset does."""
    d = root / name
    (d / "images").mkdir(parents=True)
    t_ns = S0 * 10**9 + np.sort(rng.integers(0, 2_000_000, n)) * 1000 + phase
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    p = rng.integers(0, 2, n)
    (d / "events.txt").write_text("".join(f"{seconds(t, decimals)} {a} {b} {c}\n"
                                          for t, a, b, c in zip(t_ns, x, y, p, strict=True)))
    stamps, images = [], []
    lines = []
    for k in range(frames):
        img = rng.integers(0, 256, (H, W)).astype(np.uint8)
        cv2.imwrite(str(d / "images" / f"frame_{k:08d}.png"), img)
        s = S0 * 10**9 + 300_000_000 + 500_000_000 * k + phase
        lines.append(f"{seconds(s, decimals)} images/frame_{k:08d}.png\n")
        stamps.append(s)
        images.append(img)
    (d / "images.txt").write_text("".join(lines))
    (d / "imu.txt").write_text("0.0 0 0 0 0 0 0\n")
    return d, (t_ns, x, y, np.where(p == 1, 1, -1)), stamps, images


@pytest.mark.parametrize("decimals", [9, 6, 3])
def test_rpg_folder_reads_back_exactly(tmp_path, rng, decimals):
    d, (t_ns, x, y, p), stamps, images = rpg_folder(tmp_path, rng, decimals=decimals)
    assert detect_format(d) == "rpg"
    cut = 10 ** (9 - decimals)
    with open_events(d, ReadOptions(exposure_length_us=12_345, stamp="middle")) as rec:
        assert (rec.format, rec.width, rec.height) == ("rpg", W, H)  # the frames' size
        assert rec.warnings == []
        # the written digits, floored to whole µs: never through a float
        assert_events(rec.events(), (t_ns // cut * cut) // 1000, x, y, p)
        frames = list(rec.frames())
        assert [f.name for f in frames] == ["frame_00000000", "frame_00000001",
                                            "frame_00000002"]
        for fr, s, img in zip(frames, stamps, images, strict=True):
            start = (s // cut * cut) // 1000 - 12_345 // 2
            assert fr.exposure == Exposure(start, start + 12_345)
            np.testing.assert_array_equal(np.rint(fr.image * 255).astype(int), img)


def test_parser_digit_by_digit():
    t, x, y, p, sub = rpg_mod.parse_event_lines(
        b"1468941032.229165635 33 39 1\n0.5 1 2 0\n\n12 3 4 1\r\n  7.0000009\t5 6 0")
    np.testing.assert_array_equal(t, [1468941032229165, 500_000, 12_000_000, 7_000_000])
    np.testing.assert_array_equal(sub, [635, 0, 0, 900])
    np.testing.assert_array_equal(x, [33, 1, 3, 5])
    np.testing.assert_array_equal(y, [39, 2, 4, 6])
    np.testing.assert_array_equal(p, [1, -1, 1, -1])


def test_mixed_sub_microsecond_remainders_warn(tmp_path, rng):
    d, _, _, _ = rpg_folder(tmp_path, rng, n=20)
    lines = (d / "events.txt").read_text().splitlines()
    lines[5] = lines[5].split(".")[0] + "." + lines[5].split(".")[1][:6] + "999 " + \
        " ".join(lines[5].split()[1:])
    (d / "events.txt").write_text("\n".join(lines) + "\n")
    with open_events(d) as rec:
        assert any("finer than a microsecond" in w for w in rec.warnings)


def test_rpg_streams_by_pieces_and_seeks(tmp_path, rng, monkeypatch):
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)
    monkeypatch.setattr(rpg_mod, "RPG_CHUNK_BYTES", 4096)
    d, (t_ns, x, y, p), _, _ = rpg_folder(tmp_path, rng, n=5000)
    tu = t_ns // 1000
    with open_events(d) as rec:
        assert len(rec._first) > 20
        for lo, hi in [(tu[4000], tu[4100]), (tu[3], tu[90]), (tu[2000], tu[-1] + 1)]:
            sel = (tu >= lo) & (tu < hi)
            assert_events(rec.events(lo, hi), tu[sel], x[sel], y[sel], p[sel])
        assert sum(len(c) for c in rec.iter_chunks(max_events=999)) == 5000


def test_frames_need_an_exposure_length(tmp_path, rng):
    d, _, stamps, _ = rpg_folder(tmp_path, rng)
    with open_events(d) as rec:
        assert rec.num_frames() == 3 and rec.frame_exposures() == []
        assert any("`exposure_length_us`" in w for w in rec.warnings)
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(d), "-o", str(out), "--method", "edi"])
    assert_one_error_line(r, "seq", "--exposure-length")
    r = runner.invoke(app, ["deblur", str(d), "-o", str(out), "--method", "edi",
                            "--exposure-length", "20ms", "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert (out / "frame_00000002" / "sharp.png").is_file()
    with open_inputs([d], ReadOptions(exposure_length_us=20_000)) as ins:
        assert ins.source.exposures()[1] == Exposure(stamps[1] // 1000,
                                                     stamps[1] // 1000 + 20_000)
    r = runner.invoke(app, ["eval", str(d), "--methods", "blurry,edi", "--exposure-length",
                            "20ms", "--stamp", "middle"])
    assert r.exit_code == 0, r.output


def _polarity_2_on_line_8(text: str) -> str:
    lines = text.splitlines(keepends=True)
    lines[7] = lines[7][:-2] + "2\n"
    return "".join(lines)


@pytest.mark.parametrize("damage,needle", [
    (_polarity_2_on_line_8, "line 8 of events.txt"),
    (lambda s: s[: s.index("\n", len(s) // 2) + 14], "is not 't x y p'"),  # cut mid-line
    (lambda s: s.replace(".", "e", 1), "line 1 of events.txt"),
    (lambda s: "t x y p\n" + s, "line 1 of events.txt"),
    (lambda s: s.replace(" ", " -", 1), "line 1"),
])
def test_bad_lines_are_one_clear_error(tmp_path, rng, damage, needle):
    d, _, _, _ = rpg_folder(tmp_path, rng, n=300)
    (d / "events.txt").write_text(damage((d / "events.txt").read_text()))
    with pytest.raises(FormatError, match=needle):
        open_events(d)
    r = runner.invoke(app, ["info", str(d)])
    assert_one_error_line(r, "events.txt", needle)


def test_missing_image_is_named(tmp_path, rng):
    d, _, _, _ = rpg_folder(tmp_path, rng, n=50)
    (d / "images" / "frame_00000001.png").unlink()
    with pytest.raises(InputError, match="frame_00000001.png, which does not exist"):
        open_events(d)


def test_a_frames_folder_keeps_its_meaning(tmp_path, rng):
    """A folder with blurry/ and Exposure_*.txt stays a dataset folder even with images.txt."""
    d, _, _, _ = rpg_folder(tmp_path, rng, n=50)
    (d / "Exposure_start.txt").write_text("0\n")
    r = runner.invoke(app, ["deblur", str(d), "-o", str(tmp_path / "o")])
    assert_one_error_line(r, "seq", "frames folder but no events")


def test_half_an_rpg_folder_names_the_missing_file(tmp_path):
    from trmd_cli.errors import InputError
    from trmd_cli.read import open_events

    (tmp_path / "images.txt").write_text("")
    with pytest.raises(InputError, match="holds images.txt but no events.txt"):
        open_events(tmp_path)
