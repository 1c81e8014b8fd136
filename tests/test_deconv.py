"""The motion-aware blur model, its exact adjoint, its inverse (anchored to EDI, robust to
what the motion does not explain), and the guard against EDI."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
import torch

from trmd_cli import deconv
from trmd_cli.deconv import (
    ANCHOR_CONTRAST,
    ANCHOR_DARK_GAIN,
    NOISE_SCALE,
    BlurOperator,
    DeconvConfig,
    anchor_gain,
    change_agreement,
    change_of_log,
    data_weights,
    deconvolve,
    fit_contrast,
    guard_weights,
    noise_level,
    tile_gains,
)
from trmd_cli.errors import InputError
from trmd_cli.events import EventStream, Exposure
from trmd_cli.methods import EdiMethod, MotionMethod
from trmd_cli.metrics import psnr
from trmd_cli.motion import GlobalMotion, SampledMotion, estimate_motion
from trmd_cli.oracle import TruePathMethod
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample

from .helpers.data import SHARED, needs_shared, shifted, texture

W, H = 80, 60
MOTION = GlobalMotion((10.0, 4.0), (8.0, -6.0), 0.02, 0.01, ((W - 1) / 2, (H - 1) / 2))


def _seen(op: BlurOperator, big: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A canvas frame (Hp, Wp) through ``op``: (B, the sensor's part of the frame)."""
    blurry = op.apply(torch.from_numpy(big)[None])[0].numpy()
    return blurry, big[op.pad:op.pad + H, op.pad:op.pad + W]


