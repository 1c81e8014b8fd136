"""Frame sources: blurry frames, their exposure windows, and the events of each window.

A :class:`FrameSource` yields :class:`FrameWindow` items — one frame (float32 [0, 1], with its
exposure in µs on the events' clock) and the events of that exposure — one at a time, so memory
stays bounded by one window whatever the length of the sequence. Three layouts:

* **a folder of frames + one event file** (EVDI style): images ``*.png|jpg|tif`` ordered by the
  number in their names, exposure times in ``Exposure_start.txt`` / ``Exposure_end.txt`` (in the
  image folder or its parent), one number per line, line i for the i-th image. Unit: the file's
  time unit — ``time_unit`` if given, else whole numbers are **microseconds** (EVDI writes
  integer µs since the Unix epoch) and numbers with a fraction are seconds. ``time_offset_us``
  moves these times onto the event camera's clock (frames from a second camera, e.g. with a
  Prophesee sensor that records no frames). Without exposure files, windows stored in the event
  file are used when there is one per image.
* **paired folders** (eSL-Net): ``images/NNNNNN.png`` with ``mat/eventNNNNNN.mat``, matched by the
  number in the names; each event file holds its frame's events and (``start_timestamp`` /
  ``end_timestamp``) its exposure. Any supported event format can stand in for ``.mat``.
* **frames stored in the recording** (AEDAT4 APS frames, HDF5 ``images`` with exposures):
  :func:`frames_from_recording`.

A :class:`BinnedSource` is the twin for binned events (:mod:`trmd_cli.read.bins`): a folder of
frames with one bins file, yielding :class:`BinnedWindow` items — a frame and the signed counts
of the equal bins spanning its exposure, without event times (:func:`open_binned_folder`).

Image size is the sensor size for event files that store none (eSL-Net .mat: 346×260).
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..events import EventStream, Exposure
from .base import Frame, ReadOptions, Recording
from .frames import IMAGE_EXTENSIONS, check_frame_matches, read_image, read_image_noted

__all__ = [
    "FrameWindow",
    "FrameEntry",
    "FrameSource",
    "BinnedWindow",
    "BinnedSource",
    "open_binned_folder",
    "open_frame_folder",
    "frames_from_recording",
    "pair_folders",
    "list_images",
    "frame_number",
    "read_exposure_file",
    "find_exposure_files",
    "EVENT_EXTENSIONS",
]

#: per-frame event files considered when pairing folders
EVENT_EXTENSIONS = (".mat", ".npz", ".npy", ".h5", ".hdf5", ".txt", ".csv", ".raw", ".dat",
                    ".aedat4")
#: names of sibling folders searched for per-frame event files
_EVENT_DIRS = ("mat", "events", "event")
_EXPOSURE_FILES = ("exposure_start.txt", "exposure_end.txt")


@dataclass(frozen=True, eq=False)
class FrameWindow:
    """One frame and the events of its exposure.

    Attributes:
        frame: the image (float32 [0, 1], (H, W) or (H, W, 3)) with ``exposure`` set (µs).
        events: events with ``start - margin <= t <= end + margin`` µs.
    """

    frame: Frame
    events: EventStream

    @property
    def exposure(self) -> Exposure:
        return self.frame.exposure  # type: ignore[return-value]


@dataclass(frozen=True)
class FrameEntry:
    """What is known about a frame before reading it."""

    index: int
    name: str
    exposure: Exposure
    image_path: Path | None = None
    events_path: Path | None = None


def frame_number(path: str | Path) -> int | None:
    """The last run of digits in the file's stem (``event000014.mat`` → 14), or None."""
    found = re.findall(r"\d+", Path(path).stem)
    return int(found[-1]) if found else None


def _sort_key(path: Path) -> tuple:
    n = frame_number(path)
    return (n is None, n if n is not None else 0, path.name)


