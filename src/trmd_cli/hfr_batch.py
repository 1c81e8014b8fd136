"""`trmd hfr` over many exposures and recordings, across processes and machines, resumably.

The stream of :mod:`trmd_cli.hfr` is cut into units of two phases, run through the machinery of
:mod:`trmd_cli.batch` (the stage, ``--jobs`` workers, torchrun ranks, ``--resume``):

1. ``("x", r, k)``: exposure k of recording r deblurred — its frames, and its
   :class:`~trmd_cli.hfr.Edge` (end frames, instants, c) for the gaps on either side;
2. ``("g", r, k)``: the gap between exposures k and k + 1 filled from the events in it, from
   the two edges (:func:`~trmd_cli.hfr.gap_frames`). It starts once every exposure is done.

Every exposure is deblurred once, and every frame is made by the same code from the same
numbers as in :func:`~trmd_cli.hfr.hfr_stream` (an edge's frames travel as float32 arrays), so
the output is the one-process run's, file for file. The stage::

    .<OUT>.trmd-partial/
        plan.json                what the run is (a resume with other settings is refused)
        done/x-<r>-<k>.json      exposure k of recording r is complete: its rows, c, edge
        done/g-<r>-<k>.json      so is the gap after it
        parts/<r>/x<k>/          its frames 000000.png … (and edges.npz)
        parts/<r>/g<k>/          the gap's frames
        out/                     becomes OUT when OUT is a folder

A unit's folder is written aside and renamed in whole, then recorded (as in ``batch``). When
every unit is complete one process numbers the frames in stream order and assembles each
recording's output: a frames folder gets them as hard links (copies where the file system has
none) with timestamps.txt and meta.json; a video is encoded from them in order. A video's
units write 8-bit PNGs, which hold exactly the bytes its encoder takes.

Never prints: warnings travel in each :class:`~trmd_cli.batch.ShareReport`.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from .batch import Item, Plan, RunSettings, ShardError, ShareReport, Stage, Tally, Unit

if TYPE_CHECKING:
    from .hfr import ExposureContrast
    from .methods import MethodConfig

__all__ = ["HfrSettings", "HfrPlan", "HfrSummary", "make_hfr_plan", "run_hfr_share",
           "finish_hfr", "hfr_meta", "timestamps_header", "OUTPUT_KINDS"]

#: what each recording of a run becomes: a folder of PNG frames, or a video
OUTPUT_KINDS = ("frames", "mp4", "gif")


@dataclass(frozen=True)
class HfrSettings(RunSettings):
    """What every process needs to make a unit of a stream, besides the plan (picklable).

    Attributes:
        config: the method (``settle_contrast`` on when gaps are filled; binned items turn it
            off); the others of :class:`~trmd_cli.batch.RunSettings` as there (bit_depth: of
            PNG frames).
        per_exposure: frames per exposure (None: 2N+1). fill_gaps: fill the gaps from the
            events. max_gap_frames: most frames per gap (None: 4 × per exposure).
        fps: playback rate, frames per second. kind: one of :data:`OUTPUT_KINDS`.
    """

    per_exposure: int | None = None
    fill_gaps: bool = True
    max_gap_frames: int | None = None
    fps: float = 30.0
    kind: str = "frames"

    def config_for(self, binned: bool) -> MethodConfig:
        """The method's config for one recording: binned events have no gaps to settle c for."""
        return replace(self.config, settle_contrast=False) if binned else self.config


