"""Evaluation of deblurring methods: figures against ground truth, and without it.

With ground truth (the trmd HDF5 written by ``trmd simulate``, GOPRO-style HDF5 of the paper's
release, folders of blurry frames + events + sharp frames) every method's 2N+1 output frames,
clipped to [0, 1] as users see them, are compared with the sharp frames:

* PSNR with data range 1, capped at :data:`PSNR_CAP_DB` (identical images); the *sequence*
  figure is the mean of the 2N+1 per-frame PSNRs, not the PSNR of the whole stack;
* SSIM (Wang et al. 2004: 11×11 Gaussian window, σ = 1.5, data range 1; :mod:`trmd_cli.metrics`),
  likewise for the middle frame and as the mean over the 2N+1 frames.

Without ground truth (real recordings) two figures let users judge results on their own camera:

* :func:`sharpness`: mean gradient energy of the middle frame (higher = sharper, but noise
  counts too: read it together with the next one);
* :func:`noise_sigma`: Immerkær's estimate of the σ of white noise in the middle frame (lower =
  cleaner; smooth intensity does not count): a noisy frame's sharpness is partly its noise;
* :func:`consistency`: mean ``|Δlog L − c·E|`` between consecutive output frames over pixels that
  had events, with ``E`` the signed event count between the two instants and ``c`` the contrast
  used (lower = the frames move the way the events say). EDI builds its frames exactly this way,
  so its figure is ~0 up to clipping: the figure judges methods that do not (TRMD, and
  ``blurry`` as the floor), with the data's true c or else EDI's estimate for the frame.

Methods: ``blurry`` (the blurry frame repeated: the floor), ``edi`` (EDI, contrast estimated per
frame), ``edi-true-c`` (EDI given the simulator's true mean contrast, when the data stores it:
the baseline the training targets are defined against), ``trmd`` (RE-Net + reconstruction).

Library code: nothing here prints; notes (skipped methods, LPIPS) travel in the report.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import FormatError, InputError
from .events import EventStream, Exposure
from .metrics import psnr, ssim
from .read.base import ReadOptions

__all__ = [
    "METHODS",
    "DEFAULT_METHODS",
    "PSNR_CAP_DB",
    "EvalFrame",
    "FrameOutputs",
    "FrameScore",
    "MethodResult",
    "DatasetReport",
    "EvalReport",
    "EvalSource",
    "parse_methods",
    "open_dataset",
    "evaluate_dataset",
    "evaluate",
    "sharpness",
    "noise_sigma",
    "consistency",
    "consistency_from_counts",
    "interval_counts",
    "bins_from_scer",
    "lpips_status",
]

#: every method ``trmd eval`` knows, in the order tables list them
METHODS = ("blurry", "edi", "edi-true-c", "trmd")
DEFAULT_METHODS = ("blurry", "edi", "trmd")
#: PSNR of identical images is infinite; capping keeps means and JSON finite
PSNR_CAP_DB = 100.0
#: floor under intensities before taking logs in :func:`consistency`
LOG_EPS = 1e-3
#: names of the folders of a dataset folder, first found wins
_BLURRY_DIRS = ("blurry", "blur", "images")
_SHARP_DIRS = ("sharp", "gt", "ground_truth")

#: what each method is, for the JSON report
_METHOD_NOTES = {
    "blurry": "the blurry frame repeated as every latent frame",
    "edi": "EDI as `trmd deblur --method edi` runs it: contrast estimated per frame, hot "
           "pixels ignored (binned data: events spread evenly within each bin)",
    "edi-true-c": "the same EDI given the true mean contrast stored with simulated data",
    "trmd": "RE-Net residuals + two-stage reconstruction, as `trmd deblur --method trmd`",
}
#: figures of :class:`FrameScore` that are averaged into means, in table order
FIGURES = ("psnr_mid", "psnr_seq", "ssim_mid", "ssim_seq", "lpips_mid", "lpips_seq",
           "sharpness", "noise", "consistency", "contrast", "seconds")


# --------------------------------------------------------------------------------------------
# Figures without ground truth


def _gray(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image, np.float64)
    return a.mean(axis=-1) if a.ndim == 3 else a


def sharpness(image: np.ndarray) -> float:
    """Mean gradient energy ``mean(∂x I)² + mean(∂y I)²`` with forward differences.

    Args:
        image: (H, W) or (H, W, 3) (colour is averaged to gray first), H, W ≥ 2.
    Returns:
        The energy in (intensity units / pixel)²: ``I = a·x + b·y`` gives ``a² + b²``.
    """
    g = _gray(image)
    if g.ndim != 2 or min(g.shape) < 2:
        raise InputError(f"sharpness needs an (H, W) image with H, W ≥ 2, got {np.shape(image)}")
    dx = np.diff(g, axis=1)
    dy = np.diff(g, axis=0)
    return float(np.mean(dx * dx) + np.mean(dy * dy))


def noise_sigma(image: np.ndarray) -> float:
    """σ of additive white noise, estimated as Immerkær (1996) does.

    The image is filtered with a 3×3 kernel (second differences along both axes) that removes
    smooth shading and edges along the axes; for white noise of σ the filtered values have
    standard deviation 6σ, so ``σ = sqrt(π/2) · mean|filtered| / 6``. Oblique edges and texture
    count a little: compare methods on the same frame rather than reading it as an absolute.

    Args:
        image: (H, W) or (H, W, 3) (colour averaged to gray first), [0, 1] intensity, H, W ≥ 3.
    Returns:
        σ in intensity units.
    """
    g = _gray(image)
    if g.ndim != 2 or min(g.shape) < 3:
        raise InputError(f"noise_sigma needs an (H, W) image with H, W ≥ 3, got "
                         f"{np.shape(image)}")
    # Immerkær's kernel [[1,-2,1],[-2,4,-2],[1,-2,1]] is a second difference along y times one
    # along x: zero on any image f(x) + g(y) (edges along an axis, shading), and on bilinear ones
    f = np.diff(np.diff(g, 2, axis=0), 2, axis=1)
    return float(math.sqrt(math.pi / 2) * np.abs(f).mean() / 6.0)


def interval_counts(events: EventStream, instants_us: Sequence[float]) -> tuple[np.ndarray,
                                                                                 np.ndarray]:
    """Signed event counts between consecutive instants.

    An event at time t belongs to the interval ``(instants[j], instants[j+1]]`` (an event exactly
    at an instant has happened by then, as in :mod:`trmd_cli.edi`).

    Args:
        events: the stream (events outside ``(instants[0], instants[-1]]`` are ignored).
        instants_us: (K,) increasing instants, µs.
    Returns:
        ``(net, active)``: (K−1, H, W) float64 signed counts and (K−1, H, W) bool, True where the
        pixel had at least one event in the interval (also when they cancel out).
    """
    inst = np.asarray(instants_us, np.float64).ravel()
    if len(inst) < 2 or (np.diff(inst) <= 0).any():
        raise InputError("consistency needs at least two increasing instants")
    h, w = events.height, events.width
    m = len(inst) - 1
    slot = np.searchsorted(inst, events.t, side="left") - 1
    keep = (slot >= 0) & (slot < m)
    flat = slot[keep] * (h * w) + events.y[keep].astype(np.int64) * w + events.x[keep]
    net = np.bincount(flat, weights=events.p[keep].astype(np.float64), minlength=m * h * w)
    count = np.bincount(flat, minlength=m * h * w)
    return net.reshape(m, h, w), (count > 0).reshape(m, h, w)


def consistency_from_counts(frames: np.ndarray, counts: np.ndarray, contrast: float,
                            active: np.ndarray | None = None, eps: float = LOG_EPS) -> float:
    """Mean ``|log L(k+1) − log L(k) − c·E(k)|`` over the (interval, pixel) pairs in ``active``.

    Args:
        frames: (K, H, W) or (K, H, W, 3) output frames in time order (colour averaged to gray);
            intensities are floored at ``eps`` before the log.
        counts: (K−1, H, W) signed event counts between consecutive frames.
        contrast: c, the log-intensity step of one event.
        active: (K−1, H, W) bool of pixels that had events (default: ``counts != 0``).
    Returns:
        The mean error in log-intensity units; NaN when no pixel had events.
    """
    f = np.asarray(frames)
    g = np.asarray(f, np.float64)
    g = g.mean(axis=-1) if g.ndim == 4 else g
    counts = np.asarray(counts, np.float64)
    if g.ndim != 3 or counts.shape != (g.shape[0] - 1, *g.shape[1:]):
        raise InputError(f"consistency needs frames (K, H, W[, 3]) and counts (K−1, H, W), got "
                         f"{f.shape} and {counts.shape}")
    if not (np.isfinite(contrast) and contrast > 0):
        raise InputError(f"contrast threshold must be a positive number, got {contrast}")
    mask = counts != 0 if active is None else np.asarray(active, bool)
    if not mask.any():
        return math.nan
    logs = np.log(np.maximum(g, eps))
    err = np.abs(np.diff(logs, axis=0) - contrast * counts)
    return float(err[mask].mean())


def consistency(frames: np.ndarray, events: EventStream, instants_us: Sequence[float],
                contrast: float) -> float:
    """Event consistency error of output frames (see :func:`consistency_from_counts`).

    Args:
        frames: (K, H, W) or (K, H, W, 3) frames at ``instants_us`` (K ≥ 2).
        events: the events of the span; ``E(k)`` counts those in ``(t_k, t_{k+1}]``.
        instants_us: (K,) increasing instants of the frames, µs.
        contrast: c used to turn event counts into log-intensity steps.
    Returns:
        Mean ``|Δlog L − c·E|`` over (interval, pixel) pairs with at least one event; NaN when
        there are none. Zero for frames built exactly as ``L(k) = L(0)·exp(c·E(0, k))``.
    """
    if len(frames) != len(instants_us):
        raise InputError(f"{len(frames)} frames for {len(instants_us)} instants")
    net, active = interval_counts(events, instants_us)
    return consistency_from_counts(frames, net, contrast, active)


def bins_from_scer(voxels: np.ndarray) -> np.ndarray:
    """Invert :func:`trmd_cli.voxel.scer_from_bins`: SCER (2N, H, W) → signed bin counts.

    With ``V(N) = 0`` put back in place, bin j is ``V(j+1) − V(j)`` (both halves).
    """
    v = np.asarray(voxels, np.float64)
    if v.ndim != 3 or v.shape[0] % 2 or v.shape[0] == 0:
        raise InputError(f"SCER voxels must be (2N, H, W), got {v.shape}")
    n = v.shape[0] // 2
    full = np.concatenate([v[:n], np.zeros((1, *v.shape[1:])), v[n:]], 0)
    return np.diff(full, axis=0)


# --------------------------------------------------------------------------------------------
# Datasets


@dataclass(frozen=True, eq=False)
class EvalFrame:
    """One blurry frame to evaluate and what is known about it.

    Attributes:
        index: frame number in its dataset (used for the ground truth and the stored contrast).
        name: for messages and strip file names.
        blurry: (H, W) or (H, W, 3) float32 [0, 1].
        instants_us: (2N+1,) latent instants (µs for events; fractions 0..1 for binned data).
        exposure: the exposure window (µs) when raw events are known, else None.
        events: the events of the exposure window, or None (binned data).
        bins: (2N, H, W) signed counts of 2N equal bins of the exposure, when there are no raw
            events (GOPRO-style voxels).
        truth: (2N+1, H, W[, 3]) float32 sharp frames, or None.
        contrast: the true mean contrast threshold stored with simulated data, or None.
    """

    index: int
    name: str
    blurry: np.ndarray
    instants_us: np.ndarray
    exposure: Exposure | None = None
    events: EventStream | None = None
    bins: np.ndarray | None = None
    truth: np.ndarray | None = None
    contrast: float | None = None

    def voxels(self, n: int) -> np.ndarray:
        """SCER voxels (2N, H, W) of this exposure."""
        from .voxel import event_bins, scer_from_bins

        if self.bins is not None:
            return scer_from_bins(np.asarray(self.bins, np.float32))
        assert self.events is not None and self.exposure is not None
        return scer_from_bins(event_bins(self.events, self.exposure, 2 * n))

    def counts(self) -> tuple[np.ndarray, np.ndarray]:
        """Signed counts and activity between consecutive latent instants (see
        :func:`interval_counts`)."""
        if self.bins is not None:
            b = np.asarray(self.bins, np.float64)
            return b, b != 0
        assert self.events is not None
        return interval_counts(self.events, self.instants_us)


class EvalSource:
    """An opened dataset: frames with events (or bins) and, when present, ground truth.

    Attributes:
        path, kind (``"trmd-h5" | "gopro-h5" | "folder" | "recording"``), width, height, n.
        has_ground_truth, has_true_contrast, has_raw_events.
        notes: things the user should know (printed by the CLI, stored in the report).
    """

    path: Path
    kind: str
    width: int
    height: int
    n: int
    has_ground_truth: bool = False
    has_true_contrast: bool = False
    has_raw_events: bool = True

    def __init__(self) -> None:
        self.notes: list[str] = []

    def __len__(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def frames(self, limit: int | None = None) -> Iterator[EvalFrame]:  # pragma: no cover
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> EvalSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _check_truth_count(count: int, n: int, path) -> None:
    if count != 2 * n + 1:
        m = (count - 1) // 2
        raise InputError(f"the ground truth has {count} frames per exposure, not 2N+1 = "
                         f"{2 * n + 1}", path=path,
                         hint=f"pass --n {m}" if count % 2 == 1 and m >= 1 else
                         "store 2N+1 sharp frames per blurry frame")


class _WindowSource(EvalSource):
    """Frames + exposure windows + raw events (any event file with frames, or a folder)."""

    def __init__(self, path: Path, kind: str, frames, n: int, *, recording=None,
                 truth: Callable[[int, str], np.ndarray | None] | None = None,
                 contrast: Callable[[int], float | None] | None = None,
                 has_truth: bool = False, has_contrast: bool = False) -> None:
        super().__init__()
        self.path, self.kind, self.n = path, kind, n
        self._src = frames
        self._rec = recording
        self._truth = truth
        self._contrast = contrast
        self.width, self.height = frames.width, frames.height
        self.has_ground_truth = has_truth
        self.has_true_contrast = has_contrast
        self.notes.extend(frames.warnings)

    def __len__(self) -> int:
        return len(self._src)

    def frames(self, limit: int | None = None) -> Iterator[EvalFrame]:
        src = self._src if limit is None or limit >= len(self._src) else \
            self._src.subset(range(limit))
        for win in src:
            f = win.frame
            exp = win.exposure
            truth = self._truth(f.index, f.name) if self._truth else None
            if truth is not None:
                _check_truth_count(len(truth), self.n, self.path)
                if truth.shape[1:] != f.image.shape:
                    raise InputError(f"the ground truth of frame {f.name} has shape "
                                     f"{truth.shape[1:]}, the blurry frame {f.image.shape}",
                                     path=self.path, hint="store sharp frames of the frame's size")
            c = self._contrast(f.index) if self._contrast else None
            yield EvalFrame(f.index, f.name, f.image, exp.instants_us(self.n), exp, win.events,
                            None, truth, c)

    def close(self) -> None:
        self._src.close()
        if self._rec is not None:
            self._rec.close()


class _GoproSource(EvalSource):
    """GOPRO-style HDF5 (paper release): ``blur_images`` uint8 (K, H, W, 3), ``sharp_images``
    (K, 2N+1, H, W, 3), ``voxel`` (K, 2N, H, W) SCER. No raw events, no exposure times."""

    def __init__(self, path: Path, n: int) -> None:
        import h5py

        super().__init__()
        self.path, self.kind, self.n = path, "gopro-h5", n
        self.has_raw_events = False
        try:
            self._f = h5py.File(path, "r")
        except OSError as e:
            raise FormatError(f"cannot be opened as HDF5 ({e})", path=path) from None
        f = self._f
        try:
            self._blur, self._vox = f["blur_images"], f["voxel"]
            self._sharp = f["sharp_images"] if "sharp_images" in f else None
        except KeyError as e:
            self.close()
            raise FormatError(f"GOPRO-style file lacks {e}", path=path,
                              hint="expected blur_images, sharp_images and voxel") from None
        k = self._blur.shape[0]
        if self._blur.ndim not in (3, 4) or self._vox.ndim != 4 or self._vox.shape[0] != k:
            self.close()
            raise FormatError(f"blur_images {self._blur.shape} and voxel {self._vox.shape} do "
                              "not fit (K, H, W[, 3]) and (K, 2N, H, W)", path=path)
        self.height, self.width = self._blur.shape[1:3]
        if self._vox.shape[1] != 2 * n:
            self.close()
            raise InputError(f"voxels have {self._vox.shape[1]} channels, not 2N = {2 * n}",
                             path=path, hint=f"pass --n {self._vox.shape[1] // 2}")
        if self._sharp is not None:
            if self._sharp.shape[0] != k or self._sharp.shape[2:] != self._blur.shape[1:]:
                self.close()
                raise FormatError(f"sharp_images {self._sharp.shape} do not fit blur_images "
                                  f"{self._blur.shape}", path=path)
            _check_truth_count(self._sharp.shape[1], n, path)
        self.has_ground_truth = self._sharp is not None
        self.notes.append(f"{path.name}: voxels only (no raw events): EDI integrates the bins "
                          "with the events spread evenly in each bin")

    def __len__(self) -> int:
        return int(self._blur.shape[0])

    @staticmethod
    def _unit(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a)
        if a.dtype == np.uint8:
            return a.astype(np.float32) / 255.0
        if a.dtype == np.uint16:
            return a.astype(np.float32) / 65535.0
        return a.astype(np.float32)

    def frames(self, limit: int | None = None) -> Iterator[EvalFrame]:
        k = len(self) if limit is None else min(limit, len(self))
        inst = np.linspace(0.0, 1.0, 2 * self.n + 1)
        for i in range(k):
            truth = None if self._sharp is None else self._unit(self._sharp[i])
            bins = bins_from_scer(self._vox[i])
            yield EvalFrame(i, f"{self.path.stem}#{i:06d}", self._unit(self._blur[i]), inst,
                            bins=bins, truth=truth)

    def close(self) -> None:
        f = getattr(self, "_f", None)
        if f is not None:
            f.close()
            self._f = None


def _is_gopro_h5(path: Path) -> bool:
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89HDF\r\n\x1a\n":
            return False
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "blur_images" in f and "voxel" in f
    except OSError:
        return False


def _first_dir(folder: Path, names: Sequence[str]) -> Path | None:
    return next((folder / d for d in names if (folder / d).is_dir()), None)


def _folder_truth(sharp_dir: Path) -> Callable[[int, str], np.ndarray | None]:
    """Ground truth of a folder dataset: ``sharp/<stem>/`` holding the 2N+1 frames (ordered
    by the number in their names), or flat files ``sharp/<stem>_<k>.png``."""
    from .read.folders import list_images
    from .read.frames import read_image

    def truth(index: int, stem: str) -> np.ndarray | None:
        sub = sharp_dir / stem
        if sub.is_dir():
            paths = list_images(sub)
        else:
            paths = [p for p in list_images(sharp_dir) if p.stem.rsplit("_", 1)[0] == stem]
        if not paths:
            raise InputError(f"no sharp frames for {stem}", path=sharp_dir,
                             hint=f"put the 2N+1 sharp frames in {sharp_dir.name}/{stem}/ or "
                             f"name them {stem}_0.png … {stem}_6.png")
        return np.stack([read_image(p) for p in paths])

    return truth


def open_dataset(path: str | Path, n: int = 3, options: ReadOptions | None = None) -> EvalSource:
    """Open a dataset for evaluation (the format decides the kind).

    * a folder: ``blurry/`` (or ``blur/``, ``images/``) frames with ``Exposure_start.txt`` /
      ``Exposure_end.txt``, events as ``events.*`` beside them or per-frame files in ``events/``
      (``mat/``), and optionally ``sharp/`` (``gt/``) ground truth — ``sharp/<stem>/`` with the
      2N+1 frames, or ``sharp/<stem>_<k>.png``;
    * a GOPRO-style HDF5 (``blur_images``, ``sharp_images``, ``voxel``);
    * any event file with stored frames and exposures (the trmd HDF5 with ``frames/sharp``
      carries ground truth and the true contrast).

    Raises:
        InputError / FormatError: unreadable input, frames without exposure times, ground truth
            with another 2N+1.
    """
    from .read import open_events
    from .read.folders import frames_from_recording, open_frame_folder

    path = Path(path)
    options = options or ReadOptions()
    if n < 1:
        raise InputError(f"N must be ≥ 1, got {n}", hint="use --n 3 (7 latent frames)")
    if path.is_dir():
        images = _first_dir(path, _BLURRY_DIRS)
        if images is None:
            raise InputError("the folder has no blurry/, blur/ or images/ subfolder", path=path,
                             hint="put the blurry frames in DIR/blurry/")
        event_files = sorted(p for p in path.iterdir() if p.is_file() and p.stem == "events")
        frames = open_frame_folder(images, event_files[0] if event_files else None, options)
        sharp = _first_dir(path, _SHARP_DIRS)
        return _WindowSource(path, "folder", frames, n,
                             truth=None if sharp is None else _folder_truth(sharp),
                             has_truth=sharp is not None)
    if not path.exists():
        raise InputError("not found", path=path, hint="check the path")
    if path.is_file() and _is_gopro_h5(path):
        return _GoproSource(path, n)
    rec = open_events(path, options)
    try:
        if rec.num_events() == 0:  # every method would only pass the blurry frames through
            raise InputError("the recording holds no events", path=path,
                             hint="check the file (trmd info)")
        frames = frames_from_recording(rec)
        has_truth = bool(getattr(rec, "has_ground_truth", False))
        has_c = len(frames) > 0 and hasattr(rec, "contrast") and rec.contrast(0) is not None
        if has_truth and len(frames):
            _check_truth_count(rec.ground_truth(0).shape[0], n, path)
        kind = "trmd-h5" if getattr(rec, "layout", None) == "trmd" else "recording"
        return _WindowSource(path, kind, frames, n, recording=rec,
                             truth=(lambda k, _name: rec.ground_truth(k)) if has_truth else None,
                             contrast=rec.contrast if has_c else None,
                             has_truth=has_truth, has_contrast=has_c)
    except BaseException:
        rec.close()
        raise


# --------------------------------------------------------------------------------------------
# Methods


def parse_methods(methods: str | Sequence[str]) -> tuple[str, ...]:
    """``"blurry,edi"`` or a list → validated tuple in the given order, duplicates dropped.

    Raises:
        InputError: an unknown name (the message lists the known ones).
    """
    names = methods.split(",") if isinstance(methods, str) else list(methods)
    out: list[str] = []
    for raw in names:
        m = raw.strip().lower()
        if not m:
            continue
        if m not in METHODS:
            raise InputError(f"unknown method {raw.strip()!r}",
                             hint=f"choose from {', '.join(METHODS)}")
        if m not in out:
            out.append(m)
    if not out:
        raise InputError("no method given", hint=f"choose from {', '.join(METHODS)}")
    return tuple(out)


@dataclass(frozen=True, eq=False)
class _Output:
    latent: np.ndarray  # (2N+1, H, W[, 3]) unclipped
    contrast: float | None  # the c the method used (EDI), else None
    warnings: tuple[str, ...] = ()


class _Runner:
    """Runs the methods on one frame the way ``trmd deblur`` does (through
    :func:`trmd_cli.pipeline.deblur_frames`, hot pixels ignored); holds the TRMD model."""

    def __init__(self, n: int, trmd=None) -> None:
        self.n = n
        self.trmd = trmd  # a pipeline.TrmdMethod, or None
        # imported here, not in run(): the first frame's timing should not pay for imports
        from .edi import edi_from_bins
        from .pipeline import EdiMethod, deblur_frames
        from .read.base import Frame
        from .read.folders import FrameWindow

        self._edi_method, self._deblur_frames = EdiMethod, deblur_frames
        self._edi_from_bins, self._frame, self._window = edi_from_bins, Frame, FrameWindow
        # (frame, c) of the last estimate: the frame is held so its identity stays unique
        self._auto_c: tuple[EvalFrame, float] | None = None

    def auto_contrast(self, frame: EvalFrame) -> float:
        """The contrast EDI's automatic estimate picks for this frame (cached per frame)."""
        if self._auto_c is None or self._auto_c[0] is not frame:
            self._auto_c = (frame, _estimate_contrast(frame, self.n))
        return self._auto_c[1]

    def run(self, method: str, frame: EvalFrame) -> _Output:
        if method == "blurry":
            return _Output(np.repeat(frame.blurry[None], 2 * self.n + 1, axis=0), None)
        if method in ("edi", "edi-true-c"):
            if method == "edi":
                c = None
            elif frame.contrast is None:
                raise InputError(f"frame {frame.name} stores no true contrast threshold")
            else:
                c = frame.contrast
            if frame.bins is not None:
                c = self.auto_contrast(frame) if c is None else c
                return _Output(self._edi_from_bins(frame.blurry, frame.bins, frame.instants_us,
                                                   c), c)
            out = self._deblur(frame, self._edi_method(self.n, c, hot_pixels=True))
            if method == "edi" and out.contrast is not None:
                self._auto_c = (frame, out.contrast)
            return out
        if method == "trmd":
            if frame.bins is not None:
                c = self.auto_contrast(frame) if self.trmd.model.needs_contrast else None
                return _Output(self.trmd.model(frame.blurry, frame.voxels(self.n), c), c)
            return self._deblur(frame, self.trmd)
        raise InputError(f"unknown method {method!r}", hint=f"choose from {', '.join(METHODS)}")

    def _deblur(self, frame: EvalFrame, method) -> _Output:
        win = self._window(self._frame(frame.blurry, frame.exposure, frame.index, frame.name),
                           frame.events)
        res = next(self._deblur_frames([win], method))
        return _Output(res.frames, res.estimate.contrast, res.warnings)


