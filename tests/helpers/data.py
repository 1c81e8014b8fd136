"""Paths and small synthetic data the tests share."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

#: the repository's root
ROOT = Path(__file__).resolve().parents[2]
#: real recordings and images beside the repo (never copied into it)
SHARED = ROOT.parent / "shared" / "data"

needs_shared = pytest.mark.skipif(not SHARED.exists(), reason="../shared/data is absent")


def random_stream(rng, n=5000, width=40, height=30, t_max=100_000):
    from trmd_cli.events import make_stream

    t = np.sort(rng.integers(0, t_max, n))
    return make_stream(rng.integers(0, width, n), rng.integers(0, height, n), t,
                       rng.integers(0, 2, n), width, height)


def texture(h: int = 200, w: int = 260, seed: int = 0) -> np.ndarray:
    """A smooth random texture in [0.05, 0.95] with edges at several scales."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma in (1.5, 4.0, 10.0):
        layer = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
        img += (layer - layer.mean()) / (layer.std() + 1e-6)
    img = (img - img.min()) / (img.max() - img.min())
    return (0.05 + 0.9 * img).astype(np.float32)


def shifted(img: np.ndarray, dx: float) -> np.ndarray:
    """``img`` translated right by ``dx`` px (sub-pixel, bilinear)."""
    import cv2

    m = np.array([[1, 0, dx], [0, 1, 0]], np.float32)
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT101)


def random_events(rng, n=3000, width=64, height=48, t0=1_000, span=5_000_000):
    """(t µs sorted, x, y, p ±1) of ``n`` random events on a ``width``×``height`` sensor."""
    t = np.sort(rng.integers(t0, t0 + span, n)).astype(np.int64)
    return (t, rng.integers(0, width, n), rng.integers(0, height, n),
            np.where(rng.integers(0, 2, n) == 1, 1, -1))


def assert_events(stream, t, x, y, p) -> None:
    """``stream`` holds exactly these events (t in µs)."""
    np.testing.assert_array_equal(stream.t, t)
    np.testing.assert_array_equal(stream.x, x)
    np.testing.assert_array_equal(stream.y, y)
    np.testing.assert_array_equal(stream.p, p)
