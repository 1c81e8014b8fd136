"""Inference wrapper: numpy frame + SCER voxels → 2N+1 latent frames with a trained RE-Net.

Used by ``trmd deblur --method trmd`` and ``trmd hfr --method trmd``. The network predicts the
residuals; :func:`trmd_cli.reconstruct.reconstruct` turns them into frames (Eq. 11–12), so the
mean of the output equals the input frame exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError, ShapeError
from ..precision import autocast, precision_name, resolve_precision
from ..reconstruct import reconstruct
from .inputs import RENetInputs
from .renet import RENet
from .weights import default_weights_path, load_weights, resolve_device, weights_hash

__all__ = ["TrmdEstimator"]


class TrmdEstimator:
    """A loaded RE-Net and the device it runs on.

    Colour handling: a gray model (channels = 1) given an RGB frame runs once per colour channel
    (as a batch of 3) with the same voxels — events carry no colour, and the residual of each
    channel follows the same motion. An RGB model (channels = 3) given a gray frame sees it
    replicated to three channels and returns the mean of its three outputs.

    Example (the bundled example, run from the repository's root)::

        >>> from trmd_cli.read import open_events, read_image
        >>> from trmd_cli.threshold import estimate_contrast
        >>> from trmd_cli.voxel import scer_levels, scer_voxels
        >>> blurry = read_image("examples/blurry.png")
        >>> with open_events("examples/events.npz") as rec:
        ...     exposure = rec.stored_windows()[0]
        ...     events = rec.events(exposure.start_us, exposure.end_us + 1)
        >>> est = TrmdEstimator.load(threads=2)  # the shipped weights
        >>> c = estimate_contrast(blurry, events, exposure) if est.needs_contrast else None
        >>> levels = scer_levels(events, exposure, est.n) if est.needs_timing else None
        >>> est(blurry, scer_voxels(events, exposure, est.n), c, levels).shape
        (7, 260, 346)
    """

    def __init__(self, model: RENet, meta: dict[str, Any] | None = None,
                 weights_hash: str | None = None, precision: str = "fp32") -> None:
        # channels-last weights: oneDNN's convolutions skip a layout conversion per layer, 15–20 %
        # faster in float32 on CPU (bench/bench_renet.py); the inputs stay as they are
        self.model = model.eval().to(memory_format=torch.channels_last)
        self._meta = dict(meta or {})
        self._hash = weights_hash
        self.device = next(model.parameters()).device
        #: autocast dtype of the network's convolutions (None = float32), from ``precision``
        #: (:func:`trmd_cli.precision.resolve_precision`)
        self.amp_dtype = resolve_precision(precision, self.device)

    @classmethod
    def load(cls, weights: str | Path | None = None, *, device: str = "auto",
             threads: int | None = None, expect_n: int | None = None,
             precision: str = "fp32") -> TrmdEstimator:
        """Load weights (None = the shipped default) onto ``device`` ("auto": cuda if available).

        Args:
            precision: ``fp32`` (default), ``auto`` (mixed precision where the device computes
                it natively: float16 on CUDA, bfloat16 on CPUs with AMX / AVX512-BF16), ``bf16``
                or ``fp16`` (see :mod:`trmd_cli.precision`).
            threads: CPU threads for torch (``torch.set_num_threads``); None leaves torch's
                default (all cores).
            expect_n: refuse weights trained for another N (:class:`WeightsError`).
        Raises:
            WeightsError: missing, corrupt or mismatching weights (see :func:`load_weights`).
            InputError: unknown or unavailable device, threads < 1, unknown precision.
        """
        if threads is not None:
            if threads < 1:
                raise InputError(f"threads must be ≥ 1, got {threads}")
            torch.set_num_threads(threads)
        model, meta = load_weights(weights, device=str(resolve_device(device)), expect_n=expect_n)
        path = default_weights_path() if weights is None else weights
        return cls(model, meta, weights_hash(path), precision=precision)

    @property
    def n(self) -> int:
        """N: voxels have 2N channels, outputs 2N+1 frames."""
        return self.model.n

    @property
    def channels(self) -> int:
        """Colour channels the model was trained on: 1 gray, 3 RGB."""
        return self.model.channels

    @property
    def meta(self) -> dict[str, Any]:
        """Metadata of the weights file (architecture, args, recipe, figures …)."""
        return dict(self._meta)

    @property
    def precision(self) -> str:
        """The network's arithmetic as run: ``fp32``, or ``bf16`` / ``fp16`` mixed precision."""
        return precision_name(self.amp_dtype)

    @property
    def weights_hash(self) -> str | None:
        """Short SHA-256 of the weights file (None for a model given directly)."""
        return self._hash

    @property
    def needs_contrast(self) -> bool:
        """The network takes the sensor's contrast threshold with every frame."""
        return self.model.needs.contrast

    @property
    def needs_timing(self) -> bool:
        """True when the network also takes the voxels' sub-bin timing
        (:func:`trmd_cli.voxel.scer_levels`, the ``levels`` argument)."""
        return self.model.needs.timing

    def __call__(self, blurry: np.ndarray, voxels: np.ndarray,
                 contrast: float | None = None, levels: np.ndarray | None = None) -> np.ndarray:
        """Latent frames from a blurry frame and its SCER voxels.

        Args:
            blurry: (H, W) gray or (H, W, 3) RGB, float [0, 1].
            voxels: (2N, H, W) SCER voxels (:func:`trmd_cli.voxel.scer_voxels`), N = ``self.n``.
            contrast: the threshold c (log intensity per event); required when
                :attr:`needs_contrast` (the network refuses a missing or non-positive one),
                ignored otherwise.
            levels: (2N, H, W) :func:`trmd_cli.voxel.scer_levels` of the same window, for
                networks that take them (:attr:`needs_timing`; ignored otherwise). Without raw
                events (binned data) leave it out: the counts stand in for it — within a step
                of the levels, but not what the network was trained on, so expect less.
        Returns:
            (2N+1, H, W) or (2N+1, H, W, 3) float32, time order k = 0..2N, not clipped (callers
            clip when writing images). The mean over frames equals ``blurry``.
        Raises:
            InputError: the voxel count does not match the model's N, or values are not finite.
            ShapeError: shapes do not fit together.
        """
        blurry = np.asarray(blurry, dtype=np.float32)
        voxels = np.asarray(voxels, dtype=np.float32)
        if blurry.ndim == 3 and blurry.shape[-1] == 1:
            blurry = blurry[..., 0]
        if not (blurry.ndim == 2 or (blurry.ndim == 3 and blurry.shape[-1] == 3)):
            raise ShapeError(f"blurry frame has shape {blurry.shape}, expected (H, W) or (H, W, 3)")
        h, w = blurry.shape[:2]
        if voxels.ndim != 3 or voxels.shape[1:] != (h, w):
            raise ShapeError(f"voxels have shape {voxels.shape}, expected (2N, {h}, {w}) to match "
                             f"the {w}x{h} frame")
        if voxels.shape[0] != 2 * self.n:
            raise InputError(f"got {voxels.shape[0]} voxel channels but the model was trained for "
                             f"N = {self.n} ({2 * self.n} channels)",
                             hint=f"voxelize with `n={self.n}`, or use weights trained for "
                             f"N = {voxels.shape[0] // 2}")
        if not (np.isfinite(blurry).all() and np.isfinite(voxels).all()):
            raise InputError("the frame or the voxels contain NaN or infinite values")
        lv: np.ndarray | None = None
        if self.needs_timing:
            lv = voxels if levels is None else np.asarray(levels, dtype=np.float32)
            if lv.shape != voxels.shape:
                raise ShapeError(f"levels have shape {lv.shape}, the voxels {voxels.shape}")
            if not np.isfinite(lv).all():
                raise InputError("the voxel levels contain NaN or infinite values")

        rgb = blurry.ndim == 3
        # model input: (batch, C_model, H, W); a batch of 3 runs a gray model per colour channel
        if rgb and self.channels == 1:
            b = blurry.transpose(2, 0, 1)[:, None]
        elif rgb:
            b = blurry.transpose(2, 0, 1)[None]
        elif self.channels == 3:
            b = np.repeat(blurry[None, None], 3, axis=1)
        else:
            b = blurry[None, None]

        with torch.inference_mode():
            tb = torch.from_numpy(np.ascontiguousarray(b)).to(self.device)
            batch = b.shape[0]
            tv = torch.from_numpy(voxels).to(self.device)[None].expand(batch, -1, -1, -1)
            tl = None if lv is None else \
                torch.from_numpy(lv).to(self.device)[None].expand(batch, -1, -1, -1)
            with autocast(self.device, self.amp_dtype):
                residuals = self.model(RENetInputs(tb, tv, levels=tl, contrast=contrast))
            latent = reconstruct(tb, residuals.float())  # (batch, 2N+1, C, H, W)
            out = latent.float().cpu().numpy()

        if rgb and self.channels == 1:
            return np.ascontiguousarray(out[:, :, 0].transpose(1, 2, 3, 0))
        if rgb:
            return np.ascontiguousarray(out[0].transpose(0, 2, 3, 1))
        if self.channels == 3:
            return out[0].mean(axis=1)
        return out[0, :, 0]

    def __repr__(self) -> str:
        return (f"TrmdEstimator({self._meta.get('architecture', self.model.variant)}, "
                f"n={self.n}, channels={self.channels}, device={self.device}, "
                f"weights={self._hash})")