def _estimate_contrast(frame: EvalFrame, n: int) -> float:
    """EDI's automatic contrast for one frame, as ``trmd deblur --contrast auto`` picks it."""
    from .edi import EdiBins
    from .pipeline import EdiMethod
    from .threshold import search_contrast

    if frame.bins is not None:
        return float(search_contrast(frame.blurry, EdiBins.build(frame.bins)).contrast)
    return float(EdiMethod(n, None, hot_pixels=True).prepare(frame.blurry, frame.events,
                                                             frame.exposure)[1])


# --------------------------------------------------------------------------------------------
# Scores and reports


@dataclass(frozen=True)
class FrameScore:
    """Figures of one method on one blurry frame (None = not measured, NaN = undefined).

    Attributes:
        index, name: the frame.
        psnr_mid, psnr_seq: dB, middle frame and mean of the 2N+1 per-frame PSNRs.
        ssim_mid, ssim_seq: SSIM of the middle frame and mean over the 2N+1 frames.
        lpips_mid, lpips_seq: LPIPS (AlexNet) when its weights are on disk, else None.
        sharpness: :func:`sharpness` of the middle output frame.
        noise: :func:`noise_sigma` of the middle output frame.
        consistency: :func:`consistency` of the 2N+1 output frames with contrast ``contrast``.
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
        path, kind: the dataset and what it was read as (see :class:`EvalSource`).
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
    kept apart for datasets judged with and without ground truth."""

    datasets: tuple[DatasetReport, ...]
    methods: tuple[str, ...]
    n: int
    limit: int | None = None
    notes: tuple[str, ...] = ()

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
            "protocol": {
                "clip": [0.0, 1.0],
                "psnr": {"data_range": 1.0, "cap_db": PSNR_CAP_DB,
                         "sequence": "mean of the 2N+1 per-frame PSNRs"},
                "ssim": {"window": "gaussian 11x11", "sigma": 1.5, "data_range": 1.0,
                         "sequence": "mean of the 2N+1 per-frame SSIMs"},
                "sharpness": "mean squared forward differences of the middle frame (gray)",
                "noise": "Immerkaer's white-noise sigma estimate of the middle frame (gray)",
                "consistency": "mean |dlog L - c*E| over pixels with events, consecutive "
                               f"frames, intensities floored at {LOG_EPS}; c = the method's "
                               "own (EDI), else the true c, else EDI's estimate",
                "methods": _METHOD_NOTES,
            },
            "notes": list(self.notes),
            "datasets": [d.to_dict() for d in self.datasets],
            "overall": {
                key: {m: {k: (_json_float(v) if k != "frames" else v) for k, v in figs.items()}
                      for m, figs in self.overall(gt).items()}
                for key, gt in (("ground_truth", True), ("no_ground_truth", False))
                if any(d.ground_truth == gt for d in self.datasets)},
        }


