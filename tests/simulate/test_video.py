"""Frame folders and videos: optical-flow upsampling, timestamps, exposures over the span."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.data import shifted, texture
from trmd_cli.errors import InputError
from trmd_cli.events import EventStream
from trmd_cli.metrics import psnr
from trmd_cli.simulate import SensorConfig
from trmd_cli.simulate.video import (
    FlowInterpolator,
    FolderFrames,
    fit_frame,
    iter_video,
    list_frames,
    read_timestamps,
    video_blocks,
    video_exposures,
)


def test_flow_interpolation_recovers_the_halfway_frame():
    img = texture(120, 160, seed=3)
    interp = FlowInterpolator(img, shifted(img, 8.0))
    assert 6.0 < interp.motion_px() < 10.0
    mid = interp(0.5)
    truth = shifted(img, 4.0)
    inner = (slice(10, -10), slice(20, -20))
    assert psnr(mid[inner], truth[inner]) > 32
    # far better than a cross-fade of the two frames
    fade = 0.5 * (img + shifted(img, 8.0))
    assert psnr(mid[inner], truth[inner]) > psnr(fade[inner], truth[inner]) + 5
    np.testing.assert_array_equal(interp(0.0), img)


def write_frames(folder, count: int, step_px: float) -> list:
    from trmd_cli.write import write_image

    folder.mkdir()
    img = texture(100, 140, seed=4)
    paths = []
    for k in range(count):
        # names sort naturally, not lexically: frame_2 before frame_10
        p = folder / f"frame_{k}.png"
        write_image(p, shifted(img, k * step_px))
        paths.append(p)
    return paths


def test_list_frames_natural_order(tmp_path):
    paths = write_frames(tmp_path / "f", 12, 1.0)
    assert list_frames(tmp_path / "f") == paths
    (tmp_path / "one").mkdir()
    with pytest.raises(InputError):
        list_frames(tmp_path / "one")


def test_read_timestamps(tmp_path):
    f = tmp_path / "ts.txt"
    f.write_text("# seconds\n0.0\n0.0333335\n\n0.07\n")
    np.testing.assert_array_equal(read_timestamps(f, 3), [0, 33334, 70_000])
    with pytest.raises(InputError, match="3 timestamps for 4 frames"):
        read_timestamps(f, 4)
    f.write_text("0\n0.5\n0.5\n")
    with pytest.raises(InputError, match="does not increase"):
        read_timestamps(f, 3)
    f.write_text("0\nabc\n")
    with pytest.raises(InputError, match="line 2"):
        read_timestamps(f, 2)


def test_video_exposures_defaults_and_limits():
    times = np.arange(10, dtype=np.int64) * 10_000  # 90 ms span
    exps = video_exposures(times, None, None, None)
    # 3 frame intervals, 1.2 × apart, as many as fit
    assert [(e.start_us, e.end_us) for e in exps] == [(0, 30_000), (36_000, 66_000)]
    assert len(video_exposures(times, 20_000, 25_000, 2)) == 2
    with pytest.raises(InputError, match="does not fit"):
        video_exposures(times, 100_000, None, None)


def test_fit_frame_covers_and_crops():
    img = np.tile(np.linspace(0, 1, 200, dtype=np.float32), (100, 1))
    out = fit_frame(img, (50, 50))
    assert out.shape == (50, 50)
    # scaled by 1/2 to cover 50 rows, then the middle 50 of 100 columns
    assert 0.2 < out.mean() < 0.8 and out[:, 0].mean() > 0.2


def test_frame_folder_blocks_limit_motion_and_hold_latent_instants(tmp_path):
    paths = write_frames(tmp_path / "f", 4, 6.0)
    times = np.array([0, 30_000, 60_000, 90_000], np.int64)
    source = FolderFrames(paths, times, (64, 48))
    exps = video_exposures(times, 40_000, None, None)
    blocks = list(video_blocks(source, exps, 3))
    grid = np.concatenate([t for t, _ in blocks])
    assert grid[0] == 0 and grid[-1] == 90_000 and np.all(np.diff(grid) > 0)
    # ≈ 6 px × (64/140) ≈ 2.7 px of motion per interval → at least 3 steps each
    assert len(grid) >= 1 + 3 * 3
    for e in exps:
        assert np.isin(np.rint(e.instants_us(3)), grid).all()


def test_frame_folder_events_cover_the_whole_span(tmp_path):
    paths = write_frames(tmp_path / "f", 6, 4.0)
    times = np.arange(6, dtype=np.int64) * 20_000
    source = FolderFrames(paths, times, (70, 50))
    exps = video_exposures(times, 25_000, None, None)  # at 0, 30 and 60 ms
    sensor, it = iter_video(source, exps, n=2, sensor=SensorConfig.clean(0.15),
                            rng=np.random.default_rng(0))
    items = list(it)
    ev = EventStream.concatenate([i for i in items if isinstance(i, EventStream)])
    results = [i for i in items if not isinstance(i, EventStream)]
    assert len(results) == len(exps) == 3
    assert ev.t[0] < 10_000 and ev.t[-1] > 90_000
    for r in results:
        assert r.sharp.shape == (5, 50, 70)
        assert psnr(r.sharp.mean(0), r.blurry) > 33
