"""Motion-aware blur and its inverse: non-blind deconvolution of the blurry frame along a
motion given by the events, guarded by EDI.

Blur model. With the motion ``m`` (:class:`~trmd_cli.motion.GlobalMotion`) the frame seen at
exposure fraction ``u`` is the middle frame ``L`` sampled where ``m`` carries each pixel back
to the middle, so ``B ≈ A(L) = (1/J) Σ_j L ∘ m⁻¹(u_j, ·)`` over J evenly spaced instants (at
most half a pixel of motion apart). ``L`` lives on a *padded* canvas (the sensor plus a margin
wider than the motion) so that what moved into view near the borders is an unknown, not forced
to the sensor's edge. Sampling is bilinear; ``A`` is built once as a sparse matrix summing the
J bilinear stencils (the same weights ``torch.nn.functional.grid_sample`` uses, which still
warps the result to other instants), so ``A`` and its exact transpose ``Aᵀ`` are one sparse
product each.

Inverse. ``min ½‖A(L) − B‖² + λ Σ huber_ε(|∇L|)`` by iteratively reweighted least squares:
each round solves ``(AᵀA + λ DᵀWD) L = AᵀB`` by conjugate gradients with ``W = 1/max(|∇L|, ε)``
from the previous round (a TV-like prior that keeps edges and does not amplify noise),
preconditioned by the normal matrix's diagonal (the prior's weights span two orders of
magnitude and the canvas margin is seen by few instants: Jacobi evens both out).

Guard (:func:`guard_weights`). Per tile, where re-blurring the result does not give back B
(residual well above B's noise), where the events of the tile are not sharpened by the global
motion (an independent mover), or where the motion's confidence is low, the output falls back
smoothly to EDI.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .motion.model import GlobalMotion

__all__ = ["DeconvConfig", "BlurOperator", "deconvolve", "noise_level", "guard_weights",
           "Deconvolved"]


@dataclass(frozen=True)
class DeconvConfig:
    """The solver's settings.

    Attributes:
        penalty: λ, weight of the Huber gradient prior (intensity per pixel).
        huber: ε, intensity step per pixel below which the prior is quadratic.
        rounds: IRLS rounds (1 = a plain quadratic gradient penalty with weight λ/ε).
        iterations: preconditioned conjugate-gradient iterations per round (each one product
            with ``A`` and one with ``Aᵀ``).
        step_px: largest motion between two of the J instants, pixels.
        margin_px: extra canvas around the motion's extent, pixels.
    """

    penalty: float = 2e-3
    huber: float = 0.01
    rounds: int = 3
    iterations: int = 10
    step_px: float = 0.5
    margin_px: int = 3


class BlurOperator:
    """``A``: a padded middle frame (C, H + 2P, W + 2P) → the blurry frame (C, H, W).

    ``A`` is held as one sparse matrix (rows: sensor pixels, columns: canvas pixels) summing
    the J bilinear stencils, so ``A x`` and ``Aᵀ y`` are one sparse product each.

    Args:
        motion: the exposure's motion: any object with ``to_middle(fractions, x, y)`` and
            ``max_displacement_px(width, height)`` (pixels, exposure fractions).
        width, height: sensor size, pixels.
        fractions: the J instants, exposure fractions; None = evenly spaced, at most
            ``step_px`` apart in motion, J ≥ 3.
        pad: P, canvas margin, pixels; None = the motion's largest displacement + margin.
        dtype: torch dtype of the matrix and of what :meth:`apply` / :meth:`adjoint` return
            (default float32).
    """

    def __init__(self, motion, width: int, height: int, fractions=None,
                 pad: int | None = None, step_px: float = 0.5, margin_px: int = 3,
                 dtype=None) -> None:
        import torch

        self.dtype = torch.float32 if dtype is None else dtype
        disp = motion.max_displacement_px(width, height)
        if fractions is None:
            j = min(max(3, int(math.ceil(disp / step_px)) + 1), 257)
            fractions = (np.arange(j) + 0.5) / j
        self.fractions = np.asarray(fractions, np.float64)
        self.pad = int(math.ceil(disp)) + margin_px if pad is None else int(pad)
        self.motion, self.width, self.height = motion, width, height
        real = np.float64 if self.dtype == torch.float64 else np.float32
        self.matrix = _stencil_matrix(motion, width, height, self.fractions, self.pad, real)
        # Aᵀ stored as its own CSR: a row-wise product beats the CSC view of A
        self.matrix_t = self.matrix.T.tocsr()
        self._grid = None

    @property
    def canvas(self) -> tuple[int, int]:
        """(H + 2P, W + 2P) of the padded middle frame."""
        return self.height + 2 * self.pad, self.width + 2 * self.pad

    @property
    def grid(self):
        """(J, H, W, 2) ``grid_sample`` grid of the J instants (built on first use)."""
        if self._grid is None:
            self._grid = self._grid_at(self.fractions)
        return self._grid

    def _grid_at(self, fractions):
        import torch

        hp, wp = self.canvas
        ys, xs = np.mgrid[0:self.height, 0:self.width].astype(np.float64)
        u = np.asarray(fractions, np.float64)[:, None, None]
        xm, ym = self.motion.to_middle(u, xs[None], ys[None])
        gx = 2.0 * (xm + self.pad) / (wp - 1) - 1.0
        gy = 2.0 * (ym + self.pad) / (hp - 1) - 1.0
        g = np.stack(np.broadcast_arrays(gx, gy), axis=-1)
        return torch.from_numpy(g).to(self.dtype)

    def warp(self, x, fractions=None):
        """The middle frame ``x`` (C, Hp, Wp) seen at ``fractions``: (K, C, H, W)."""
        import torch.nn.functional as F

        grid = self.grid if fractions is None else self._grid_at(fractions)
        inp = x.unsqueeze(0).expand(grid.shape[0], *x.shape)
        return F.grid_sample(inp.to(grid.dtype), grid, mode="bilinear", padding_mode="zeros",
                             align_corners=True)

    def apply_np(self, x: np.ndarray) -> np.ndarray:
        """``A x`` on pixel-major arrays: (Hp·Wp, C) → (H·W, C)."""
        return self.matrix @ x

    def adjoint_np(self, y: np.ndarray) -> np.ndarray:
        """``Aᵀ y`` on pixel-major arrays: (H·W, C) → (Hp·Wp, C)."""
        return self.matrix_t @ y

    def apply(self, x):
        """``A x``: (C, Hp, Wp) → (C, H, W), the mean of the J warped frames."""
        import torch

        c = x.shape[0]
        out = self.apply_np(x.detach().reshape(c, -1).T.numpy())
        return torch.from_numpy(np.ascontiguousarray(out.T)).reshape(
            c, self.height, self.width).to(self.dtype)

    def adjoint(self, y):
        """``Aᵀ y``: (C, H, W) → (C, Hp, Wp), the exact transpose of :meth:`apply`."""
        import torch

        c = y.shape[0]
        out = self.adjoint_np(y.detach().reshape(c, -1).T.numpy())
        return torch.from_numpy(np.ascontiguousarray(out.T)).reshape(
            c, *self.canvas).to(self.dtype)

    def pad_frame(self, frame: np.ndarray):
        """A (H, W[, 3]) frame onto the canvas (edges replicated): (C, Hp, Wp) tensor."""
        import torch

        f = frame[..., None] if frame.ndim == 2 else frame
        p = self.pad
        f = np.pad(f, ((p, p), (p, p), (0, 0)), mode="edge")
        return torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1))).to(self.dtype)


def _stencil_matrix(motion, width: int, height: int, fractions: np.ndarray, pad: int,
                    real) -> object:
    """``A`` as a (H·W, Hp·Wp) CSR matrix of dtype ``real``: row ``y·W + x`` holds the J
    bilinear stencils (weight 1/J each) of where ``motion`` carries sensor pixel (x, y) back to
    on the canvas; taps off the canvas weigh nothing (as ``grid_sample`` with zero padding)."""
    import scipy.sparse as sp

    hp, wp = height + 2 * pad, width + 2 * pad
    n, nj = height * width, len(fractions)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    # (J, 4, n): each instant's taps written contiguously, reordered row-major once at the end
    cols = np.empty((nj, 4, n), np.int32)
    vals = np.empty((nj, 4, n), real)
    for j in range(nj):
        # one instant at a time: (H, W) temporaries, not J times as many
        xm, ym = motion.to_middle(fractions[j:j + 1, None, None], xs[None], ys[None])
        xc = np.broadcast_to(xm, (1, height, width)).reshape(n) + pad
        yc = np.broadcast_to(ym, (1, height, width)).reshape(n) + pad
        x0, y0 = np.floor(xc), np.floor(yc)
        fx, fy = (xc - x0) / nj, yc - y0
        gx, gy = 1.0 / nj - fx, 1.0 - fy
        i0 = y0 * wp + x0
        inside = bool(((x0 >= 0) & (x0 < wp - 1) & (y0 >= 0) & (y0 < hp - 1)).all())
        for k, (off, wt) in enumerate(((0, gx * gy), (1, fx * gy), (wp, gx * fy),
                                       (wp + 1, fx * fy))):
            cols[j, k] = i0 + off if inside else 0
            vals[j, k] = wt
        if not inside:
            # a tap is kept where it lands on the canvas (rare: the motion leaves its margin)
            xi, yi = x0.astype(np.int64), y0.astype(np.int64)
            for k, (ox, oy) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
                cx, cy = xi + ox, yi + oy
                ok = (cx >= 0) & (cx < wp) & (cy >= 0) & (cy < hp)
                cols[j, k] = np.where(ok, cy * wp + cx, 0)
                vals[j, k] = np.where(ok, vals[j, k], 0)
    k = 4 * nj
    cols = np.ascontiguousarray(cols.reshape(k, n).T)
    vals = np.ascontiguousarray(vals.reshape(k, n).T)
    indptr = np.arange(0, n * k + 1, k, dtype=np.int64 if n * k >= 2**31 else np.int32)
    a = sp.csr_matrix((vals.reshape(-1), cols.reshape(-1), indptr), shape=(n, hp * wp))
    # consecutive instants share taps: merged, each product touches ~2× fewer entries
    a.sum_duplicates()
    return a


def _grad(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward differences of a (Hp, Wp, C) image along x and y (0 on the last column/row)."""
    gx = np.zeros_like(x)
    gy = np.zeros_like(x)
    np.subtract(x[:, 1:], x[:, :-1], out=gx[:, :-1])
    np.subtract(x[1:], x[:-1], out=gy[:-1])
    return gx, gy


