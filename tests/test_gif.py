"""Animated GIFs that common readers open: gray frames share one palette and read back exactly."""

from __future__ import annotations

import numpy as np

from trmd_cli.video import VideoWriter
from trmd_cli.write import to_uint


def _local_color_tables(path) -> tuple[int, int]:
    """(image blocks, of which with a local colour table), walking the GIF's blocks by the
    GIF89a specification."""
    b = path.read_bytes()
    flags = b[10]
    i = 13 + (3 * 2 ** ((flags & 7) + 1) if flags & 0x80 else 0)
    frames = local = 0
    while i < len(b) and b[i] != 0x3B:
        if b[i] == 0x21:  # extension: label, then sub-blocks
            i += 2
        else:  # 0x2C image descriptor
            frames += 1
            packed = b[i + 9]
            i += 10
            if packed & 0x80:
                local += 1
                i += 3 * 2 ** ((packed & 7) + 1)
            i += 1  # LZW minimum code size
        while b[i]:
            i += b[i] + 1
        i += 1
    return frames, local


def test_gray_gif_frames_share_one_palette_and_read_back_exactly(tmp_path):
    import imageio.v3 as iio
    from PIL import Image, ImageSequence

    rng = np.random.default_rng(0)
    frames = [np.clip(rng.normal(0.2 + 0.1 * k, 0.05, (30, 41)), 0, 1).astype(np.float32)
              for k in range(6)]
    out = tmp_path / "v.gif"
    with VideoWriter(out, fps=10) as vw:
        for f in frames:
            vw.append(f)
    want = np.stack([to_uint(f, 8) for f in frames])
    assert _local_color_tables(out) == (6, 0)
    np.testing.assert_array_equal(iio.imread(out, index=None, mode="L"), want)
    # read with no mode asked for: gray, as written
    np.testing.assert_array_equal(iio.imread(out, index=None), want)
    modes = [im.mode for im in ImageSequence.Iterator(Image.open(out))]
    assert modes == ["L"] * 6
    assert Image.open(out).info["duration"] == 100


def test_colour_gif_still_writes(tmp_path):
    import imageio.v3 as iio

    rng = np.random.default_rng(1)
    out = tmp_path / "c.gif"
    with VideoWriter(out, fps=25) as vw:
        for _ in range(3):
            vw.append(rng.random((20, 24, 3)).astype(np.float32))
    assert iio.imread(out, index=None).shape[:3] == (3, 20, 24)


def test_a_frame_rate_the_video_cannot_play_is_refused(tmp_path):
    import pytest

    from trmd_cli.errors import InputError

    # a GIF's frames last whole hundredths of a second, and players stretch those under 20 ms
    with pytest.raises(InputError, match="up to 50 for a .gif"):
        VideoWriter(tmp_path / "fast.gif", fps=1e9)
    with pytest.raises(InputError, match="up to 1000 for a .mp4"):
        VideoWriter(tmp_path / "fast.mp4", fps=1e9)
    assert not list(tmp_path.iterdir())
    from PIL import Image

    with VideoWriter(tmp_path / "50.gif", fps=50) as vw:
        for v in (0.2, 0.8):
            vw.append(np.full((8, 8), v, np.float32))
    assert Image.open(tmp_path / "50.gif").info["duration"] == 20


def test_a_gif_plays_at_whole_hundredths_and_says_so(tmp_path):
    from PIL import Image

    from trmd_cli.video import played_fps

    assert played_fps("a.gif", 50) == 50 and played_fps("a.gif", 40) == 50
    assert played_fps("a.gif", 25) == 25 and played_fps("a.mp4", 30) == 30
    assert abs(played_fps("a.gif", 30) - 100 / 3) < 1e-9
    with VideoWriter(tmp_path / "30.gif", fps=30) as vw:
        for v in (0.2, 0.8):
            vw.append(np.full((8, 8), v, np.float32))
    assert Image.open(tmp_path / "30.gif").info["duration"] == 30  # what it plays, not 33
