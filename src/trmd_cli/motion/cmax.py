"""Contrast maximisation (Gallego et al., CVPR 2018) of a global motion over one exposure.

Events are carried back to the middle of the exposure by a candidate
:class:`~trmd_cli.motion.model.GlobalMotion` and accumulated into an image of warped events
(IWE, bilinear votes by one ``np.bincount`` on a flat index; an event carried outside the
sensor votes nowhere). The right motion makes that image sharpest. The objective is its
variance after a small Gaussian (σ = 1 cell on the coarse grids; 0.7 px on the finest, whose
cells are half a pixel, see :data:`FINE_SCALE`), *divided by* that of the unwarped events (a
normalised gain, as Shiba et al., ECCV 2022, to guard against event collapse), with the zoom,
rotation and perspective bounded. On the finest grid the search leaves out each event's
overlap with itself (see :class:`_Level`): what is left rewards events that land on each
other, not events that land on the grid's cells.

Search: a grid over the velocity (step 8 px per exposure on an 8× downsampled image, then the
step-4 neighbours of the best three on 4×), then quasi-Newton (BFGS) ascent on the analytic
gradient of the gain — translation + acceleration from the best three on 4×, with rotation and
zoom on 2× and on the finest grid, then the perspective there, kept only
when it sharpens the events by more than :data:`PERSPECTIVE_MIN_GAIN`, then the
translation's jerk with everything else free, kept only when it sharpens events it was not
fitted to by more than :data:`JERK_MIN_GAIN`. The gradient is exact for the
bilinear votes: the image's derivative ``2/n · g ∗ (g ∗ IWE − μ)`` read back at each event by
the derivative of its bilinear stencil, chained through the closed-form warp.
"""

from __future__ import annotations

import math

import numpy as np

from ..events import EventStream, Exposure
from .model import GlobalMotion

__all__ = ["estimate_motion", "split_agreement", "warped_image", "window_points", "MIN_EVENTS",
           "PERSPECTIVE_MIN_GAIN", "JERK_MIN_GAIN", "MotionSearch"]

#: fewer events than this in the window: no estimate (confidence 0)
MIN_EVENTS = 500

#: the perspective is kept when it raises the full-resolution gain by more than this share
PERSPECTIVE_MIN_GAIN = 1e-3
#: the least relative rise of the held-out events' gain for which the jerk is kept
JERK_MIN_GAIN = 3e-4

from dataclasses import dataclass  # noqa: E402


@dataclass(frozen=True)
class MotionSearch:
    """How far and how finely to search.

    Attributes:
        max_velocity_px: the velocity grid spans ±this, pixels per exposure.
        max_rotation: |ω| bound, radians per exposure.
        max_zoom: |ζ| bound, log scale per exposure.
        max_perspective: |π|·R bound (R: half the sensor's longer side), the relative change
            of scale across the view per exposure.
        rotation_zoom: refine rotation, zoom and perspective too (else translation +
            acceleration only).
        jerk: refine the translation's jerk last (fitted to every other event, kept when it
            raises the gain of the rest by more than :data:`JERK_MIN_GAIN`).
        max_events: events used per level (a fixed random subset when there are more).
        seed: the subset's generator seed.
        iterations: quasi-Newton steps per refinement, at most.
    """

    max_velocity_px: float = 48.0
    max_rotation: float = 0.12
    max_zoom: float = 0.12
    max_perspective: float = 0.1
    rotation_zoom: bool = True
    jerk: bool = True
    max_events: int = 60_000
    seed: int = 0
    iterations: int = 30