@dataclass(frozen=True)
class HfrPlan(Plan):
    """The recordings of an hfr run: its exposures, then the gaps between them.

    Each item's ``folder`` is its output relative to OUT (``""``: OUT itself, for one input):
    a folder of frames, or a ``.mp4`` / ``.gif``."""

    settings: HfrSettings
    command: ClassVar[str] = "hfr"
    noun: ClassVar[str] = "parts"
    counted: ClassVar[str] = "parts (exposures and gaps)"
    verb: ClassVar[str] = "made"
    label: ClassVar[str] = "hfr"

    def gaps(self, item: Item) -> bool:
        """The gaps of ``item`` are filled (binned events have no times to fill them at)."""
        return self.settings.fill_gaps and not item.meta.get("binned", False)

    def phases(self) -> list[list[Unit]]:
        exposures = [("x", r, k) for r, item in enumerate(self.items) for k in range(item.frames)]
        gaps = [("g", r, k) for r, item in enumerate(self.items) if self.gaps(item)
                for k in range(item.frames - 1)]
        return [exposures, gaps] if gaps else [exposures]

    def units(self) -> list[Unit]:
        return [u for phase in self.phases() for u in phase]

    def stream(self, r: int) -> list[Unit]:
        """The units of recording ``r`` in stream order: exposure, gap, exposure, …"""
        item = self.items[r]
        out: list[Unit] = []
        for k in range(item.frames):
            out.append(("x", r, k))
            if self.gaps(item) and k < item.frames - 1:
                out.append(("g", r, k))
        return out

    def place(self, unit: Unit) -> Path:
        return Path("parts") / str(unit[1])

    def places(self) -> list[Path]:
        return [Path("parts") / str(r) for r in range(len(self.items))]

    @property
    def output_is_folder(self) -> bool:
        """OUT is a folder (frames, or one output per recording), swapped in from ``out/``."""
        return self.settings.kind == "frames" or any(it.folder for it in self.items)

    def run(self, stage: Stage, share: Sequence[Unit],
            tick: Callable[[], None] = lambda: None) -> ShareReport:
        return run_hfr_share(self, stage, share, tick)

    def finish(self, stage: Stage) -> HfrSummary:
        return finish_hfr(self, stage)


@dataclass(frozen=True)
class HfrSummary:
    """What a finished run's records say, over all its recordings.

    Attributes:
        exposure, gap: frames from exposures and filling gaps. contrasts: each exposure's c
        (:class:`~trmd_cli.hfr.ExposureContrast`), in stream order. clipped: each exposure's
        fraction of values clipped. capped: some gap got fewer frames than real time needs.
    """

    exposure: int
    gap: int
    contrasts: tuple[ExposureContrast, ...]
    clipped: tuple[float, ...]
    capped: bool


def timestamps_header(binned: bool) -> str:
    """The first line of timestamps.txt."""
    if binned:
        return ("# file fraction kind source (fraction of the source's exposure: binned "
                "events, no event clock)")
    return "# file time_us kind source"


def hfr_meta(ins, est, *, per_exposure: int | None, fps: float, fill_gaps: bool,
             offset_us: int, config: MethodConfig, settled=None) -> dict:
    """meta.json of a frames output, with ``contrast`` and ``frames`` still to fill in (their
    places kept).

    Args:
        ins: the :class:`~trmd_cli.read.inputs.Inputs`. est: the method run on them.
        per_exposure: frames per exposure (None: 2N+1). fps: playback rate. fill_gaps: asked
            for. offset_us: exposure shift, µs. config, settled: the method's settings and
            what was settled for the recording (a :class:`~trmd_cli.deblur.Settled`; None:
            nothing), for where c came from and whether the fixed pattern was removed.
    """
    from . import __version__
    from .batch import binned_meta, contrast_meta, pattern_meta

    meta = {
        "tool": f"trmd {__version__}", "method": est.name, "n": est.n,
        "weights_hash": est.weights_hash, "inputs": ins.paths, "precision": est.precision,
        "per_exposure": per_exposure or 2 * est.n + 1, "fps": fps, "fill_gaps": fill_gaps,
        "time_offset_us": offset_us, "contrast": None, "frames": None,
        **contrast_meta(config, None if settled is None else settled.contrast),
        **pattern_meta(config, None if settled is None else settled.pattern)}
    if ins.binned:
        del meta["time_offset_us"]
        meta.update(fill_gaps=False, **binned_meta(ins.source))
    return meta


def make_hfr_plan(groups: Sequence[Sequence[str | Path]], folders: Sequence[str],
                  settings: HfrSettings, warn: Callable[[str], None] = lambda _: None
                  ) -> HfrPlan:
    """Open every recording once to count its exposures, check their order and settle its
    meta.json head.

    Args:
        groups: the inputs of each recording. folders: each one's output in OUT (``""``: OUT
            itself). warn: receives what the inputs say (and the note on binned events).
    Raises:
        InputError: inputs that are one image, two outputs of the same name, no frame, or
            exposures out of time order.
    """
    from .batch import plan_items, settled
    from .deblur import binned_note
    from .hfr import check_time_order

    s = settings
    method = _methods(s)

    def head(ins, path, settled) -> dict:
        est = method(ins.binned)  # its name, N, weights hash, precision
        if ins.binned:
            warn(binned_note(ins.source, est, stream=True))
        return hfr_meta(ins, est, per_exposure=s.per_exposure, fps=s.fps,
                        fill_gaps=s.fill_gaps, offset_us=s.offset_us,
                        config=s.config_for(ins.binned), settled=settled)

    def settle(ins, path):
        # before any frame is read for the threshold
        if not ins.binned:
            check_time_order(ins.source.exposures(), path)
        return settled(method(ins.binned), ins.source, s.config_for(ins.binned))

    return HfrPlan(plan_items(groups, folders, s, head, warn, settle=settle), settings)


