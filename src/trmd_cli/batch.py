"""Deblurring many frames, of one recording or many, across processes and machines, resumably.

A run is a :class:`Plan`: the recordings (each an input of
:func:`~trmd_cli.read.inputs.open_inputs`) with their frame counts and the meta.json head they
share. Its work is the list of (recording, frame) units in order; a process of ``world`` takes
every ``world``-th unit from its ``rank`` (:meth:`Plan.share`), so the shares are disjoint,
deterministic and need no talking between processes while they run.

The machinery — the stage, local worker processes, torchrun ranks, resuming — knows a plan only
by its units, their :meth:`~Plan.phases` (a phase starts when every process has finished the
one before), where each unit's folder goes (:meth:`~Plan.place`) and how a share of them is
done (:meth:`~Plan.run`) and finished (:meth:`~Plan.finish`); ``trmd hfr`` runs through it
with a plan of its own (:mod:`trmd_cli.hfr_batch`). :func:`run_staged` is a whole run, from the
checks of the output to the output in place, the same for every command.

Frames land in a persistent *stage* beside the output, never in the output itself
(:class:`Stage`)::

    .<OUT>.trmd-partial/
        plan.json            what the run is; a resume with other inputs or settings is refused
        done/<r>-<k>.json    frame k of recording r is complete: its folder name, its meta part
        out/                 becomes OUT: one folder per frame (per recording: out/<name>/…)

A frame folder is written aside and renamed into ``out/`` when complete (``atomic_dir``); its
record in ``done/`` is written after that, so "record present and folder present" means the
frame is complete, and a rerun with ``resume`` skips exactly those. When every unit is done,
one process writes each recording's meta.json from the records and swaps ``out/`` in as the
output — the output is still all-or-nothing, and equal file for file to a one-process run.

Never prints: warnings travel in each :class:`ShareReport`; :func:`run_staged` hands what it has
to say to the caller's functions.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import AbstractContextManager
from dataclasses import asdict, dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from .errors import InputError, TrmdError
from .threads import usable_cores

if TYPE_CHECKING:  # not at run time: the CLI imports this module before it knows the mode
    from .deblur import FrameResult
    from .methods import MethodConfig
    from .read.base import ReadOptions

__all__ = [
    "Item", "RunSettings", "Settings", "Plan", "Stage", "ShareReport", "Ranks", "ShardError",
    "discard_stage",
    "run_meta", "recordings_in", "make_plan", "prepare_stage", "run_share", "finish",
    "frame_folder_name", "worker_threads", "ranks_from_env", "RECORDING_SUFFIXES", "Unit",
    "open_item", "swap_in", "run_pool", "run_plan", "todo", "agreed", "joined",
    "recording_folders", "plan_items", "Tally", "staged", "run_staged", "Outcome",
    "from_rank0", "auto_jobs", "choose_jobs", "count_work", "free_memory_bytes",
    "AUTO_METHODS",
]

#: one piece of a run's work: (recording, frame) for deblur; plans of their own may add a tag
Unit = tuple

#: file types a folder of recordings is searched for (each may hold frames and events);
#: recording folders (RPG, ROS 2) inside it count too
RECORDING_SUFFIXES = (".h5", ".hdf5", ".hdf", ".aedat4", ".aedat", ".bag")


class PoolUnavailable(Exception):
    """Worker processes cannot be started here (the reason); nothing was made yet."""


class ShardError(TrmdError):
    """A problem met by another process of the run (a worker, another rank), as its line."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


@dataclass(frozen=True)
class RunSettings:
    """What every process of a run needs to open its recordings and run its method, besides
    the plan (picklable); a command's settings add their own.

    Attributes:
        config: the method. read: how to read the inputs. exposure: ``--exposure`` (file's
            unit) or None. offset_us: exposure shift, µs. bit_depth: PNG bit depth, 8 or 16.
    """

    config: MethodConfig
    read: ReadOptions
    exposure: tuple[float, float] | None = None
    offset_us: int = 0
    bit_depth: int = 8


@dataclass(frozen=True)
class Settings(RunSettings):
    """What every process needs to deblur a unit, besides the plan (picklable).

    Attributes:
        compare: also write compare.png (the others: :class:`RunSettings`).
    """

    compare: bool = False


@dataclass(frozen=True)
class Item:
    """One recording of a run.

    Attributes:
        inputs: the paths given to ``open_inputs`` for it. folder: its sub-folder of the output
            (``""``: the output itself, when the run has one recording). frames: how many.
        meta: the head of its meta.json (and of each frame's).
        settled: what was settled for it when the plan was made, so that every process uses
            the same (:class:`~trmd_cli.deblur.Settled`: its one estimated contrast threshold,
            its sensor's fixed pattern); None when nothing was.
    """

    inputs: tuple[str, ...]
    folder: str
    frames: int
    meta: dict = field(hash=False)
    settled: object = field(default=None, hash=False)


