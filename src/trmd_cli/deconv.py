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

Inverse. ``min ½ Σ dᵢ (A(L) − B)ᵢ² + ½ α ‖L − E‖² + λ Σ huber_ε(|∇L|)`` by iteratively
reweighted least squares: each round solves ``(Aᵀ D A + α I_S + λ DᵀWD) L = Aᵀ D B + α E`` by
conjugate gradients with ``W = 1/max(|∇L|, ε)`` from the previous round (a TV-like prior that
keeps edges and does not amplify noise), preconditioned by the normal matrix's diagonal (the
prior's weights span two orders of magnitude and the canvas margin is seen by few instants:
Jacobi evens both out). ``E`` is an anchor, EDI's middle frame, held on the sensor pixels
``S``: it fills what the blur erased (the zeros of the motion's spectrum) from the events'
reading. ``D = diag(d)`` are data weights (:func:`data_weights`), 1 in the first round, then 0
where the local re-blur residual is well above the frame's residual floor: where the motion
does not explain B (an independent mover) the frame follows the anchor instead of smearing the
misfit around.

Guard (:func:`guard_weights`, :func:`agreement`, in :func:`motion_deblur`). Per pixel, the
deconvolution's share is where B is explained (the final data weights, widened) or the
motion predicts the events' change of log intensity (:func:`change_agreement`), where the
events of the tile are sharpened by the motion (:func:`tile_gains`), scaled by the motion's
global confidence; at each instant it is raised where the warped frame agrees with EDI's frame
of that instant. Elsewhere the output is EDI's. Where tiles of the frame move otherwise than
the global motion (:func:`~trmd_cli.motion.tiles.disputed_tiles`: something moves on its own
there), or the motion explains under half of the frame (it may have followed such a thing),
the background's motion (:func:`~trmd_cli.motion.tiles.background_motion`) is deconvolved
instead and kept where it predicts the events' change of log intensity over the exposure
(:func:`change_agreement`); when no background motion holds, a disputed global motion still
goes through the guard above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .motion.model import GlobalMotion
from .threads import RowBlocks, beside, product_threads, run_split

__all__ = ["DeconvConfig", "ANCHOR_CONTRAST", "NOISE_SCALE", "ANCHOR_DARK_GAIN", "anchor_gain",
           "BlurOperator", "deconvolve",
           "noise_level", "guard_weights", "Deconvolved", "data_weights", "agreement",
           "tile_gains", "tile_score", "trust_score", "FULL_TRUST_GAIN", "trusted_gain",
           "SPLIT_TRUST_PX", "motion_deblur", "MotionDeblur",
           "explained", "change_of_log", "predicted_change", "change_agreement", "CHANGE_SIGMA_PX",
           "CHANGE_TOLERANCE", "fit_contrast", "FIT_MIN_PIXELS", "FIT_MIN_SHARE",
           "FIT_MIN_CORRELATION"]


@dataclass(frozen=True)
class DeconvConfig:
    """The solver's settings.

    Attributes:
        penalty: λ, weight of the Huber gradient prior (intensity per pixel).
        huber: ε, intensity step per pixel below which the prior is quadratic.
        rounds: IRLS rounds (1 = a plain quadratic gradient penalty with weight λ/ε and no
            data reweighting).
        iterations: preconditioned conjugate-gradient iterations per round (each one product
            with ``A`` and one with ``Aᵀ``).
        step_px: largest motion between two of the J instants, pixels.
        margin_px: extra canvas around the motion's extent, pixels.
        anchor: α, weight of ``‖L − E‖²`` on the sensor pixels when an anchor frame ``E`` is
            given (EDI's middle frame): the ratio of B's noise variance to E's error variance.
            It fills what the blur erased (the zeros of the motion's spectrum) from the
            events' reading instead of from the gradient prior alone. This is its value at
            c = :data:`ANCHOR_CONTRAST`; :func:`motion_deblur` given the frame's c scales it
            by ``(ANCHOR_CONTRAST / c)²`` (:meth:`for_contrast`), and on a frame noisier
            than ``noise_ref`` by the square of their ratio (:meth:`for_noise`).
        anchor_reference: intensity ([0, 1]) below which a pixel's α grows as
            ``(anchor_reference / E)²``, E the anchor frame there (:func:`anchor_gain`).
            EDI's error is relative (each pixel's log intensity known to within a step c),
            so in intensity it shrinks with E: in a dark region the anchor knows the frame
            far better than ``anchor`` says, and a uniform α left the solver's noise at the
            blur's spectral zeros there (stripes across the motion inside esl-cups' dark
            cup). Above it α is kept, not lowered: the anchor also holds the frame where the
            motion is wrong, and lowering it cost mover frames 0.2 dB. None: uniform α.
        outlier: (lo, hi), with an anchor: the local RMS of the re-blur residual over the
            frame's residual floor (see :func:`data_weights`) at which a pixel of B starts to
            lose its data weight, and at which it has none; None = no reweighting.
        window_px: side of the square over which that local RMS is taken, pixels.
        noise_ref: B's noise σ (intensity) at which ``penalty`` and ``anchor`` are given;
            :func:`motion_deblur` scales them by B's measured σ over this (:meth:`for_noise`).
            None: as given.
        noise: B's noise σ (intensity) to scale by and to judge the re-blur residual against
            (:func:`data_weights`); None: measured on B (:func:`noise_level`). Given for a
            frame whose fixed pattern was removed (:mod:`trmd_cli.fixed_pattern`), whose σ
            falls to a third on esl-cups: the σ measured after the removal lets the solver's
            rings through there (events explained 0.820 with the pattern kept → 0.793), the
            σ as recorded holds back what simulated pans gain (motion method, the three pans
            of bench/bench_fixed_pattern.py: −0.36 / −0.05 / +0.03 dB against +0.44 / +0.42 /
            +0.02). Halfway in variance: +0.13 / +0.29 / +0.39 dB, and 0.837 on esl-cups.
    """

    penalty: float = 2e-4
    huber: float = 0.01
    rounds: int = 3
    iterations: int = 10
    step_px: float = 0.5
    margin_px: int = 3
    anchor: float = 0.003
    anchor_reference: float | None = 0.3
    outlier: tuple[float, float] | None = (1.3, 2.2)
    window_px: int = 9
    noise_ref: float | None = 0.005
    noise: float | None = None

    def for_noise(self, sigma: float) -> DeconvConfig:
        """These settings for a blurry frame whose noise σ is ``sigma`` (intensity, e.g.
        :func:`noise_level`), with ``r = σ / noise_ref``: λ scaled by ``r`` up to σ =
        ``noise_ref`` and by ``r²`` above it, α by ``r²`` above it, each factor within
        :data:`NOISE_SCALE`.

        The data term weighs B as 1/σ² would, so the prior and the anchor held against it
        should weigh σ² as much. Below ``noise_ref`` the prior only has to hold back what the
        data cannot tell from noise: on a clean frame a weaker one keeps finer texture (on the
        pinned set, whose frames measure σ ≈ 0.002, λ ∝ σ gave +0.17 / +0.46 dB middle /
        sequence over a fixed λ), and the anchor keeps its weight. Above it, λ ∝ σ let the
        noise through: on the pinned set with Gaussian noise of σ = 0.01 added to B the
        motion method went from 30.15 / 30.20 to 31.30 / 30.78 dB with λ and α ∝ σ² (EDI given
        the true c 29.06 / 27.60), and from 30.31 / 30.33 to 31.35 / 30.87 with shot noise
        (σ² = 4e-5 + 1.2e-4·B)."""
        if self.noise_ref is None or not (math.isfinite(sigma) and sigma >= 0):
            return self
        lo, hi = NOISE_SCALE
        r = sigma / self.noise_ref
        if r <= 1.0:
            return replace(self, penalty=self.penalty * max(r, lo))
        f = min(r * r, hi)
        return replace(self, penalty=self.penalty * f, anchor=self.anchor * f)

    def for_contrast(self, contrast: float | None) -> DeconvConfig:
        """These settings for a frame whose events step by ``contrast`` (c, log intensity):
        α scaled by ``(ANCHOR_CONTRAST / c)²``. EDI's error is the events' quantisation —
        each pixel's log intensity known to within one step c, an intensity error ∝ c — so
        its variance, and the anchor's weight against B, go as 1/c². None: unchanged."""
        if contrast is None or not (math.isfinite(contrast) and contrast > 0):
            return self
        return replace(self, anchor=self.anchor * (ANCHOR_CONTRAST / float(contrast)) ** 2)


#: the contrast threshold c at which :attr:`DeconvConfig.anchor` is given (a DAVIS-like
#: sensor: on the pinned set α = 0.003 there is best among 0.0003–0.03, and on a c = 0.7
#: set α scaled by (0.3 / 0.7)² is within 0.03 dB of the best fixed α found there)
ANCHOR_CONTRAST = 0.3
#: the range of the factors :meth:`DeconvConfig.for_noise` scales λ and α by
NOISE_SCALE = (0.25, 32.0)
#: the most :func:`anchor_gain` raises α by (reached at a tenth of the reference intensity)
ANCHOR_DARK_GAIN = 100.0


def anchor_gain(anchor: np.ndarray, reference: float, sigma_px: float = 1.0) -> np.ndarray:
    """The factor on each pixel's anchor weight α: ``(reference / E)²`` where E is below
    ``reference``, 1 elsewhere, at most :data:`ANCHOR_DARK_GAIN`.

    Args:
        anchor: (H, W[, 3]) the anchor frame (intensity, [0, 1]); channels are averaged.
        reference: intensity at which the factor is 1.
        sigma_px: E is the anchor smoothed over this σ (pixels), so that one pixel's noise
            does not set its own weight.
    Returns:
        (H, W) float32, ≥ 1.
    """
    import cv2

    e = anchor.mean(-1) if anchor.ndim == 3 else anchor
    e = cv2.GaussianBlur(np.ascontiguousarray(e, np.float32), (0, 0), sigma_px,
                         borderType=cv2.BORDER_REFLECT)
    floor = reference / math.sqrt(ANCHOR_DARK_GAIN)
    return np.square(reference / np.clip(e, floor, reference)).astype(np.float32)


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
        # Aᵀ stored as its own CSR: a row-wise product beats the CSC view of A
        self.matrix, self.matrix_t = _stencil_matrix(motion, width, height, self.fractions,
                                                     self.pad, real)
        self._apply, self._adjoint = RowBlocks(self.matrix), RowBlocks(self.matrix_t)
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
        return self._apply @ x

    def adjoint_np(self, y: np.ndarray) -> np.ndarray:
        """``Aᵀ y`` on pixel-major arrays: (H·W, C) → (Hp·Wp, C)."""
        return self._adjoint @ y

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
                    real) -> tuple[object, object]:
    """``A`` as a (H·W, Hp·Wp) CSR matrix of dtype ``real``, and ``Aᵀ`` as its own CSR
    matrix: row ``y·W + x`` of ``A`` holds the J bilinear stencils (weight 1/J each) of where
    ``motion`` carries sensor pixel (x, y) back to on the canvas; taps off the canvas weigh
    nothing (as ``grid_sample`` with zero padding). Both have sorted, unique indices. Bands
    of sensor rows are built on :func:`~trmd_cli.threads.product_threads` threads (their
    array work releases the interpreter): the same matrix."""
    import scipy.sparse as sp

    parts = min(product_threads(), height)
    cuts = [height * k // parts for k in range(parts + 1)]
    bands = run_split(lambda k: _stencil_rows(motion, cuts[k], cuts[k + 1], width, height,
                                              fractions, pad, real), parts)
    if parts == 1:
        return bands[0]
    return (sp.vstack([a for a, _ in bands], format="csr"),
            sp.hstack([at for _, at in bands], format="csr"))


def _stencil_rows(motion, first: int, stop: int, width: int, height: int,
                  fractions: np.ndarray, pad: int, real) -> tuple[object, object]:
    """Rows ``first·W`` to ``stop·W`` of :func:`_stencil_matrix`'s ``A`` (sensor rows
    ``first`` to ``stop``) and their transpose, merged and sorted."""
    import scipy.sparse as sp

    hp, wp = height + 2 * pad, width + 2 * pad
    rows = stop - first
    n, nj = rows * width, len(fractions)
    ys, xs = np.mgrid[first:stop, 0:width].astype(np.float64)
    # (J, 4, n): each instant's taps written contiguously, reordered row-major once at the end
    cols = np.empty((nj, 4, n), np.int32)
    vals = np.empty((nj, 4, n), real)
    for j in range(nj):
        # one instant at a time: (rows, W) temporaries, not J times as many
        xm, ym = motion.to_middle(fractions[j:j + 1, None, None], xs[None], ys[None])
        xc = np.broadcast_to(xm, (1, rows, width)).reshape(n) + pad
        yc = np.broadcast_to(ym, (1, rows, width)).reshape(n) + pad
        x0, y0 = np.floor(xc), np.floor(yc)
        fx, fy = (xc - x0) / nj, yc - y0
        gx, gy = 1.0 / nj - fx, 1.0 - fy
        inside = bool(x0.min() >= 0 and x0.max() < wp - 1 and y0.min() >= 0
                      and y0.max() < hp - 1)
        # the products in float64, rounded once into the table; the indices in int32 from the
        # start (exact: the canvas has far fewer than 2³¹ pixels)
        i0 = (y0 * wp + x0).astype(np.int32) if inside else None
        for k, (off, a, b) in enumerate(((0, gx, gy), (1, fx, gy), (wp, gx, fy),
                                         (wp + 1, fx, fy))):
            if inside:
                np.add(i0, off, out=cols[j, k])
            np.multiply(a, b, out=vals[j, k], casting="unsafe")
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
    # consecutive instants share taps: merged, each product touches ~2× fewer entries. The
    # transpose is built by a counting sort over the rows in order, so each of its rows comes
    # out sorted with the duplicates side by side and is merged in one pass; sorting A's rows
    # instead cost 1.4× the whole build (a 30 px motion: 22 M taps)
    at = a.T.tocsr()
    at.has_sorted_indices = True
    at.sum_duplicates()
    return at.T.tocsr(), at


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
        data_weight: (H, W) float32 [0, 1], how much each pixel of B counted in the last
            round (1 everywhere without reweighting; 0 = the motion does not explain it).
        rounds: the IRLS rounds solved (fewer than asked when ``deconvolve``'s ``stop``
            ended it).
    """

    operator: BlurOperator
    middle: object
    reblurred: np.ndarray
    data_weight: np.ndarray | None = None
    rounds: int = 0

    def frames(self, fractions) -> np.ndarray:
        """The middle frame warped to ``fractions`` of the exposure: (K, H, W[, 3]) float32."""
        import torch

        with torch.no_grad():
            out = self.operator.warp(self.middle, fractions).numpy()
        out = out.transpose(0, 2, 3, 1)
        return np.ascontiguousarray(out[..., 0] if out.shape[-1] == 1 else out,
                                    dtype=np.float32)


#: smallest residual floor (intensity RMS) the data weights are measured against: what the
#: bilinear blur model and a motion good to ~0.1 px leave at strong edges of a noise-free
#: frame, so that is not taken for a wrong motion (on the docs figure's noise-free frame a
#: floor of 0.002 dropped 8 % of it along the exact path, 0.003 drops 1 %)
RESIDUAL_FLOOR = 0.003


def data_weights(residual: np.ndarray, blurry: np.ndarray, outlier: tuple[float, float],
                 window_px: int = 9, noise: float | None = None) -> np.ndarray:
    """How much each pixel of B should count, from the re-blur residual ``A(L) − B``.

    The residual's local RMS (a ``window_px`` square) is compared with the frame's residual
    floor ``s``: its lower quartile over the frame — the level a right motion leaves, noise
    *and* the solver's own regularisation bias included, as long as a quarter of the frame
    follows the motion — but never above :func:`noise_level` of B (a motion that explains B
    nowhere has a high floor, and is judged against B's noise instead) nor below
    :data:`RESIDUAL_FLOOR`. A pixel weighs 1 up to ``lo·s``, 0 from ``hi·s``, linearly
    between.

    Args:
        residual, blurry: (H, W[, 3]) float32 (intensity).
        outlier: (lo, hi), ratios of the local RMS to ``s``.
        noise: B's noise σ to cap ``s`` with (None: :func:`noise_level` of B).
    Returns:
        (H, W) float32 in [0, 1].
    """
    import cv2

    r2 = residual * residual
    r2 = r2.mean(-1) if r2.ndim == 3 else r2
    k = max(int(window_px), 1)
    local = cv2.blur(np.ascontiguousarray(r2, np.float32), (k, k),
                     borderType=cv2.BORDER_REFLECT)
    floor = math.sqrt(max(float(np.percentile(local, 25)), 0.0))
    s = max(min(floor, noise_level(blurry) if noise is None else noise), RESIDUAL_FLOOR)
    lo, hi = outlier
    rho = np.sqrt(np.maximum(local, 0.0)) / s
    return np.clip((hi - rho) / (hi - lo), 0.0, 1.0).astype(np.float32)


def deconvolve(blurry: np.ndarray, motion, config: DeconvConfig | None = None,
               start: np.ndarray | None = None, fractions=None,
               anchor: np.ndarray | None = None, stop=None) -> Deconvolved:
    """Recover the middle frame of ``blurry`` (H, W[, 3]) float32 along ``motion``.

    ``start`` (H, W[, 3]): the first guess (default: B itself), e.g. EDI's middle frame;
    ``fractions``: the blur model's J instants (default: see :class:`BlurOperator`);
    ``anchor`` (H, W[, 3]): a second reading of the middle frame (EDI's), held with weight
    ``config.anchor``; with it, from the second round on, pixels of B that re-blurring does not
    explain lose their data weight (:func:`data_weights`, ``config.outlier``), so the frame
    follows the anchor where the motion is wrong instead of smearing the misfit around.
    ``stop``: ``(k, data_weight) -> bool``, asked before reweighted round ``k`` (1, 2, …) with
    the (H, W) data weights the frame so far earns; True ends the solve there, the result
    that frame with those weights (:attr:`Deconvolved.rounds` says how many rounds ran). For
    a caller that discards a motion explaining too little of B: the rounds left would not
    change that verdict, only cost its time.
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
    # A² for the Jacobi preconditioner's data term, diag(Aᵀ diag(d) A) = (A²)ᵀ d: Aᵀ's
    # entries squared in place of a copy (merged entries, so each is one tap's whole weight)
    sq_t = op.matrix_t.copy()
    np.square(sq_t.data, out=sq_t.data)
    aw = np.zeros((hp, wp, 1), np.float32)
    if anchor is not None and cfg.anchor > 0:
        # only the sensor is read by the anchor: what moved into view stays B's to explain
        p = op.pad
        gain = 1.0 if cfg.anchor_reference is None else \
            anchor_gain(anchor, cfg.anchor_reference)[..., None]
        aw[p:p + h, p:p + w] = cfg.anchor * gain
        e = np.ascontiguousarray(op.pad_frame(anchor).numpy().transpose(1, 2, 0), np.float32)
        ae = aw * e
    else:
        ae = None
    reweight = ae is not None and cfg.outlier is not None
    d = np.ones((h * w, 1), np.float32)
    lam, eps = float(cfg.penalty), float(cfg.huber)
    rounds = solved = max(cfg.rounds, 1)
    re = None
    for k in range(rounds):
        if k > 0 and reweight:
            re = op.apply_np(x.reshape(hp * wp, c)).reshape(h, w, c)
            res = re - b.reshape(h, w, c)
            d = data_weights(res[..., 0] if c == 1 else res, blurry, cfg.outlier,
                             cfg.window_px, cfg.noise).reshape(h * w, 1)
            if stop is not None and stop(k, d.reshape(h, w)):
                solved = k
                break
        if k == 0 or reweight:
            rhs = op.adjoint_np(d * b).reshape(hp, wp, c)
            if ae is not None:
                rhs += ae
            ata = np.asarray(sq_t @ d, np.float32).reshape(hp, wp, 1)
        if cfg.rounds == 1:
            lw = np.full((hp, wp, c), lam / eps, np.float32)
        else:
            gx, gy = _grad(x)
            lw = (lam / np.maximum(np.sqrt(gx * gx + gy * gy), eps)).astype(np.float32)

        def normal(v: np.ndarray, lw: np.ndarray = lw, d: np.ndarray = d) -> np.ndarray:
            vx, vy = _grad(v)
            vx *= lw
            vy *= lw
            av = op.apply_np(v.reshape(hp * wp, c))
            if reweight:
                av *= d
            out = op.adjoint_np(av).reshape(hp, wp, c)
            out += _grad_t(vx, vy)
            if ae is not None:
                out += aw * v
            return out

        # diag(λ DᵀWD): the difference leaving a pixel and the one arriving from its left
        # (upper) neighbour, each with its own weight
        dia = ata + 2.0 * lw + aw
        dia[:, -1] -= lw[:, -1]
        dia[-1] -= lw[-1]
        dia[:, 1:] += lw[:, :-1]
        dia[1:] += lw[:-1]
        x = _pcg(normal, rhs, x, 1.0 / np.maximum(dia, 1e-12), cfg.iterations)
    if solved == rounds:
        re = op.apply_np(x.reshape(hp * wp, c)).reshape(h, w, c)
    re = re[..., 0] if blurry.ndim == 2 else re
    if reweight and solved == rounds:
        # the weights the final frame earns (the last round used the previous frame's)
        d = data_weights(re - blurry, blurry, cfg.outlier, cfg.window_px,
                         cfg.noise).reshape(h * w, 1)
    middle = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))
    return Deconvolved(op, middle, np.ascontiguousarray(re, dtype=np.float32),
                       np.ascontiguousarray(d.reshape(h, w), dtype=np.float32), solved)


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
    """σ of the white noise of ``blurry`` (intensity), by Immerkær's estimate (1996): the mean
    absolute response to the 3×3 mask that annihilates planes (and so most of what motion
    blur leaves of the scene), ``σ = √(π/2) · mean|I ∗ N| / 6``, on the interior; texture
    can only raise it."""
    import cv2

    g = blurry.mean(-1) if blurry.ndim == 3 else blurry
    if min(g.shape) < 3:
        return 0.0
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(np.ascontiguousarray(g, np.float32), -1, mask)[1:-1, 1:-1]
    return float(math.sqrt(math.pi / 2.0) * np.abs(r).mean() / 6.0)


def guard_weights(data_weight: np.ndarray, confidence: float,
                  tile_gain: np.ndarray | None = None, tile: int = 16, spread_px: int = 5,
                  events_agree: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel weight (H, W) float32 in [0, 1] of the deconvolution against EDI.

    ``data_weight`` (H, W) is where re-blurring the deconvolution explains B
    (:attr:`Deconvolved.data_weight`): a pixel of B the motion does not explain was swept by
    something that moved otherwise at some instant of the exposure, so EDI is kept there at
    every instant. It is widened by its minimum over ``spread_px`` (the misfit's edge is soft)
    and smoothed by a box of the same size. Times a score from each tile's own event contrast
    gain ``tile_gain`` (⌈H/tile⌉, ⌈W/tile⌉; see :func:`tile_gains`: 0 where the motion blurs
    the tile's events, a gain ≤ 0.8, 1 from a gain of 1, interpolated bilinearly); times a
    global score from ``confidence`` (the motion's contrast gain: 0 at 1.05, 1 from 1.1).
    ``events_agree`` (H, W) in [0, 1] (:func:`change_agreement`), when given, raises the
    widened data weight to itself: where the events' change of log intensity confirms the
    motion, B's noise (an APS's shot noise, which grows with intensity) failing the residual
    test does not hand the pixel to EDI and its events' speckle.
    """
    h, w = data_weight.shape
    wgt = explained(data_weight, spread_px)
    if events_agree is not None:
        wgt = np.maximum(wgt, events_agree)
    if tile_gain is not None:
        wgt = wgt * tile_score(tile_gain, w, h, tile)
    wgt = wgt * trust_score(confidence)
    return np.ascontiguousarray(wgt, np.float32)


def explained(data_weight: np.ndarray, spread_px: int = 5) -> np.ndarray:
    """Where re-blurring explains B, softly: ``data_weight`` (H, W) widened by its minimum over
    ``spread_px`` (the misfit's edge is soft) and smoothed by a box of the same size; (H, W)
    float32 in [0, 1]."""
    import cv2

    k = max(int(spread_px), 1)
    wgt = cv2.erode(np.ascontiguousarray(data_weight, np.float32), np.ones((k, k), np.uint8),
                    borderType=cv2.BORDER_REPLICATE)
    return cv2.blur(wgt, (k, k), borderType=cv2.BORDER_REPLICATE)


#: σ (pixels) of the neighbourhood over which the events' and the deconvolution's changes of
#: log intensity are compared, and over which a rejection spreads
CHANGE_SIGMA_PX = 4.0
#: largest local RMS of the two changes' difference where the motion holds, in contrast
#: thresholds (one level: the events' own rounding is c/√12 RMS)
CHANGE_TOLERANCE = 1.0


def change_of_log(events, exposure, width: int, height: int, contrast: float,
                  hot_mask: np.ndarray | None = None) -> np.ndarray:
    """What the events say each pixel's log intensity did over ``exposure``: ``c · Σ p``,
    (H, W) float32 (hot pixels' events left out)."""
    ev = events.within(exposure)
    x, y = ev.x.astype(np.int64), ev.y.astype(np.int64)
    p = ev.p.astype(np.float64)
    if hot_mask is not None and hot_mask.any() and len(x):
        keep = ~hot_mask[y, x]
        x, y, p = x[keep], y[keep], p[keep]
    s = np.bincount(y * width + x, weights=p, minlength=width * height)
    return (contrast * s).reshape(height, width).astype(np.float32)


def predicted_change(solved: Deconvolved) -> np.ndarray:
    """The change of log intensity over the exposure a deconvolution predicts: its frame
    carried to the exposure's two ends, ``log(L(1) + 0.02) − log(L(0) + 0.02)`` (the offset
    keeps dark pixels' noise from dominating), (H, W) float32 (colour: the channels' mean)."""
    ends = solved.frames([0.0, 1.0])
    if ends.ndim == 4:
        ends = ends.mean(-1)
    ends = np.log(np.maximum(ends, 0.0) + np.float32(0.02))
    return ends[1] - ends[0]


def change_agreement(solved: Deconvolved, change: np.ndarray, contrast: float,
                     sigma_px: float = CHANGE_SIGMA_PX,
                     tolerance: float = CHANGE_TOLERANCE) -> np.ndarray:
    """Where the deconvolution's motion predicts the events: (H, W) float32 in [0, 1].

    The frame carried to the exposure's two ends gives each pixel's change of log intensity
    over the exposure under that motion; the events measured it (``change``, see
    :func:`change_of_log`). The RMS of their difference over a σ = ``sigma_px`` Gaussian
    neighbourhood is at most ``tolerance`` thresholds (``tolerance · contrast``) where the
    motion holds; a pixel beyond it is rejected, and the rejection spreads by the same
    Gaussian (weight 0 where at least half of the neighbourhood is rejected).

    The RMS, not the smoothed signed difference: a motion a pixel off mispredicts the change
    by ±the texture's gradient, which cancels in a mean over a textured neighbourhood and not
    in its square (a background motion 1.4 px off at the start of a noise-free exposure with
    a mover passed a signed test, the smoothed difference within 0.06, on 68 % of the frame
    and lost 1.5 dB to EDI; the RMS kept 40 % and gained 0.2). Something that moves
    otherwise changes its pixels as the motion does not, whether or not B shows it.
    """
    import cv2

    miss = np.ascontiguousarray(predicted_change(solved) - change, np.float32)
    local = np.sqrt(np.maximum(cv2.GaussianBlur(miss * miss, (0, 0), sigma_px), 0.0))
    rejected = cv2.GaussianBlur((local > tolerance * contrast).astype(np.float32), (0, 0),
                                sigma_px)
    return (1.0 - np.clip(2.0 * rejected, 0.0, 1.0)).astype(np.float32)


#: the global contrast gain below which the events show no clear global motion (EDI is used)
MIN_GAIN = 1.05
#: the global contrast gain from which :func:`trust_score` trusts a motion whole (from
#: :data:`MIN_GAIN`, where trust begins)
FULL_TRUST_GAIN = 1.1


def trust_score(confidence: float) -> float:
    """How far the motion's global contrast gain lets it be trusted: 0 at 1.05, 1 from
    :data:`FULL_TRUST_GAIN` (a small motion sharpens its events little even when exact: 1.13
    along a true path that moves the frame at most 3.3 px from the middle; the data and tile
    tests judge the rest)."""
    return float(np.clip((confidence - MIN_GAIN) / (FULL_TRUST_GAIN - MIN_GAIN), 0.0, 1.0))


#: an estimate whose gain earns only partial trust (:func:`trust_score`) is trusted whole when
#: the motions found from its even and its odd events lie within this many pixels
#: (:func:`~trmd_cli.motion.split_agreement`): many events agreeing on a small motion
SPLIT_TRUST_PX = 0.1


def trusted_gain(motion, events, exposure, hot_mask: np.ndarray | None = None) -> float:
    """The contrast gain an estimated ``motion`` is trusted as: its own, or
    :data:`FULL_TRUST_GAIN` where the gain alone gives partial trust and its two halves of
    events agree within :data:`SPLIT_TRUST_PX`. A small motion's gain is low even when its
    estimate is right to a tenth of a pixel (pinned frame 6: 1.058 at 0.08 px); estimates
    0.2–0.4 px off have gains as low, but there the halves disagree (on few events the error
    is mostly their noise)."""
    from .motion import split_agreement

    gain = float(motion.confidence)
    if not 0.0 < trust_score(gain) < 1.0:
        return gain
    spread = split_agreement(events, exposure, motion, hot_mask)
    return FULL_TRUST_GAIN if spread <= SPLIT_TRUST_PX else gain


def tile_score(tile_gain: np.ndarray, width: int, height: int, tile: int = 16) -> np.ndarray:
    """(H, W) float32 in [0, 1] from the tiles' event contrast gains (see :func:`tile_gains`):
    0 where the motion blurs a tile's events (a gain ≤ 0.8), 1 from a gain of 1, interpolated
    bilinearly between the tiles."""
    import cv2

    th, tw = tile_gain.shape
    score = np.clip((tile_gain - 0.8) / 0.2, 0.0, 1.0).astype(np.float32)
    up = cv2.resize(score, (tw * tile, th * tile), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(up[:height, :width])


#: least mean guard weight (share of the frame the motion explains; for an estimate, before
#: the global gain's trust, :func:`trust_score`) for the deconvolution to be used at all
MIN_SHARE = 0.5

#: the share of the frame (mean guard weight) under which the deconvolution along the global
#: motion stops before IRLS round k (of 3): its verdict, under :data:`MIN_SHARE`, would not
#: change. The share rose by at most 0.14 after round 1 and 0.05 after round 2 on 24 frames
#: with independent movers (0.05 and 0.005 on the 48 pinned frames); a stop there saves two
#: thirds or a third of that deconvolution where the second chance follows
EARLY_SHARE = {1: 0.3, 2: 0.4}

#: least mean weight of the background's motion (:func:`change_agreement` times
#: :func:`explained`) for its deconvolution to be used where one global motion did not hold
BACKGROUND_SHARE = 0.25

#: least share of the frame the motion must explain for :func:`agreement` to be measured
AGREEMENT_SHARE = 0.25


def agreement(frame: np.ndarray, edi_frame: np.ndarray, explained: np.ndarray,
              lo: float = 1.5, hi: float = 3.0, window_px: int = 9) -> np.ndarray:
    """Where the deconvolution carried to one instant agrees with EDI's frame of that instant:
    (H, W) float32 in [0, 1].

    The local RMS (a ``window_px`` square) of their difference is compared with its median
    over the pixels the motion explains (``explained`` (H, W) bool): there the deconvolution
    is right, so that median is EDI's own error at this instant, whatever c and the events'
    noise make it — no absolute threshold rejects a right motion because EDI is poor. 1 up to
    ``lo`` times it, 0 from ``hi`` times. Something that moved otherwise sits elsewhere in the
    two frames at any instant but the middle, and disagrees by its own contrast. All zeros
    where less than :data:`AGREEMENT_SHARE` of the frame is explained (no reference).
    """
    import cv2

    if explained.mean() < AGREEMENT_SHARE:
        return np.zeros(explained.shape, np.float32)
    d2 = (frame - edi_frame) ** 2
    d2 = d2.mean(-1) if d2.ndim == 3 else d2
    k = max(int(window_px), 1)
    local = np.sqrt(np.maximum(cv2.blur(np.ascontiguousarray(d2, np.float32), (k, k),
                                        borderType=cv2.BORDER_REFLECT), 0.0))
    floor = max(float(np.median(local[explained])), 1e-6)
    return np.clip((hi - local / floor) / (hi - lo), 0.0, 1.0).astype(np.float32)


def tile_gains(motion, x, y, u, width: int, height: int, tile: int = 16,
               min_events: int = 150) -> np.ndarray:
    """Per tile (⌈H/tile⌉, ⌈W/tile⌉): how much ``motion`` sharpens the tile's own events.

    A tile's events are those ``motion`` carries into it (middle-frame position): the energy
    of their image carried to the middle over that of the same events as recorded, each
    voted bilinearly and smoothed by a σ = 1 px Gaussian in a window around the tile wide
    enough for both. Judging one set of events both ways keeps the ratio a contrast gain even
    where the motion is several tiles long (tiles cut at fixed sensor positions would compare
    different events). Tiles with fewer than ``min_events`` events get +inf (no evidence
    against the motion).

    Args:
        motion: anything with ``to_middle`` and ``max_displacement_px`` (pixels, exposure
            fractions).
        x, y, u: the events, pixels and exposure fractions.
    """
    from scipy.ndimage import gaussian_filter

    th, tw = -(-height // tile), -(-width // tile)
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    xm, ym = motion.to_middle(np.asarray(u, np.float64), x, y)
    tx, ty = np.floor(xm / tile), np.floor(ym / tile)
    keep = (tx >= 0) & (tx < tw) & (ty >= 0) & (ty < th)
    x, y, xm, ym = x[keep], y[keep], xm[keep], ym[keep]
    tid = (ty[keep] * tw + tx[keep]).astype(np.int64)
    count = np.bincount(tid, minlength=th * tw).reshape(th, tw)
    gain = np.full((th, tw), np.inf)
    if not len(tid):
        return gain
    # the window: the tile, the largest displacement (where its events were recorded) and
    # the Gaussian's reach, on every side
    reach = int(math.ceil(motion.max_displacement_px(width, height))) + 5
    side = tile + 2 * reach
    ox = (tid % tw) * tile - reach
    oy = (tid // tw) * tile - reach
    base = tid * (side * side)

    def energy(px: np.ndarray, py: np.ndarray) -> np.ndarray:
        lx = np.clip(px - ox, 0.0, side - 1.001)
        ly = np.clip(py - oy, 0.0, side - 1.001)
        x0, y0 = np.floor(lx), np.floor(ly)
        fx, fy = lx - x0, ly - y0
        i = base + (y0 * side + x0).astype(np.int64)
        acc = np.bincount(np.concatenate((i, i + 1, i + side, i + side + 1)),
                          np.concatenate(((1 - fx) * (1 - fy), fx * (1 - fy),
                                          (1 - fx) * fy, fx * fy)),
                          minlength=th * tw * side * side)
        img = gaussian_filter(acc.reshape(th * tw, side, side).astype(np.float32),
                              (0, 1.0, 1.0), mode="constant", truncate=4.0)
        return (img.astype(np.float64) ** 2).sum((1, 2)).reshape(th, tw)

    e1 = energy(xm, ym)
    e0 = energy(x, y)
    ok = count >= min_events
    gain[ok] = e1[ok] / np.maximum(e0[ok], 1e-12)
    return gain


@dataclass(frozen=True, eq=False)
class MotionDeblur:
    """What :func:`motion_deblur` made of one exposure.

    Attributes:
        frames: (K, H, W[, 3]) float32, the guarded blend of the deconvolution and EDI.
        weight: (H, W) float32 [0, 1], where the motion explains B (:func:`guard_weights`):
            the deconvolution's share at every instant at least (0 = EDI).
        motion: the estimated motion.
        notes: what the user should know (a fallback to EDI and why).
        weights: (K, H, W) float32 [0, 1], the deconvolution's share in each frame (``weight``
            or more where the frame agrees with EDI's, see :func:`agreement`); None where
            EDI was used throughout.
        fallback_contrast: c of the EDI frames blended in, fitted to the deconvolution along
            the global motion where re-blurring explains B (:func:`fit_contrast`); None:
            the ``contrast`` given.
    """

    frames: np.ndarray
    weight: np.ndarray
    motion: GlobalMotion
    notes: tuple[str, ...] = ()
    weights: np.ndarray | None = None
    fallback_contrast: float | None = None


def motion_deblur(blurry: np.ndarray, events, exposure, fractions, edi_frames: np.ndarray,
                  edi_middle: np.ndarray, hot_mask: np.ndarray | None = None,
                  config: DeconvConfig | None = None, motion=None,
                  contrast: float | None = None, edi_at=None) -> MotionDeblur:
    """Deconvolve ``blurry`` along the events' global motion, anchored to EDI, and blend with
    EDI's frames where the motion does not explain B or the events (see the module docstring).

    Args:
        blurry: (H, W[, 3]) float32; events, exposure: the window's events (µs).
        fractions: (K,) exposure fractions of the wanted frames.
        edi_frames: (K, H, W[, 3]) EDI's frames at ``fractions`` (the fallback).
        edi_middle: (H, W[, 3]) EDI's middle frame (the solver's first guess and its
            anchor).
        hot_mask: (H, W) bool pixels whose events are ignored.
        motion: a motion to use instead of the estimate (e.g. the simulator's true path), with
            its ``confidence`` and ``events`` measured on these events; the guard is the same.
        contrast: c the EDI frames were made with; it sets the anchor's weight
            (:meth:`DeconvConfig.for_contrast`). None = ``config.anchor`` as given.
        edi_at: ``c -> (K, H, W[, 3])`` EDI's frames at ``fractions`` for another c. Given,
            the EDI frames blended in (and given back where the motion is not used) are
            those with the c the deconvolution along the global motion implies where
            re-blurring explains B (:func:`fit_contrast`); the anchor keeps ``contrast``.

    The prior's weight follows B's measured noise (:meth:`DeconvConfig.for_noise`).
    """
    from .motion.tiles import TileEvidence

    # the tiles' votes and the background's motion do not depend on the global estimate:
    # begun in the helper process (when one is ready) while this one makes that estimate
    tiles = TileEvidence(events, exposure, hot_mask) \
        if motion is None and contrast is not None else None
    try:
        return _motion_deblur(blurry, events, exposure, fractions, edi_frames, edi_middle,
                              hot_mask, config, motion, contrast, edi_at, tiles)
    finally:
        if tiles is not None:
            tiles.drop()


def _motion_deblur(blurry: np.ndarray, events, exposure, fractions, edi_frames: np.ndarray,
                   edi_middle: np.ndarray, hot_mask: np.ndarray | None,
                   config: DeconvConfig | None, motion, contrast: float | None, edi_at,
                   tiles) -> MotionDeblur:
    """:func:`motion_deblur`, with ``tiles`` (a :class:`~trmd_cli.motion.tiles.TileEvidence`)
    where the motion is estimated and c is known."""
    from .motion import MIN_EVENTS, estimate_motion
    from .motion.cmax import window_points
    from .motion.tiles import disputed_tiles, outvoted_tiles

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
    cfg = (DeconvConfig() if config is None else config).for_contrast(contrast)
    cfg = cfg.for_noise(noise_level(blurry) if cfg.noise is None else cfg.noise)

    fitted = None
    tried = False  # the background's deconvolution was tried and fell back to EDI

    def second_chance(reason: str, solved: Deconvolved | None = None) -> MotionDeblur:
        # (``edi_frames`` and ``fitted`` as they stand when called)
        fallback = MotionDeblur(edi_frames, zero, motion, (reason,), fallback_contrast=fitted)
        if tried:
            return fallback
        return _background_deblur(blurry, events, exposure, fractions, edi_frames, edi_middle,
                                  hot_mask, cfg, contrast, fallback,
                                  motion if given else None, solved, tiles)

    points = window_points(events, exposure, hot_mask)
    if tiles is not None:
        # tiles that something else moves (:func:`~trmd_cli.motion.tiles.disputed_tiles`)
        # send the frame to the background's motion first, with the events' change test
        votes = tiles.votes()
        disputed = disputed_tiles(votes, motion, points, w, h)
        if disputed and outvoted_tiles(votes, w, h) is not None:
            res = second_chance(f"{len(disputed)} of {len(votes)} tiles move otherwise than "
                                f"the global motion: used EDI")
            if res.weights is not None:
                return res
            # no background motion holds: the global motion, guarded as on any frame
            tried = True

    if motion.confidence < MIN_GAIN or motion.max_displacement_px(w, h) < 0.25:
        said = ("the events are not sharpened by the given motion" if given else
                "the events show no clear global motion")
        reason = f"{said} (contrast gain {motion.confidence:.2f}): used EDI"
        # a given path may be right where something else's events pull its gain down; an
        # estimate with no clear gain has no motion for the tiles to find either
        return second_chance(reason) if given else MotionDeblur(edi_frames, zero, motion,
                                                                (reason,))
    # the tiles' gains, and how far an estimate is trusted, need only the motion: measured
    # beside the deconvolution
    gains_later = beside(tile_gains, motion, *points, w, h)
    trust_later = None if given else beside(trusted_gain, motion, events, exposure, hot_mask)

    def hopeless(k: int, data_weight: np.ndarray) -> bool:
        # the share as the verdict below counts it: before the global gain's trust (a gain
        # of 1.1 is full trust)
        floor = EARLY_SHARE.get(k)
        return floor is not None and float(guard_weights(
            data_weight, 1.1, gains_later.result()).mean()) < floor

    # an estimate that plainly explains too little is let go early, unless its frame is
    # wanted whole: a given path's is reused for the background's deconvolution below, and
    # the c refitted to the deconvolution (``edi_at``) needs the last round's frame (fitted
    # to the first round's, it cost 0.27 dB on two frames with movers that stop there)
    refit = edi_at is not None and contrast is not None
    d = deconvolve(blurry, motion, cfg, start=edi_middle, anchor=edi_middle,
                   stop=None if given or refit else hopeless)
    gains = gains_later.result()
    gain = motion.confidence if trust_later is None else trust_later.result()
    if refit:
        # where re-blurring explains B the deconvolution's change of log over the exposure is
        # right even when the guard does not keep the motion: the c it implies is EDI's, in
        # every frame blended in below and every fallback
        fitted = fit_contrast(d, events, exposure, explained(d.data_weight), hot_mask,
                              near=contrast)
        if fitted is not None:
            edi_frames = edi_at(fitted)
    wgt = guard_weights(d.data_weight, gain, gains)
    # an estimate's share counts what it explains; the gain's trust only sets how much of
    # the deconvolution is used (a small motion's gain is low even when the estimate is right
    # to a tenth of a pixel, and a partial blend with EDI holds an estimate's error back). A
    # given path short of the share is judged by the events' change test instead, below.
    trust = 1.0 if given else trust_score(gain)
    share = float(wgt.mean()) / trust if trust > 0 else 0.0
    if share < MIN_SHARE:
        # a motion that explains less than half of B is mostly something else's (movers as
        # large as the background, or both mixed): what it does explain is not to be trusted
        # either (on 16 frames with two foreground layers, the frames below this share lost
        # 0.4–3.3 dB to EDI with the rest blended in)
        return second_chance(f"the motion explains only {100 * share:.0f} % of the frame "
                             f"(needs {100 * MIN_SHARE:.0f} %): used EDI", d if given else None)
    if contrast is not None and not given:
        # the frame's verdict above is the residual test's alone (the events' test would let a
        # motion that explains a quarter of B through: −5 dB on a frame with two movers); the
        # blend also keeps what the events confirm (esl-cups: 86 → 97 % of frame 000017)
        change = change_of_log(events, exposure, w, h, contrast, hot_mask)
        wgt = guard_weights(d.data_weight, gain, gains,
                            events_agree=change_agreement(d, change, contrast))
    deb = d.frames(fractions)
    # per instant, also where the frame agrees with EDI's: B cannot tell where a mover was
    # when, so the background it swept is judged at each instant against the events' reading
    # (the events' own tile test still applies)
    events_ok = trust_score(gain) * tile_score(gains, w, h)
    held = wgt > 0.5
    weights = np.stack([np.maximum(wgt, events_ok * agreement(f, e, held))
                        for f, e in zip(deb, edi_frames)])
    return MotionDeblur(_blend(deb, edi_frames, weights), wgt, motion, (), weights,
                        fitted)


def _background_deblur(blurry: np.ndarray, events, exposure, fractions, edi_frames: np.ndarray,
                       edi_middle: np.ndarray, hot_mask: np.ndarray | None,
                       cfg: DeconvConfig, contrast: float | None, fallback: MotionDeblur,
                       given=None, solved: Deconvolved | None = None,
                       tiles=None) -> MotionDeblur:
    """When one global motion does not hold: the deconvolution along the background's motion
    (``given``, deconvolved already when ``solved``; else estimated apart from the tiles that
    move otherwise, :func:`~trmd_cli.motion.tiles.background_motion`), kept where that motion
    predicts the events' change of log intensity (:func:`change_agreement`) and re-blurring
    explains B (:func:`explained`); EDI elsewhere, at every instant. ``fallback`` (EDI's
    frames) when there is no such motion, no c to read the events with, or it holds on less
    than :data:`BACKGROUND_SHARE` of the frame. ``tiles``: the exposure's
    :class:`~trmd_cli.motion.tiles.TileEvidence`, whose background motion is the one used.

    On eight noise-free simulated exposures with a foreground layer moving on its own
    (``bench/bench_mover_guard.py``), the global estimate followed the layer in five; on those
    the middle frame went from EDI's to +0.8 … +3.6 dB above it (one stayed EDI's), and the
    eight from +1.1 to +1.9 dB over EDI on average.
    """
    from .motion import MIN_EVENTS
    from .motion.tiles import background_motion

    if contrast is None:
        return fallback
    h, w = blurry.shape[:2]
    motion = given if given is not None else tiles.background() if tiles is not None else \
        background_motion(events, exposure, hot_mask)
    if motion is None or motion.events < MIN_EVENTS or motion.max_displacement_px(w, h) < 0.25:
        return fallback
    d = solved if solved is not None else \
        deconvolve(blurry, motion, cfg, start=edi_middle, anchor=edi_middle)
    change = change_of_log(events, exposure, w, h, contrast, hot_mask)
    wgt = change_agreement(d, change, contrast) * explained(d.data_weight)
    share = float(wgt.mean())
    which = "the given motion" if given is not None else \
        "the motion of the tiles that move together"
    if share < BACKGROUND_SHARE:
        return replace(fallback, notes=(f"{fallback.notes[0]}; {which} predicts the events on "
                                        f"only {100 * share:.0f} % of the frame",))
    deb = d.frames(fractions)
    weights = np.repeat(wgt[None], len(deb), axis=0)
    reason = fallback.notes[0].removesuffix(": used EDI")
    return MotionDeblur(_blend(deb, edi_frames, weights), wgt, motion,
                        (f"{reason}; deconvolved along {which}, where it predicts the events "
                         f"({100 * share:.0f} % of the frame), EDI elsewhere",), weights,
                        fallback.fallback_contrast)


#: pixels the fit of :func:`fit_contrast` needs at least, and their least share of the pixels
#: where the events changed the log intensity (the smoothed count at least 0.3 in size)
FIT_MIN_PIXELS, FIT_MIN_SHARE = 1000, 0.05
#: least local correlation of the predicted change with the events' count for a pixel to
#: enter the fit (over a σ = 4 px Gaussian neighbourhood)
FIT_MIN_CORRELATION = 0.5


def fit_contrast(solved: Deconvolved, events, exposure, weight: np.ndarray,
                 hot_mask: np.ndarray | None = None, near: float | None = None,
                 sigma_px: float = 1.0) -> float | None:
    """The contrast threshold a deconvolution implies: the least-squares slope of its change
    of log intensity over the exposure (the frame carried to the exposure's two ends) on the
    events' signed count ``Σ p``, both smoothed by a σ = ``sigma_px`` Gaussian. The pixels:
    where re-blurring explains B (``weight`` (H, W) > 0.9), the smoothed count is at least
    0.3 in size and the two correlate locally (:data:`FIT_MIN_CORRELATION`: where the motion
    is wrong the prediction is unrelated to the events and would pull the slope to 0). None
    when they are fewer than :data:`FIT_MIN_PIXELS` or :data:`FIT_MIN_SHARE` of the pixels the
    events changed (the motion holds almost nowhere), or the slope lies outside
    ``[near / 2, 2 · near]`` (given ``near``).

    Why: the threshold search (:mod:`trmd_cli.threshold`) reads c from the blurry frame and
    the events alone, and on DAVIS-like sensors it lands 1.2× high in the median (1.3× with
    movers). A deconvolution along a motion that holds predicts each pixel's change without
    c (its anchor weighs little), so the events' count gives c directly: on 16 simulated
    frames with two movers the slope was 1.06× the true mean threshold in the median
    (0.94–1.43×), the search 1.30× (1.18–1.70×).
    """
    import cv2

    h, w = weight.shape
    change = cv2.GaussianBlur(np.ascontiguousarray(predicted_change(solved)), (0, 0), sigma_px)
    count = cv2.GaussianBlur(change_of_log(events, exposure, w, h, 1.0, hot_mask), (0, 0),
                             sigma_px)

    def local(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(np.ascontiguousarray(a, np.float32), (0, 0), CHANGE_SIGMA_PX)

    mc, ms = local(change), local(count)
    cov = local(change * count) - mc * ms
    spread = np.maximum(local(change * change) - mc * mc, 1e-12) * \
        np.maximum(local(count * count) - ms * ms, 1e-12)
    active = np.abs(count) >= 0.3
    sel = active & (weight > 0.9) & (cov > FIT_MIN_CORRELATION * np.sqrt(spread))
    n = int(sel.sum())
    if n < FIT_MIN_PIXELS or n < FIT_MIN_SHARE * int(active.sum()):
        return None
    s = count[sel].astype(np.float64)
    # numpy's own sums, not BLAS's dot: the same digits whatever the thread count (``--jobs``
    # workers run BLAS on one thread)
    c = float(np.sum(change[sel].astype(np.float64) * s) / np.sum(s * s))
    if not c > 0 or (near is not None and not 0.5 * near <= c <= 2.0 * near):
        return None
    return c


def _blend(frames: np.ndarray, edi_frames: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``weights`` (K, H, W) of ``frames`` and the rest of ``edi_frames`` (K, H, W[, 3]),
    float32."""
    ww = weights[..., None] if frames.ndim == 4 else weights
    return (ww * frames + (1.0 - ww) * edi_frames).astype(np.float32)
