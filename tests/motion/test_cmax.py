"""Contrast maximisation recovers a known global motion from simulated events."""

from __future__ import annotations

import numpy as np
import pytest

from trmd_cli.edi import hot_pixel_mask
from trmd_cli.events import EventStream, Exposure
from trmd_cli.motion import GlobalMotion, MotionSearch, estimate_motion
from trmd_cli.simulate import MotionRanges, make_sample
from trmd_cli.simulate.sample import plan_sequence

from ..helpers.data import texture

W, H = 346, 260


def true_epe(plan, motion: GlobalMotion) -> float:
    """Mean end-point error (px) against the simulator's camera homographies over the
    exposure (they map a pixel at time u to the middle frame: positions are their inverse)."""
    u = np.linspace(0.0, 1.0, 9)
    hs = plan.scene.camera.homographies(u)
    gx, gy = np.meshgrid(np.linspace(0, W - 1, 8), np.linspace(0, H - 1, 8))
    pts = np.stack([gx.ravel(), gy.ravel(), np.ones(64)])
    err = []
    for k in range(len(u)):
        q = np.linalg.inv(hs[k]) @ pts
        x, y = motion.positions(u[k], pts[0], pts[1])
        err.append(np.hypot(x - q[0] / q[2], y - q[1] / q[2]).mean())
    return float(np.mean(err))


def camera_sample(seed: int, translation_px: float = 20, perspective: float = 0.0,
                  curvature: float = 0.3, **sample):
    """A simulated exposure of a camera moving over a 700×520 texture (``seed``), and its
    plan (the true camera path, for :func:`true_epe`)."""
    img = texture(520, 700, seed=seed)
    motion = MotionRanges(translation_px=translation_px, rotation_deg=1, scale=0.02,
                          perspective=perspective, curvature=curvature)
    s = make_sample(img, rng=np.random.default_rng(seed), motion=motion, **sample)
    plan = plan_sequence(img, rng=np.random.default_rng(seed), motion=motion)
    return s, plan


@pytest.mark.parametrize("perspective", [(0.0, 0.0), (2e-4, -1e-4)])
def test_model_inverse_is_exact(perspective):
    m = GlobalMotion((7.0, -3.0), (2.0, 1.0), 0.05, 0.03, (172.5, 129.5),
                     perspective=perspective)
    u = np.linspace(0, 1, 5)[:, None]
    x0, y0 = np.array([[0.0, 100.0, 345.0]]), np.array([[0.0, 50.0, 259.0]])
    x, y = m.positions(u, x0, y0)
    xb, yb = m.to_middle(u, x, y)
    assert np.allclose(xb, x0) and np.allclose(yb, y0)
    xm, ym = m.positions(0.5, x0, y0)
    assert np.allclose(xm, x0) and np.allclose(ym, y0)  # the middle frame is the reference


@pytest.mark.parametrize("seed", [2])
def test_cmax_recovers_simulated_camera_motion(seed):
    s, plan = camera_sample(seed)
    m = estimate_motion(s.events, s.exposure, hot_pixel_mask(s.events, s.exposure))
    assert true_epe(plan, m) < 0.2
    assert m.confidence > 1.2


def test_cmax_from_a_start_velocity_recovers_rotation_and_zoom():
    """Started from a velocity 3 px off the true mean one (as the background's estimate is,
    from the tiles' vote), the single way it then takes frees rotation and zoom at 2× and
    still finds the camera's path, rotation and zoom included, within 0.2 px."""
    s, plan = camera_sample(2)
    hot = hot_pixel_mask(s.events, s.exposure)
    free = estimate_motion(s.events, s.exposure, hot)
    vx, vy = free.velocity
    m = estimate_motion(s.events, s.exposure, hot, start=(vx + 3.0, vy - 2.0))
    assert true_epe(plan, m) < 0.2
    assert abs(m.rotation) > 0.005 or abs(m.zoom) > 0.005, "the motion has rotation or zoom"


@pytest.mark.parametrize("perspective", [(0.0, 0.0), (4.0, -3.0)])
def test_contrast_gradient_matches_finite_differences(perspective):
    """The analytic gradient of the contrast gain (all ten parameters: the jerk's too) against
    central differences of the gain itself, on random events at every pyramid scale, with and
    without a perspective term."""
    from trmd_cli.motion.cmax import _Level

    rng = np.random.default_rng(3)
    n = 20_000
    x, y = rng.uniform(0, W, n), rng.uniform(0, H, n)
    # structure to sharpen: events concentrated on a few lines
    x[: n // 2] = rng.integers(0, 12, n // 2) * 29.0 + rng.normal(0, 0.7, n // 2)
    u = rng.uniform(0, 1, n)
    q = np.array([3.0, -6.0, 2.0, 1.0, -2.0, 2.5, *perspective, 1.5, -2.0])
    for scale in (1.0, 2.0, 4.0):
        level = _Level(x, y, u, W, H, scale, ((W - 1) / 2, (H - 1) / 2), 0.5 * W)
        _, grad = level.gain_and_gradient(q, free=10)
        fd = np.array([(level.gain(q + e) - level.gain(q - e)) / 0.02
                       for e in 0.01 * np.eye(10)])
        # the gain is piecewise smooth (bilinear votes): differences agree to ~1 % of |∇|
        np.testing.assert_allclose(grad, fd, rtol=0.02, atol=0.01 * np.linalg.norm(fd))


def test_perspective_term_follows_a_panning_camera():
    """A camera path with a perspective term (the homography a pan or tilt gives): the search
    keeps the term and lands nearer the true path than the same search without it."""
    s, plan = camera_sample(7, perspective=0.03)
    hot = hot_pixel_mask(s.events, s.exposure)
    m = estimate_motion(s.events, s.exposure, hot)
    flat = estimate_motion(s.events, s.exposure, hot, MotionSearch(max_perspective=0.0))
    assert m.perspective != (0.0, 0.0) and flat.perspective == (0.0, 0.0)
    assert true_epe(plan, m) < 0.3
    assert true_epe(plan, m) < true_epe(plan, flat) - 0.1


def test_too_few_events_give_no_estimate():
    ev = EventStream(np.array([1, 2], np.uint16), np.array([1, 2], np.uint16),
                     np.array([0, 10], np.int64), np.array([1, -1], np.int8), W, H)
    m = estimate_motion(ev, Exposure(0, 100))
    assert m.confidence == 0.0 and m.events == 2 and m.velocity == (0.0, 0.0)


def test_jerk_follows_a_bending_path():
    """A camera path that bends within the exposure (the simulator's cubic knots, curvature
    1): the search keeps a jerk and lands nearer the true path than without one (measured
    0.19 against 0.28 px)."""
    from trmd_cli.simulate import SensorConfig

    s, plan = camera_sample(3, translation_px=24, curvature=1.0, sensor=SensorConfig.clean(0.2))
    hot = hot_pixel_mask(s.events, s.exposure)
    m = estimate_motion(s.events, s.exposure, hot)
    flat = estimate_motion(s.events, s.exposure, hot, MotionSearch(jerk=False))
    assert m.jerk != (0.0, 0.0) and flat.jerk == (0.0, 0.0)
    assert true_epe(plan, m) < 0.22
    assert true_epe(plan, m) < true_epe(plan, flat) - 0.05
