"""Contrast maximisation (Gallego et al., CVPR 2018) of a global motion over one exposure.

Events are carried back to the middle of the exposure by a candidate
:class:`~trmd_cli.motion.model.GlobalMotion` and accumulated into an image of warped events
(IWE, bilinear votes by one ``np.bincount`` on a flat index; an event carried outside the
sensor votes nowhere). The right motion makes that image sharpest. The objective is its
variance after a small Gaussian, *divided by* that of the unwarped events (a normalised gain,
as Shiba et al., ECCV 2022, to guard against event collapse), with the zoom and rotation bounded.

Search: a grid over the velocity on a 4× downsampled image, then Nelder–Mead refinement of
translation + acceleration on 2× and of all six parameters at full resolution.
"""

from __future__ import annotations

import math

import numpy as np

from ..events import EventStream, Exposure
from .model import GlobalMotion

__all__ = ["estimate_motion", "warped_image", "MIN_EVENTS", "MotionSearch"]

#: fewer events than this in the window: no estimate (confidence 0)
MIN_EVENTS = 500

from dataclasses import dataclass  # noqa: E402


@dataclass(frozen=True)
class MotionSearch:
    """How far and how finely to search.

    Attributes:
        max_velocity_px: the velocity grid spans ±this, pixels per exposure.
        max_rotation: |ω| bound, radians per exposure.
        max_zoom: |ζ| bound, log scale per exposure.
        rotation_zoom: refine rotation and zoom too (else translation + acceleration only).
        max_events: events used per level (a fixed random subset when there are more).
        seed: the subset's generator seed.
    """

    max_velocity_px: float = 48.0
    max_rotation: float = 0.12
    max_zoom: float = 0.12
    rotation_zoom: bool = True
    max_events: int = 60_000
    seed: int = 0


def _params_to_motion(q: np.ndarray, centre, radius: float, conf: float = 0.0,
                      n: int = 0) -> GlobalMotion:
    return GlobalMotion((float(q[0]), float(q[1])), (float(q[2]), float(q[3])),
                        float(q[4]) / radius, float(q[5]) / radius,
                        (float(centre[0]), float(centre[1])), conf, n)


def warped_image(motion: GlobalMotion, x: np.ndarray, y: np.ndarray, u: np.ndarray,
                 width: int, height: int, scale: float = 1.0) -> np.ndarray:
    """The image of events ``(x, y)`` (pixels) at exposure fractions ``u`` carried to the
    middle by ``motion``, on a grid ``scale`` times coarser: (h, w) float64 vote counts."""
    xm, ym = motion.to_middle(u, x, y)
    w, h = int(math.ceil(width / scale)), int(math.ceil(height / scale))
    return _votes(xm / scale, ym / scale, w, h)


