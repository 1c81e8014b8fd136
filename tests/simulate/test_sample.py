"""Sharp sequences from a still image, blur, and the EDI acceptance check on clean data."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.data import texture
from trmd_cli.events import Exposure
from trmd_cli.metrics import psnr
from trmd_cli.simulate import (
    MotionRanges,
    SensorConfig,
    make_sample,
    make_sequence,
    plan_sequence,
    uniform_grid,
)
from trmd_cli.simulate.blur import steps_for_motion

SIZE = (96, 72)


def edi(blurry: np.ndarray, events, exposure: Exposure, instants, c: float,
        eps: float) -> np.ndarray:
    """Exact EDI with a known threshold, written out independently for this test.

    L(f) = (B + eps) / mean_t exp(c·E(f, t)) − eps: E is piecewise constant between events, so
    the mean is a sum over each pixel's inter-event intervals.
    """
    h, w = blurry.shape
    sel = (events.t >= exposure.start_us) & (events.t <= exposure.end_us)
    t = events.t[sel].astype(np.float64)
    pix = events.y[sel].astype(np.int64) * w + events.x[sel]
    p = events.p[sel].astype(np.float64)
    order = np.lexsort((t, pix))
    t, pix, p = t[order], pix[order], p[order]
    # level S(t) since t0 just after each event: a cumulative sum restarted at each pixel
    start = np.r_[True, pix[1:] != pix[:-1]]
    csum = np.cumsum(p)
    base = np.maximum.accumulate(np.where(start, np.arange(len(p)), 0))
    level_after = csum - (csum[base] - p[base])
    t_next = np.r_[t[1:], 0.0]
    last = np.r_[pix[1:] != pix[:-1], True]
    t_next[last] = exposure.end_us
    integral = np.bincount(pix, weights=(t_next - t) * np.exp(c * level_after),
                           minlength=h * w)
    first_t = np.full(h * w, float(exposure.end_us))
    first_t[pix[start]] = t[start]
    integral += first_t - exposure.start_us  # before the first event the level is 0
    mean = (integral / exposure.duration_us).reshape(h, w)
    out = []
    for f in instants:
        before = t <= f
        s_f = np.bincount(pix[before], weights=p[before], minlength=h * w).reshape(h, w)
        out.append((blurry + eps) * np.exp(c * s_f) / mean - eps)
    return np.stack(out)


@pytest.fixture(scope="module")
def clean_sample():
    return make_sample(texture(), n=3, size=SIZE, exposure_us=12_000,
                       rng=np.random.default_rng(11), sensor=SensorConfig.clean(0.1),
                       motion=MotionRanges(translation_px=25.0, rotation_deg=2.0))


def test_sample_shapes_and_event_window(clean_sample):
    s = clean_sample
    w, h = SIZE
    assert s.blurry.shape == (h, w) and s.blurry.dtype == np.float32
    assert s.sharp.shape == (7, h, w) and s.sharp.dtype == np.float32
    assert s.exposure == Exposure(0, 12_000)
    assert len(s.events) > 1000
    assert s.events.t.min() >= 0 and s.events.t.max() <= 12_000
    assert np.all(np.diff(s.events.t) >= 0)
    assert s.contrast == pytest.approx(0.1)
    assert 0 <= s.blurry.min() and s.blurry.max() <= 1


def test_sharp_frames_average_to_the_blurry_frame(clean_sample):
    s = clean_sample
    # both are quadratures of the same integral; the blur itself is far from any one frame
    assert psnr(s.sharp.mean(0), s.blurry) > 33
    assert psnr(s.sharp[3], s.blurry) < psnr(s.sharp.mean(0), s.blurry) - 8


def test_edi_with_true_threshold_reconstructs_the_middle_frame(clean_sample):
    s = clean_sample
    inst = s.exposure.instants_us(3)
    latent = edi(s.blurry, s.events, s.exposure, inst, s.contrast, SensorConfig.clean().eps)
    mid = psnr(np.clip(latent[3], 0, 1), s.sharp[3])
    # what remains is the quantisation of log intensity to multiples of c
    assert mid > 31
    assert mid > psnr(s.blurry, s.sharp[3]) + 7
    assert psnr(np.clip(latent, 0, 1), s.sharp) > 30


def test_edi_module_agrees_when_present(clean_sample):
    edi_mod = pytest.importorskip("trmd_cli.edi")
    s = clean_sample
    eps = SensorConfig.clean().eps
    latent = edi_mod.edi_latent(s.blurry + eps, s.events, s.exposure,
                                s.exposure.instants_us(3), s.contrast) - eps
    assert psnr(np.clip(latent[3], 0, 1), s.sharp[3]) > 31


def test_sub_steps_move_at_most_one_pixel():
    img = texture(seed=1)
    for seed in range(4):
        plan = plan_sequence(img, n=3, size=SIZE, exposure_us=10_000,
                             rng=np.random.default_rng(seed),
                             motion=MotionRanges(translation_px=60.0, rotation_deg=5.0,
                                                 scale=0.1, perspective=0.05, curvature=0.8,
                                                 foreground_prob=1.0, max_layers=2))
        u = plan.grid_us / 10_000
        w, h = SIZE
        pts = np.array([[x, y, 1.0] for x in np.linspace(0, w - 1, 5)
                        for y in np.linspace(0, h - 1, 5)]).T
        g = plan.scene.camera.homographies(u) @ pts[None]
        xy = g[:, :2] / g[:, 2:3]
        assert np.linalg.norm(np.diff(xy, axis=0), axis=1).max() <= 1.0
        for layer in plan.scene.layers:
            lh, lw = layer.mask.shape
            lp = np.array([[0, 0, 1.0], [lw - 1, lh - 1, 1.0], [0, lh - 1, 1.0]]).T
            xy = layer.affines(u) @ lp[None]
            assert np.linalg.norm(np.diff(xy, axis=0), axis=1).max() <= 1.0
        # the latent instants are sub-steps
        assert np.isin(np.rint(Exposure(0, 10_000).instants_us(3)), plan.grid_us).all()


def test_steps_for_motion_is_a_multiple_of_2n():
    assert steps_for_motion(0.0, 3) == 6
    assert steps_for_motion(13.2, 3) == 18
    assert steps_for_motion(13.2, 2, max_px_per_step=0.5) == 28


def test_uniform_grid_covers_exposures_and_gaps():
    exps = [Exposure(0, 600), Exposure(1000, 1600)]
    grid = uniform_grid(exps, 3, 12)
    assert grid[0] == 0 and grid[-1] == 1600
    assert np.all(np.diff(grid) > 0) and np.diff(grid).max() <= 50
    for e in exps:
        assert np.isin(np.rint(e.instants_us(3)), grid).all()


def test_static_scene_blur_equals_every_sharp_frame():
    s = make_sample(texture(), n=2, size=SIZE, exposure_us=5000, rng=np.random.default_rng(0),
                    sensor=SensorConfig.clean(), motion=MotionRanges.static())
    assert len(s.events) == 0
    for k in range(5):
        np.testing.assert_allclose(s.sharp[k], s.blurry, atol=1e-5)


def test_same_seed_same_sample_other_seed_other_sample():
    kw = dict(n=1, size=(48, 40), exposure_us=4000, sensor=SensorConfig())
    a = make_sample(texture(), rng=np.random.default_rng(3), **kw)
    b = make_sample(texture(), rng=np.random.default_rng(3), **kw)
    c = make_sample(texture(), rng=np.random.default_rng(4), **kw)
    np.testing.assert_array_equal(a.blurry, b.blurry)
    np.testing.assert_array_equal(a.events.t, b.events.t)
    assert not np.array_equal(a.blurry, c.blurry)


def test_read_noise_has_the_requested_sigma():
    kw = dict(n=1, size=(80, 60), exposure_us=4000, sensor=SensorConfig.clean(),
              motion=MotionRanges(translation_px=5.0))
    a = make_sample(texture(), rng=np.random.default_rng(5), read_noise=0.0, **kw)
    b = make_sample(texture(), rng=np.random.default_rng(5), read_noise=0.02, **kw)
    inside = (a.blurry > 0.1) & (a.blurry < 0.9)  # away from the [0, 1] clip
    assert abs(np.std((b.blurry - a.blurry)[inside]) - 0.02) < 0.002


def test_consecutive_exposures_with_gaps():
    seq = make_sequence(texture(), n=3, size=SIZE, exposure_us=6000, frames=3,
                        frame_interval_us=10_000, rng=np.random.default_rng(2),
                        sensor=SensorConfig.clean(0.15),
                        motion=MotionRanges(translation_px=12.0))
    assert [(e.start_us, e.end_us) for e in seq.exposures] == [(0, 6000), (10_000, 16_000),
                                                                (20_000, 26_000)]
    assert seq.blurry.shape == (3, SIZE[1], SIZE[0]) and seq.sharp.shape[:2] == (3, 7)
    in_gap = (seq.events.t > 6000) & (seq.events.t < 10_000)
    assert in_gap.sum() > 100  # the camera keeps moving between exposures
    # each exposure's own sharp frames average to its blurry frame
    for k in range(3):
        assert psnr(seq.sharp[k].mean(0), seq.blurry[k]) > 33
    # motion during the gap: the next exposure does not start where the last one ended
    assert psnr(seq.sharp[0, -1], seq.sharp[1, 0]) < 35


def test_foreground_layers_occlude_the_background():
    motion = MotionRanges(translation_px=0.0, rotation_deg=0.0, scale=0.0, perspective=0.0,
                          foreground_prob=1.0, max_layers=1, layer_translation_px=30.0)
    s = make_sample(texture(), n=1, size=SIZE, exposure_us=6000, rng=np.random.default_rng(9),
                    sensor=SensorConfig.clean(0.15), motion=motion)
    # the camera is still, so the events come from the moving layer only: a compact region
    moved = np.abs(s.sharp[0] - s.sharp[2]) > 1e-4
    assert 0.01 < moved.mean() < 0.9
    assert len(s.events) > 100
