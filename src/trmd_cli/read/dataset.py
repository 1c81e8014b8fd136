"""Datasets for evaluation: blurry frames with their events (or binned counts) and, when
stored, ground truth.

:func:`open_dataset` tells the kinds apart by their format:

* a folder: ``blurry/`` (or ``blur/``, ``images/``, ``blurred/``) frames with
  ``Exposure_start.txt`` / ``Exposure_end.txt``, events as ``events.*`` beside them or
  per-frame files in ``events/`` (``mat/``), and optionally ``sharp/`` (``gt/``) ground truth;
* a folder of such frames with a bins file instead of events (:mod:`trmd_cli.read.bins`):
  binned events only;
* a GOPRO-style HDF5 (:mod:`trmd_cli.read.gopro`): binned events only;
* any event file with stored frames and exposures (the trmd HDF5 with ``frames/sharp`` carries
  ground truth and the true contrast; simulated from a still, also ``frames/motion``, the true
  camera path of each exposure).

Frames come from the same readers and frame sources ``trmd deblur`` uses.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..events import EventStream, Exposure
from ..motion.sampled import SampledMotion
from .base import Frame, ReadOptions

__all__ = ["EvalFrame", "EvalSource", "open_dataset"]

#: names of the folders of a dataset folder, first found wins
_BLURRY_DIRS = ("blurry", "blur", "images", "blurred")
_SHARP_DIRS = ("sharp", "gt", "ground_truth")


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
        bins: (M, H, W) signed counts of M equal bins of the exposure, when there are no raw
            events (GOPRO-style voxels: M = 2N; a bins file: its bins per frame).
        truth: (2N+1, H, W[, 3]) float32 sharp frames, or None.
        contrast: the true mean contrast threshold stored with simulated data, or None.
        motion: the true camera path over the exposure stored with simulated data, or None.
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
    motion: SampledMotion | None = None


class EvalSource:
    """An opened dataset: frames with events (or bins) and, when present, ground truth.

    Attributes:
        path, kind (``"trmd-h5" | "gopro-h5" | "folder" | "binned" | "recording"``), width,
            height, n.
        has_ground_truth, has_true_contrast, has_true_motion (the simulator's camera path),
            has_raw_events.
        notes: things the user should know (printed by the CLI, stored in the report).
    """

    path: Path
    kind: str
    width: int
    height: int
    n: int
    has_ground_truth: bool = False
    has_true_contrast: bool = False
    has_true_motion: bool = False
    has_raw_events: bool = True

    def __init__(self) -> None:
        self.notes: list[str] = []

    def __len__(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def frames(self, limit: int | None = None) -> Iterator[EvalFrame]:  # pragma: no cover
        raise NotImplementedError

    def blurry_frames(self, positions: Sequence[int]) -> Iterator[Frame]:
        """The blurry frames at ``positions`` (0-based, in order) alone, for the fixed pattern
        (:mod:`trmd_cli.fixed_pattern`); this default reads the frames in turn."""
        wanted = set(positions)
        if not wanted:
            return
        for i, f in enumerate(self.frames(max(wanted) + 1)):
            if i in wanted:
                yield Frame(f.blurry, f.exposure, f.index, f.name)

    def close(self) -> None:
        pass

    def __enter__(self) -> EvalSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _checked_truth(truth_of, frame, n: int, path) -> np.ndarray | None:
    """The ground truth of ``frame`` from ``truth_of(index, name)`` (None: none), checked
    against N and the frame's size."""
    truth = truth_of(frame.index, frame.name) if truth_of else None
    if truth is not None:
        _check_truth_count(len(truth), n, path)
        if truth.shape[1:] != frame.image.shape:
            raise InputError(f"the ground truth of frame {frame.name} has shape "
                             f"{truth.shape[1:]}, the blurry frame {frame.image.shape}",
                             path=path, hint="store sharp frames of the frame's size")
    return truth


def _check_truth_count(count: int, n: int, path) -> None:
    if count != 2 * n + 1:
        m = (count - 1) // 2
        raise InputError(f"the ground truth has {count} frames per exposure, not 2N+1 = "
                         f"{2 * n + 1}", path=path,
                         hint=f"pass `n={m}`" if count % 2 == 1 and m >= 1 else
                         "store 2N+1 sharp frames per blurry frame")


class _WindowSource(EvalSource):
    """Frames + exposure windows + raw events (any event file with frames, or a folder)."""

    def __init__(self, path: Path, kind: str, frames, n: int, *, recording=None,
                 truth: Callable[[int, str], np.ndarray | None] | None = None,
                 contrast: Callable[[int], float | None] | None = None,
                 motion: Callable[[int], np.ndarray | None] | None = None,
                 has_truth: bool = False, has_contrast: bool = False) -> None:
        super().__init__()
        self.path, self.kind, self.n = path, kind, n
        self._src = frames
        self._rec = recording
        self._truth = truth
        self._contrast = contrast
        self._motion = motion
        self.width, self.height = frames.width, frames.height
        self.has_ground_truth = has_truth
        self.has_true_contrast = has_contrast
        self.has_true_motion = motion is not None
        self.notes.extend(frames.warnings)

    def __len__(self) -> int:
        return len(self._src)

    def frames(self, limit: int | None = None) -> Iterator[EvalFrame]:
        src = self._src if limit is None or limit >= len(self._src) else \
            self._src.subset(range(limit))
        for win in src:
            f = win.frame
            exp = win.exposure
            truth = _checked_truth(self._truth, f, self.n, self.path)
            c = self._contrast(f.index) if self._contrast else None
            yield EvalFrame(f.index, f.name, f.image, exp.instants_us(self.n), exp, win.events,
                            None, truth, c, self._true_motion(f.index))

    def blurry_frames(self, positions: Sequence[int]) -> Iterator[Frame]:
        """The frames at ``positions`` without their events."""
        return self._src.subset(positions).frames()

    def _true_motion(self, index: int) -> SampledMotion | None:
        h = self._motion(index) if self._motion else None
        if h is None:
            return None
        return SampledMotion(h, centre=((self.width - 1) / 2, (self.height - 1) / 2))

    def close(self) -> None:
        self._src.close()
        if self._rec is not None:
            self._rec.close()


class _GoproSource(EvalSource):
    """A GOPRO-style HDF5 (:class:`~trmd_cli.read.gopro.GoproFile`): frames with binned events,
    latent instants as fractions of the exposure."""

    def __init__(self, path: Path, n: int) -> None:
        from .gopro import GoproFile

        super().__init__()
        self.path, self.kind, self.n = path, "gopro-h5", n
        self.has_raw_events = False
        self._file = GoproFile(path, n)
        if self._file.has_sharp:
            try:
                _check_truth_count(self._file.sharp_count, n, path)
            except InputError:
                self._file.close()
                raise
        self.width, self.height = self._file.width, self._file.height
        self.has_ground_truth = self._file.has_sharp
        self.notes.append(f"{path.name}: voxels only (no raw events): EDI integrates the bins "
                          "with the events spread evenly in each bin")

    def __len__(self) -> int:
        return len(self._file)

    def frames(self, limit: int | None = None) -> Iterator[EvalFrame]:
        k = len(self) if limit is None else min(limit, len(self))
        inst = np.linspace(0.0, 1.0, 2 * self.n + 1)
        for i in range(k):
            truth = self._file.sharp(i)
            bins = self._file.bins(i)
            yield EvalFrame(i, f"{self.path.stem}#{i:06d}", self._file.blurry(i), inst,
                            bins=bins, truth=truth)

    def close(self) -> None:
        self._file.close()


class _BinnedSource(EvalSource):
    """A folder of blurry frames with a bins file (:mod:`trmd_cli.read.bins`): binned events
    only, latent instants as fractions of the exposure."""

    def __init__(self, path: Path, images: Path, bins: Path, n: int, *,
                 truth: Callable[[int, str], np.ndarray | None] | None = None) -> None:
        from .folders import open_binned_folder

        super().__init__()
        self.path, self.kind, self.n = path, "binned", n
        self.has_raw_events = False
        self._src = open_binned_folder(images, bins)
        self._truth = truth
        self.width, self.height = self._src.width, self._src.height
        self.has_ground_truth = truth is not None
        b = self._src.bins_per_frame
        note = (f"{bins.name}: binned events only ({b} bins per frame, no event times): EDI "
                "integrates the bins with the events spread evenly in each bin")
        if b % (2 * n):
            note += (f"; {b} bins do not split into 2N = {2 * n} equal parts, so the bins that "
                     "straddle an instant are split evenly")
        self.notes.append(note)
        self.notes.extend(self._src.warnings)

    def __len__(self) -> int:
        return len(self._src)

    def frames(self, limit: int | None = None) -> Iterator[EvalFrame]:
        src = self._src if limit is None or limit >= len(self._src) else \
            self._src.subset(range(limit))
        inst = np.linspace(0.0, 1.0, 2 * self.n + 1)
        for win in src:
            f = win.frame
            truth = _checked_truth(self._truth, f, self.n, self.path)
            yield EvalFrame(f.index, f.name, f.image, inst, bins=win.bins, truth=truth)


def _bins_file(folder: Path, event_files: Sequence[Path]) -> Path | None:
    """The bins file of a dataset folder: ``events.*`` when it holds bins, else the one
    ``.mat`` / ``.npz`` / ``.npy`` beside the frames that does; None when there is none."""
    from .bins import is_bins_file

    if event_files:
        return event_files[0] if is_bins_file(event_files[0]) else None
    found = [p for p in sorted(folder.iterdir()) if p.is_file()
             and p.suffix.lower() in (".mat", ".npz", ".npy") and is_bins_file(p)]
    if len(found) > 1:
        raise InputError(f"holds {len(found)} bins files ({', '.join(p.name for p in found)})",
                         path=folder, hint="keep the one that belongs to the frames")
    return found[0] if found else None


def _first_dir(folder: Path, names: Sequence[str]) -> Path | None:
    return next((folder / d for d in names if (folder / d).is_dir()), None)


def _folder_truth(sharp_dir: Path) -> Callable[[int, str], np.ndarray | None]:
    """Ground truth of a folder dataset: ``sharp/<stem>/`` holding the 2N+1 frames (ordered
    by the number in their names), or flat files ``sharp/<stem>_<k>.png``."""
    from .folders import list_images
    from .frames import read_image

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

    * a folder: ``blurry/`` (or ``blur/``, ``images/``, ``blurred/``) frames with
      ``Exposure_start.txt`` / ``Exposure_end.txt``, events as ``events.*`` beside them or
      per-frame files in ``events/`` (``mat/``), and optionally ``sharp/`` (``gt/``) ground
      truth — ``sharp/<stem>/`` with the 2N+1 frames, or ``sharp/<stem>_<k>.png``;
    * the same folder with a bins file instead of events — ``events.*`` holding bins, or the
      one ``.mat`` / ``.npz`` / ``.npy`` beside the frames that holds them
      (:mod:`trmd_cli.read.bins`);
    * a GOPRO-style HDF5 (``blur_images``, ``sharp_images``, ``voxel``);
    * any event file with stored frames and exposures (the trmd HDF5 with ``frames/sharp``
      carries ground truth and the true contrast), a ROS 2 bag folder or an RPG folder among
      them.

    Raises:
        InputError / FormatError: unreadable input, frames without exposure times, ground truth
            with another 2N+1.
    """
    from ..window import check_windows
    from . import open_events
    from .folders import frames_from_recording, open_frame_folder
    from .gopro import is_gopro_h5
    from .sniff import is_recording_folder

    path = Path(path)
    options = options or ReadOptions()
    if n < 1:
        raise InputError(f"N must be ≥ 1, got {n}", hint="use `n=3` (7 latent frames)")
    if path.is_dir() and not is_recording_folder(path):
        images = _first_dir(path, _BLURRY_DIRS)
        if images is None:
            raise InputError("the folder has no blurry/, blur/, images/ or blurred/ subfolder",
                             path=path, hint="put the blurry frames in DIR/blurry/")
        event_files = sorted(p for p in path.iterdir() if p.is_file() and p.stem == "events")
        sharp = _first_dir(path, _SHARP_DIRS)
        bins = _bins_file(path, event_files)
        if bins is not None:
            return _BinnedSource(path, images, bins, n,
                                 truth=None if sharp is None else _folder_truth(sharp))
        frames = open_frame_folder(images, event_files[0] if event_files else None, options)
        if frames.recording is not None:
            # (a score of frames passed through unchanged would rank nothing)
            check_windows(frames.exposures(), frames.recording, frames.recording.path)
        return _WindowSource(path, "folder", frames, n,
                             truth=None if sharp is None else _folder_truth(sharp),
                             has_truth=sharp is not None)
    if not path.exists():
        raise InputError("not found", path=path, hint="check the path")
    if path.is_file() and is_gopro_h5(path):
        return _GoproSource(path, n)
    rec = open_events(path, options)
    try:
        if rec.is_empty():  # every method would only pass the blurry frames through
            raise InputError("the recording holds no events", path=path,
                             hint="check the file (trmd info)")
        frames = frames_from_recording(rec)
        check_windows(frames.exposures(), rec, path)
        has_truth = bool(getattr(rec, "has_ground_truth", False))
        has_c = len(frames) > 0 and hasattr(rec, "contrast") and rec.contrast(0) is not None
        if has_truth and len(frames):
            _check_truth_count(rec.ground_truth(0).shape[0], n, path)
        kind = "trmd-h5" if getattr(rec, "layout", None) == "trmd" else "recording"
        has_motion = bool(getattr(rec, "has_true_motion", False))
        return _WindowSource(path, kind, frames, n, recording=rec,
                             truth=(lambda k, _name: rec.ground_truth(k)) if has_truth else None,
                             contrast=rec.contrast if has_c else None,
                             motion=rec.true_motion if has_motion else None,
                             has_truth=has_truth, has_contrast=has_c)
    except BaseException:
        rec.close()
        raise