@dataclass(frozen=True, eq=False)
class FrameOutputs:
    """What a frame looked like, for compare strips: handed to ``on_frame`` callbacks.

    Attributes:
        dataset: path of the dataset. frame: the input.
        middle: method → middle output frame, clipped to [0, 1].
        scores: method → :class:`FrameScore`.
    """

    dataset: str
    frame: EvalFrame
    middle: dict[str, np.ndarray] = field(default_factory=dict)
    scores: dict[str, FrameScore] = field(default_factory=dict)


def _score(frame: EvalFrame, latent: np.ndarray, n: int, *, truth: bool, contrast: float | None,
           counts: tuple[np.ndarray, np.ndarray] | None, seconds: float, lpips=None
           ) -> FrameScore:
    out = np.clip(latent, 0.0, 1.0)
    figs: dict[str, Any] = {"sharpness": sharpness(out[n]), "noise": noise_sigma(out[n]),
                            "contrast": contrast, "seconds": seconds}
    if counts is not None and contrast is not None:
        figs["consistency"] = consistency_from_counts(out, counts[0], contrast, counts[1])
    if truth and frame.truth is not None:
        gt = frame.truth
        p = [min(psnr(o, g), PSNR_CAP_DB) for o, g in zip(out, gt, strict=True)]
        s = [ssim(o, g) for o, g in zip(out, gt, strict=True)]
        figs.update(psnr_mid=p[n], psnr_seq=float(np.mean(p)), ssim_mid=s[n],
                    ssim_seq=float(np.mean(s)))
        if lpips is not None:
            ls = lpips(out, gt)
            figs.update(lpips_mid=ls[n], lpips_seq=float(np.mean(ls)))
    return FrameScore(frame.index, frame.name, **figs)


