"""Ghosts in a network's frames: found where the frames' change disagrees with the events' over
an area, replaced by the middle frame carried by the events; isolated noise events change
nothing."""

from __future__ import annotations

import numpy as np
import pytest

from trmd_cli.errors import ShapeError
from trmd_cli.ghosts import without_ghosts
from trmd_cli.metrics import psnr

N = 3


def _moving_square(shift_per_step: int = 4) -> np.ndarray:
    """(2N+1, 64, 96) frames of a bright square on a grey ground moving right, [0, 1]."""
    frames = np.full((2 * N + 1, 64, 96), 0.3, np.float32)
    for k in range(2 * N + 1):
        x0 = 30 + shift_per_step * (k - N)
        frames[k, 20:44, x0:x0 + 24] = 0.8
    return frames


def _truth_and_change() -> tuple[np.ndarray, np.ndarray]:
    """The moving square and its exact events' change from the middle frame (noise-free
    events, exact c)."""
    truth = _moving_square()
    return truth, np.log(truth) - np.log(truth[N])


def test_a_double_image_is_replaced_by_what_the_events_report():
    truth, change = _truth_and_change()
    # the network's ghost: every frame half its own square, half the middle frame's
    ghosted = 0.5 * truth + 0.5 * truth[N]
    out = without_ghosts(ghosted, change, N)
    np.testing.assert_array_equal(out[N], ghosted[N])
    # frame 0: its square spans columns 18–41, the middle frame's 30–53. Away from their
    # edges (σ = 1.5 px: 4 px is 2.7 σ) the disagreement in log(L + 0.02) is, by hand,
    # where only the middle frame's square is a ghost: |log(0.57 / 0.32)| = 0.577 → weight 1,
    # the carried frame (the ground, 0.3) replaces it whole;
    np.testing.assert_allclose(out[0, 24:40, 46:50], 0.3, atol=1e-3)
    # where frame 0's own square is half there: |log(0.57 / 0.82)| = 0.364 → weight
    # (0.364 − 0.2) / 0.3 = 0.546 of the carried frame's 0.8, the rest the ghosted 0.55
    w = (np.log(0.82 / 0.57) - 0.2) / 0.3
    np.testing.assert_allclose(out[0, 24:40, 22:26], 0.55 + w * 0.25, atol=3e-3)
    # and over the whole frame the ghost is mostly gone
    assert psnr(out[0], truth[0]) > psnr(ghosted[0], truth[0]) + 5  # 22.3 → 28.5 dB


def test_isolated_noise_events_leave_consistent_frames_as_they_are():
    rng = np.random.default_rng(3)
    truth, change = _truth_and_change()
    noisy = change.copy()
    for k in range(2 * N + 1):
        if k == N:
            continue
        # one event of c = 0.3 either way at 0.5 % of the pixels, none beside another
        ys, xs = rng.integers(1, 63, 30), rng.integers(1, 95, 30)
        noisy[k, ys, xs] += rng.choice([-0.3, 0.3], 30)
    out = without_ghosts(truth, noisy, N)
    np.testing.assert_array_equal(out, truth)


def test_colour_frames_share_one_weight_per_pixel():
    truth, change = _truth_and_change()
    ghosted = 0.5 * truth + 0.5 * truth[N]
    gains = np.array([1.0, 0.9, 0.8], np.float32)
    out = without_ghosts(ghosted[..., None] * gains, change, N)
    # each channel is its grey frame scaled: one weight per pixel for the three
    for j in (1, 2):
        np.testing.assert_allclose(out[..., j] / gains[j], out[..., 0], atol=1e-6)
    assert psnr(out[0, ..., 0], truth[0]) > psnr(ghosted[0], truth[0]) + 5


def test_shapes_are_checked():
    truth = _moving_square()
    with pytest.raises(ShapeError, match="2N"):
        without_ghosts(truth[:5], np.zeros((5, 64, 96), np.float32), N)
    with pytest.raises(ShapeError, match="changes"):
        without_ghosts(truth, np.zeros((7, 64, 95), np.float32), N)