def test_adjoint_is_exact():
    op = BlurOperator(MOTION, W, H, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    x = torch.rand((2, *op.canvas), generator=g, dtype=torch.float64)
    y = torch.rand((2, H, W), generator=g, dtype=torch.float64)
    lhs = float((op.apply(x) * y).sum())
    rhs = float((x * op.adjoint(y)).sum())
    assert abs(lhs - rhs) <= 1e-10 * abs(lhs)


def test_constant_frame_blurs_to_itself():
    op = BlurOperator(MOTION, W, H)
    x = torch.full((1, *op.canvas), 0.4)
    assert torch.allclose(op.apply(x), torch.full((1, H, W), 0.4), atol=1e-6)


def test_operator_is_the_mean_of_the_warped_frames():
    """The sparse ``A`` sums the same bilinear stencils as ``grid_sample`` does per instant."""
    op = BlurOperator(MOTION, W, H, dtype=torch.float64)
    x = torch.rand((1, *op.canvas), generator=torch.Generator().manual_seed(2),
                   dtype=torch.float64)
    expected = op.warp(x).mean(0)
    assert torch.allclose(op.apply(x), expected, atol=1e-12)


def test_known_blur_is_undone_with_exact_motion():
    """Noise-free blur of a blocky pattern by the same model: the TV-regularised inverse
    recovers the interior (what was in view all the exposure) to > 40 dB (measured 41.2 dB;
    blurry: 18 dB)."""
    op = BlurOperator(MOTION, W, H)
    hp, wp = op.canvas
    rng = np.random.default_rng(0)
    big = np.kron(rng.uniform(0.1, 0.9, (hp // 8 + 1, wp // 8 + 1)),
                  np.ones((8, 8)))[:hp, :wp].astype(np.float32)
    blurry, sharp = _seen(op, big)
    d = deconvolve(blurry, MOTION, DeconvConfig(penalty=3e-5, huber=1e-3, rounds=8,
                                                iterations=80))
    out = d.frames([0.5])[0]
    inner = (slice(6, -6), slice(8, -8))
    assert psnr(blurry[inner], sharp[inner]) < 20
    assert psnr(out[inner], sharp[inner]) > 40
    # the other instants are the middle frame carried along the motion
    late = d.frames([1.0])[0]
    shifted = op.warp(torch.from_numpy(big)[None], [1.0])[0, 0].numpy()
    assert psnr(late[inner], shifted[inner]) > 36


def test_noise_level_of_white_noise():
    rng = np.random.default_rng(1)
    img = (0.5 + 0.01 * rng.standard_normal((200, 200))).astype(np.float32)
    assert noise_level(img) == pytest.approx(0.01, rel=0.1)


def test_noise_level_ignores_planes():
    """The 3×3 mask annihilates any plane: a steep ramp adds nothing to the noise."""
    ys, xs = np.mgrid[0:200, 0:200]
    ramp = (0.1 + 0.003 * xs + 0.001 * ys).astype(np.float32)
    assert noise_level(ramp) == pytest.approx(0.0, abs=1e-6)
    noise = 0.01 * np.random.default_rng(2).standard_normal((200, 200))
    assert noise_level((ramp + noise).astype(np.float32)) == pytest.approx(0.01, rel=0.1)


def test_data_weights_against_the_residual_floor():
    """Residual at B's noise (σ = 0.01) everywhere but a block 5× higher: weight 1 away from
    the block, 0 inside it. The same high residual everywhere — a motion that explains B
    nowhere — is judged against B's noise, not against itself: weight 0 everywhere."""
    rng = np.random.default_rng(3)
    blurry = (0.5 + 0.01 * rng.standard_normal((60, 80))).astype(np.float32)
    res = (0.01 * rng.standard_normal((60, 80))).astype(np.float32)
    res[20:40, 30:50] *= 5
    w = data_weights(res, blurry, (1.3, 2.2), window_px=9)
    assert w[25:35, 35:45].max() == 0.0
    far = np.ones_like(w, bool)
    far[10:50, 20:60] = False
    assert w[far].mean() > 0.97
    w = data_weights(5 * res, blurry, (1.3, 2.2), window_px=9)
    assert w.max() == 0.0


def test_anchor_fills_what_the_blur_erased():
    """A 16 px horizontal sweep averages a 16 px period away: B holds none of it, so the
    deconvolution alone cannot bring it back (17 dB, as blurry); anchored to a noisy reading
    of the frame (EDI's part; 34 dB) it comes back from the anchor and the rest from B, better
    than either (measured 37.6 dB)."""
    m = GlobalMotion((16.0, 0.0), centre=((W - 1) / 2, (H - 1) / 2))
    op = BlurOperator(m, W, H)
    hp, wp = op.canvas
    ys, xs = np.mgrid[0:hp, 0:wp].astype(np.float32)
    big = (0.5 + 0.2 * np.sin(2 * np.pi * xs / 16) + 0.1 * np.cos(2 * np.pi * ys / 23))
    big = big.astype(np.float32)
    blurry, sharp = _seen(op, big)
    noisy = sharp + 0.02 * np.random.default_rng(0).standard_normal(sharp.shape)
    noisy = noisy.astype(np.float32)
    inner = (slice(4, -4), slice(20, -20))
    alone = deconvolve(blurry, m, start=blurry).frames([0.5])[0]
    # α set for this anchor's noise, not the default's DAVIS-like EDI error
    anchored = deconvolve(blurry, m, DeconvConfig(anchor=0.01), start=blurry,
                          anchor=noisy).frames([0.5])[0]
    assert psnr(alone[inner], sharp[inner]) < 20
    assert psnr(anchored[inner], sharp[inner]) > psnr(noisy[inner], sharp[inner]) + 2


def test_anchor_gain_is_the_relative_error_below_the_reference():
    """α ∝ 1 / (E's error)², E's error ∝ E: (0.3 / 0.15)² = 4 on a flat 0.15, 1 above the
    reference, :data:`ANCHOR_DARK_GAIN` from a tenth of it down; colour channels averaged."""
    flat = np.ones((20, 30), np.float32)
    assert np.allclose(anchor_gain(0.15 * flat, 0.3), 4.0)
    assert np.allclose(anchor_gain(0.6 * flat, 0.3), 1.0)
    assert np.allclose(anchor_gain(0.003 * flat, 0.3), ANCHOR_DARK_GAIN)
    assert np.allclose(anchor_gain(np.zeros((20, 30)), 0.3), ANCHOR_DARK_GAIN)
    rgb = np.stack([0.05 * flat, 0.1 * flat, 0.15 * flat], -1)
    assert np.allclose(anchor_gain(rgb, 0.3), 9.0)


def test_dark_regions_follow_the_anchor_they_can_trust():
    """A 16 px sweep over a scene half dark (0.02–0.06), half bright (0.4–0.8); B with noise of
    σ = 0.005, the anchor with a relative error of 10 % (as EDI's, quantised in log). The noise
    at the sweep's spectral zeros is what a uniform α leaves in the dark half (measured RMS
    error 0.0065, the anchor's own 0.0037); α grown as the anchor's error shrinks halves it
    (0.0031) and leaves the bright half as it was (0.0160 → 0.0162)."""
    m = GlobalMotion((16.0, 0.0), centre=((W - 1) / 2, (H - 1) / 2))
    op = BlurOperator(m, W, H)
    hp, wp = op.canvas
    tex = texture(hp, wp, seed=3).astype(np.float32)
    left = np.arange(wp)[None, :] < wp // 2
    big = np.where(left, 0.02 + 0.04 * tex, 0.4 + 0.4 * tex).astype(np.float32)
    blurry, sharp = _seen(op, big)
    rng = np.random.default_rng(0)
    blurry = (blurry + 0.005 * rng.standard_normal(blurry.shape)).astype(np.float32)
    anchor = (sharp * np.exp(0.1 * rng.standard_normal(sharp.shape))).astype(np.float32)
    dark, bright = (slice(4, -4), slice(8, W // 2 - 12)), (slice(4, -4), slice(W // 2 + 12, -8))

    def rms(cfg: DeconvConfig, where) -> float:
        f = deconvolve(blurry, m, cfg, start=anchor, anchor=anchor).frames([0.5])[0]
        return float(np.sqrt(np.mean((f[where] - sharp[where]) ** 2)))

    uniform, relative = DeconvConfig(anchor_reference=None), DeconvConfig(anchor_reference=0.3)
    assert rms(relative, dark) < 0.6 * rms(uniform, dark)
    assert rms(relative, dark) < float(np.sqrt(np.mean((anchor - sharp)[dark] ** 2)))
    assert abs(rms(relative, bright) - rms(uniform, bright)) < 0.05 * rms(uniform, bright)


def test_guard_trusts_an_exact_motion_and_drops_a_wrong_one():
    """B blurred by the model itself (+ σ = 0.005): along the exact motion B is explained
    everywhere and the guard keeps the deconvolution (measured weight 0.996); along a motion
    with velocity turned by 90° it is not (measured 0.06)."""
    op = BlurOperator(MOTION, W, H)
    hp, wp = op.canvas
    rng = np.random.default_rng(5)
    big = texture(hp, wp, seed=3).astype(np.float32)
    blurry, sharp = _seen(op, big)
    blurry = (blurry + 0.005 * rng.standard_normal((H, W))).astype(np.float32)
    edi = (sharp + 0.03 * rng.standard_normal(sharp.shape)).astype(np.float32)
    # α near B's noise variance over the anchor's, (0.005 / 0.03)²
    cfg = DeconvConfig(anchor=0.01)
    d = deconvolve(blurry, MOTION, cfg, start=edi, anchor=edi)
    assert guard_weights(d.data_weight, 2.0).mean() > 0.95
    assert psnr(d.frames([0.5])[0], sharp) > psnr(edi, sharp) + 3
    turned = GlobalMotion((4.0, 10.0), centre=MOTION.centre)
    d = deconvolve(blurry, turned, cfg, start=edi, anchor=edi)
    assert guard_weights(d.data_weight, 2.0).mean() < 0.2
    # no confidence in the motion: nothing is kept
    assert guard_weights(np.ones((H, W), np.float32), 1.05).max() == 0.0


def test_guard_keeps_what_the_events_confirm():
    """Where re-blurring does not explain B, the events' change test can still keep the
    deconvolution (B's noise, not the motion, failed the residual test); where both reject
    it, EDI stays; without the events' reading the guard is the residual test's alone."""
    dw = np.ones((H, W), np.float32)
    dw[10:30, 10:40] = 0.0
    plain = guard_weights(dw, 2.0)
    assert plain[15:25, 15:35].max() == 0.0 and plain[40:, 50:].min() == 1.0
    agree = np.ones((H, W), np.float32)
    assert guard_weights(dw, 2.0, events_agree=agree).min() == 1.0
    agree[12:28, 12:38] = 0.0
    both = guard_weights(dw, 2.0, events_agree=agree)
    assert both[15:25, 15:35].max() == 0.0
    # the global gain's and the tiles' verdicts still apply on top
    assert guard_weights(dw, 1.05, events_agree=np.ones((H, W), np.float32)).max() == 0.0


@needs_shared
def test_real_frame_kept_where_the_events_confirm_the_motion():
    """esl-cups frame 000017: re-blurring explains 86 % of it, the APS's noise on the white cup
    and the lit table failing the residual test where the motion is right; with the events'
    change test the deconvolution is kept on 97 % (measured), and so the frames there are
    not EDI's, whose events' speckle shows at the exposure's ends."""
    from trmd_cli.read.base import ReadOptions
    from trmd_cli.read.inputs import open_inputs

    base = SHARED / "real" / "esl-cups"
    with open_inputs([base / "images", base / "mat"], ReadOptions()) as ins:
        item = next(iter(ins.source.subset([3])))
    assert item.frame.name == "000017"
    b, ev, ex = item.frame.image, item.events, item.frame.exposure
    edi = EdiMethod(contrast=0.444)(b, ev, ex)
    res = deconv.motion_deblur(b, ev, ex, np.linspace(0.0, 1.0, 7), edi.frames, edi.frames[3], None,
                               contrast=0.444)
    assert not res.notes, res.notes
    assert res.weight.mean() > 0.93, res.weight.mean()


def test_stop_ends_the_solve_with_the_frame_so_far():
    """``stop`` is asked before each reweighted round (1, then 2 of 3) with the weights the
    frame so far earns; True there gives that frame, re-blurred, with exactly those weights
    (the residual of its own re-blur); never True gives the solve without ``stop``, bit for
    bit."""
    op = BlurOperator(MOTION, W, H)
    hp, wp = op.canvas
    big = texture(hp, wp, seed=3).astype(np.float32)
    blurry, sharp = _seen(op, big)
    edi = (sharp + 0.03 * np.random.default_rng(5).standard_normal(sharp.shape)).astype(
        np.float32)
    cfg = DeconvConfig(anchor=0.01)
    full = deconvolve(blurry, MOTION, cfg, start=edi, anchor=edi)
    asked, seen = [], []

    def never(k, weights):
        asked.append(k)
        return False

    same = deconvolve(blurry, MOTION, cfg, start=edi, anchor=edi, stop=never)
    assert asked == [1, 2] and same.rounds == full.rounds == 3
    assert np.array_equal(same.middle.numpy(), full.middle.numpy())
    assert np.array_equal(same.data_weight, full.data_weight)

    def first(k, weights):
        seen.append(weights.copy())
        return True

    early = deconvolve(blurry, MOTION, cfg, start=edi, anchor=edi, stop=first)
    assert early.rounds == 1 and len(seen) == 1
    assert np.array_equal(early.data_weight, seen[0])
    again = op.apply(early.middle)[0].numpy()
    np.testing.assert_allclose(early.reblurred, again, atol=1e-6)
    np.testing.assert_allclose(data_weights(again - blurry, blurry, cfg.outlier, cfg.window_px),
                               seen[0], atol=1e-5)
    # one round is not the solve: the frame differs from the three rounds'
    assert not np.allclose(early.middle.numpy(), full.middle.numpy(), atol=1e-4)


def test_tile_gains_tell_the_direction_of_time():
    """Dots moving along MOTION, each recording 60 events: carried back by MOTION their events
    collapse (gain > 1.5 per tile); by the time-reversed motion — which blurs B exactly as
    MOTION does — they spread to twice the streak (gain < 1); by no motion, gain 1 exactly."""
    rng = np.random.default_rng(0)
    x0, y0 = rng.uniform(0, W - 1, 60), rng.uniform(0, H - 1, 60)
    u = rng.uniform(0, 1, (60, 60))
    x, y = MOTION.positions(u, x0[:, None], y0[:, None])
    x, y, u = np.rint(x).ravel(), np.rint(y).ravel(), u.ravel()
    ok = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    x, y, u = x[ok], y[ok], u[ok]
    gains = {}
    for name, m in (("true", MOTION),
                    ("reversed", GlobalMotion((-10.0, -4.0), (8.0, -6.0), 0.02, 0.01,
                                              MOTION.centre)),
                    ("still", GlobalMotion(centre=MOTION.centre))):
        g = tile_gains(m, x, y, u, W, H)
        gains[name] = g[np.isfinite(g)]
        assert gains[name].size >= 8
    assert gains["true"].min() > 1.5
    assert gains["reversed"].max() < 1.0 and np.median(gains["reversed"]) < 0.8
    np.testing.assert_allclose(gains["still"], 1.0, rtol=1e-9)


def _sample(seed, foreground):
    motion = MotionRanges(translation_px=14, rotation_deg=0.5, scale=0.01, perspective=0,
                          curvature=0.2, foreground_prob=1.0 if foreground else 0.0,
                          max_layers=1, layer_translation_px=25, layer_size=(0.4, 0.5))
    return make_sample(texture(300, 400, seed=seed), size=(160, 120),
                       rng=np.random.default_rng(seed), motion=motion,
                       sensor=SensorConfig.clean(0.2), read_noise=0.003)


def _seq(frames, sharp):
    return float(np.mean([psnr(a, b) for a, b in zip(frames, sharp)]))


def test_independent_mover_falls_back_to_edi():
    """A foreground patch moving on its own: the output is never worse than EDI, middle or
    sequence (measured EDI 29.97 / 28.95, motion 30.76 / 29.83 dB: the patch's tiles dispute
    the global estimate, and the background's motion is deconvolved where it predicts the
    events); along the true camera path the background is trusted while the patch is not
    (measured 32.43 / 32.23 dB)."""
    s = _sample(4, foreground=True)
    edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    mot = MotionMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    true = TruePathMethod(motion=SampledMotion(s.motion), contrast=s.contrast)(
        s.blurry, s.events, s.exposure)
    p_edi = psnr(edi.frames[3], s.sharp[3])
    p_mot = psnr(mot.frames[3], s.sharp[3])
    assert p_mot >= p_edi - 0.1, (p_mot, p_edi)
    assert _seq(mot.frames, s.sharp) >= _seq(edi.frames, s.sharp) - 0.1
    assert psnr(true.frames[3], s.sharp[3]) > p_edi + 1.5
    assert _seq(true.frames, s.sharp) > _seq(edi.frames, s.sharp) + 1.5


def test_change_of_log_counts_the_events():
    """c times each pixel's signed event count in the window; a hot pixel's and the events
    outside the window left out."""
    ev = EventStream(np.array([1, 1, 1, 3, 0, 2], np.uint16),
                     np.array([0, 0, 0, 1, 1, 0], np.uint16),
                     np.array([5, 6, 7, 8, 9, 50], np.int64),
                     np.array([1, 1, -1, -1, 1, 1], np.int8), 4, 2)
    hot = np.zeros((2, 4), bool)
    hot[1, 0] = True
    got = change_of_log(ev, Exposure(0, 20), 4, 2, 0.25, hot)
    expected = np.zeros((2, 4), np.float32)
    expected[0, 1] = 0.25  # +1 +1 −1
    expected[1, 3] = -0.25
    assert np.array_equal(got, expected)


class _Ends:
    """Stands for a deconvolution: its frames at the exposure's two ends."""

    def __init__(self, first, last):
        self._ends = np.stack([first, last]).astype(np.float32)

    def frames(self, fractions):
        assert list(fractions) == [0.0, 1.0]
        return self._ends


def test_change_agreement_where_the_motion_predicts_the_events():
    """Frames at the ends whose log ratio is exactly the events' change: weight 1. A block
    whose predicted change is 0.3 off (1.5 thresholds of 0.2): weight 0 inside it, 1 well
    away from it (more than three σ beyond its edge)."""
    rng = np.random.default_rng(5)
    first = rng.uniform(0.2, 0.8, (60, 80))
    change = rng.normal(0.0, 0.3, (60, 80)).astype(np.float32)
    last = (first + 0.02) * np.exp(change) - 0.02  # the ±0.02 of the log's offset
    assert change_agreement(_Ends(first, last), change, 0.2).min() > 0.999
    wrong = change.copy()
    wrong[20:40, 30:50] += 0.3
    w = change_agreement(_Ends(first, last), wrong, 0.2)
    assert w[25:35, 35:45].max() == 0.0
    far = np.ones_like(w, bool)
    far[6:54, 16:64] = False
    assert w[far].min() > 0.99


def test_change_agreement_rejects_a_motion_off_by_a_pixel_or_two():
    """A texture translated 6 px over the exposure, its events' change whole thresholds
    (c = 0.2): frames carried along the right motion keep weight 1 everywhere; along 9 px
    (1.5 px off at each end) nearly nothing is kept (measured 0.02 on the interior), though
    the misprediction is ± the texture's gradient and its mean over a neighbourhood is near
    zero."""
    img = texture(60, 80, seed=3)

    def log(a):
        return np.log(np.maximum(a, 0.0) + 0.02)

    change = log(shifted(img, 3.0)) - log(shifted(img, -3.0))
    change = (np.round(change / 0.2) * 0.2).astype(np.float32)
    right = change_agreement(_Ends(shifted(img, -3.0), shifted(img, 3.0)), change, 0.2)
    assert right[8:-8, 8:-8].min() > 0.99
    off = change_agreement(_Ends(shifted(img, -4.5), shifted(img, 4.5)), change, 0.2)
    assert off[8:-8, 8:-8].mean() < 0.1


def _counted(counts: np.ndarray) -> EventStream:
    """Events whose signed count at each pixel is ``counts`` (H, W) whole numbers, one
    microsecond apart inside ``Exposure(0, 10**6)``."""
    h, w = counts.shape
    pix = np.repeat(np.arange(h * w), np.abs(counts).reshape(-1))
    pol = np.sign(counts.reshape(-1))[pix].astype(np.int8)
    return EventStream((pix % w).astype(np.uint16), (pix // w).astype(np.uint16),
                       np.arange(len(pix), dtype=np.int64), pol, w, h)


def test_fit_contrast_reads_the_threshold_the_frames_imply():
    """Frames at the ends whose log ratio is c times the events' count: the slope is c (both
    sides smoothed alike); ends unrelated to the events give no fit (they correlate nowhere),
    and neither does a slope outside [near/2, 2·near]."""
    rng = np.random.default_rng(8)
    counts = np.rint(rng.normal(0.0, 2.0, (60, 80))).astype(np.int64)
    ev = _counted(counts)
    first = rng.uniform(0.2, 0.8, (60, 80))
    ones = np.ones((60, 80), np.float32)
    for c in (0.15, 0.32):
        last = (first + 0.02) * np.exp(c * counts) - 0.02
        got = fit_contrast(_Ends(first, last), ev, Exposure(0, 10**6), ones)
        assert got == pytest.approx(c, rel=1e-4)
        assert fit_contrast(_Ends(first, last), ev, Exposure(0, 10**6), ones,
                            near=0.5 * c - 0.01) is None
    unrelated = rng.uniform(0.2, 0.8, (60, 80))
    assert fit_contrast(_Ends(first, unrelated), ev, Exposure(0, 10**6), ones) is None
    # where re-blurring does not explain B nothing is read
    last = (first + 0.02) * np.exp(0.2 * counts) - 0.02
    assert fit_contrast(_Ends(first, last), ev, Exposure(0, 10**6), 0 * ones) is None


def test_estimated_threshold_is_refitted_for_edis_frames():
    """A DAVIS-like sensor (mean threshold 0.25): the search says 0.277, the deconvolution
    implies 0.253 (measured), and EDI's frames blended in by the motion method use that; a c
    the user gives is kept."""
    motion = MotionRanges(translation_px=14, rotation_deg=0.5, scale=0.01, perspective=0,
                          curvature=0.2, foreground_prob=0.0, max_layers=1)
    s = make_sample(texture(300, 400, seed=6), size=(160, 120),
                    rng=np.random.default_rng(6), motion=motion, sensor=SensorConfig())
    est = MotionMethod()(s.blurry, s.events, s.exposure)
    assert est.contrast_estimated and est.fallback_contrast is not None
    assert abs(np.log(est.fallback_contrast / s.contrast)) < 0.05
    assert abs(np.log(est.fallback_contrast / s.contrast)) < \
        abs(np.log(est.contrast / s.contrast)) - 0.05
    given = MotionMethod(contrast=est.contrast)(s.blurry, s.events, s.exposure)
    assert given.fallback_contrast is None


def test_background_motion_when_the_estimate_follows_a_mover(monkeypatch):
    """A foreground patch moving on its own, which the global estimate follows: its tiles
    dispute it, and the motion of the tiles that move together is deconvolved where it
    predicts the events (measured: EDI 29.20 / 28.59, motion 31.67 / 31.73 dB, middle /
    sequence; with EDI's frames alone before). That is the only deconvolution: the global
    estimate's, which explains 10 % of B, is not solved at all."""
    motion = MotionRanges(translation_px=14, rotation_deg=0.5, scale=0.01, perspective=0,
                          curvature=0.2, foreground_prob=1.0, max_layers=1,
                          layer_translation_px=30, layer_size=(0.3, 0.45))
    s = make_sample(texture(300, 400, seed=6), size=(160, 120), rng=np.random.default_rng(6),
                    motion=motion, sensor=SensorConfig.clean(0.2), read_noise=0.003)
    edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    solved, original = [], deconv.deconvolve

    def spy(*args, **kwargs):
        solved.append(original(*args, **kwargs))
        return solved[-1]

    monkeypatch.setattr("trmd_cli.deconv.deconvolve", spy)
    mot = MotionMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    monkeypatch.undo()
    assert any("tiles that move together" in note for note in mot.notes), mot.notes
    assert psnr(mot.frames[3], s.sharp[3]) > psnr(edi.frames[3], s.sharp[3]) + 1.5
    assert "tiles move otherwise than the global motion" in mot.notes[0], mot.notes
    assert [d.rounds for d in solved] == [3]
    assert _seq(mot.frames, s.sharp) > _seq(edi.frames, s.sharp) + 2
    # a colour frame takes the same way, its unscaled channel as well restored
    rgb = np.stack([s.blurry, 0.9 * s.blurry, 0.8 * s.blurry], -1).astype(np.float32)
    col = MotionMethod(contrast=s.contrast)(rgb, s.events, s.exposure)
    assert col.frames.shape == (7, 120, 160, 3)
    assert "tiles that move together" in col.notes[0], col.notes
    assert psnr(col.frames[3, ..., 0], s.sharp[3]) > psnr(edi.frames[3], s.sharp[3]) + 1.5


@pytest.fixture
def no_helper():
    """No helper process: the tiles vote in this process (where a mock can count them), not
    in a helper an earlier test of this worker may have started."""
    from trmd_cli import helper_process

    helper_process.allow(False)
    yield
    helper_process.allow(True)


def test_disputed_frame_without_a_background_motion_keeps_the_guarded_global_one(
        monkeypatch, no_helper):
    """A tile disputes the global motion, but no background motion holds: the frame is the
    global motion's guarded deconvolution, exactly as if nothing had disputed it, and the
    tiles vote once. (A small patch whose global motion the guard keeps; the dispute and the
    missing background motion are forced.)"""
    from trmd_cli.motion import tiles

    motion = MotionRanges(translation_px=14, rotation_deg=0.5, scale=0.01, perspective=0,
                          curvature=0.2, foreground_prob=1.0, max_layers=1,
                          layer_translation_px=25, layer_size=(0.15, 0.2))
    s = make_sample(texture(300, 400, seed=0), size=(160, 120), rng=np.random.default_rng(0),
                    motion=motion, sensor=SensorConfig.clean(0.2), read_noise=0.003)
    votes = mock.Mock(wraps=tiles.tile_velocities)
    monkeypatch.setattr(tiles, "tile_velocities", votes)
    monkeypatch.setattr(tiles, "outvoted_tiles", lambda *a, **k: np.ones((120, 160), bool))
    monkeypatch.setattr(tiles, "background_motion", lambda *a, **k: None)
    monkeypatch.setattr(tiles, "disputed_tiles", lambda *a, **k: [(0, 0)])
    disputed = MotionMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    assert votes.call_count == 1
    monkeypatch.setattr(tiles, "disputed_tiles", lambda *a, **k: [])
    plain = MotionMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    assert disputed.notes == plain.notes == ()
    assert np.array_equal(disputed.frames, plain.frames)
    edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    assert psnr(plain.frames[3], s.sharp[3]) > psnr(edi.frames[3], s.sharp[3]) + 1.0


def test_exact_motion_is_trusted_without_movers():
    """The same scene without the patch: along the true path the guard keeps the
    deconvolution nearly everywhere (measured EDI 31.32 / 29.92, true path 36.62 / 37.37 dB,
    middle / sequence)."""
    s = _sample(4, foreground=False)
    edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    true = TruePathMethod(motion=SampledMotion(s.motion), contrast=s.contrast)(
        s.blurry, s.events, s.exposure)
    assert psnr(true.frames[3], s.sharp[3]) > psnr(edi.frames[3], s.sharp[3]) + 4
    assert _seq(true.frames, s.sharp) > _seq(edi.frames, s.sharp) + 5


def test_small_motion_with_a_low_gain_is_blended_not_dropped():
    """About 3 px of camera motion: the estimate sharpens its events little (a gain between
    1.05 and 1.1, where the gain's trust is partial) though it is right to half a pixel. The
    deconvolution is blended in by that trust, not dropped for explaining "too little" of the
    frame (measured: gain 1.08, the motion method +3.1 / +5.6 dB over EDI, middle / sequence,
    with OpenCV 5's warps in the simulator and +3.7 / +6.2 with OpenCV 4's; before, EDI's)."""
    motion = MotionRanges(translation_px=7, rotation_deg=0.1, scale=0.002, perspective=0,
                          curvature=0.2)
    s = make_sample(texture(300, 400, seed=4), size=(160, 120), rng=np.random.default_rng(4),
                    motion=motion, sensor=SensorConfig.clean(0.2), read_noise=0.003)
    est = estimate_motion(s.events, s.exposure)
    assert 1.05 < est.confidence < 1.1, est.confidence  # the case this test is about
    edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    mot = MotionMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    assert not mot.notes, mot.notes
    assert psnr(mot.frames[3], s.sharp[3]) > psnr(edi.frames[3], s.sharp[3]) + 1.5
    assert _seq(mot.frames, s.sharp) > _seq(edi.frames, s.sharp) + 1.0


def test_too_few_events_give_edi_with_a_note():
    rng = np.random.default_rng(0)
    blurry = rng.uniform(0.2, 0.8, (H, W)).astype(np.float32)
    n = 50
    ev = EventStream(rng.integers(0, W, n).astype(np.uint16),
                     rng.integers(0, H, n).astype(np.uint16),
                     np.sort(rng.integers(0, 1000, n)).astype(np.int64),
                     rng.choice([-1, 1], n).astype(np.int8), W, H)
    ex = Exposure(0, 1000)
    est = MotionMethod(contrast=0.2)(blurry, ev, ex)
    ref = EdiMethod(contrast=0.2)(blurry, ev, ex)
    assert np.array_equal(est.frames, ref.frames)
    assert any("events" in note for note in est.notes)
    empty = EventStream.empty(W, H)
    est = MotionMethod(contrast=0.2)(blurry, empty, ex)
    assert np.allclose(est.frames, blurry[None]) and est.notes


def test_binned_data_is_refused():
    with pytest.raises(InputError, match="event times"):
        MotionMethod().from_bins(np.zeros((4, 5), np.float32), np.zeros((6, 4, 5)))


def test_anchor_weight_follows_the_threshold():
    """EDI's error is one event step: α goes as 1/c², equal to the given α at c = 0.3."""
    cfg = DeconvConfig(anchor=0.003)
    assert cfg.for_contrast(ANCHOR_CONTRAST).anchor == pytest.approx(0.003)
    assert cfg.for_contrast(0.6).anchor == pytest.approx(0.003 / 4)
    assert cfg.for_contrast(None) is cfg


def test_prior_weight_follows_the_noise():
    """λ goes with B's noise σ up to noise_ref and with σ² above it, where α does too; equal
    to the given λ and α at σ = noise_ref, within NOISE_SCALE."""
    cfg = DeconvConfig(penalty=2e-4, anchor=0.003, noise_ref=0.005)
    assert cfg.for_noise(0.005).penalty == pytest.approx(2e-4)
    assert cfg.for_noise(0.005).anchor == pytest.approx(0.003)
    assert cfg.for_noise(0.0025).penalty == pytest.approx(1e-4)
    assert cfg.for_noise(0.0025).anchor == pytest.approx(0.003)
    assert cfg.for_noise(0.01).penalty == pytest.approx(8e-4)
    assert cfg.for_noise(0.01).anchor == pytest.approx(0.012)
    assert cfg.for_noise(0.0).penalty == pytest.approx(2e-4 * NOISE_SCALE[0])
    assert cfg.for_noise(1.0).penalty == pytest.approx(2e-4 * NOISE_SCALE[1])
    assert cfg.for_noise(1.0).anchor == pytest.approx(0.003 * NOISE_SCALE[1])
    assert DeconvConfig(noise_ref=None).for_noise(0.01).penalty == DeconvConfig().penalty


@pytest.mark.parametrize("sigma", [0.01, 0.02])
def test_noisy_frame_deconvolved_better_than_its_anchor(sigma):
    """B with noise of 2× and 4× the reference σ, blurred along an exact motion, anchored to a
    reading of the frame with σ = 0.03 noise (30.6 dB): the deconvolution with the settings
    for the measured noise is better than the anchor (measured 33.8 and 33.1 dB; with λ ∝ σ
    and a fixed α it was 30.4 and 23.1, below the anchor and, at 4×, below B's 24.8)."""
    op = BlurOperator(MOTION, W, H)
    hp, wp = op.canvas
    rng = np.random.default_rng(1)
    big = texture(hp, wp, 1).astype(np.float32)
    blurry, sharp = _seen(op, big)
    blurry = (blurry + sigma * rng.standard_normal(blurry.shape)).astype(np.float32)
    anchor = (sharp + 0.03 * rng.standard_normal(sharp.shape)).astype(np.float32)
    cfg = DeconvConfig().for_noise(noise_level(blurry))
    out = deconvolve(blurry, MOTION, cfg, start=anchor, anchor=anchor).frames([0.5])[0]
    inner = (slice(6, -6), slice(6, -6))
    assert psnr(out[inner], sharp[inner]) > psnr(anchor[inner], sharp[inner]) + 0.5


def test_a_partly_trusted_gain_is_trusted_whole_when_its_halves_agree(monkeypatch):
    import trmd_cli.motion as motion_pkg

    asked = []

    def spread(value):
        def split(events, exposure, motion, hot_mask=None):
            asked.append(motion.confidence)
            return value
        return split

    m = GlobalMotion((2.0, 1.0), centre=(10.0, 10.0), confidence=1.07)
    monkeypatch.setattr(motion_pkg, "split_agreement", spread(0.08))
    assert deconv.trusted_gain(m, None, None) == 1.1  # 0.08 px ≤ SPLIT_TRUST_PX: whole trust
    monkeypatch.setattr(motion_pkg, "split_agreement", spread(0.25))
    assert deconv.trusted_gain(m, None, None) == 1.07  # halves apart: the gain's own
    monkeypatch.setattr(motion_pkg, "split_agreement", spread(float("nan")))
    assert deconv.trusted_gain(m, None, None) == 1.07  # nothing to compare: the gain's own
    # full or no trust from the gain alone: the halves are not asked
    for gain in (1.03, 1.05, 1.1, 1.4):
        assert deconv.trusted_gain(GlobalMotion((2.0, 1.0), centre=(10.0, 10.0),
                                                confidence=gain), None, None) == gain
    assert asked == [1.07, 1.07, 1.07]