def window_points(events: EventStream, exposure: Exposure,
                  hot_mask: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The events of ``exposure`` as points: (x, y) pixels and u, the fraction of the exposure
    (float64 each), the events of ``hot_mask``'s (H, W) pixels left out."""
    ev = events.within(exposure)
    x = ev.x.astype(np.float64)
    y = ev.y.astype(np.float64)
    u = (ev.t - exposure.start_us).astype(np.float64) / exposure.duration_us
    if hot_mask is not None and hot_mask.any() and len(x):
        keep = ~hot_mask[ev.y, ev.x]
        x, y, u = x[keep], y[keep], u[keep]
    return x, y, u


def _params_to_motion(q: np.ndarray, centre, radius: float, conf: float = 0.0,
                      n: int = 0) -> GlobalMotion:
    persp = (float(q[6]) / radius ** 2, float(q[7]) / radius ** 2) if len(q) > 6 else (0.0, 0.0)
    jerk = (6.0 * float(q[8]), 6.0 * float(q[9])) if len(q) > 8 else (0.0, 0.0)
    return GlobalMotion((float(q[0]), float(q[1])), (float(q[2]), float(q[3])),
                        float(q[4]) / radius, float(q[5]) / radius,
                        (float(centre[0]), float(centre[1])), conf, n, persp, jerk)


def warped_image(motion: GlobalMotion, x: np.ndarray, y: np.ndarray, u: np.ndarray,
                 width: int, height: int, scale: float = 1.0) -> np.ndarray:
    """The image of events ``(x, y)`` (pixels) at exposure fractions ``u`` carried to the
    middle by ``motion``, on a grid ``scale`` times coarser: (h, w) float64 vote counts."""
    xm, ym = motion.to_middle(u, x, y)
    w, h = int(math.ceil(width / scale)), int(math.ceil(height / scale))
    return _votes(xm / scale, ym / scale, w, h)


def _votes(xs: np.ndarray, ys: np.ndarray, w: int, h: int) -> np.ndarray:
    """Bilinear votes of points ``(xs, ys)`` (pixels of a (h, w) grid): (h, w) float64; a
    vote that lands off the grid is dropped."""
    return _Taps(xs, ys, w, h).image()


class _Taps:
    """Where points ``(xs, ys)`` vote on a (h, w) grid: the flat index of each point's
    top-left tap on the grid padded by two cells, and its bilinear fractions. A point is
    first clipped into that margin: one that lies off the grid still votes only into the
    margin (cropped away), so no mask is needed and its gradient comes out zero."""

    def __init__(self, xs: np.ndarray, ys: np.ndarray, w: int, h: int) -> None:
        xs = np.clip(xs, -2.0, w + 0.5)
        ys = np.clip(ys, -2.0, h + 0.5)
        x0, y0 = np.floor(xs), np.floor(ys)
        self.fx, self.fy = xs - x0, ys - y0
        self.w, self.h = w, h
        self.stride = w + 4
        y0 *= self.stride
        y0 += x0
        y0 += 2 * self.stride + 2
        self.index = y0.astype(np.intp)

    def image(self) -> np.ndarray:
        """The (h, w) image of the votes."""
        fx, fy, s, i = self.fx, self.fy, self.stride, self.index
        gx, gy = 1.0 - fx, 1.0 - fy
        # one bincount over the four taps (four separate ones cost ~4× the passes)
        acc = np.bincount(np.concatenate((i, i + 1, i + s, i + s + 1)),
                          np.concatenate((gx * gy, fx * gy, gx * fy, fx * fy)),
                          minlength=(self.h + 4) * s)
        return acc.reshape(self.h + 4, s)[2:-2, 2:-2]

    def gradient(self, dimg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Given ∂f/∂image (h, w), ∂f/∂xs and ∂f/∂ys of each point (the exact derivative of
        the bilinear votes, piecewise constant in the point's cell)."""
        s = self.stride
        pad = np.zeros((self.h + 4, s))
        pad[2:-2, 2:-2] = dimg
        flat = pad.reshape(-1)
        i = self.index
        r00, r10 = flat[i], flat[i + 1]
        r01, r11 = flat[i + s], flat[i + s + 1]
        d0 = r10 - r00
        d1 = r11 - r01
        gxs = d0 + self.fy * (d1 - d0)
        e0 = r01 - r00
        e1 = r11 - r10
        gys = e0 + self.fx * (e1 - e0)
        return gxs, gys


#: taps of :func:`_blur`'s Gaussian along each axis (radius 4 cells: 2.9σ on the half-pixel grid)
_TAPS = 9


def _blur(img: np.ndarray, sigma: float = 1.0, out: np.ndarray | None = None) -> np.ndarray:
    """Gaussian of σ = ``sigma`` cells (:data:`_TAPS` taps) with zeros beyond the border;
    symmetric, so it is its own transpose. ``out``: an array of ``img``'s shape and type (a
    view of rows is fine) to write into."""
    import cv2

    return cv2.GaussianBlur(img, (_TAPS, _TAPS), sigma, dst=out,
                            borderType=cv2.BORDER_CONSTANT)


def _kernel(sigma: float) -> np.ndarray:
    """The 1-D taps :func:`_blur` filters with along each axis."""
    import cv2

    return cv2.getGaussianKernel(_TAPS, sigma)[:, 0]


#: pixels per cell of the finest grid: half a pixel. The bilinear votes of an event that lands
#: on a cell's centre weigh more in the variance than those of one that lands between cells,
#: so on whole pixels the plain gain rewards motions that carry events (recorded at whole
#: pixels) back onto whole pixels: on five Kodak exposures the estimate's gain there exceeded
#: the true path's by 0.02–0.26 %, 0.13–0.24 px from it. Leaving out each event's overlap
#: with itself (:class:`_Level`'s ``cross_only``) removes that reward, and half-pixel cells
#: under the same σ = 0.7 px bring the estimate nearer still. Mean end-point error against the
#: true path on 8 + 8 simulated textures of the default and the clean sensor and on 7 Kodak
#: exposures with movers: plain on whole pixels 0.27 / 0.19 / 0.17 px, without the overlap
#: 0.19 / 0.12 / 0.15, and on half-pixel cells too 0.19 / 0.10 / 0.11 (the pinned set's 48:
#: 0.159 → 0.125 px). Only a last refinement on half-pixel cells (the rest on whole pixels)
#: cost a third as much but left the pinned set at 0.137 px, one frame 0.38 px off
FINE_SCALE = 0.5
#: σ of the image of warped events' Gaussian: pixels at full resolution and finer (0.7 px,
#: whatever the cells), cells on the coarser grids. At full resolution a narrower one
#: (0.7 px) placed the optimum nearer the true path than 1 px did (mean end-point error on
#: the pinned set's first 24 frames 0.196 → 0.184 px, on the sparse domain-shift sensor
#: 0.237 → 0.211); the coarser levels keep 1 cell, which their search needs to converge from
#: the velocity grid
FINE_SIGMA, COARSE_SIGMA = 0.7, 1.0


class _Level:
    """One resolution: the events, the grid, and the unwarped image's variance.

    The objective is the gain ``var(g ∗ IWE(q)) / var(g ∗ IWE(0))`` with ``q`` = (vx, vy, ax,
    ay, ω·R, ζ·R, πx·R², πy·R²) (pixels per exposure, per exposure², and the rotation, zoom
    and perspective scaled by the radius ``R`` so that every parameter moves a far pixel by
    comparable amounts). The warp is :meth:`GlobalMotion.to_middle` written out on per-level
    constants. With ``cross_only`` the numerator leaves out each event's overlap with itself,
    ``Σ‖g ∗ its votes‖² / cells`` (see :data:`FINE_SCALE`); the denominator stays the plain
    variance, so the gain is then below the plain one by about that share."""

    def __init__(self, x, y, u, width, height, scale, centre, radius,
                 sigma: float | None = None, cross_only: bool = False):
        self.x, self.y, self.u = x, y, u
        # per-event arithmetic in float32: half the memory traffic of float64, and positions
        # of a few hundred pixels keep ~3e-5 px
        f32 = np.float32
        self.tau = (u - 0.5).astype(f32)
        self.half_tau2 = (0.5 * self.tau * self.tau).astype(f32)
        # the jerk enters as q[8:10]·τ³ (q = j/6): the reach of the acceleration's a·τ²/2
        self.tau3 = (2.0 * self.tau * self.half_tau2).astype(f32)
        self.rx, self.ry = (x - centre[0]).astype(f32), (y - centre[1]).astype(f32)
        self.scale = scale
        self.w, self.h = int(math.ceil(width / scale)), int(math.ceil(height / scale))
        self.centre, self.radius = centre, radius
        if sigma is None:
            # σ = 0.7 px at and below full resolution, in this grid's cells
            sigma = FINE_SIGMA / scale if scale <= 1.0 else COARSE_SIGMA
        self.sigma = sigma
        # each event's overlap with itself, Σ (g ∗ its votes)², is separable: per axis
        # c0 − 2·(c0 − c1)·f·(1 − f) at a fraction f of a cell, with c0 and c1 the kernel's
        # autocorrelation at lags 0 and 1 (1 at f = 0, ½ at f = ½ without the Gaussian)
        self.cross_only = cross_only
        if cross_only:
            taps = _kernel(sigma)
            self._c0, self._c1 = float(taps @ taps), float(taps[:-1] @ taps[1:])
        img = _blur(_votes(x / scale, y / scale, self.w, self.h), self.sigma)
        self.base = max(float(img.var()), 1e-12)

    def _warp(self, q: np.ndarray):
        """The events carried to the middle by ``q`` before the perspective is undone, about
        the centre (pixels), and the per-event ``(a, b)`` of the inverse rotation-zoom
        ``[[a, b], [−b, a]]``."""
        t, t2 = self.tau, self.half_tau2
        # Python floats, which keep the float32 arrays float32 (numpy's float64 scalars would
        # promote them)
        q = [float(v) for v in q]
        rx = self.rx - q[0] * t
        rx -= q[2] * t2
        ry = self.ry - q[1] * t
        ry -= q[3] * t2
        if len(q) > 8 and (q[8] != 0.0 or q[9] != 0.0):
            rx -= q[8] * self.tau3
            ry -= q[9] * self.tau3
        om, ze = q[4] / self.radius, q[5] / self.radius
        if om == 0.0 and ze == 0.0:
            return rx, ry, 1.0, 0.0
        e = np.exp(-ze * t)
        a = np.cos(om * t) * e
        b = np.sin(om * t) * e
        return a * rx + b * ry, a * ry - b * rx, a, b

    def _perspective(self, q: np.ndarray, mx: np.ndarray, my: np.ndarray):
        """``1 / D`` with ``D = 1 − τ·π·r'`` per event (None when π = 0): the middle-frame
        point is ``r' / D``."""
        if len(q) < 8 or (q[6] == 0.0 and q[7] == 0.0):
            return None
        q = [float(v) for v in q]
        r2 = self.radius * self.radius
        d = mx * (q[6] / r2)
        d += my * (q[7] / r2)
        d *= self.tau
        np.subtract(1.0, d, out=d)
        np.reciprocal(d, out=d)
        return d

    def gain(self, q: np.ndarray) -> float:
        """The gain at ``q``."""
        return self.gain_and_gradient(q, False)[0]

    def _buffers(self) -> dict:
        # per-event work arrays kept between evaluations: fresh ones of this size cost a
        # page fault per 4 KiB each time, which outweighs the arithmetic on them
        if not hasattr(self, "_work"):
            n = len(self.x)
            self._work = {"f": np.empty((8, n), np.float32), "i": np.empty(4 * n, np.intp),
                          "w": np.empty(4 * n, np.float32),
                          "pad": np.zeros((self.h + 4, self.w + 4), np.float32)}
        return self._work

    def gain_and_gradient(self, q: np.ndarray, gradient: bool = True, free: int = 6
                          ) -> tuple[float, np.ndarray | None]:
        """The gain at ``q`` and (with ``gradient``) its gradient in ``q`` (only the
        first ``free`` entries are computed, the rest are 0; the jerk's two, ``q[8:10]``,
        with ``free = 10``)."""
        import cv2

        rx, ry, a, b = self._warp(q)
        inv_d = self._perspective(q, rx, ry)
        mx, my = (rx, ry) if inv_d is None else (rx * inv_d, ry * inv_d)
        work = self._buffers()
        f, idx, wts = work["f"], work["i"], work["w"]
        n, w, h = len(self.x), self.w, self.h
        stride = w + 4
        inv = 1.0 / self.scale
        xs, ys, x0, y0 = f[0], f[1], f[2], f[3]
        # the events on the grid, clipped into its two-cell margin (see :class:`_Taps`)
        np.add(mx, self.centre[0], out=xs)
        xs *= inv
        np.add(my, self.centre[1], out=ys)
        ys *= inv
        np.clip(xs, -2.0, w + 0.5, out=xs)
        np.clip(ys, -2.0, h + 0.5, out=ys)
        np.floor(xs, out=x0)
        np.floor(ys, out=y0)
        xs -= x0
        ys -= y0
        fx, fy = xs, ys
        y0 *= stride
        y0 += x0
        y0 += 2 * stride + 2
        i0 = idx[:n]
        np.copyto(i0, y0, casting="unsafe")
        np.add(i0, 1, out=idx[n:2 * n])
        np.add(i0, stride, out=idx[2 * n:3 * n])
        np.add(i0, stride + 1, out=idx[3 * n:])
        gx, gy = x0, y0
        np.subtract(1.0, fx, out=gx)
        np.subtract(1.0, fy, out=gy)
        np.multiply(gx, gy, out=wts[:n])
        np.multiply(fx, gy, out=wts[n:2 * n])
        np.multiply(gx, fy, out=wts[2 * n:3 * n])
        np.multiply(fx, fy, out=wts[3 * n:])
        votes = np.bincount(idx, wts, minlength=(h + 4) * stride)
        # the filter in float32 too (several times faster in OpenCV than in float64)
        img = _blur(votes.reshape(h + 4, stride)[2:-2, 2:-2].astype(np.float32), self.sigma)
        # mean and variance in one pass (accumulated in float64)
        mean, std = cv2.meanStdDev(img)
        g = float(std[0, 0]) ** 2 / self.base
        if self.cross_only:
            c0, dc = self._c0, 2.0 * (self._c0 - self._c1)
            sx = c0 - dc * fx * (1.0 - fx)
            sy = c0 - dc * fy * (1.0 - fy)
            k_self = 1.0 / (img.size * self.base)
            # (every event's, also one voting into the margin: continuous as it leaves)
            g -= float(np.dot(sx, sy)) * k_self
        if not gradient:
            return g, None
        # d var / d image = (2 / n) gᵀ(g ∗ I − μ): the mean's own term sums to zero
        pad = work["pad"]
        img -= float(mean[0, 0])
        img *= 2.0 * inv / (img.size * self.base)
        _blur(img, self.sigma, out=pad[2:-2, 2:-2])
        flat = pad.reshape(-1)
        r00, r10, r01, r11 = f[2], f[3], f[4], f[5]
        np.take(flat, i0, out=r00)
        np.take(flat, idx[n:2 * n], out=r10)
        np.take(flat, idx[2 * n:3 * n], out=r01)
        np.take(flat, idx[3 * n:], out=r11)
        # ∂/∂xs = (r10 − r00) + fy·(r11 − r01 − r10 + r00), and likewise for ys
        e0, e1 = f[6], f[7]
        np.subtract(r01, r00, out=e0)
        np.subtract(r11, r10, out=e1)
        r10 -= r00
        r11 -= r01
        r11 -= r10
        r11 *= fy
        r11 += r10
        e1 -= e0
        e1 *= fx
        e1 += e0
        gxs, gys = r11, e1
        if self.cross_only:
            gxs += (k_self * inv * dc) * (1.0 - 2.0 * fx) * sy
            gys += (k_self * inv * dc) * (1.0 - 2.0 * fy) * sx
        grad = np.zeros(len(q))
        if inv_d is not None or free > 6:
            # through m = r'/D: ∂f/∂r' = g/D + τ·π·(r'·g)/D², ∂f/∂π = τ·r'·(r'·g)/D²
            dots = gxs * rx
            dots += gys * ry
            if inv_d is not None:
                dots *= inv_d
                dots *= inv_d
                r2 = self.radius * self.radius
                tpx, tpy = self.tau * float(q[6] / r2), self.tau * float(q[7] / r2)
                gxs = gxs * inv_d + tpx * dots
                gys = gys * inv_d + tpy * dots
            if free > 6:
                td = self.tau * dots
                grad[6] = np.dot(td, rx) / (self.radius * self.radius)
                grad[7] = np.dot(td, ry) / (self.radius * self.radius)
            mx, my = rx, ry
        # ∂(xm, ym)/∂d = −[[a, b], [−b, a]] for the translation d = v·τ + a·τ²/2
        if isinstance(a, float):
            ex, ey = gxs, gys
        else:
            ex = a * gxs - b * gys
            ey = b * gxs + a * gys
        t, t2 = self.tau, self.half_tau2
        grad[:4] = (-np.dot(t, ex), -np.dot(t, ey), -np.dot(t2, ex), -np.dot(t2, ey))
        if free > 8:
            grad[8:10] = (-np.dot(self.tau3, ex), -np.dot(self.tau3, ey))
        if free > 4:
            rot = gxs * my
            rot -= gys * mx
            zoom = gxs * mx
            zoom += gys * my
            grad[4] = np.dot(t, rot) / self.radius
            grad[5] = -np.dot(t, zoom) / self.radius
        return g, grad


def _start(vx: float, vy: float) -> np.ndarray:
    """The parameters of a pure velocity (vx, vy) pixels per exposure."""
    return np.array([vx, vy, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


def _subset(n: int, k: int, seed: int) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def estimate_motion(events: EventStream, exposure: Exposure,
                    hot_mask: np.ndarray | None = None,
                    search: MotionSearch | None = None,
                    start: tuple[float, float] | None = None) -> GlobalMotion:
    """The global motion of the exposure's events by contrast maximisation.

    Args:
        events: the stream (only events inside ``exposure`` are used).
        exposure: the window, µs.
        hot_mask: (H, W) bool pixels whose events are ignored.
        search: search ranges (default :class:`MotionSearch`).
        start: a velocity (pixels per exposure) known to be near the answer: the search
            starts there instead of on the velocity grid, and takes rotation and zoom up
            at 2× at once (one way at 2×, not two).
    Returns:
        the motion, with ``confidence`` its contrast gain at full resolution over no motion;
        zero motion with confidence 0 when the window holds fewer than :data:`MIN_EVENTS`.
    """
    search = MotionSearch() if search is None else search
    w, h = events.width, events.height
    centre = ((w - 1) / 2, (h - 1) / 2)
    radius = 0.5 * max(w, h)
    x, y, u = window_points(events, exposure, hot_mask)
    n = len(x)
    if n < MIN_EVENTS:
        return GlobalMotion(centre=centre, events=n)
    idx = _subset(n, search.max_events, search.seed)
    x, y, u = x[idx], y[idx], u[idx]
    # coarser levels need fewer events: a quarter, a half
    few = _subset(len(x), max(search.max_events // 4, MIN_EVENTS), search.seed + 1)
    half = _subset(len(x), max(search.max_events // 2, MIN_EVENTS), search.seed + 2)

    lim = (search.max_rotation * radius, search.max_zoom * radius,
           search.max_perspective * radius)

    def refine(level: _Level, q0: np.ndarray, free: int, step: float) -> np.ndarray:
        return _ascend(level, q0, free, lim, search.iterations, step)

    # the velocity grid, coarse to fine: every step-8 velocity on an 8× coarser image, then
    # the step-4 neighbours of the best few on a 4× coarser one
    vmax = search.max_velocity_px
    coarse = _Level(x[few], y[few], u[few], w, h, 4.0, centre, radius)
    if start is not None:
        best = [(0.0, float(start[0]), float(start[1]))]
    else:
        rough = _Level(x[few], y[few], u[few], w, h, 8.0, centre, radius)
        grid = np.arange(-vmax, vmax + 1e-9, rough.scale)
        seeds = sorted(((rough.gain(_start(vx, vy)), vx, vy)
                        for vx in grid for vy in grid), reverse=True)[:3]
        near = {(vx + dx, vy + dy) for _, vx, vy in seeds
                for dx in (-coarse.scale, 0.0, coarse.scale)
                for dy in (-coarse.scale, 0.0, coarse.scale)}
        best = sorted(((coarse.gain(_start(vx, vy)), vx, vy)
                       for vx, vy in sorted(near)), reverse=True)
    candidates = []
    for _, vx, vy in best[:3]:
        q = refine(coarse, _start(vx, vy), 4, coarse.scale)
        candidates.append((coarse.gain(q), q))
    q = max(candidates, key=lambda c: c[0])[1]
    mid = _Level(x[half], y[half], u[half], w, h, 2.0, centre, radius)
    fine = _Level(x, y, u, w, h, FINE_SCALE, centre, radius, cross_only=True)
    free = 6 if search.rotation_zoom else 4
    if start is None and free > 4:
        # two ways on from 4× at 2×: rotation and zoom taken up at once (on sparse events a
        # search that took them up only at full resolution stalled on a wrong velocity), or
        # after the translation alone (on dense ones, the safer way); only the one that
        # sharpens the 2× image more goes on to full resolution. Both taken there and
        # judged there cost 1.25× the time for the same estimates (mean end-point error on
        # 8 + 8 textures of the default and the clean sensor and 7 mover exposures 0.184 /
        # 0.091 / 0.106 px against 0.190 / 0.094 / 0.108, the pinned set's 0.125 either way)
        q = max((refine(mid, refine(mid, q, 4, 0.5), free, 0.5), refine(mid, q, free, 0.5)),
                key=mid.gain)
    else:
        # from a given velocity (the background's, after the first estimate) only the
        # second way: on the frames with movers the same to 0.01 dB, and faster
        q = refine(mid, q, free, 0.5)
    q = refine(fine, q, free, 0.25)
    if search.rotation_zoom and search.max_perspective > 0:
        # the perspective last, from the six-parameter optimum, and kept only when it
        # sharpens the events by more than fitting their noise does: on views with no
        # perspective the two extra parameters raised the gain by ≤ 0.08 % and cost 0.03 px
        # of end-point error; where the camera's path had some, they raised it by 0.2–0.8 %
        # and the error fell from 0.33 to 0.20 px
        g6 = fine.gain(q)
        q8 = refine(fine, q, 8, 0.25)
        if fine.gain(q8) > g6 * (1.0 + PERSPECTIVE_MIN_GAIN):
            q = q8
    if search.jerk:
        # then the jerk, with everything already free
        sel = [0, 1, 2, 3] + ([4, 5] if search.rotation_zoom else []) + \
            ([6, 7] if q[6] != 0.0 or q[7] != 0.0 else []) + [8, 9]
        # judged on events it was not fitted to: fitted on every other event, kept only when
        # it sharpens the rest (a jerk fitted to all 16k events of a uniform translation
        # raised their gain by 0.35 % and doubled the end-point error)
        fit = _Level(x[0::2], y[0::2], u[0::2], w, h, FINE_SCALE, centre, radius,
                     cross_only=True)
        held = _Level(x[1::2], y[1::2], u[1::2], w, h, FINE_SCALE, centre, radius,
                      cross_only=True)
        qa = refine(fit, q, sel, 0.25)
        if held.gain(qa) > held.gain(q) * (1.0 + JERK_MIN_GAIN):
            qj = refine(fine, qa, sel, 0.25)
            if fine.gain(qj) > fine.gain(q):
                q = qj
    # the confidence as the guard reads it everywhere: the gain with the 1-pixel Gaussian
    # (:func:`~trmd_cli.motion.sampled.event_gain`), whatever σ the search used
    score = _Level(x, y, u, w, h, 1.0, centre, radius, sigma=1.0)
    return _params_to_motion(q, centre, radius, score.gain(q), n)


def split_agreement(events: EventStream, exposure: Exposure, motion: GlobalMotion,
                    hot_mask: np.ndarray | None = None,
                    search: MotionSearch | None = None) -> float:
    """How far apart (pixels, :meth:`GlobalMotion.end_point_error_px`) the motions estimated
    from the window's even and from its odd events lie, each search started at ``motion``'s
    velocity: the part of an estimate's error that comes from its events' noise and number.
    A bias both halves share (the objective's own) does not show; nan when a half holds
    fewer than :data:`MIN_EVENTS` events.
    """
    inside = events.within(exposure)
    start = (float(motion.velocity[0]), float(motion.velocity[1]))
    halves = [estimate_motion(inside.take(slice(k, None, 2)), exposure, hot_mask, search,
                              start=start) for k in (0, 1)]
    if min(m.events for m in halves) < MIN_EVENTS:
        return float("nan")
    return halves[0].end_point_error_px(halves[1], events.width, events.height)


def _ascend(level: _Level, q0: np.ndarray, free, lim: tuple[float, float, float],
            iterations: int, step: float, tol: float = 0.03) -> np.ndarray:
    """Maximise ``level``'s gain over the parameters ``free`` of ``q0`` (the first ``free``
    when an int, else a sequence of indices) by BFGS on the analytic gradient with a
    backtracking (Armijo) line search, the scaled rotation, zoom and perspective kept within
    ``±lim``; stops after ``iterations`` steps or one shorter than ``tol`` (pixels of the
    parameters)."""
    sel = np.arange(free) if isinstance(free, int) else np.asarray(free, np.intp)
    upto = int(sel.max()) + 1
    hi = np.array([np.inf] * 4 + [lim[0], lim[1], lim[2], lim[2]] + [np.inf] * 2)[sel]
    n = len(sel)

    def f(v: np.ndarray) -> tuple[float, np.ndarray]:
        q = q0.copy()
        q[sel] = v
        g, grad = level.gain_and_gradient(q, free=upto)
        return -g, -grad[sel]

    x = np.clip(q0[sel], -hi, hi)
    fx, gx = f(x)
    hinv = None
    for _ in range(iterations):
        if hinv is None:
            # first step: ``step`` along the steepest ascent
            d = -gx * (step / max(float(np.linalg.norm(gx)), 1e-300))
        else:
            d = -hinv @ gx
        t = 1.0
        while True:
            xn = np.clip(x + t * d, -hi, hi)
            fn, gn = f(xn)
            if fn <= fx + 1e-4 * float(gx @ (xn - x)) or t < 1e-3:
                break
            t *= 0.5
        if fn >= fx:
            if hinv is None:
                break
            hinv = None  # a poor quasi-Newton direction: start again from steepest ascent
            continue
        sv, yv = xn - x, gn - gx
        sy = float(sv @ yv)
        if sy > 1e-12:
            if hinv is None:
                hinv = np.eye(n) * (sy / float(yv @ yv))
            rho = 1.0 / sy
            m = np.eye(n) - rho * np.outer(sv, yv)
            hinv = m @ hinv @ m.T + rho * np.outer(sv, sv)
        x, fx, gx = xn, fn, gn
        if float(np.linalg.norm(sv)) < tol:
            break
    q = q0.copy()
    q[sel] = x
    return q
