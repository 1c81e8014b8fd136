"""The positional inputs of ``trmd deblur`` / ``trmd hfr`` → frames, exposure windows and events.

:func:`open_inputs` tells the layouts apart (a recording with frames; a blurry image and its
events; a frames folder with an event file or per-frame event files; several images with one
event file) and returns them as one :class:`~trmd_cli.read.folders.FrameSource`, every exposure
window moved by the time offset — or, for a frames folder with a bins file, as a
:class:`~trmd_cli.read.folders.BinnedSource` (binned events, no event times). Never prints:
warnings travel in :attr:`Inputs.warnings`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from ..errors import InputError
from ..events import Exposure
from ..window import check_in_range, check_windows, exposure_from_user, resolve_windows
from . import open_events
from .base import ReadOptions
from .bins import is_bins_file
from .folders import (
    BinnedSource,
    FrameEntry,
    FrameSource,
    frame_number,
    frames_from_recording,
    open_binned_folder,
    open_frame_folder,
    sibling_events,
)
from .frames import IMAGE_EXTENSIONS, check_frame_matches, read_image
from .paths import check_input_path
from .sniff import is_recording_folder

__all__ = ["Inputs", "open_inputs"]


@dataclass(eq=False)
class Inputs:
    """Frames to deblur with their windows and events.

    Attributes:
        source: the frames, one :class:`FrameWindow` at a time — or, for binned events, one
            :class:`~trmd_cli.read.folders.BinnedWindow` at a time.
        single: one blurry image given directly (outputs go flat into OUT/, not per frame).
        paths: the input files, for meta.json.
        warnings: things the user should hear (printed by the CLI).
    """

    source: FrameSource | BinnedSource
    single: bool
    paths: list[str]
    warnings: list[str] = field(default_factory=list)

    @property
    def binned(self) -> bool:
        """The events are binned (no event times: instants are fractions of the exposure)."""
        return isinstance(self.source, BinnedSource)

    def close(self) -> None:
        self.source.close()

    def __post_init__(self) -> None:
        # the same file may be opened twice (window, then frames): say each warning once
        self.warnings = list(dict.fromkeys(self.warnings))

    def __enter__(self) -> Inputs:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_inputs(inputs: Sequence[str | Path], options: ReadOptions | None = None, *,
                exposure: Sequence[float] | None = None, offset_us: int = 0) -> Inputs:
    """Understand the positional inputs of ``trmd deblur`` / ``trmd hfr``.

    * ``RECORDING`` (AEDAT 2.0/3.1/4, HDF5 with frames, a ROS bag with images, an RPG folder):
      every stored frame, its own exposure;
    * ``BLURRY EVENTS``: one image and an event file (or a folder of per-frame event files);
      the window is ``exposure`` (file's unit), else the one stored, else the events' span;
    * ``IMAGES_DIR EVENTS``: a frames folder with an event file (+ Exposure_start/end.txt) or a
      folder of per-frame event files paired by number; ``IMAGES_DIR`` alone when such a
      folder (``mat/``, ``events/``) stands beside it, as eSL-Net's;
    * ``BLURRY1 BLURRY2 … EVENTS``: several images, one event file storing one window each;
    * ``IMAGES_DIR BINS_FILE``: a frames folder with binned events (:mod:`trmd_cli.read.bins`),
      the i-th image in sorted order with the i-th block of bins; no event clock, so
      ``exposure``, ``offset_us`` and the options about event times do not apply (bad input).

    ``offset_us`` (µs) moves every exposure window relative to the events.

    Raises:
        InputError: missing files, a window outside the events' time range, image size not
            matching the sensor, counts that disagree. FormatError: unreadable files.
    """
    options = options or ReadOptions()
    paths = [Path(p) for p in inputs]
    if not paths:
        raise InputError("no input given", hint="trmd deblur BLURRY EVENTS -o OUT/")
    for p in paths:
        check_input_path(p)  # missing, a pipe, unreadable: one line, nothing opened
    names = [str(p) for p in paths]
    is_image = [p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS for p in paths]

    if len(paths) == 1:
        if is_image[0]:
            raise InputError("got a blurry image but no events", path=paths[0],
                             hint="trmd deblur BLURRY EVENTS -o OUT/")
        if paths[0].is_dir() and not is_recording_folder(paths[0]):
            beside = sibling_events(paths[0])
            if beside is None:
                raise InputError("got a frames folder but no events", path=paths[0],
                                 hint="trmd deblur IMAGES_DIR EVENTS -o OUT/")
            return open_inputs([paths[0], beside], options, exposure=exposure,
                               offset_us=offset_us)
        rec = open_events(paths[0], options)
        if exposure is not None:
            has_frames = next(iter(rec.frames()), None) is not None
            rec.close()
            raise InputError("`exposure` applies to one blurry image given with its events",
                             path=paths[0],
                             hint="a recording's frames carry their own exposure windows"
                             if has_frames else "this file holds events only: give the blurry "
                             "image before it (BLURRY EVENTS)")
        try:
            src = frames_from_recording(rec)
            src = FrameSource(_shift(src.entries, offset_us), src.width, src.height,
                              recording=rec, stored_frames=True, options=options,
                              warnings=list(src.warnings), owns_recording=True)
            check_windows(src.exposures(), rec, paths[0])
        except BaseException:
            rec.close()
            raise
        return Inputs(src, False, names, list(src.warnings))

    if len(paths) == 2 and is_image[0]:
        image, events = paths
        options = _with_frame_size(options, image)
        warnings: list[str] = []
        if events.is_dir():
            src = open_frame_folder(image, events, options)
            if exposure is not None or offset_us:
                wins = src.exposures()
                src.close()
                if exposure is not None:
                    wins = [exposure_from_user(exposure[0], exposure[1], options.time_unit)]
                src = open_frame_folder(image, events, options,
                                        exposures=_shift_windows(wins, offset_us))
            return Inputs(src, True, names, list(src.warnings))
        with open_events(events, options) as rec:
            plan = resolve_windows(rec, exposure, options.time_unit, offset_us=offset_us)
            warnings.extend(rec.warnings)
            warnings.extend(plan.warnings)
            if len(plan.windows) != 1:
                raise InputError(
                    f"the event file stores {len(plan.windows)} exposure windows; which one "
                    "belongs to this image?", path=events,
                    hint="pass `exposure=(T0, T1)`, or give the frames folder / the recording")
            check_in_range(plan.windows[0], rec.time_range_us(), "exposure window", events)
        del rec  # else its events stay in memory beside the second opening's
        src = open_frame_folder(image, events, options, exposures=plan.windows)
        return Inputs(src, True, names, warnings + list(src.warnings))

    if len(paths) == 2 and paths[0].is_dir() and is_bins_file(paths[1]):
        _check_binned_options(options, exposure, offset_us, paths[1])
        src = open_binned_folder(paths[0], paths[1])
        if options.sensor is not None and options.sensor != (src.width, src.height):
            raise InputError(f"the bins are {src.width}x{src.height}, not the sensor "
                             f"{options.sensor[0]}x{options.sensor[1]} given", path=paths[1],
                             hint="leave out `sensor`: the bins' size is the sensor's")
        return Inputs(src, False, names, list(src.warnings))

    if len(paths) == 2 and paths[0].is_dir():
        if exposure is not None:
            raise InputError("`exposure` applies to one blurry image, not a frames folder",
                             hint="put Exposure_start.txt / Exposure_end.txt beside the frames")
        src = open_frame_folder(paths[0], paths[1], options)
        if offset_us:
            wins = src.exposures()
            src.close()
            src = open_frame_folder(paths[0], paths[1], options,
                                    exposures=_shift_windows(wins, offset_us))
        if src.recording is not None:
            check_windows(src.exposures(), src.recording, paths[1])
        return Inputs(src, False, names, list(src.warnings))

    if len(paths) >= 2 and all(is_image[:-1]):
        images, events = paths[:-1], paths[-1]
        if exposure is not None and len(images) > 1:
            raise InputError("`exposure` applies to one blurry image",
                             hint="store one window per frame in the event file")
        options = _with_frame_size(options, images[0])
        rec = open_events(events, options)
        try:
            if exposure is not None:
                plan = resolve_windows(rec, exposure, options.time_unit, offset_us=offset_us)
                wins = plan.windows
            else:
                wins = _shift_windows(rec.stored_windows() or rec.frame_exposures(), offset_us)
            if len(wins) != len(images):
                raise InputError(f"{len(images)} images but the event file stores "
                                 f"{len(wins)} exposure window(s)", path=events,
                                 hint="give a frames folder with Exposure_start.txt / "
                                 "Exposure_end.txt, or one image with `exposure=(T0, T1)`")
            check_windows(wins, rec, events)
            check_frame_matches(read_image(images[0]), rec.width, rec.height, images[0])
            entries = [FrameEntry(frame_number(p) if frame_number(p) is not None else i,
                                  p.stem, w, p)
                       for i, (p, w) in enumerate(zip(images, wins, strict=True))]
            src = FrameSource(entries, rec.width, rec.height, recording=rec, options=options,
                              warnings=list(rec.warnings), owns_recording=True)
        except BaseException:
            rec.close()
            raise
        return Inputs(src, len(images) == 1, names, list(src.warnings))

    raise InputError("cannot tell what these inputs are: " + " ".join(names),
                     hint="give RECORDING, or BLURRY EVENTS, or IMAGES_DIR EVENTS")


def _check_binned_options(options: ReadOptions, exposure, offset_us: int, path: Path) -> None:
    """Binned events have no event times: what would place or read times is bad input."""
    why = "binned events have no event clock"
    if exposure is not None:
        raise InputError(f"{why}: `exposure` does not apply", path=path,
                         hint="the bins span each frame's exposure; leave out `exposure`")
    if offset_us:
        raise InputError(f"{why}: `offset_us` cannot shift them", path=path,
                         hint="the bins span each frame's exposure; leave out `offset_us`")
    for name, value in (("time_unit", options.time_unit), ("columns", options.columns),
                        ("one_based", options.one_based or None)):
        if value is not None:
            raise InputError(f"binned events are an array of counts: `{name}` does not apply",
                             path=path, hint=f"leave out `{name}`")


def _with_frame_size(options: ReadOptions, image: Path) -> ReadOptions:
    """``options`` knowing the paired image's size: the sensor's, for event files that state
    none. An unreadable image is left for the frame source to report, as it always has."""
    from ..errors import TrmdError

    if options.sensor is not None:
        return options
    try:
        h, w = read_image(image).shape[:2]
    except TrmdError:
        return options
    return replace(options, frame_size=(int(w), int(h)))


def _shift_windows(windows: Iterable[Exposure], offset_us: int) -> list[Exposure]:
    return [w.shifted(offset_us) if offset_us else w for w in windows]


def _shift(entries: Iterable[FrameEntry], offset_us: int) -> list[FrameEntry]:
    return [replace(e, exposure=e.exposure.shifted(offset_us)) if offset_us else e
            for e in entries]


