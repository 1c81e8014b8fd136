"""The motion-aware blur model, its exact adjoint, its inverse, and the EDI guard."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from trmd_cli.deconv import BlurOperator, DeconvConfig, deconvolve, noise_level
from trmd_cli.errors import InputError
from trmd_cli.events import EventStream, Exposure
from trmd_cli.methods import EdiMethod, MotionMethod
from trmd_cli.metrics import psnr
from trmd_cli.motion import GlobalMotion
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample

from .helpers.data import texture

W, H = 80, 60
MOTION = GlobalMotion((10.0, 4.0), (8.0, -6.0), 0.02, 0.01, ((W - 1) / 2, (H - 1) / 2))


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
    blurry = op.apply(torch.from_numpy(big)[None])[0].numpy()
    sharp = big[op.pad:op.pad + H, op.pad:op.pad + W]
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


def _sample(seed, foreground):
    motion = MotionRanges(translation_px=14, rotation_deg=0.5, scale=0.01, perspective=0,
                          curvature=0.2, foreground_prob=1.0 if foreground else 0.0,
                          max_layers=1, layer_translation_px=25, layer_size=(0.4, 0.5))
    return make_sample(texture(300, 400, seed=seed), size=(160, 120),
                       rng=np.random.default_rng(seed), motion=motion,
                       sensor=SensorConfig.clean(0.2), read_noise=0.003)


def test_independent_mover_falls_back_to_edi():
    """A foreground patch moving on its own: the output is never worse than EDI."""
    s = _sample(4, foreground=True)
    edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    mot = MotionMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
    p_edi = psnr(edi.frames[3], s.sharp[3])
    p_mot = psnr(mot.frames[3], s.sharp[3])
    assert p_mot >= p_edi - 0.1, (p_mot, p_edi)


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