@dataclass(frozen=True)
class Plan:
    """The recordings of a run and how to deblur them; every process builds the same one.

    A plan of another command subclasses this one, with settings of its own (a
    :class:`RunSettings`), and says how its units are done and finished."""

    items: tuple[Item, ...]
    settings: Settings
    #: the command whose stage this is: a resume by another command is refused
    command: ClassVar[str] = "deblur"
    #: what the run's messages call its units, how a resume counts them, what making one is
    #: called, and the progress bar's label
    noun: ClassVar[str] = "frames"
    counted: ClassVar[str] = "frames"
    verb: ClassVar[str] = "deblurred"
    label: ClassVar[str] = "deblurring"

    @property
    def output_is_folder(self) -> bool:
        """The output is a folder (deblur: always)."""
        return True

    def units(self) -> list[Unit]:
        """Every (recording, frame position) of the run, in output order."""
        return [(i, k) for i, item in enumerate(self.items) for k in range(item.frames)]

    def phases(self) -> list[list[Unit]]:
        """The units in the order their phases run: each one starts when every process has
        finished the one before (deblur: one phase)."""
        return [self.units()]

    def place(self, unit: Unit) -> Path:
        """The folder, relative to the stage, that holds ``unit``'s folder."""
        return Path("out") / self.items[unit[0]].folder

    def places(self) -> list[Path]:
        """Every folder :meth:`place` names, relative to the stage (made by ``prepare_stage``)."""
        return [Path("out") / item.folder for item in self.items]

    def run(self, stage: Stage, share: Sequence[Unit],
            tick: Callable[[], None] = lambda: None) -> ShareReport:
        """Do the units of ``share`` that are not complete yet (in this process)."""
        return run_share(self, stage, share, tick)

    def finish(self, stage: Stage):
        """Once every unit is complete: the output put in place from the stage (which goes).
        Returns what the command reports (deblur: every frame's meta part, in output order)."""
        return finish(self, stage)

    def share(self, rank: int, world: int,
              units: Sequence[Unit] | None = None) -> list[Unit]:
        """Unit u (of ``units``, default all) goes to process u mod ``world``."""
        units = self.units() if units is None else units
        return list(units[rank::world])

    def fingerprint(self) -> dict:
        """What must match for a resume: the command, the inputs, frames, meta heads and every
        setting that changes a written byte (not device or threads)."""
        settings = asdict(self.settings)
        settings["config"] = {k: v for k, v in settings["config"].items()
                              if k not in ("device", "threads")}
        doc = {"command": self.command,
               "items": [{"inputs": list(it.inputs), "folder": it.folder, "frames": it.frames,
                          "meta": it.meta} for it in self.items], **settings}
        return json.loads(json.dumps(doc, default=_plain))


def _plain(o):
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def pattern_meta(config: MethodConfig, pattern) -> dict:
    """What meta.json says of the sensor's fixed pattern (a
    :class:`~trmd_cli.fixed_pattern.FixedPattern` or None): removed, from which frames, or why
    not."""
    if not config.fixed_pattern:
        return {"fixed_pattern": {"removed": False, "reason": "kept as asked "
                                  "(`fixed_pattern=False`)"}}
    if pattern is None:
        return {"fixed_pattern": {"removed": False, "reason": "one frame: no pattern to tell "
                                  "from the scene"}}
    return {"fixed_pattern": pattern.meta()}


def contrast_meta(config: MethodConfig, recording) -> dict:
    """What meta.json says of the contrast threshold's origin: ``contrast_mode`` "given",
    "recording" (one estimate, ``contrast_recording`` says from which frames) or "frame"
    (estimated per frame, also when no frame of the recording held enough events for one
    estimate)."""
    if config.contrast is not None:
        return {"contrast_mode": "given"}
    if recording is None:
        return {"contrast_mode": "frame"}
    return {"contrast_mode": "recording",
            "contrast_recording": {"contrast": recording.contrast,
                                   "frames": list(recording.frames),
                                   "evaluations": recording.evaluations,
                                   "at_bound": recording.at_bound}}


def run_meta(ins, est, config: MethodConfig, offset_us: int, bit_depth: int,
             settled=None) -> dict:
    """The head of meta.json for a run on ``ins`` (:class:`~trmd_cli.read.inputs.Inputs`) by
    ``est`` (a :class:`~trmd_cli.methods.Method`); ``settled``: what was settled for the
    recording (a :class:`~trmd_cli.deblur.Settled`), if anything."""
    from . import __version__

    recording = None if settled is None else settled.contrast
    pattern = None if settled is None else settled.pattern
    meta = {
        "tool": f"trmd {__version__}",
        "method": est.name,
        "n": est.n,
        "weights_hash": est.weights_hash,
        "precision": est.precision,
        "inputs": ins.paths,
        "time_offset_us": offset_us,
        **contrast_meta(config, recording),
        "hot_pixels_ignored": config.hot_pixels,
        "isolated_events_dropped": config.drop_isolated,
        **pattern_meta(config, pattern),
        "bit_depth": bit_depth,
    }
    if ins.binned:
        del meta["time_offset_us"]
        meta.update(binned_meta(ins.source))
    return meta


def binned_meta(source) -> dict:
    """What meta.json says about binned events (a ``BinnedSource``): no clock, no µs."""
    return {"binned": True, "bins_per_frame": source.bins_per_frame,
            "time": "binned events have no event clock: instants are fractions of each "
                    "exposure (0 = start, 1 = end)"}


def frame_folder_name(name: str, index: int) -> str:
    """A frame's folder name in the output (its name made safe for any file system)."""
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name).strip(".")
    return safe or f"{index:06d}"