def lpips_status() -> tuple[bool, str]:
    """Whether LPIPS can run without downloading anything: (available, note)."""
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        return False, "LPIPS skipped: the 'lpips' package is not installed"
    try:
        import torch

        hub = Path(torch.hub.get_dir()) / "checkpoints"
    except Exception:  # noqa: BLE001 - any failure means "not available"
        return False, "LPIPS skipped: torch is not usable"
    if not list(hub.glob("alexnet-*.pth")):
        return False, ("LPIPS skipped: its AlexNet backbone weights are not on disk "
                       f"({hub}) and nothing is downloaded")
    return True, "LPIPS: AlexNet variant (lpips package)"


def _lpips_fn():
    """(2N+1, H, W[, 3]) pair → per-frame LPIPS list (inputs in [0, 1])."""
    import lpips as lp
    import torch

    net = lp.LPIPS(net="alex", verbose=False).eval()

    def fn(out: np.ndarray, gt: np.ndarray) -> list[float]:
        def t(a):
            a = torch.from_numpy(np.ascontiguousarray(a, np.float32))
            a = a[:, None].expand(-1, 3, -1, -1) if a.ndim == 3 else a.permute(0, 3, 1, 2)
            return a * 2 - 1
        with torch.inference_mode():
            return [float(v) for v in net(t(out), t(gt)).flatten()]

    return fn