def _methods(settings: HfrSettings) -> Callable[[bool], object]:
    """The method for binned or timed events, each made once, when first asked for."""
    from .methods import make_method

    return cache(lambda binned: make_method(settings.config_for(binned)))


def run_hfr_share(plan: HfrPlan, stage: Stage, share: Sequence[Unit],
                  tick: Callable[[], None] = lambda: None) -> ShareReport:
    """Make the units of ``share`` that are not complete yet: each one's folder renamed into the
    stage when complete, then its record written. A gap's exposures must be complete.

    Args:
        tick: called after every unit (progress).
    Raises:
        ShardError: a gap whose exposures are not complete.
    """
    from .batch import open_item
    from .deblur import deblur_frames
    from .hfr import ExposureContrast, exposure_frames, gap_frames
    from .write import clipped_fraction, write_json

    s = plan.settings
    todo = stage.pending(plan, share)
    tally = Tally(tick)
    method = _methods(s)
    for r, item in enumerate(plan.items):
        exposures = [k for (kind, i, k) in todo if kind == "x" and i == r]
        gaps = [k for (kind, i, k) in todo if kind == "g" and i == r]
        if not exposures and not gaps:
            continue
        binned = bool(item.meta.get("binned", False))
        with open_item(item, s) as ins:
            if exposures:
                m = method(binned)
                if item.settled is not None:
                    m = item.settled.applied_to(m)
                results = deblur_frames(ins.source.subset(exposures), m,
                                        per_exposure=s.per_exposure)
                for k, res in tally.deblurred(r, exposures, results):
                    frames = list(exposure_frames(res))
                    edge = _write_edge(res) if plan.gaps(item) else None
                    unit = ("x", r, k)
                    _write_unit(stage, plan, unit, frames, edge)
                    said = ExposureContrast.of(res)
                    write_json(stage.record(unit), {
                        "folder": f"x{k}", "rows": _rows(frames), "frame": said.frame,
                        "contrast": said.contrast, "contrast_default": said.default,
                        "clipped": clipped_fraction(res.frames),
                        "edge": None if edge is None else edge[0]})
                    tally.made()
            for k in gaps:
                a, b = (_read_edge(stage, plan, ("x", r, j)) for j in (k, k + 1))
                frames, capped = gap_frames(a, b, ins.source.recording,
                                            max_gap_frames=s.max_gap_frames,
                                            contrast=s.config.contrast)
                unit = ("g", r, k)
                _write_unit(stage, plan, unit, frames)
                write_json(stage.record(unit), {"folder": f"g{k}", "rows": _rows(frames),
                                                "capped": capped})
                tally.made()
    return tally.report()


def _rows(frames) -> list[str]:
    from .hfr import timestamp_row

    return [timestamp_row(fr) for fr in frames]


def _depth(plan: HfrPlan) -> int:
    """Bit depth of a unit's PNGs: the output's for frames; a video's encoder takes 8 bits."""
    return plan.settings.bit_depth if plan.settings.kind == "frames" else 8


def _write_edge(res) -> tuple[dict, dict]:
    """An exposure's edge as its record's part and its arrays (:class:`~trmd_cli.hfr.Edge`)."""
    from .hfr import Edge

    e = Edge.of(res)
    doc = {"name": e.name, "first_us": e.first_us, "last_us": e.last_us, "count": e.count,
           "duration_us": int(e.duration_us),
           "contrast": None if e.contrast is None else float(e.contrast)}
    return doc, {"first": e.first, "last": e.last}