def recordings_in(inputs: Sequence[Path]) -> list[Path] | None:
    """The recordings when ``inputs`` name several (REC1 REC2 …) or a folder of them; None
    when they are one of ``open_inputs``' layouts (a recording, BLURRY EVENTS, IMAGES_DIR …).

    A folder counts as a folder of recordings when it is not a recording itself, holds no
    image and holds files ending in :data:`RECORDING_SUFFIXES` or recording folders; they are
    taken in name order.
    """
    from .read.frames import IMAGE_EXTENSIONS
    from .read.sniff import is_recording_folder

    def is_image(p: Path) -> bool:
        return p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS

    if len(inputs) == 1:
        folder = inputs[0]
        if not folder.is_dir() or is_recording_folder(folder):
            return None
        entries = sorted(folder.iterdir())
        if any(is_image(p) for p in entries):
            return None
        found = [p for p in entries if not p.name.startswith(".") and (
            (p.is_file() and p.suffix.lower() in RECORDING_SUFFIXES)
            or (p.is_dir() and is_recording_folder(p)))]
        return found or None
    if len(inputs) >= 2 and all(
            (p.is_file() and not is_image(p)) or (p.is_dir() and is_recording_folder(p))
            for p in inputs):
        # two plain files: IMAGES_DIR-less layouts all start with an image or a frames folder
        from .read.bins import is_bins_file

        if any(is_bins_file(p) for p in inputs):
            return None
        return list(inputs)
    return None


def recording_folders(recordings: Sequence[Path] | None) -> list[str]:
    """Each recording's name in the output of a run on several (``[""]`` for one input): a
    file's stem, a recording folder's name."""
    if recordings is None:
        return [""]
    return [p.stem if p.is_file() else p.name for p in recordings]


def check_unique(folders: Sequence[str]) -> None:
    """Raises InputError: two recordings would write the same name."""
    if len(set(folders)) != len(folders):
        dup = next(f for f in folders if folders.count(f) > 1)
        raise InputError(f"two recordings would both write {dup!r} in the output",
                         hint="rename one, or run them separately")


def check_shareable(ins, path) -> None:
    """Raises InputError: ``ins`` is one blurry image (nothing to share out), or no frame."""
    if ins.single:
        raise InputError("one blurry image is one frame: there is nothing to share "
                         "out or resume", path=path,
                         hint="run it without --jobs / --resume / torchrun")
    if len(ins.source) == 0:
        raise InputError("no frame to deblur", path=path, hint="check the inputs")


def make_plan(groups: Sequence[Sequence[str | Path]], folders: Sequence[str],
              settings: Settings, warn: Callable[[str], None] = lambda _: None) -> Plan:
    """Open every recording once to count its frames and settle its meta.json head.

    Args:
        groups: the inputs of each recording (for ``open_inputs``). folders: each one's
            sub-folder of the output (``""`` for a run on one recording).
        warn: receives what the inputs say (each recording's reader warnings).
    Raises:
        InputError: one recording's inputs are one image (nothing to shard), two share a
            folder name, or one holds no frame.
    """
    from .methods import make_method

    s = settings
    method = cache(lambda: make_method(s.config))  # its name, N, weights hash, precision
    return Plan(plan_items(groups, folders, s, lambda ins, _, done: run_meta(
        ins, method(), s.config, s.offset_us, s.bit_depth, done), warn,
        settle=lambda ins, _: settled(method(), ins.source, s.config)), settings)


def settled(method, source, config: MethodConfig):
    """What is settled for ``method`` over the recording ``source``: a
    :class:`~trmd_cli.deblur.Settled` (see :func:`~trmd_cli.deblur.settle`)."""
    from .deblur import settle

    return settle(method, source, config)[1]


def plan_items(groups: Sequence[Sequence[str | Path]], folders: Sequence[str],
               settings: RunSettings, head: Callable[..., dict],
               warn: Callable[[str], None] = lambda _: None,
               settle: Callable[..., object] | None = None) -> tuple[Item, ...]:
    """Every recording of a new plan opened once: what its reader says given to ``warn``, it
    checked to hold frames to share out, what is settled over it by ``settle(ins, path)``
    (a :class:`~trmd_cli.deblur.Settled`; None: nothing), its meta.json head from
    ``head(ins, path, settled)`` (``ins``: its ``Inputs``; ``path``: its first input, for
    messages; it may check more and warn).

    Raises:
        InputError: two recordings share a folder name; one is one image or holds no frame.
    """
    from .read.inputs import open_inputs

    check_unique(folders)
    s = settings
    items = []
    for paths, folder in zip(groups, folders, strict=True):
        with open_inputs(list(paths), s.read, exposure=s.exposure, offset_us=s.offset_us) as ins:
            for w in ins.warnings:
                warn(w)
            check_shareable(ins, paths[0])
            done = None if settle is None else settle(ins, paths[0])
            items.append(Item(tuple(str(p) for p in paths), folder, len(ins.source),
                              head(ins, paths[0], done), done))
    return tuple(items)