def _load_trmd(weights: str | Path | None, n: int, device: str = "auto",
               threads: int | None = None, precision: str = "auto"):
    """(pipeline.TrmdMethod, None), or (None, note) when no weights are given and none ship."""
    from .weights import default_weights_path

    if weights is None and not default_weights_path().is_file():
        return None, ("trmd skipped: this installation ships no trained weights; "
                      "pass --weights PATH to a .safetensors file from `trmd train`")
    from .pipeline import TrmdMethod

    return TrmdMethod(n, weights, device, threads, precision=precision), None


def evaluate_dataset(
    path: str | Path,
    methods: str | Sequence[str] = DEFAULT_METHODS,
    n: int = 3,
    limit: int | None = None,
    weights: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    *,
    ground_truth: bool | None = None,
    options: ReadOptions | None = None,
    trmd=None,
    lpips: bool | None = None,
    on_frame: Callable[[FrameOutputs], None] | None = None,
    precision: str = "auto",
) -> DatasetReport:
    """Run the methods on one dataset and score them.

    Args:
        path: a dataset (see :func:`open_dataset`).
        methods: names from :data:`METHODS` (a comma-separated string or a sequence).
        n: 2N+1 latent frames (must match the ground truth and the weights).
        limit: evaluate only the first ``limit`` frames.
        weights: RE-Net weights for ``trmd``; None = the shipped default (``trmd`` is skipped
            with a note when there is none).
        progress: called as ``progress(done, total)`` after each frame.
        ground_truth: True = require ground truth (InputError without it); False = figures
            without ground truth even when it exists; None = whichever the dataset allows.
        options: how to read event files (``--time-unit`` …).
        trmd: an already loaded :class:`~trmd_cli.pipeline.TrmdMethod` (shared across
            datasets by :func:`evaluate`); overrides ``weights``.
        lpips: compute LPIPS (None = when :func:`lpips_status` says it can).
        on_frame: called with each frame's :class:`FrameOutputs` (compare strips).
        precision: the network's arithmetic when ``weights`` are loaded here
            (:mod:`trmd_cli.precision`).
    Returns:
        :class:`DatasetReport`.
    Raises:
        InputError: unknown method, ``ground_truth=True`` on data without it, bad ``limit``.
        FormatError / WeightsError: unreadable data or weights.
    """
    methods = parse_methods(methods)
    if limit is not None and limit < 1:
        raise InputError(f"--limit must be ≥ 1, got {limit}")
    notes: list[str] = []
    with open_dataset(path, n, options) as src:
        if ground_truth and not src.has_ground_truth:
            raise InputError("holds no ground truth (sharp frames)", path=src.path,
                             hint="evaluate it with --no-gt (sharpness, noise and event "
                                  "consistency), or give a set made by `trmd simulate`")
        use_gt = src.has_ground_truth if ground_truth is None else ground_truth
        if ground_truth is None and not use_gt:
            notes.append(f"{src.path.name}: no ground truth: reporting sharpness, noise and event "
                         "consistency instead")
        notes.extend(src.notes)
        skipped: dict[str, str] = {}
        if "edi-true-c" in methods and not src.has_true_contrast:
            skipped["edi-true-c"] = ("edi-true-c skipped: the data stores no true contrast "
                                     "threshold (only simulated sets do)")
        if "trmd" in methods and trmd is None:
            trmd, note = _load_trmd(weights, n, precision=precision)
            if note:
                skipped["trmd"] = note
        notes.extend(skipped.values())
        if ("trmd" in methods and "trmd" not in skipped and trmd is not None
                and not src.has_raw_events and trmd.model.needs_timing):
            notes.append("the data is binned (no event times): the network's timing inputs get "
                         "the counts instead — expect less than on raw events")
        lpips_fn = None
        if use_gt and lpips is not False:
            ok, note = lpips_status()
            if ok:
                lpips_fn = _lpips_fn()
            elif lpips:
                raise InputError(note)
        runner = _Runner(n, trmd)
        active = [m for m in methods if m not in skipped]
        scores: dict[str, list[FrameScore]] = {m: [] for m in methods}
        total = len(src) if limit is None else min(limit, len(src))
        done = 0
        for frame in src.frames(limit):
            runs: dict[str, tuple[_Output, float]] = {}
            for m in active:
                t0 = time.perf_counter()
                runs[m] = (runner.run(m, frame), time.perf_counter() - t0)
                notes.extend(runs[m][0].warnings)
            counts = frame.counts()
            # methods without a threshold of their own are judged with the data's true c,
            # else the c EDI's automatic estimate picks for this frame
            ref_c = frame.contrast
            if ref_c is None and active:
                ref_c = runner.auto_contrast(frame)
            outputs = FrameOutputs(str(src.path), frame)
            for m, (out, seconds) in runs.items():
                c = out.contrast if out.contrast is not None else ref_c
                score = _score(frame, out.latent, n, truth=use_gt, contrast=c, counts=counts,
                               seconds=seconds, lpips=lpips_fn)
                scores[m].append(score)
                outputs.middle[m] = np.clip(out.latent[n], 0.0, 1.0)
                outputs.scores[m] = score
            if on_frame is not None:
                on_frame(outputs)
            done += 1
            if progress is not None:
                progress(done, total)
        return DatasetReport(
            str(src.path), src.kind, bool(use_gt), n, (src.width, src.height), done,
            tuple(MethodResult(m, tuple(scores[m]), skipped.get(m)) for m in methods),
            tuple(dict.fromkeys(notes)))