def _votes(xs: np.ndarray, ys: np.ndarray, w: int, h: int) -> np.ndarray:
    x0 = np.floor(xs)
    y0 = np.floor(ys)
    fx, fy = xs - x0, ys - y0
    xi, yi = x0.astype(np.int64), y0.astype(np.int64)
    acc = np.zeros(h * w)
    for ox, oy, wt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                       (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        cx, cy = xi + ox, yi + oy
        ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        acc += np.bincount(cy[ok] * w + cx[ok], weights=wt[ok], minlength=h * w)
    return acc.reshape(h, w)


class _Level:
    """One resolution: the events, the grid, and the unwarped image's variance."""

    def __init__(self, x, y, u, width, height, scale, centre, radius):
        self.x, self.y, self.u = x, y, u
        self.scale = scale
        self.w, self.h = int(math.ceil(width / scale)), int(math.ceil(height / scale))
        self.centre, self.radius = centre, radius
        self.base = max(self._variance(x / scale, y / scale), 1e-12)

    def _variance(self, xs, ys) -> float:
        from scipy.ndimage import gaussian_filter

        img = gaussian_filter(_votes(xs, ys, self.w, self.h), 1.0, mode="constant")
        return float(img.var())

    def gain(self, q: np.ndarray) -> float:
        m = _params_to_motion(q, self.centre, self.radius)
        xm, ym = m.to_middle(self.u, self.x, self.y)
        return self._variance(xm / self.scale, ym / self.scale) / self.base


def _subset(n: int, k: int, seed: int) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def estimate_motion(events: EventStream, exposure: Exposure,
                    hot_mask: np.ndarray | None = None,
                    search: MotionSearch | None = None) -> GlobalMotion:
    """The global motion of the exposure's events by contrast maximisation.

    Args:
        events: the stream (only events inside ``exposure`` are used).
        exposure: the window, µs.
        hot_mask: (H, W) bool pixels whose events are ignored.
        search: search ranges (default :class:`MotionSearch`).
    Returns:
        the motion, with ``confidence`` its contrast gain at full resolution over no motion;
        zero motion with confidence 0 when the window holds fewer than :data:`MIN_EVENTS`.
    """
    from scipy.optimize import minimize

    search = MotionSearch() if search is None else search
    ev = events.within(exposure)
    w, h = events.width, events.height
    centre = ((w - 1) / 2, (h - 1) / 2)
    radius = 0.5 * max(w, h)
    x = ev.x.astype(np.float64)
    y = ev.y.astype(np.float64)
    u = (ev.t - exposure.start_us).astype(np.float64) / exposure.duration_us
    if hot_mask is not None and hot_mask.any() and len(x):
        keep = ~hot_mask[ev.y, ev.x]
        x, y, u = x[keep], y[keep], u[keep]
    n = len(x)
    if n < MIN_EVENTS:
        return GlobalMotion(centre=centre, events=n)
    idx = _subset(n, search.max_events, search.seed)
    x, y, u = x[idx], y[idx], u[idx]
    # coarser levels need fewer events: a quarter, a half
    few = _subset(len(x), max(search.max_events // 4, MIN_EVENTS), search.seed + 1)
    half = _subset(len(x), max(search.max_events // 2, MIN_EVENTS), search.seed + 2)

    def bound(q):
        q = np.array(q, np.float64)
        lim_r, lim_z = search.max_rotation * radius, search.max_zoom * radius
        over = max(abs(q[4]) - lim_r, 0.0) + max(abs(q[5]) - lim_z, 0.0)
        q[4] = np.clip(q[4], -lim_r, lim_r)
        q[5] = np.clip(q[5], -lim_z, lim_z)
        return q, over

    def refine(level: _Level, q0: np.ndarray, free: int, step: float) -> np.ndarray:
        def f(qf):
            q = q0.copy()
            q[:free] = qf
            q, over = bound(q)
            return -level.gain(q) + 0.01 * over

        start = q0[:free]
        simplex = np.vstack([start] + [start + step * np.eye(free)[i] for i in range(free)])
        r = minimize(f, start, method="Nelder-Mead",
                     options={"initial_simplex": simplex, "xatol": 0.02 * step,
                              "fatol": 1e-5, "maxfev": 60 * free})
        q = q0.copy()
        q[:free] = r.x
        return bound(q)[0]

    coarse = _Level(x[few], y[few], u[few], w, h, 4.0, centre, radius)
    vmax, st = search.max_velocity_px, coarse.scale
    grid = np.arange(-vmax, vmax + 1e-9, st)
    best = []
    for vx in grid:
        for vy in grid:
            q = np.array([vx, vy, 0, 0, 0, 0], np.float64)
            best.append((coarse.gain(q), vx, vy))
    best.sort(reverse=True)
    candidates = []
    for _, vx, vy in best[:3]:
        q = refine(coarse, np.array([vx, vy, 0, 0, 0, 0], np.float64), 4, st)
        candidates.append((coarse.gain(q), q))
    q = max(candidates, key=lambda c: c[0])[1]
    mid = _Level(x[half], y[half], u[half], w, h, 2.0, centre, radius)
    q = refine(mid, q, 4, 1.0)
    fine = _Level(x, y, u, w, h, 1.0, centre, radius)
    q = refine(fine, q, 6 if search.rotation_zoom else 4, 0.5)
    return _params_to_motion(q, centre, radius, fine.gain(q), n)
