"""SampledMotion against the simulator: the recorded true camera path reproduces the simulated
sharp frames and the blurry frame, and answers as GlobalMotion answers."""

from __future__ import annotations

import numpy as np
import pytest

from trmd_cli.deconv import BlurOperator
from trmd_cli.errors import InputError
from trmd_cli.metrics import psnr
from trmd_cli.motion import GlobalMotion, SampledMotion, event_gain
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample, make_sequence

from ..helpers.data import texture

W, H = 160, 120
#: content that moved into view from outside the frame is unknown to the middle frame
INNER = (slice(16, -16), slice(16, -16))


@pytest.fixture(scope="module")
def sample():
    """A clean 160×120 exposure with every kind of camera motion (translation, rotation,
    zoom, perspective, a bending path)."""
    motion = MotionRanges(translation_px=30, rotation_deg=4, scale=0.05, perspective=0.03,
                          curvature=0.6)
    return make_sample(texture(300, 400, seed=3), n=3, size=(W, H),
                       rng=np.random.default_rng(11), motion=motion,
                       sensor=SensorConfig.clean(0.2), read_noise=0.0)


def _centre():
    return ((W - 1) / 2, (H - 1) / 2)


def test_true_path_carries_the_middle_frame_onto_every_sharp_frame(sample):
    m = SampledMotion(sample.motion, centre=_centre())
    assert m.samples == 33
    # a real motion: the latent frames differ a lot from the middle one
    assert m.max_displacement_px(W, H) > 8
    op = BlurOperator(m, W, H)
    fr = np.arange(7) / 6
    warped = op.warp(op.pad_frame(sample.sharp[3]), fr).numpy()[:, 0]
    for k in range(7):
        if k != 3:
            assert psnr(sample.sharp[3][INNER], sample.sharp[k][INNER]) < 30
        assert psnr(warped[k][INNER], sample.sharp[k][INNER]) > 40, k


def test_reblurring_along_the_true_path_gives_back_the_blurry_frame(sample):
    m = SampledMotion(sample.motion, centre=_centre())
    op = BlurOperator(m, W, H)
    re = op.apply(op.pad_frame(sample.sharp[3])).numpy()[0]
    assert psnr(sample.blurry[INNER], sample.sharp[3][INNER]) < 30
    assert psnr(re[INNER], sample.blurry[INNER]) > 40


def test_positions_and_to_middle(sample):
    m = SampledMotion(sample.motion)
    x0 = np.array([0.0, 40.0, 159.0])
    y0 = np.array([0.0, 70.0, 119.0])
    # the middle frame is the reference
    x, y = m.positions(0.5, x0, y0)
    np.testing.assert_allclose(x, x0, atol=1e-9)
    np.testing.assert_allclose(y, y0, atol=1e-9)
    # at a sampled instant: the stored matrix applied by hand
    hm = sample.motion[8]
    q = hm @ np.stack([x0, y0, np.ones(3)])
    x, y = m.positions(8 / 32, x0, y0)
    np.testing.assert_allclose(x, q[0] / q[2], atol=1e-9)
    np.testing.assert_allclose(y, q[1] / q[2], atol=1e-9)
    # between samples, and broadcast as the blur operator calls it: exact inverse
    u = np.array([0.0, 0.013, 0.37, 0.999, 1.0])[:, None]
    x, y = m.positions(u, x0[None], y0[None])
    xb, yb = m.to_middle(u, x, y)
    np.testing.assert_allclose(xb, np.broadcast_to(x0, xb.shape), atol=1e-8)
    np.testing.assert_allclose(yb, np.broadcast_to(y0, yb.shape), atol=1e-8)


def _as_sampled(g: GlobalMotion, j: int = 65) -> SampledMotion:
    """A GlobalMotion's affine (no perspective) path as homographies fitted through 3 points."""
    u = np.linspace(0, 1, j)
    src = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]])
    hs = []
    for uj in u:
        x, y = g.positions(uj, src[:, 0], src[:, 1])
        a = np.linalg.solve(np.c_[src, np.ones(3)], np.c_[x, y])
        hs.append(np.r_[a.T, [[0.0, 0.0, 1.0]]])
    return SampledMotion(np.array(hs), centre=g.centre)


def test_a_sampled_global_motion_answers_like_the_global_motion():
    g = GlobalMotion((12.0, -5.0), (4.0, 2.0), 0.06, 0.04, _centre())
    s = _as_sampled(g)
    # the path bends between samples (acceleration, rotation): a few hundredths of a pixel
    assert s.end_point_error_px(g, W, H) < 0.02
    assert g.end_point_error_px(s, W, H) < 0.02
    assert s.max_displacement_px(W, H) == pytest.approx(g.max_displacement_px(W, H), abs=0.05)
    # and is not trivially close to nothing
    assert s.end_point_error_px(GlobalMotion(centre=g.centre), W, H) > 3


def test_event_gain_of_the_true_path(sample):
    m = SampledMotion(sample.motion)
    gain, n = event_gain(m, sample.events, sample.exposure)
    assert n == len(sample.events.within(sample.exposure))
    assert gain > 1.2
    assert event_gain(GlobalMotion(), sample.events, sample.exposure)[0] == pytest.approx(1.0)
    m2 = m.with_evidence(sample.events, sample.exposure)
    assert m2.confidence == pytest.approx(gain) and m2.events == n
    assert m2.homographies is not None and np.array_equal(m2.homographies, m.homographies)


def test_sequences_record_each_exposure_relative_to_its_own_middle():
    """With several exposures the path's reference is the middle of the whole span, not of
    each exposure: every recorded path must still be the identity at its own middle, and
    carry the middle sharp frame to the others."""
    seq = make_sequence(texture(200, 260, seed=4), n=2, size=(96, 72), exposure_us=10_000,
                        frames=2, rng=np.random.default_rng(2),
                        sensor=SensorConfig.clean(0.2),
                        motion=MotionRanges(translation_px=20, rotation_deg=2, scale=0.03,
                                            perspective=0.0))
    assert seq.motion.shape == (2, 33, 3, 3)
    np.testing.assert_allclose(seq.motion[:, 16], np.broadcast_to(np.eye(3), (2, 3, 3)),
                               atol=1e-9)
    inner = (slice(12, -12), slice(12, -12))
    for k in range(2):
        m = SampledMotion(seq.motion[k])
        op = BlurOperator(m, 96, 72)
        warped = op.warp(op.pad_frame(seq.sharp[k, 2]), [0.0, 1.0]).numpy()[:, 0]
        assert psnr(warped[0][inner], seq.sharp[k, 0][inner]) > 38
        assert psnr(warped[1][inner], seq.sharp[k, 4][inner]) > 38


@pytest.mark.parametrize("bad", [np.zeros((1, 3, 3)), np.zeros((4, 2, 3)),
                                 np.full((3, 3, 3), np.nan)])
def test_bad_homographies_are_refused(bad):
    with pytest.raises(InputError):
        SampledMotion(bad)


def test_fractions_must_match_and_increase():
    hs = np.broadcast_to(np.eye(3), (3, 3, 3))
    with pytest.raises(InputError, match="fractions"):
        SampledMotion(hs, fractions=[0.0, 1.0])
    with pytest.raises(InputError, match="fractions"):
        SampledMotion(hs, fractions=[0.0, 0.5, 0.5])