def _grad_t(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Exact transpose of :func:`_grad`."""
    out = np.zeros_like(gx)
    out[:, 1:] += gx[:, :-1]
    out[:, :-1] -= gx[:, :-1]
    out[1:] += gy[:-1]
    out[:-1] -= gy[:-1]
    return out


@dataclass(frozen=True, eq=False)
class Deconvolved:
    """The deconvolution of one blurry frame.

    Attributes:
        operator: the blur model used.
        middle: (C, Hp, Wp) tensor, the recovered middle frame on the padded canvas.
        reblurred: (H, W[, 3]) float32, ``A`` of the result (compare with B).
    """

    operator: BlurOperator
    middle: object
    reblurred: np.ndarray

    def frames(self, fractions) -> np.ndarray:
        """The middle frame warped to ``fractions`` of the exposure: (K, H, W[, 3]) float32."""
        import torch

        with torch.no_grad():
            out = self.operator.warp(self.middle, fractions).numpy()
        out = out.transpose(0, 2, 3, 1)
        return np.ascontiguousarray(out[..., 0] if out.shape[-1] == 1 else out,
                                    dtype=np.float32)


def deconvolve(blurry: np.ndarray, motion, config: DeconvConfig | None = None,
               start: np.ndarray | None = None, fractions=None) -> Deconvolved:
    """Recover the middle frame of ``blurry`` (H, W[, 3]) float32 along ``motion``.

    ``start`` (H, W[, 3]): the first guess (default: B itself), e.g. EDI's middle frame;
    ``fractions``: the blur model's J instants (default: see :class:`BlurOperator`).
    """
    import torch

    cfg = DeconvConfig() if config is None else config
    h, w = blurry.shape[:2]
    op = BlurOperator(motion, w, h, fractions, step_px=cfg.step_px, margin_px=cfg.margin_px)
    hp, wp = op.canvas
    c = 1 if blurry.ndim == 2 else blurry.shape[2]
    b = np.ascontiguousarray(blurry, np.float32).reshape(h * w, c)
    x = op.pad_frame(blurry if start is None else start).numpy().transpose(1, 2, 0)
    x = np.ascontiguousarray(x, np.float32)
    rhs = op.adjoint_np(b).reshape(hp, wp, c)
    # diag(AᵀA): the Jacobi preconditioner's data term (column sums of A²)
    ata = np.asarray(op.matrix.multiply(op.matrix).sum(axis=0), np.float32).reshape(hp, wp, 1)
    lam, eps = float(cfg.penalty), float(cfg.huber)
    for _ in range(max(cfg.rounds, 1)):
        if cfg.rounds == 1:
            lw = np.full((hp, wp, c), lam / eps, np.float32)
        else:
            gx, gy = _grad(x)
            lw = (lam / np.maximum(np.sqrt(gx * gx + gy * gy), eps)).astype(np.float32)

        def normal(v: np.ndarray, lw: np.ndarray = lw) -> np.ndarray:
            vx, vy = _grad(v)
            vx *= lw
            vy *= lw
            out = op.adjoint_np(op.apply_np(v.reshape(hp * wp, c))).reshape(hp, wp, c)
            out += _grad_t(vx, vy)
            return out

        # diag(λ DᵀWD): the difference leaving a pixel and the one arriving from its left
        # (upper) neighbour, each with its own weight
        dia = ata + 2.0 * lw
        dia[:, -1] -= lw[:, -1]
        dia[-1] -= lw[-1]
        dia[:, 1:] += lw[:, :-1]
        dia[1:] += lw[:-1]
        x = _pcg(normal, rhs, x, 1.0 / np.maximum(dia, 1e-12), cfg.iterations)
    re = op.apply_np(x.reshape(hp * wp, c)).reshape(h, w, c)
    re = re[..., 0] if blurry.ndim == 2 else re
    middle = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))
    return Deconvolved(op, middle, np.ascontiguousarray(re, dtype=np.float32))


def _pcg(normal, rhs: np.ndarray, x: np.ndarray, inv_diag: np.ndarray,
         iterations: int) -> np.ndarray:
    """``iterations`` of conjugate gradients on ``normal(x) = rhs`` from ``x``, preconditioned
    by ``inv_diag`` (the inverse of the normal matrix's diagonal)."""
    r = rhs - normal(x)
    z = r * inv_diag
    p = z.copy()
    rz = float(np.vdot(r, z))
    r0 = rz
    for _ in range(iterations):
        if rz <= 1e-20 * max(r0, 1e-30):
            break
        q = normal(p)
        alpha = rz / max(float(np.vdot(p, q)), 1e-30)
        x = x + alpha * p
        r -= alpha * q
        z = r * inv_diag
        rz_new = float(np.vdot(r, z))
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x


def noise_level(blurry: np.ndarray) -> float:
    """Robust σ of the noise of ``blurry`` (intensity), from the median absolute value of its
    finest diagonal differences (Donoho's estimate on a Haar band)."""
    g = blurry.mean(-1) if blurry.ndim == 3 else blurry
    d = (g[1:, 1:] - g[:-1, :-1] - g[1:, :-1] + g[:-1, 1:]) / 2.0
    return float(np.median(np.abs(d)) / 0.6745)


def guard_weights(blurry: np.ndarray, reblurred: np.ndarray, confidence: float,
                  tile_gain: np.ndarray | None, global_gain: float, tile: int = 16,
                  middle: np.ndarray | None = None, edi_middle: np.ndarray | None = None,
                  ) -> np.ndarray:
    """Per-pixel weight (H, W) float32 in [0, 1] of the deconvolution against EDI.

    A tile scores 0 where the re-blurred result misses B by more than
    ``3σ + 0.01`` (RMS; σ = :func:`noise_level`), 1 below ``1.5σ + 0.004``, linearly between;
    times a score from the tile's own event contrast gain ``tile_gain`` (tiles, see
    :func:`tile_gains`; 0 where the motion blurs the tile's events, a gain ≤ 0.8, 1 from a
    gain of 1; ``global_gain`` is kept for callers that scale by it); times a
    global score from ``confidence`` (0 at a gain of 1.05, 1 from 1.2). Each tile then takes the
    smallest score of its 3×3 neighbourhood and the tiles are interpolated bilinearly.
    With ``middle`` and ``edi_middle`` (H, W[, 3]) a tile also scores 0 where the two middle
    frames differ by more than 0.06 RMS (1 below 0.03): EDI is the events' own reading of the
    frame, and a deconvolution along a wrong motion strays far from it.
    """
    import cv2
    from scipy.ndimage import minimum_filter

    h, w = blurry.shape[:2]
    sigma = noise_level(blurry)
    r = reblurred - blurry
    r2 = (r * r).mean(-1) if r.ndim == 3 else r * r
    th, tw = -(-h // tile), -(-w // tile)
    def tile_rms(sq):
        sq = sq.mean(-1) if sq.ndim == 3 else sq
        p = np.pad(sq, ((0, th * tile - h), (0, tw * tile - w)), mode="edge")
        return np.sqrt(p.reshape(th, tile, tw, tile).mean((1, 3)))

    rms = tile_rms(r2)
    lo, hi = 1.5 * sigma + 0.004, 3.0 * sigma + 0.01
    score = np.clip((hi - rms) / (hi - lo), 0.0, 1.0)
    if middle is not None and edi_middle is not None:
        diff = tile_rms((middle - edi_middle) ** 2)
        score = score * np.clip((0.06 - diff) / 0.03, 0.0, 1.0)
    if tile_gain is not None:
        score = score * np.clip((tile_gain - 0.8) / 0.2, 0.0, 1.0)
    score = score * float(np.clip((confidence - 1.05) / 0.15, 0.0, 1.0))
    score = minimum_filter(score, size=3, mode="nearest")
    up = cv2.resize(score.astype(np.float32), (tw * tile, th * tile),
                    interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(up[:h, :w])


def tile_gains(motion: GlobalMotion, x, y, u, width: int, height: int, tile: int = 16,
               min_events: int = 150) -> np.ndarray:
    """Per tile (⌈H/tile⌉, ⌈W/tile⌉): the contrast gain of the tile's events warped by
    ``motion`` over unwarped (variance ratio of the event images after a σ = 1 px Gaussian,
    both summed over the tile); tiles with fewer than ``min_events`` events get +inf (no
    evidence against the motion)."""
    from .motion.cmax import _blur, _votes

    zero = GlobalMotion(centre=motion.centre)
    th, tw = -(-height // tile), -(-width // tile)

    def tiled_energy(m):
        xm, ym = m.to_middle(u, x, y)
        img = _blur(_votes(xm, ym, width, height))
        img = np.pad(img, ((0, th * tile - height), (0, tw * tile - width)))
        blk = img.reshape(th, tile, tw, tile)
        return (blk * blk).sum((1, 3))

    # tiles are judged where their events *start* (the sensor position at zero motion)
    e0 = tiled_energy(zero)
    e1 = tiled_energy(motion)
    count = np.bincount((np.asarray(y, np.int64) // tile) * tw + np.asarray(x, np.int64) // tile,
                        minlength=th * tw).reshape(th, tw)
    gain = e1 / np.maximum(e0, 1e-12)
    gain[count < min_events] = np.inf
    return gain


@dataclass(frozen=True, eq=False)
class MotionDeblur:
    """What :func:`motion_deblur` made of one exposure.

    Attributes:
        frames: (K, H, W[, 3]) float32, the guarded blend of the deconvolution and EDI.
        weight: (H, W) float32 [0, 1], the deconvolution's share (0 = EDI).
        motion: the estimated motion.
        notes: what the user should know (a fallback to EDI and why).
    """

    frames: np.ndarray
    weight: np.ndarray
    motion: GlobalMotion
    notes: tuple[str, ...] = ()


def motion_deblur(blurry: np.ndarray, events, exposure, fractions, edi_frames: np.ndarray,
                  edi_middle: np.ndarray, hot_mask: np.ndarray | None = None,
                  config: DeconvConfig | None = None, motion=None) -> MotionDeblur:
    """Deconvolve ``blurry`` along the events' global motion and blend with EDI per tile.

    Args:
        blurry: (H, W[, 3]) float32; events, exposure: the window's events (µs).
        fractions: (K,) exposure fractions of the wanted frames.
        edi_frames: (K, H, W[, 3]) EDI's frames at ``fractions`` (the fallback).
        edi_middle: (H, W[, 3]) EDI's middle frame (the solver's first guess).
        hot_mask: (H, W) bool pixels whose events are ignored.
        motion: a motion to use instead of the estimate (e.g. the simulator's true path), with
            its ``confidence`` and ``events`` measured on these events; the guard is the same.
    """
    from .motion import MIN_EVENTS, estimate_motion

    given = motion is not None
    if motion is None:
        motion = estimate_motion(events, exposure, hot_mask)
    h, w = blurry.shape[:2]
    zero = np.zeros((h, w), np.float32)
    if motion.events < MIN_EVENTS:
        who = "the guard" if given else "motion"
        return MotionDeblur(edi_frames, zero, motion,
                            (f"only {motion.events} events in the exposure ({who} needs ≥ "
                             f"{MIN_EVENTS}): used EDI",))
    if motion.confidence < 1.05 or motion.max_displacement_px(w, h) < 0.25:
        said = ("the events are not sharpened by the given motion" if given else
                "the events show no clear global motion")
        return MotionDeblur(edi_frames, zero, motion,
                            (f"{said} (contrast gain {motion.confidence:.2f}): used EDI",))
    d = deconvolve(blurry, motion, config, start=edi_middle)
    ev = events.within(exposure)
    x, y = ev.x, ev.y
    u = (ev.t - exposure.start_us).astype(np.float64) / exposure.duration_us
    if hot_mask is not None and hot_mask.any() and len(x):
        keep = ~hot_mask[y, x]
        x, y, u = x[keep], y[keep], u[keep]
    gains = tile_gains(motion, x.astype(np.float64), y.astype(np.float64), u, w, h)
    wgt = guard_weights(blurry, d.reblurred, motion.confidence, gains, motion.confidence,
                        middle=d.frames([0.5])[0], edi_middle=edi_middle)
    deb = d.frames(fractions)
    ww = wgt[None, ..., None] if deb.ndim == 4 else wgt[None]
    out = (ww * deb + (1.0 - ww) * edi_frames).astype(np.float32)
    notes: tuple[str, ...] = ()
    share = float(wgt.mean())
    if share < 0.5:
        notes = (f"the motion explains only {100 * share:.0f} % of the frame: EDI used for "
                 "the rest",)
    return MotionDeblur(out, wgt, motion, notes)
