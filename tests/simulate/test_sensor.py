"""The level-crossing event sensor against analytic cases."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from trmd_cli.errors import InputError, ShapeError
from trmd_cli.events import EventStream
from trmd_cli.simulate import EventSensor, SensorConfig, simulate_events

EPS = 0.01


def log_ramp(times_us: np.ndarray, start: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """Frames (S, H, W) whose log(I + eps) is exactly ``start + slope·t`` per pixel."""
    t = np.asarray(times_us, np.float64)[:, None, None]
    return np.exp(start[None] + slope[None] * t) - EPS


def quiet(**kw) -> SensorConfig:
    """Clean sensor with some fields changed."""
    return replace(SensorConfig.clean(0.2, eps=EPS), **kw)


def test_log_ramp_gives_exact_times_and_counts():
    # pixels rise by different amounts; irregular sub-steps, several crossings per step
    times = np.array([0, 700, 1900, 2300, 5200, 8000, 10_000], np.int64)
    rise = np.array([[0.1, 0.45, 0.7], [1.33, 2.05, 3.17]])  # log units over 10 ms
    start = np.log(np.full((2, 3), 0.2) + EPS)
    frames = log_ramp(times, start, rise / 10_000)
    c = 0.2
    ev = simulate_events(frames, times, SensorConfig.clean(c, eps=EPS), np.random.default_rng(0))
    assert np.all(np.diff(ev.t) >= 0)
    assert ev.t.dtype == np.int64 and ev.p.dtype == np.int8
    for y in range(2):
        for x in range(3):
            k = np.arange(1, math.floor(rise[y, x] / c + 1e-9) + 1)
            expected = np.rint(k * c / (rise[y, x] / 10_000)).astype(np.int64)
            sel = (ev.x == x) & (ev.y == y)
            np.testing.assert_array_equal(ev.t[sel], expected)
            assert (ev.p[sel] == 1).all()


def test_falling_ramp_with_asymmetric_thresholds():
    times = np.linspace(0, 20_000, 5).astype(np.int64)
    drop = 1.0  # log units over 20 ms
    frames = log_ramp(times, np.array([[np.log(0.9 + EPS)]]), np.array([[-drop / 20_000]]))
    cfg = quiet(contrast_on=0.1, contrast_off=0.3)
    ev = simulate_events(frames, times, cfg, np.random.default_rng(0))
    # OFF crossings at 0.3, 0.6, 0.9 below the start; the ON threshold plays no part
    np.testing.assert_array_equal(ev.t, np.rint(np.array([0.3, 0.6, 0.9]) / drop * 20_000))
    assert (ev.p == -1).all()


def test_refractory_period_spaces_events_by_period_plus_crossing_time():
    times = np.array([0, 10_000], np.int64)
    rise = 0.9
    frames = log_ramp(times, np.array([[np.log(0.1 + EPS)]]), np.array([[rise / 10_000]]))
    cfg = quiet(refractory_us=1000.0)
    ev = simulate_events(frames, times, cfg, np.random.default_rng(0))
    # c/rate = 2222.2 µs; each event blinds the pixel 1000 µs during which the reference follows
    gap = 0.2 / (rise / 10_000)
    expected = gap + np.arange(4) * (1000 + gap)
    expected = expected[expected <= 10_000]
    np.testing.assert_array_equal(ev.t, np.rint(expected))


def test_static_scene_without_noise_gives_no_events():
    frames = np.full((20, 8, 9), 0.4, np.float32)
    times = np.arange(20, dtype=np.int64) * 1000
    cfg = replace(SensorConfig(), shot_noise_hz=0, leak_hz=0, hot_pixel_fraction=0)
    assert len(simulate_events(frames, times, cfg, np.random.default_rng(1))) == 0


def test_static_scene_shot_noise_matches_poisson_rate():
    h, w, steps = 40, 50, 50
    frames = np.full((steps + 1, h, w), 0.5, np.float32)
    times = np.arange(steps + 1, dtype=np.int64) * 20_000  # 1 s
    rate = 2.0
    cfg = quiet(shot_noise_hz=rate)
    ev = simulate_events(frames, times, cfg, np.random.default_rng(2))
    # at mid-grey the rate factor is 1.75 − 1.5·0.5 = 1
    expect = rate * 1.0 * h * w * 1.0
    assert abs(len(ev) - expect) < 5 * math.sqrt(expect)
    assert abs(np.mean(ev.p > 0) - 0.5) < 5 * 0.5 / math.sqrt(expect)


def test_shot_noise_is_higher_in_the_dark():
    h, w = 40, 40
    img = np.zeros((h, w), np.float32)
    img[:, 20:] = 1.0
    frames = np.repeat(img[None], 26, 0)
    times = np.arange(26, dtype=np.int64) * 40_000  # 1 s
    ev = simulate_events(frames, times, quiet(shot_noise_hz=2.0), np.random.default_rng(3))
    dark, bright = np.sum(ev.x < 20), np.sum(ev.x >= 20)
    # expected 1.75 and 0.25 × 2 Hz × 800 px
    assert abs(dark - 2800) < 5 * math.sqrt(2800)
    assert abs(bright - 400) < 5 * math.sqrt(400)


def test_leak_gives_on_events_at_the_leak_rate():
    h, w = 30, 30
    frames = np.full((11, h, w), 0.3, np.float32)
    times = np.arange(11, dtype=np.int64) * 1_000_000  # 10 s
    cfg = quiet(leak_hz=1.0, random_phase=True)
    ev = simulate_events(frames, times, cfg, np.random.default_rng(4))
    assert (ev.p == 1).all()
    # per-pixel rates are 1 Hz × U(0.5, 1.5); with random phase, 10 s give ≈ 10 per pixel
    per_pixel = len(ev) / (h * w)
    assert 9.0 < per_pixel < 11.0


def test_hot_pixels_fire_at_their_rate_and_nowhere_else():
    h, w = 100, 100
    frames = np.full((11, h, w), 0.5, np.float32)
    times = np.arange(11, dtype=np.int64) * 100_000  # 1 s
    cfg = quiet(hot_pixel_fraction=0.002, hot_pixel_hz=50.0)
    sensor = EventSensor(cfg, w, h, np.random.default_rng(5))
    ev = sensor.feed(frames, times)
    assert sensor.hot.sum() == 20
    assert sensor.hot[ev.y, ev.x].all()
    assert abs(len(ev) - 1000) < 5 * math.sqrt(1000)


def test_threshold_mismatch_statistics_match_sigma():
    h, w = 100, 100
    cfg = quiet(contrast_on=0.25, contrast_off=0.2, contrast_sigma=0.03)
    sensor = EventSensor(cfg, w, h, np.random.default_rng(6))
    assert abs(sensor.c_on.mean() - 0.25) < 0.002 and abs(sensor.c_off.mean() - 0.2) < 0.002
    assert abs(sensor.c_on.std() - 0.03) < 0.002 and abs(sensor.c_off.std() - 0.03) < 0.002
    # the events follow the per-pixel thresholds: a rise of 20 log units gives floor(20/c_on)
    rise = 20.0
    times = np.array([0, 50_000, 100_000], np.int64)
    frames = log_ramp(times, np.full((h, w), np.log(1e-6 + EPS)), np.full((h, w), rise / 1e5))
    ev = sensor.feed(frames, times)
    counts = np.bincount(ev.y.astype(np.int64) * w + ev.x, minlength=w * h).reshape(h, w)
    expected = np.floor(rise / sensor.c_on)
    # float32 logs may flip a pixel sitting exactly on an integer ratio
    assert np.abs(counts - expected).max() <= 1 and np.mean(counts == expected) > 0.999
    estimate = rise / counts  # each pixel's threshold measured from its events alone
    assert abs(estimate.std() - 0.03) < 0.003
    assert (ev.p == 1).all()


@pytest.mark.parametrize("cuts", [[1], [5, 17, 18], [3, 6, 9, 12, 15, 30, 45]])
def test_feeding_in_chunks_gives_identical_events(cuts):
    rng = np.random.default_rng(7)
    base = rng.random((30, 40)).astype(np.float32)
    times = np.cumsum(rng.integers(50, 400, 60)).astype(np.int64)
    frames = np.stack([np.roll(base, k, axis=1) * (0.5 + 0.4 * np.sin(k / 5)) for k in range(60)])
    cfg = SensorConfig(hot_pixel_fraction=0.01, shot_noise_hz=50.0, leak_hz=5.0)
    whole = simulate_events(frames, times, cfg, np.random.default_rng(8))
    sensor = EventSensor(cfg, 40, 30, np.random.default_rng(8))
    bounds = [0, *cuts, 60]
    parts = [sensor.feed(frames[a:b], times[a:b])
             for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    chunked = EventStream.concatenate(parts)
    assert len(whole) > 1000
    for k in "xytp":
        np.testing.assert_array_equal(getattr(whole, k), getattr(chunked, k))


def test_clean_config_is_clean_and_default_is_not():
    assert SensorConfig.clean().is_clean
    assert not SensorConfig().is_clean
    assert SensorConfig.clean(0.3).mean_contrast == pytest.approx(0.3)


def test_bad_inputs_raise_typed_errors():
    sensor = EventSensor(SensorConfig.clean(), 4, 3, np.random.default_rng(0))
    with pytest.raises(ShapeError):
        sensor.feed(np.zeros((2, 4, 3)), np.array([0, 1]))
    with pytest.raises(InputError):
        sensor.feed(np.zeros((2, 3, 4)), np.array([5, 5]))
    sensor.feed(np.zeros((1, 3, 4)), np.array([10]))
    with pytest.raises(InputError):
        sensor.feed(np.zeros((1, 3, 4)), np.array([10]))  # not after the last sample
    with pytest.raises(InputError):
        SensorConfig(contrast_on=0.0)
    with pytest.raises(InputError):
        SensorConfig(shot_noise_hz=-1.0)