class Stage:
    """The persistent place of a run's finished frames, beside the output (see the module)."""

    def __init__(self, output: str | Path) -> None:
        self.output = Path(output)
        self.root = self.output.with_name(f".{self.output.name}.trmd-partial")
        self.out = self.root / "out"
        self.done = self.root / "done"
        self.plan_file = self.root / "plan.json"

    def record(self, unit: Unit) -> Path:
        return self.done / ("-".join(str(part) for part in unit) + ".json")

    def folder(self, plan: Plan, unit: Unit) -> Path:
        """The folder that holds ``unit``'s folder (named in its record)."""
        return self.root / plan.place(unit)

    def finished(self, plan: Plan, unit: Unit) -> dict | None:
        """The record of a complete unit (its folder and meta part), or None."""
        try:
            rec = json.loads(self.record(unit).read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(rec, dict) or not (self.folder(plan, unit) / str(rec.get("folder"))
                                             ).is_dir():
            return None
        return rec

    def pending(self, plan: Plan, units: Sequence[Unit] | None = None) -> list[Unit]:
        """The units (of ``units``, default all) not complete yet, in order."""
        units = plan.units() if units is None else units
        return [u for u in units if self.finished(plan, u) is None]


def _discarded(output: Path, what: str = "") -> str:
    return (f"an unfinished run of {output}{what} is discarded; --resume would have continued "
            "it")


def discard_stage(output: str | Path, warn: Callable[[str], None]) -> None:
    """A run in one process, not resumed: the stage an unfinished run of the same output left
    goes (said through ``warn``), as a staged run's does — else a later ``--resume`` would
    finish that older run over this one's output."""
    stage = Stage(output)
    if stage.root.exists():
        warn(_discarded(stage.output))
        shutil.rmtree(stage.root)


def nothing_to_resume(output: Path, folder: bool) -> InputError:
    """The error of a resume without a stage; its hint says whether ``output`` (a folder, or
    a file when not ``folder``) looks complete."""
    done = output.exists() and output.is_dir() == folder and (not folder
                                                              or any(output.iterdir()))
    return InputError("nothing to resume: no unfinished run of this output", path=output,
                      hint="the output is complete already" if done
                      else "run it without --resume")


def prepare_stage(plan: Plan, output: str | Path, resume: bool) -> tuple[Stage, int]:
    """Make the stage of a new run, or check the one a resumed run continues.

    Returns:
        the stage and how many frames a previous run left there (0 without ``resume``; an
        unfinished run's stage is then discarded: the caller says so beforehand).
    Raises:
        InputError: ``resume`` without an unfinished run, or with one of other inputs or
            settings.
    """
    from .write import write_json

    stage = Stage(output)
    if resume:
        if not stage.root.is_dir():
            raise nothing_to_resume(stage.output, plan.output_is_folder)
        try:
            previous = json.loads(stage.plan_file.read_text())
        except (OSError, ValueError):
            previous = None
        if previous != plan.fingerprint():
            raise InputError("the unfinished run of this output was made from other inputs or "
                             "settings", path=output, hint="resume with the same inputs and "
                             "options, or rerun without --resume to start again")
        return stage, len(plan.units()) - len(stage.pending(plan))
    if stage.root.exists():
        shutil.rmtree(stage.root)
    stage.done.mkdir(parents=True)
    stage.out.mkdir()
    for place in plan.places():
        (stage.root / place).mkdir(parents=True, exist_ok=True)
    write_json(stage.plan_file, plan.fingerprint())  # last: the stage is then usable
    return stage, 0


@dataclass(frozen=True)
class ShareReport:
    """What one process's share said.

    Attributes:
        frames: frames written. warnings: ((recording, frame), message) for the user, of every
            frame written.
        contrast_notes: ((recording, frame), frame name, note or None, reliable) of every
            frame written, for ``ContrastNotes`` (in output order once sorted).
    """

    frames: int = 0
    warnings: tuple[tuple[tuple[int, int], str], ...] = ()
    contrast_notes: tuple[tuple[tuple[int, int], str, str | None, bool], ...] = ()


    @staticmethod
    def merged(reports: Sequence[ShareReport]) -> ShareReport:
        """One report of several (one process's phases), in their order."""
        return ShareReport(sum(r.frames for r in reports),
                           tuple(w for r in reports for w in r.warnings),
                           tuple(n for r in reports for n in r.contrast_notes))


@contextlib.contextmanager
def open_item(item: Item, settings: RunSettings) -> Iterator:
    """The inputs of one recording of a plan (``open_inputs``' ``Inputs``), checked to hold
    the frames they held when the plan was made.

    Raises:
        InputError: the frame count changed (the input was changed during the run).
    """
    from .read.inputs import open_inputs

    s = settings
    with open_inputs(list(item.inputs), s.read, exposure=s.exposure,
                     offset_us=s.offset_us) as ins:
        if len(ins.source) != item.frames:
            raise InputError(f"the input now holds {len(ins.source)} frames, not "
                             f"{item.frames}", path=item.inputs[0],
                             hint="was it changed during the run?")
        yield ins


class Tally:
    """A share's :class:`ShareReport`, gathered as its units are made (in one process)."""

    def __init__(self, tick: Callable[[], None] = lambda: None) -> None:
        self.tick = tick
        self.units = 0
        self.warnings: list[tuple[tuple[int, int], str]] = []
        self.notes: list[tuple[tuple[int, int], str, str | None, bool]] = []

    def deblurred(self, r: int, positions: Sequence[int], results: Iterable[FrameResult]
                  ) -> Iterator[tuple[int, FrameResult]]:
        """(k, result) of frames ``positions`` of recording ``r``, from ``results`` (theirs, in
        order; the next made while the last is written), each one's warnings and contrast
        note kept for the report."""
        from contextlib import closing

        from .overlap import ahead

        with closing(ahead(results)) as made:
            for k, res in zip(positions, made, strict=True):
                self.warnings.extend(((r, k), w) for w in res.warnings)
                self.notes.append(((r, k), res.name, res.estimate.contrast_note,
                                   bool(res.estimate.contrast_reliable)))
                yield k, res

    def made(self) -> None:
        """One more unit complete (folder and record written)."""
        self.units += 1
        self.tick()

    def report(self) -> ShareReport:
        return ShareReport(self.units, tuple(self.warnings), tuple(self.notes))


def run_share(plan: Plan, stage: Stage, share: Sequence[tuple[int, int]],
              tick: Callable[[], None] = lambda: None) -> ShareReport:
    """Deblur the units of ``share`` that are not complete yet, each frame folder renamed into
    the stage when complete, then its record written.

    Args:
        tick: called after every frame (progress).
    """
    from .deblur import deblur_frames
    from .methods import make_method
    from .write import atomic_dir, write_json, write_result_folder

    s = plan.settings
    todo = stage.pending(plan, share)
    tally = Tally(tick)
    method = cache(lambda: make_method(s.config))
    for i, item in enumerate(plan.items):
        positions = [k for (r, k) in todo if r == i]
        if not positions:
            continue
        with open_item(item, s) as ins:
            m = method() if item.settled is None else item.settled.applied_to(method())
            results = deblur_frames(ins.source.subset(positions), m)
            for k, res in tally.deblurred(i, positions, results):
                name = frame_folder_name(res.name, res.index)
                with atomic_dir(stage.out / item.folder / name) as tmp:
                    info = write_result_folder(tmp, res, bit_depth=s.bit_depth,
                                               compare=s.compare, meta=item.meta)
                write_json(stage.record((i, k)), {"folder": name, "info": info})
                tally.made()
    return tally.report()


#: what atomic writers name their temporaries (see trmd_cli.write): left by killed processes
_TEMP = re.compile(r"^\..*\.trmd-\d+-.*\.tmp")


def sweep_temps(folder: Path) -> None:
    """Remove what atomic writers of killed processes left in ``folder``: it must not ship."""
    for p in folder.iterdir():
        if _TEMP.match(p.name):
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()


def swap_in(stage: Stage) -> None:
    """Put the stage's ``out/`` where the output goes (replacing a previous output only once it
    is in place), then remove the stage."""
    from .signals import deferred, raise_if_received

    output = stage.output
    raise_if_received()
    with deferred():  # between the renames an interrupt would leave no output at all
        if output.exists():
            old = output.with_name(f".{output.name}.trmd-{os.getpid()}-old.tmp")
            os.replace(output, old)
            try:
                os.replace(stage.out, output)
            except BaseException:
                os.replace(old, output)
                raise
            shutil.rmtree(old) if old.is_dir() else old.unlink()
        else:
            os.replace(stage.out, output)
    shutil.rmtree(stage.root, ignore_errors=True)


def finish(plan: Plan, stage: Stage) -> list[dict]:
    """Write each recording's meta.json from the records and swap the stage in as the output.

    Returns:
        every frame's meta part, in output order.
    Raises:
        ShardError: a unit is not complete (a process did not finish its share).
    """
    from .write import write_json

    summary: list[dict] = []
    for i, item in enumerate(plan.items):
        infos = []
        for k in range(item.frames):
            rec = stage.finished(plan, (i, k))
            if rec is None:
                raise ShardError(f"frame {k} of {item.inputs[0]} was not written; rerun with "
                                 "--resume to finish it")
            infos.append(rec["info"])
        folder = stage.out / item.folder
        sweep_temps(folder)
        write_json(folder / "meta.json", {**item.meta, "frames": infos})
        summary.extend(infos)
    swap_in(stage)
    return summary


def worker_threads(jobs: int, threads: int | None, cores: int | None = None) -> int:
    """Torch / BLAS threads per process: ``threads`` if given, else the cores shared out so
    that ``jobs`` × threads ≤ cores (at least 1)."""
    if threads is not None:
        return threads
    cores = cores if cores is not None else usable_cores()
    return max(1, cores // max(jobs, 1))


#: methods ``--jobs auto`` shares out over worker processes. Their frames take about a second
#: each, much of it on one core (contrast maximisation, the tiles' votes), so one process
#: leaves the others idle. 48 simulated 346×260 frames on 2 cores: ``motion`` 63 → 35 s and
#: ``fused`` 87 → 59 s with two workers; ``trmd`` 18 s either way (its network already keeps
#: every core busy) and ``edi`` loses the workers' start-up (esl-cups' 8 frames: 1.1 → 1.7 s)
AUTO_METHODS = frozenset({"motion", "fused"})
#: pixels × frames (or exposures) each worker of ``--jobs auto`` gets at least, four 346×260
#: frames: starting one (importing torch, reading the weights, the recording's threshold) costs
#: one or two of those frames
AUTO_MIN_WORK = 4 * 346 * 260
#: at most this many workers, and no more than free memory holds at
#: :data:`AUTO_WORKER_BYTES` each (a 346×260 frame of ``motion`` peaks near 1.2–1.5 GB)
AUTO_MAX_JOBS = 8
AUTO_WORKER_BYTES = 3 << 29


def auto_jobs(method: str, work: int, threads: int | None = None, *,
              cores: int | None = None, free_bytes: int | None = None) -> int:
    """Worker processes ``--jobs auto`` starts for ``work`` (frames × pixels per frame) of
    ``method``: one per ``threads`` cores (one per core by default) for the methods of
    :data:`AUTO_METHODS`, each with at least :data:`AUTO_MIN_WORK`, at most
    :data:`AUTO_MAX_JOBS` and as many as ``free_bytes`` of memory hold (None: not limited); 1
    (one process, as ``--jobs 1``) for the other methods. ``cores``: the usable cores (default:
    this process's)."""
    if method not in AUTO_METHODS:
        return 1
    cores = usable_cores() if cores is None else cores
    jobs = min(cores // max(threads or 1, 1), work // AUTO_MIN_WORK, AUTO_MAX_JOBS)
    if free_bytes is not None:
        jobs = min(jobs, free_bytes // AUTO_WORKER_BYTES)
    return max(int(jobs), 1)


def choose_jobs(requested: int | None, config: MethodConfig, count: Callable[[], int], *,
                ranks: Ranks, in_order: bool = False) -> int:
    """The worker processes of a run: ``requested`` when given (``--jobs K``), else
    :func:`auto_jobs` for the run's ``count()`` (frames × pixels, :func:`count_work`; called
    only when it matters). One under torchrun (the ranks are the processes), when the outputs
    must be made in order in one process (``in_order``: a video), or when the method's network
    runs on a GPU."""
    if requested is not None:
        return requested
    if ranks.enabled or in_order or config.method not in AUTO_METHODS:
        return 1
    from .methods import REGISTRY

    if REGISTRY[config.method].needs.weights and config.device != "cpu":
        from .models.weights import resolve_device

        if resolve_device(config.device).type != "cpu":
            return 1
    return auto_jobs(config.method, count(), config.threads, free_bytes=free_memory_bytes())


def count_work(inputs: Sequence[Path], recordings: Sequence[Path] | None,
               read: ReadOptions, exposure=None, offset_us: int = 0) -> int:
    """Frames × pixels per frame of a run's inputs (every recording of ``recordings``, or
    ``inputs``) that the motion methods work on: 0 for a blurry image and its events (one
    frame: nothing to share out; the files unopened) and for binned events (no event times:
    those methods give TRMD's or EDI's frames, which cost less than a worker's start)."""
    from .read.frames import IMAGE_EXTENSIONS
    from .read.inputs import open_inputs

    if recordings is None and len(inputs) == 2 and inputs[0].is_file() \
            and inputs[0].suffix.lower() in IMAGE_EXTENSIONS:
        return 0
    total = 0
    for group in ([[p] for p in recordings] if recordings is not None else [list(inputs)]):
        with open_inputs(group, read, exposure=exposure, offset_us=offset_us) as ins:
            if not ins.binned:
                total += len(ins.source) * ins.source.width * ins.source.height
    return total


def free_memory_bytes() -> int | None:
    """Memory available to new processes (Linux: ``MemAvailable``); None where unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


# --------------------------------------------------------------------------------------------
# Processes of one run: local workers (`jobs`) and torchrun ranks


@dataclass(frozen=True)
class Ranks:
    """This process's place in a torchrun launch: ``rank`` of ``world``; ``local_world``
    processes on this machine."""

    rank: int = 0
    world: int = 1
    local_world: int = 1

    @property
    def enabled(self) -> bool:
        return self.world > 1


def ranks_from_env(environ: dict[str, str] | None = None) -> Ranks:
    """RANK / WORLD_SIZE / LOCAL_WORLD_SIZE as torchrun sets them (absent: one process).

    Raises:
        InputError: a value that is not an integer, or a rank outside 0..world-1.
    """
    env = os.environ if environ is None else environ

    def read(name: str, default: int) -> int:
        text = env.get(name)
        if text is None or text == "":
            return default
        try:
            return int(text)
        except ValueError:
            raise InputError(f"environment variable {name}={text!r} is not an integer") from None

    world = read("WORLD_SIZE", 1)
    rank = read("RANK", 0)
    if world < 1 or not 0 <= rank < world:
        raise InputError(f"RANK={rank} with WORLD_SIZE={world}: the rank must be in "
                         f"0..{max(world - 1, 0)}", hint="launch it with torchrun")
    return Ranks(rank, world, max(1, read("LOCAL_WORLD_SIZE", world)))


@contextlib.contextmanager
def joined(ranks: Ranks):
    """The process group of a torchrun launch (gloo: the ranks only exchange small objects),
    left on the way out. Its timeout is long: ranks wait at the end for the slowest share,
    which on a long recording takes hours."""
    if not ranks.enabled:
        yield
        return
    from datetime import timedelta

    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo", rank=ranks.rank, world_size=ranks.world,
                                timeout=timedelta(days=7))
    try:
        yield
    finally:
        dist.destroy_process_group()


def from_rank0(ranks: Ranks, value):
    """Rank 0's ``value`` on every rank (``value`` itself without torchrun)."""
    if not ranks.enabled:
        return value
    import torch.distributed as dist

    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def agreed(ranks: Ranks, step: Callable[[], object]):
    """Run ``step`` on every rank and wait for all: when it failed on any, fail on every one
    (a rank left waiting for a failed one would hang). Returns ``step``'s result."""
    if not ranks.enabled:
        return step()
    import torch.distributed as dist

    result, failure, own = None, None, None
    try:
        result = step()
    except TrmdError as e:
        failure, own = (str(e), e.exit_code), e
    except BaseException as e:  # an interrupt or a bug still lets the others stop
        failure, own = (f"{type(e).__name__}: {e}", 1), e
    said: list = [None] * ranks.world
    dist.all_gather_object(said, failure)
    if own is not None:
        raise own
    for r, f in enumerate(said):
        if f is not None:
            raise ShardError(f"rank {r}: {f[0]}", f[1])
    return result


#: environment variables that size the thread pools of numpy's BLAS, OpenMP and torch: set in
#: a worker before it imports them (later is too late for some)
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _worker(plan: Plan, output: str, shares: list[list[Unit]], threads: int, queue,
            barrier) -> None:
    """A local worker process: its share of each phase (between phases, ``barrier``: every
    worker finished the one before), then one message ("done", report) or ("error", line, exit
    code); a ("tick",) after every unit."""
    import signal

    from .heap import tune_memory
    from .signals import handled, shielded

    def tick() -> None:
        # SIGTERM raised inside the queue's lock left it held, and the worker's own "stopped"
        # message below then waited for it for ever (as did the parent, joining the worker)
        with shielded():
            queue.put(("tick",))

    tune_memory()  # as the command that started it (a spawned process starts afresh)
    try:
        with handled():
            # Ctrl-C reaches the whole terminal's process group: the parent alone answers it
            # and stops the workers with SIGTERM, which unwinds their writers here
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            stage = Stage(output)
            reports = []
            for i, share in enumerate(shares):
                if i:
                    barrier.wait()
                reports.append(plan.run(stage, share, tick=tick))
        queue.put(("done", ShareReport.merged(reports)))
    except TrmdError as e:
        queue.put(("error", str(e), e.exit_code))
    except KeyboardInterrupt:
        queue.put(("error", "stopped", 130))
    except BaseException as e:  # noqa: BLE001 - one line to the parent, never a traceback
        queue.put(("error", f"unexpected {type(e).__name__}: {e}", 1))


def run_pool(plan: Plan, stage: Stage, units: Sequence[Unit], jobs: int,
             threads: int, tick: Callable[[], None] = lambda: None, *,
             phases: Sequence[Sequence[Unit]] | None = None) -> list[ShareReport]:
    """``units`` done by ``jobs`` worker processes (spawned: no state copied from this one),
    worker w taking every jobs-th unit from w; each with ``threads`` threads.

    Args:
        phases: instead of ``units``: the units of each phase, in order; the same workers do
            them all, each phase starting once every worker has finished the one before.
    Raises:
        ShardError: a worker failed (its line) or died; the others are stopped first.
        KeyboardInterrupt: on Ctrl-C / SIGTERM, once the workers are stopped.
    """
    import multiprocessing as mp
    import queue as queues

    from .signals import shielded

    phases = [list(units)] if phases is None else [list(p) for p in phases]
    plan = replace(plan, settings=replace(plan.settings, config=replace(
        plan.settings.config, threads=threads)))
    shares = [[phase[w::jobs] for phase in phases] for w in range(jobs)]
    shares = [s for s in shares if any(s)]
    procs: list = []
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    try:
        ctx = mp.get_context("spawn")
        messages = ctx.Queue()
        barrier = ctx.Barrier(len(shares)) if len(phases) > 1 and shares else None
        # the children copy this environment when they start
        os.environ.update({k: str(threads) for k in _THREAD_VARS if saved[k] is None})
        for share in shares:
            p = ctx.Process(target=_worker, args=(plan, str(stage.output), share, threads,
                                                  messages, barrier), daemon=True)
            p.start()
            procs.append(p)
    except OSError as e:
        # no semaphores or no processes here (a sandbox without /dev/shm, a process limit)
        _stop(procs)
        raise PoolUnavailable(str(e) or type(e).__name__) from None
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
    reports: list[ShareReport] = []
    try:
        while len(reports) < len(procs):
            try:
                with shielded():
                    msg = messages.get(timeout=0.5)
            except queues.Empty:
                dead = [p for p in procs if p.exitcode not in (None, 0)]
                if dead:
                    raise ShardError(f"a worker process died (exit code {dead[0].exitcode}); "
                                     "rerun with --resume to finish", 1) from None
                continue
            if msg[0] == "tick":
                tick()
            elif msg[0] == "done":
                reports.append(msg[1])
            else:
                raise ShardError(msg[1], msg[2])
    finally:
        _stop(procs)
    return reports


def _stop(procs: Sequence) -> None:
    """Stop the worker processes still running (SIGTERM: their writers clean up their
    temporaries) and wait for every one."""
    from .signals import deferred

    # a second signal (a terminal's Ctrl-C reaches the group, `timeout` signals this process
    # and then its group) is held until the workers are gone: raised in the join, it would
    # leave them to multiprocessing's exit handler, whose second SIGTERM lands in their cleanup
    with deferred():
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join()


def todo(plan: Plan, stage: Stage, ranks: Ranks) -> list[list[Unit]]:
    """What this process does of each phase: under torchrun its rank's share of the phase (cut
    from all its units, so every rank cuts the same), less what is complete; else every unit
    not complete yet."""
    if ranks.enabled:
        return [stage.pending(plan, plan.share(ranks.rank, ranks.world, phase))
                for phase in plan.phases()]
    return [stage.pending(plan, phase) for phase in plan.phases()]


def run_plan(plan: Plan, stage: Stage, ranks: Ranks, work: Sequence[Sequence[Unit]], *,
             jobs: int = 1, threads: int = 1,
             tick: Callable[[], None] = lambda: None) -> list[ShareReport]:
    """Do ``work`` (from :func:`todo`) phase by phase: as this rank of a torchrun launch
    (the ranks meet after every phase, and all stop when one fails), in ``jobs`` local
    workers, or here.

    Raises:
        ShardError: another rank or a worker failed. TrmdError / KeyboardInterrupt: here.
    """
    if ranks.enabled:
        return [agreed(ranks, lambda share=share: plan.run(stage, share, tick))
                for share in work]
    said: list[ShareReport] = []
    if jobs > 1 and sum(len(phase) for phase in work) > 1:
        try:
            return run_pool(plan, stage, [], jobs, threads, tick, phases=work)
        except PoolUnavailable as e:
            # before any unit was made: the same units, here (told first: key before all)
            said.append(ShareReport(warnings=(((-1, -1), f"could not start {jobs} worker "
                                               f"processes ({e}): the work was done in this "
                                               "one"),)))
    return said + [plan.run(stage, share, tick) for share in work]


# --------------------------------------------------------------------------------------------
# A whole run through a stage, as a command makes it


def staged(jobs: int, resume: bool, ranks: Ranks, recordings: Sequence[Path] | None) -> bool:
    """A run goes through a stage when it shares work out (``jobs``, torchrun), may be resumed
    or covers several recordings; else one process writes its output aside and swaps it in."""
    return jobs > 1 or resume or ranks.enabled or recordings is not None


@dataclass(frozen=True)
class Outcome:
    """What a run through a stage did, as this process saw it.

    Attributes:
        plan: the run's plan. reports: this process's report of each phase. main: this
            process finished the run (rank 0). summary: what ``plan.finish`` returned (None
            where not ``main``).
    """

    plan: Plan
    reports: tuple[ShareReport, ...]
    main: bool
    summary: object = None


@contextlib.contextmanager
def _no_progress(label: str, total: int) -> Iterator[Callable[[], None]]:
    yield lambda: None


def _quiet(_: str) -> None:
    pass


def run_staged(make: Callable[..., Plan], inputs: Sequence[Path],
               recordings: Sequence[Path] | None, settings: RunSettings,
               output: str | Path, *,
               ranks: Ranks, jobs: int = 1, resume: bool = False, overwrite: bool = False,
               guard: Sequence[Path | None] = (), suffix: str = "", folder: bool = True,
               warn: Callable[[str], None] = _quiet, say: Callable[[str], None] = _quiet,
               progress: Callable[[str, int], AbstractContextManager[Callable[[], None]]]
               = _no_progress) -> Outcome:
    """A run through a stage, from the checks of the output to the output in place: one
    recording (``inputs``) or several (``recordings``, one output each in OUT, named after it
    with ``suffix``), in ``jobs`` local workers or as this rank of a torchrun launch,
    resumable.

    The ranks do each step together (:func:`agreed`: when it fails on one, every one stops):
    check the output, make the plan, prepare the stage, every phase, finish. Only rank 0
    checks, makes the plan (the others get it from it), prepares, finishes and warns of what
    the inputs say.

    Args:
        make: the plan's maker, ``(groups, folders, settings, warn) -> Plan``
            (:func:`make_plan`, or a command's own). settings: the plan's settings, with the
            threads per process still to share out (``config.threads`` None: the cores).
        guard: what the output must never replace (the inputs, the weights). folder: the
            output is a folder (not a file).
        warn: what the user should hear (the inputs' warnings, the shares', the contrast notes,
            a discarded stage). say: what the run tells (a resume's count, a rank's part).
        progress: ``(label, total)`` → a context giving a function called after every unit;
            rank 0's only.
    Raises:
        InputError: ``jobs`` under torchrun, nothing to resume, an output that may not be
            written, bad inputs. ShardError: another rank or a worker failed.
            KeyboardInterrupt: the run was stopped (the finished units stay for a resume).
    """
    from .write import check_output

    if ranks.enabled and jobs > 1:
        raise InputError(f"--jobs {jobs} under torchrun (WORLD_SIZE={ranks.world})",
                         hint="let torchrun start the processes: --nproc_per_node K")
    output = Path(output)
    groups = [[p] for p in recordings] if recordings is not None else [list(inputs)]
    folders = [f"{name}{suffix}" for name in recording_folders(recordings)] \
        if recordings is not None else [""]
    main = ranks.rank == 0
    stage = Stage(output)
    # per process: the cores of this machine shared out among its processes
    threads = worker_threads(jobs if not ranks.enabled else ranks.local_world,
                             settings.config.threads)
    settings = replace(settings, config=replace(settings.config, threads=threads))

    def check() -> None:
        if not main:
            return
        if resume and not stage.root.is_dir():
            raise nothing_to_resume(output, folder)
        check_output(output, overwrite, inputs=guard, folder=folder)

    def prepare(plan: Plan) -> None:
        if not main:
            return
        if stage.root.exists() and not resume:
            left = len(plan.units()) - len(stage.pending(plan)) if stage.plan_file.is_file() \
                else 0
            warn(_discarded(output, f" ({left} {plan.noun})"))
        _, before = prepare_stage(plan, output, resume)
        if before:
            say(f"resuming: {before} of {len(plan.units())} {plan.counted} are done already")

    with joined(ranks):
        agreed(ranks, check)
        # rank 0 makes the plan and hands it to the others: what it settles once per recording
        # (the contrast threshold) is then the same number on every rank, whatever machine
        plan = from_rank0(ranks, agreed(ranks, lambda: make(groups, folders, settings, warn)
                                        if main else None))
        agreed(ranks, lambda: prepare(plan))
        try:
            work = todo(plan, stage, ranks)
            with (progress if main else _no_progress)(
                    plan.label, sum(len(phase) for phase in work)) as tick:
                reports = run_plan(plan, stage, ranks, work, jobs=jobs, threads=threads,
                                   tick=tick)
        except (KeyboardInterrupt, TrmdError):
            if main and stage.plan_file.is_file():
                warn(f"the {plan.noun} finished so far are kept in {stage.root}: rerun with "
                     "--resume to finish")
            raise
        summary = agreed(ranks, lambda: plan.finish(stage) if main else None)

    for line in _said(reports):
        warn(line)
    if not main:
        say(f"rank {ranks.rank}: {plan.verb} {sum(r.frames for r in reports)} {plan.noun}; "
            f"rank 0 wrote {output}")
    return Outcome(plan, tuple(reports), main, summary)


def _said(reports: Sequence[ShareReport]) -> list[str]:
    """What the shares said: their frames' warnings, then their contrast notes, in output
    order (as one process says them, whichever process made which frame); the notes told once
    (``ContrastNotes``)."""
    from .deblur import ContrastNotes

    notes = ContrastNotes()
    for _, name, note, reliable in sorted(n for r in reports for n in r.contrast_notes):
        notes.add_note(name, note, reliable)
    said = sorted((n for r in reports for n in r.warnings), key=lambda n: n[0])
    return [w for _, w in said] + notes.lines()