def list_images(folder: str | Path) -> list[Path]:
    """Images in ``folder`` (PNG, JPG, TIFF, …), ordered by the number in their names."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("not a folder", path=folder, hint="give the folder holding the frames")
    found = [p for p in folder.iterdir()
             if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".")]
    return sorted(found, key=_sort_key)


def pair_folders(images_dir: str | Path, events_dir: str | Path) -> list[tuple[Path, Path, int]]:
    """Match images with per-frame event files by the number in their names.

    Returns:
        ``(image_path, events_path, number)`` sorted by number; unmatched files are left out.
    Raises:
        InputError: missing folders, two files with the same number, or no pair at all.
    """
    images_dir, events_dir = Path(images_dir), Path(events_dir)
    if not events_dir.is_dir():
        raise InputError("not a folder", path=events_dir)
    images = _by_number(list_images(images_dir), images_dir)
    files = [p for p in events_dir.iterdir()
             if p.is_file() and p.suffix.lower() in EVENT_EXTENSIONS and not p.name.startswith(".")]
    events = _by_number(files, events_dir)
    pairs = [(images[n], events[n], n) for n in sorted(images.keys() & events.keys())]
    if not pairs:
        raise InputError(f"no image in {images_dir} has an event file with the same number in "
                         f"{events_dir}", path=events_dir,
                         hint="name them like images/000014.png and mat/event000014.mat")
    return pairs


def _by_number(paths: Sequence[Path], folder: Path) -> dict[int, Path]:
    out: dict[int, Path] = {}
    for p in paths:
        n = frame_number(p)
        if n is None:
            continue
        if n in out:
            raise InputError(f"two files carry the number {n}: {out[n].name} and {p.name}",
                             path=folder, hint="keep one file per frame number")
        out[n] = p
    return out


def read_exposure_file(path: str | Path, unit: str | None = None) -> np.ndarray:
    """Exposure times, one per line (blank lines and ``#`` comments skipped) → int64 µs.

    ``unit``: ``s | ms | us | ns``; None = whole numbers are µs, numbers with a fraction are
    seconds (the rule used for event files).
    """
    from .mat import seconds_to_us

    path = Path(path)
    values: list[str] = []
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as e:
        raise InputError(f"cannot read exposure times ({e.strerror})", path=path) from None
    for n, line in enumerate(lines, 1):
        token = line.split("#", 1)[0].replace(",", " ").split()
        if not token:
            continue
        try:
            float(token[0])
        except ValueError:
            raise InputError(f"line {n}: {token[0]!r} is not a number", path=path,
                             hint="one exposure time per line") from None
        values.append(token[0])
    whole = all(re.fullmatch(r"[-+]?\d+", v) for v in values)
    arr = np.array([int(v) for v in values], np.int64) if whole else np.array(values, np.float64)
    if not whole and not np.isfinite(arr).all():
        raise InputError("holds a non-finite exposure time", path=path)
    return seconds_to_us(arr, unit)


def find_exposure_files(images_dir: str | Path) -> tuple[Path, Path] | None:
    """``Exposure_start.txt`` / ``Exposure_end.txt`` (any case) in the folder or its parent."""
    images_dir = Path(images_dir)
    for folder in (images_dir, images_dir.parent):
        if not folder.is_dir():
            continue
        names = {p.name.lower(): p for p in folder.iterdir() if p.is_file()}
        if all(n in names for n in _EXPOSURE_FILES):
            return names[_EXPOSURE_FILES[0]], names[_EXPOSURE_FILES[1]]
    return None


def _exposures_from_files(files: tuple[Path, Path], count: int, unit: str | None,
                          offset_us: int) -> list[Exposure]:
    start, end = (read_exposure_file(f, unit) for f in files)
    for f, arr in zip(files, (start, end), strict=False):
        if len(arr) != count:
            raise InputError(f"holds {len(arr)} exposure times for {count} frames", path=f,
                             hint="one line per image, in the images' order")
    bad = np.flatnonzero(end <= start)
    if len(bad):
        i = int(bad[0])
        raise InputError(f"line {i + 1}: exposure end {end[i]} µs is not after start "
                         f"{start[i]} µs", path=files[1],
                         hint="check the two files are not swapped, and `time_unit`")
    return [Exposure(int(a) + offset_us, int(b) + offset_us)
            for a, b in zip(start, end, strict=True)]


#: events a source keeps in all for its own pass from windows read ahead by a subset
KEEP_EVENTS = 2_000_000


class FrameSource:
    """Frames with exposure windows, and the events of each window, one frame at a time.

    Iterate it (or call :meth:`iter_windows`) to get :class:`FrameWindow` items in order; only
    the current frame and its events are held in memory. ``exposures()`` and ``len()`` are cheap.
    """

    def __init__(self, entries: Sequence[FrameEntry], width: int, height: int, *,
                 recording: Recording | None = None, stored_frames: bool = False,
                 options: ReadOptions | None = None, warnings: list[str] | None = None,
                 owns_recording: bool = False) -> None:
        self.entries = list(entries)
        self.width = int(width)
        self.height = int(height)
        self.recording = recording
        self.warnings = [] if warnings is None else warnings
        self._stored = stored_frames
        self._options = options or ReadOptions()
        self._owns = owns_recording
        # windows read ahead through a subset (``keep=True``), by entry, until this source's
        # own pass reaches them: shared with the subsets
        self._kept: dict[FrameEntry, FrameWindow] = {}

    def __len__(self) -> int:
        return len(self.entries)

    def exposures(self) -> list[Exposure]:
        return [e.exposure for e in self.entries]

    def names(self) -> list[str]:
        return [e.name for e in self.entries]

    def subset(self, positions: Sequence[int], keep: bool = False) -> FrameSource:
        """The same source restricted to the frames at ``positions`` (0-based, in order).

        ``keep``: the windows the subset reads from per-frame files (up to
        :data:`KEEP_EVENTS` events in all) are kept for this source's own pass, which then
        does not read them again (a recording's threshold reads frames before they are
        deblurred)."""
        chosen = sorted(set(int(i) for i in positions))
        if chosen and (chosen[0] < 0 or chosen[-1] >= len(self.entries)):
            raise InputError(f"frame positions {chosen[0]}..{chosen[-1]} outside "
                             f"0..{len(self) - 1}")
        sub = FrameSource([self.entries[i] for i in chosen], self.width, self.height,
                          recording=self.recording, stored_frames=self._stored,
                          options=self._options, warnings=list(self.warnings))
        sub._kept, sub._keeping = self._kept, keep
        return sub

    #: whether the windows this source reads are kept for the source it is a subset of
    _keeping = False

    def __iter__(self) -> Iterator[FrameWindow]:
        return self.iter_windows()

    def iter_windows(self, margin_us: int = 0) -> Iterator[FrameWindow]:
        """Frames in order with the events of ``[start - margin, end + margin]`` µs."""
        if self.recording is None and not self._stored and margin_us == 0:
            # per-frame files: one frame at a time, windows read ahead by a subset reused
            for entry in self.entries:
                item = self._kept.pop(entry, None)
                if item is None:
                    item = FrameWindow(self._read_frame(entry), self._file_events(entry, 0))
                elif not self._keeping:
                    yield item
                    continue
                if self._keeping and len(item.events) + sum(
                        len(w.events) for w in self._kept.values()) <= KEEP_EVENTS:
                    self._kept[entry] = item
                yield item
            return
        frames = self.frames()
        events = self._events(margin_us)
        for frame, ev in zip(frames, events, strict=False):
            yield FrameWindow(frame, ev)

    def frames(self) -> Iterator[Frame]:
        """The frames alone, in order: no event is read (a window a subset kept gives its
        frame)."""
        if self._stored:
            wanted = {e.index: e for e in self.entries}
            assert self.recording is not None
            exposed = (f for f in self.recording.frames() if f.exposure is not None)
            for k, f in enumerate(exposed):
                entry = wanted.get(k)
                if entry is None:
                    continue
                check_frame_matches(f.image, self.width, self.height, self.recording.path)
                yield Frame(f.image, entry.exposure, f.index, f.name, f.note)
            return
        for entry in self.entries:
            kept = self._kept.get(entry)
            yield self._read_frame(entry) if kept is None else kept.frame

    def _read_frame(self, entry: FrameEntry) -> Frame:
        img, note = read_image_noted(entry.image_path)  # type: ignore[arg-type]
        check_frame_matches(img, self.width, self.height, entry.image_path)
        return Frame(img, entry.exposure, entry.index, entry.name, note)

    def _events(self, margin_us: int) -> Iterator[EventStream]:
        if self.recording is not None:
            yield from self.recording.iter_windows(self.exposures(), margin_us)
            return
        for entry in self.entries:
            yield self._file_events(entry, margin_us)

    def _file_events(self, entry: FrameEntry, margin_us: int) -> EventStream:
        from . import open_events

        opts = self._options
        if opts.sensor is None:
            opts = replace(opts, sensor=(self.width, self.height))
        e = entry.exposure
        with open_events(entry.events_path, opts) as rec:  # type: ignore[arg-type]
            if rec.sensor_size() != (self.width, self.height):
                raise InputError(f"events are {rec.width}x{rec.height} but the frames are "
                                 f"{self.width}x{self.height}", path=entry.events_path)
            return rec.events(e.start_us - margin_us, e.end_us + margin_us + 1)

    def close(self) -> None:
        self._kept.clear()
        if self._owns and self.recording is not None:
            self.recording.close()

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True, eq=False)
class BinnedWindow:
    """One frame and the binned events of its exposure (no event times).

    Attributes:
        frame: the image (float32 [0, 1], (H, W) or (H, W, 3)); ``exposure`` is None: binned
            data has no event clock.
        bins: (B, H, W) signed counts of the B equal bins spanning the exposure, in time order.
    """

    frame: Frame
    bins: np.ndarray


class BinnedSource:
    """Frames with the binned events of their exposures, one frame at a time: the i-th image
    in sorted order with the i-th block of bins (see :mod:`trmd_cli.read.bins`).

    Attributes:
        images: the frames' files, in order. binned: the bins
            (:class:`~trmd_cli.read.bins.BinnedEvents`). width, height: the frames' size.
        warnings: things the user should hear.
    """

    #: no recording to fill gaps between exposures from (the bins hold only the exposures)
    recording = None

    def __init__(self, images: Sequence[Path], binned, warnings: list[str] | None = None
                 ) -> None:
        from .bins import BinnedEvents

        self.images = list(images)
        self.binned: BinnedEvents = binned
        self.width, self.height = binned.width, binned.height
        self.warnings = [] if warnings is None else warnings
        if len(self.images) != binned.frames:
            raise InputError(f"{len(self.images)} images for the bins of {binned.frames} frames",
                             path=binned.path, hint="give one image per frame")

    @property
    def path(self) -> Path:
        """The bins file."""
        return self.binned.path

    @property
    def bins_per_frame(self) -> int:
        return self.binned.bins_per_frame

    def __len__(self) -> int:
        return len(self.images)

    def names(self) -> list[str]:
        return [p.stem for p in self.images]

    def subset(self, positions: Sequence[int], keep: bool = False) -> BinnedSource:
        """The same source restricted to the frames at ``positions`` (0-based, in order).
        ``keep`` is accepted as :meth:`FrameSource.subset` takes it; binned counts are read
        from one file, already cheap to read again."""
        from .bins import BinnedEvents

        keep = sorted(set(int(i) for i in positions))
        if keep and (keep[0] < 0 or keep[-1] >= len(self.images)):
            raise InputError(f"frame positions {keep[0]}..{keep[-1]} outside 0..{len(self) - 1}")
        return BinnedSource([self.images[i] for i in keep],
                            BinnedEvents(self.binned.path, self.binned.counts[keep]),
                            list(self.warnings))

    def __iter__(self) -> Iterator[BinnedWindow]:
        for i, frame in enumerate(self.frames()):
            yield BinnedWindow(frame, self.binned.frame(i))

    def frames(self) -> Iterator[Frame]:
        """The frames alone, in order (no bins read)."""
        for i, path in enumerate(self.images):
            img, note = read_image_noted(path)
            check_frame_matches(img, self.width, self.height, path)
            n = frame_number(path)
            yield Frame(img, None, n if n is not None else i, path.stem, note)

    def close(self) -> None:
        pass

    def __enter__(self) -> BinnedSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_binned_folder(images: str | Path, bins: str | Path) -> BinnedSource:
    """Frames from a folder with the binned events of one bins file, paired in sorted order.

    Raises:
        InputError: no images; the bins' frame count, bins per frame or size do not fit the
            images; NaN or fractional counts. FormatError: an unreadable bins file.
    """
    from .bins import read_bins

    images = Path(images)
    paths = list_images(images)
    if not paths:
        raise InputError("the folder holds no images", path=images,
                         hint="frames must be PNG, JPG or TIFF files")
    h, w = read_image(paths[0]).shape[:2]
    return BinnedSource(paths, read_bins(bins, len(paths), (w, h)))


def frames_from_recording(recording: Recording) -> FrameSource:
    """Frames stored in an event file (AEDAT4 APS frames, HDF5 images) with their events.

    Frames without an exposure window are left out (the reader warns about them); entries are
    numbered by their position among the frames that have one.
    Raises:
        InputError: the file stores no frames with exposure times.
    """
    exposures = recording.frame_exposures()
    if not exposures:
        if next(iter(recording.frames()), None) is None:
            raise InputError("the file holds events but no frames: deblurring needs the "
                             "blurry frames too", path=recording.path,
                             hint="deblur and hfr take the blurry image before it (BLURRY "
                                  "EVENTS) or a frames folder (IMAGES_DIR EVENTS); eval needs "
                                  "a recording that stores its frames (.h5, .aedat4)")
        # formats whose frames carry one stamp each say how to give the exposure time
        hint = recording.exposure_hint or (
            "give the frames as a folder (with Exposure_start.txt / Exposure_end.txt) or one "
            "image with `exposure=(T0, T1)`")
        raise InputError("the file stores frames but not their exposure times",
                         path=recording.path, hint=hint)
    entries = [FrameEntry(k, f"{k:06d}", e) for k, e in enumerate(exposures)]
    return FrameSource(entries, recording.width, recording.height, recording=recording,
                       stored_frames=True, warnings=list(recording.warnings))


def open_frame_folder(
    images: str | Path,
    events: str | Path | None = None,
    options: ReadOptions | None = None,
    *,
    exposures: Sequence[Exposure] | None = None,
    time_offset_us: int = 0,
) -> FrameSource:
    """Frames from a folder (or one image file) with the events of each exposure.

    Args:
        images: a folder of frames, or one image file.
        events: one event file for all frames; a folder of per-frame event files (paired by
            number); or None to look for a sibling ``mat``/``events`` folder.
        options: how to read the event files (``time_unit`` also applies to the exposure files).
        exposures: windows in µs on the events' clock, one per image; overrides everything else.
        time_offset_us: added to the times of ``Exposure_start.txt``/``Exposure_end.txt`` (the
            frame camera's clock → the event camera's clock).

    Exposure windows, first rule that applies: ``exposures``; exposure files beside the images;
    windows stored in the event file(s) (one per frame).

    Raises:
        InputError: no images, no events, no exposure times, counts or sizes that disagree.
    """
    from . import open_events

    options = options or ReadOptions()
    images = Path(images)
    if images.is_file():
        image_paths, images_dir = [images], images.parent
    elif images.is_dir():
        image_paths, images_dir = list_images(images), images
    else:
        raise InputError("not found", path=images, hint="give a folder of frames or an image")
    if not image_paths:
        raise InputError("the folder holds no images", path=images,
                         hint="frames must be PNG, JPG or TIFF files")
    if exposures is not None and len(exposures) != len(image_paths):
        raise InputError(f"{len(exposures)} exposure window(s) for {len(image_paths)} frames",
                         path=images, hint="give one window per frame")
    if events is None:
        events = sibling_events(images_dir)
        if events is None:
            raise InputError("no events given for these frames", path=images,
                             hint="pass the event file, or the folder of per-frame event files")
    events = Path(events)
    warnings: list[str] = []
    expo_files = None if exposures is not None or images.is_file() else \
        find_exposure_files(images_dir)
    first = read_image(image_paths[0])
    height, width = first.shape[:2]

    if events.is_dir():
        pairs = pair_folders(images_dir, events) if images.is_dir() else \
            [(images, *_single_pair(images, events))]
        unmatched = len(image_paths) - len(pairs)
        if unmatched:
            warnings.append(f"{unmatched} image(s) have no event file with the same number; "
                            "skipped")
        if expo_files is not None and unmatched:
            raise InputError("exposure files list every image but some images have no event "
                             "file", path=events, hint="pair every image with an event file")
        if exposures is not None:
            windows = list(exposures)
        elif expo_files is not None:
            windows = _exposures_from_files(expo_files, len(pairs), options.time_unit,
                                            time_offset_us)
        else:
            windows = [_stored_window(ev, options) for _, ev, _ in pairs]
        entries = [FrameEntry(n, img.stem, w, img, ev)
                   for (img, ev, n), w in zip(pairs, windows, strict=True)]
        return FrameSource(entries, width, height, options=options, warnings=warnings)

    if options.sensor is None and options.frame_size is None:
        # the frames' size is the sensor's, for event files that state none (a text file
        # whose last column never fired is not a narrower sensor)
        options = replace(options, frame_size=(width, height))
    recording = open_events(events, options)
    try:
        check_frame_matches(first, recording.width, recording.height, image_paths[0])
        warnings.extend(recording.warnings)
        if exposures is not None:
            windows = list(exposures)
        elif expo_files is not None:
            windows = _exposures_from_files(expo_files, len(image_paths), options.time_unit,
                                            time_offset_us)
        else:
            stored = recording.stored_windows() or recording.frame_exposures()
            if len(stored) != len(image_paths):
                raise InputError(
                    f"no exposure times for the {len(image_paths)} frame(s)"
                    + (f" (the event file stores {len(stored)} windows)" if stored else ""),
                    path=images,
                    hint="add Exposure_start.txt and Exposure_end.txt (one time per line, µs) "
                         "beside the images, or pass `exposure=(T0, T1)` for a single frame")
            windows = list(stored)
        _warn_outside(windows, recording.time_range_us(), warnings)
        entries = [FrameEntry(frame_number(p) if frame_number(p) is not None else i, p.stem, w, p)
                   for i, (p, w) in enumerate(zip(image_paths, windows, strict=True))]
        return FrameSource(entries, width, height, recording=recording, options=options,
                           warnings=warnings, owns_recording=True)
    except BaseException:
        recording.close()
        raise


def sibling_events(images_dir: Path) -> Path | None:
    """The per-frame events folder beside a frames folder (eSL-Net's ``mat/``, or ``events/``),
    or None."""
    images_dir = Path(images_dir)
    return next((images_dir.parent / d for d in _EVENT_DIRS
                 if (images_dir.parent / d).is_dir() and images_dir.parent / d != images_dir),
                None)


def _single_pair(image: Path, events_dir: Path) -> tuple[Path, int]:
    n = frame_number(image)
    match = [p for p in events_dir.iterdir() if p.suffix.lower() in EVENT_EXTENSIONS
             and frame_number(p) == n] if n is not None else []
    if len(match) != 1:
        raise InputError(f"expected one event file numbered {n} for {image.name}",
                         path=events_dir)
    return match[0], n  # type: ignore[return-value]


def _stored_window(path: Path, options: ReadOptions) -> Exposure:
    if path.suffix.lower() == ".mat":
        from .mat import read_mat_window

        window = read_mat_window(path, options)
        windows = [window] if window else []
    else:
        from . import open_events

        with open_events(path, options) as rec:
            windows = rec.stored_windows()
    if len(windows) != 1:
        raise InputError(f"stores {len(windows)} exposure windows; a per-frame event file "
                         "needs exactly one", path=path,
                         hint="add Exposure_start.txt / Exposure_end.txt beside the images")
    return windows[0]


def _warn_outside(windows: Sequence[Exposure], trange: tuple[int, int],
                  warnings: list[str]) -> None:
    first, last = trange
    outside = sum(w.end_us < first or w.start_us > last for w in windows)
    if outside:
        warnings.append(f"{outside} of {len(windows)} exposure windows lie outside the events' "
                        f"time range [{first}, {last}] µs: check `time_unit` and the time "
                        "offset between the cameras")
