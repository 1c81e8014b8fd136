"""The evaluation report: per-frame figures, their means per method and dataset, and the JSON
form ``trmd eval --json`` writes (non-finite figures become null, others 6 decimals).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["FIGURES", "FrameScore", "MethodResult", "DatasetReport", "EvalReport"]

#: figures of :class:`FrameScore` that are averaged into means, in table order
FIGURES = ("psnr_mid", "psnr_seq", "ssim_mid", "ssim_seq", "lpips_mid", "lpips_seq",
           "sharpness", "noise", "explained", "consistency", "contrast", "seconds")


@dataclass(frozen=True)
class FrameScore:
    """Figures of one method on one blurry frame (None = not measured, NaN = undefined).

    Attributes:
        index, name: the frame.
        psnr_mid, psnr_seq: dB, middle frame and mean of the 2N+1 per-frame PSNRs.
        ssim_mid, ssim_seq: SSIM of the middle frame and mean over the 2N+1 frames.
        lpips_mid, lpips_seq: LPIPS (AlexNet) when its weights are on disk, else None.
        sharpness: :func:`~trmd_cli.metrics.sharpness` of the middle output frame.
        noise: :func:`~trmd_cli.metrics.noise_sigma` of the middle output frame.
        explained: :func:`~trmd_cli.threshold.explained_share` of the middle output frame and
            the events around its instant.
        consistency: :func:`~trmd_cli.metrics.consistency` of the 2N+1 output frames with
            contrast ``contrast``.
        contrast: c the method used (EDI) or the reference c used for the consistency figure.
        seconds: wall time of the method on this frame (reading excluded).
    """

    index: int
    name: str
    psnr_mid: float | None = None
    psnr_seq: float | None = None
    ssim_mid: float | None = None
    ssim_seq: float | None = None
    lpips_mid: float | None = None
    lpips_seq: float | None = None
    sharpness: float | None = None
    noise: float | None = None
    explained: float | None = None
    consistency: float | None = None
    contrast: float | None = None
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {k: _json_float(getattr(self, k)) if k in FIGURES else getattr(self, k)
                for k in ("index", "name", *FIGURES)}


def _json_float(v):
    if v is None:
        return None
    v = float(v)
    return None if not math.isfinite(v) else round(v, 6)


def _mean(values: Sequence[float | None]) -> float | None:
    vals = [float(v) for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


@dataclass(frozen=True)
class MethodResult:
    """One method on one dataset: per-frame scores, or why it was skipped."""

    method: str
    frames: tuple[FrameScore, ...] = ()
    skipped: str | None = None

    def mean(self, figure: str) -> float | None:
        """Mean of a figure over the frames (None if it was never measured)."""
        return _mean([getattr(f, figure) for f in self.frames])

    @property
    def means(self) -> dict[str, float | None]:
        return {k: self.mean(k) for k in FIGURES}

    def to_dict(self) -> dict[str, Any]:
        return {"skipped": self.skipped, "frames": len(self.frames),
                "mean": {k: _json_float(v) for k, v in self.means.items()},
                "per_frame": [f.to_dict() for f in self.frames]}


@dataclass(frozen=True)
class DatasetReport:
    """All methods on one dataset.

    Attributes:
        path, kind: the dataset and what it was read as (see
            :class:`~trmd_cli.read.dataset.EvalSource`).
        ground_truth: figures against ground truth (True) or without it (False).
        n: 2N+1 latent frames. size: (width, height). frames: frames evaluated.
        methods: one :class:`MethodResult` per requested method, in the requested order.
        notes: skipped methods, reader warnings, fallbacks.
    """

    path: str
    kind: str
    ground_truth: bool
    n: int
    size: tuple[int, int]
    frames: int
    methods: tuple[MethodResult, ...]
    notes: tuple[str, ...] = ()

    def method(self, name: str) -> MethodResult:
        return next(m for m in self.methods if m.method == name)

    def to_dict(self) -> dict[str, Any]:
        return {"path": self.path, "kind": self.kind, "ground_truth": self.ground_truth,
                "n": self.n, "size": list(self.size), "frames": self.frames,
                "notes": list(self.notes),
                "methods": {m.method: m.to_dict() for m in self.methods}}


@dataclass(frozen=True)
class EvalReport:
    """Every dataset, plus overall means (over all frames evaluated by a method, pooled),
    kept apart for datasets judged with and without ground truth.

    Attributes:
        datasets: one :class:`DatasetReport` each. methods: the requested methods, in order.
        n: 2N+1 latent frames. limit: frames per dataset at most (None = all).
        notes: remarks that hold for every dataset.
        protocol: how the figures were computed (clipping, PSNR cap, SSIM window, what each
            method is), for the JSON report.
    """

    datasets: tuple[DatasetReport, ...]
    methods: tuple[str, ...]
    n: int
    limit: int | None = None
    notes: tuple[str, ...] = ()
    protocol: Mapping[str, Any] = field(default_factory=dict)

    def overall(self, ground_truth: bool | None = None) -> dict[str, dict[str, float | None]]:
        """method → figure → mean over every frame of the datasets (frame-weighted);
        ``ground_truth`` keeps only datasets judged with (True) or without (False) it.
        ``"frames"`` counts the frames pooled."""
        out: dict[str, dict[str, float | None]] = {}
        sets = [d for d in self.datasets if ground_truth is None or d.ground_truth == ground_truth]
        for m in self.methods:
            scores = [f for d in sets for r in d.methods if r.method == m for f in r.frames]
            out[m] = {k: _mean([getattr(f, k) for f in scores]) for k in FIGURES}
            out[m]["frames"] = len(scores)  # type: ignore[assignment]
        return out

    def to_dict(self) -> dict[str, Any]:
        from . import __version__

        return {
            "trmd_version": __version__,
            "n": self.n,
            "methods": list(self.methods),
            "limit": self.limit,
            "protocol": dict(self.protocol),
            "notes": list(self.notes),
            "datasets": [d.to_dict() for d in self.datasets],
            "overall": {
                key: {m: {k: (_json_float(v) if k != "frames" else v) for k, v in figs.items()}
                      for m, figs in self.overall(gt).items()}
                for key, gt in (("ground_truth", True), ("no_ground_truth", False))
                if any(d.ground_truth == gt for d in self.datasets)},
        }