def evaluate(
    paths: Sequence[str | Path],
    methods: str | Sequence[str] = DEFAULT_METHODS,
    n: int = 3,
    limit: int | None = None,
    weights: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    *,
    ground_truth: bool | None = None,
    options: ReadOptions | None = None,
    lpips: bool | None = None,
    on_frame: Callable[[FrameOutputs], None] | None = None,
    device: str = "auto",
    threads: int | None = None,
    precision: str = "auto",
) -> EvalReport:
    """:func:`evaluate_dataset` over several datasets, loading the weights once (on
    ``device``, with ``threads`` torch CPU threads, the network in ``precision``).

    ``progress`` is called as ``progress(dataset_path, done, total)``.
    """
    methods = parse_methods(methods)
    trmd, notes = None, []
    if "trmd" in methods:
        trmd, note = _load_trmd(weights, n, device, threads, precision)
        if note:
            notes.append(note)
    reports = []
    for p in paths:
        cb = None if progress is None else (lambda d, t, _p=str(p): progress(_p, d, t))
        reports.append(evaluate_dataset(
            p, methods, n, limit, weights, cb, ground_truth=ground_truth, options=options,
            trmd=trmd, lpips=lpips, on_frame=on_frame))
    if lpips is not False and any(r.ground_truth for r in reports):
        ok, note = lpips_status()
        if not ok:
            notes.append(note)
    return EvalReport(tuple(reports), methods, n, limit, tuple(notes))