def _read_edge(stage: Stage, plan: HfrPlan, unit: Unit):
    from .hfr import Edge

    rec = stage.finished(plan, unit)
    if rec is None or not rec.get("edge"):
        raise ShardError(f"exposure {unit[2]} of {plan.items[unit[1]].inputs[0]} is not "
                         "complete, but the gap beside it was started; rerun with --resume")
    with np.load(stage.folder(plan, unit) / rec["folder"] / "edges.npz") as arrays:
        first, last = arrays["first"], arrays["last"]
    return Edge(first=first, last=last, **rec["edge"])


def _write_unit(stage: Stage, plan: HfrPlan, unit: Unit, frames, edge=None) -> None:
    """A unit's frames (and an exposure's edge arrays) as a folder, renamed in when whole."""
    from .write import atomic_dir, write_image, write_npz

    depth = _depth(plan)
    with atomic_dir(stage.folder(plan, unit) / f"{unit[0]}{unit[2]}") as tmp:
        for j, fr in enumerate(frames):
            write_image(tmp / f"{j:06d}.png", fr.image, depth)
        if edge is not None:
            write_npz(tmp / "edges.npz", **edge[1])


def finish_hfr(plan: HfrPlan, stage: Stage) -> HfrSummary:
    """Number every recording's frames in stream order and write its output: a frames folder
    (frames, timestamps.txt, meta.json) or a video; then put the output in place and remove the
    stage.

    Raises:
        ShardError: a unit is not complete (a process did not finish its share).
    """
    from .batch import swap_in, sweep_temps
    from .hfr import ExposureContrast, contrast_meta
    from .video import VideoWriter
    from .write import write_json, write_text

    s = plan.settings
    exposure = gap = 0
    contrasts: list[ExposureContrast] = []
    clipped: list[float] = []
    capped = False
    for r, item in enumerate(plan.items):
        files: list[Path] = []
        rows: list[str] = []
        count = {"exposure": 0, "gap": 0}
        mine: list[ExposureContrast] = []  # this recording's, for its meta.json
        for unit in plan.stream(r):
            rec = stage.finished(plan, unit)
            if rec is None:
                what = "exposure" if unit[0] == "x" else "the gap after exposure"
                raise ShardError(f"{what} {unit[2]} of {item.inputs[0]} was not made; rerun "
                                 "with --resume to finish it")
            folder = stage.folder(plan, unit) / rec["folder"]
            files += [folder / f"{j:06d}.png" for j in range(len(rec["rows"]))]
            rows += rec["rows"]
            count["exposure" if unit[0] == "x" else "gap"] += len(rec["rows"])
            if unit[0] == "x":
                mine.append(ExposureContrast(rec["frame"], rec["contrast"],
                                             rec["contrast_default"]))
                clipped.append(rec["clipped"])
            else:
                capped = capped or rec["capped"]
        exposure += count["exposure"]
        gap += count["gap"]
        contrasts += mine
        if s.kind == "frames":
            target = stage.out / item.folder
            if target.exists():  # an earlier finish was cut short: start it again
                shutil.rmtree(target)
            target.mkdir()
            lines = [timestamps_header(bool(item.meta.get("binned", False)))]
            for i, (src, row) in enumerate(zip(files, rows, strict=True)):
                name = f"{i:06d}.png"
                _link(src, target / name)
                lines.append(f"{name} {row}")
            write_text(target / "timestamps.txt", "\n".join(lines) + "\n")
            write_json(target / "meta.json", {**item.meta, **contrast_meta(mine),
                                              "frames": count})
        else:
            target = stage.out / item.folder if item.folder else stage.output
            with VideoWriter(target, s.fps) as vw:
                for src in files:
                    vw.append(_read_u8(src) / np.float32(255))
    if plan.output_is_folder:
        sweep_temps(stage.out)
        swap_in(stage)
    else:
        shutil.rmtree(stage.root, ignore_errors=True)
    return HfrSummary(exposure, gap, tuple(contrasts), tuple(clipped), capped)


def _link(src: Path, dst: Path) -> None:
    """``dst`` as a hard link to ``src`` (no bytes copied: the stage goes once the output is in
    place), a copy where the file system has no links."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _read_u8(path: Path) -> np.ndarray:
    """A unit's 8-bit PNG as the uint8 array written (RGB for colour). ``/ 255`` as float32
    gives it back to the video writer exactly: its rounding maps v / 255 to v for every v."""
    import cv2

    img = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ShardError(f"a frame of the run's stage is damaged: {path}; rerun without "
                         "--resume", 1)
    return img[..., ::-1] if img.ndim == 3 else img
