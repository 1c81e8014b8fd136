"""Render ``blurry | EDI | TRMD`` compare strips, on demand, into a folder of your choice.

    python docs/gallery.py [OUT] [--weights W.safetensors] [--only example,esl-cups,davis346]
                           [--davis-frames 4] [--limit K] [--shared DIR] [--overwrite]

Sources (each skipped with a note when it is absent):

- ``example``: the bundled simulated example (``examples/``), with its ground truth as a fourth
  column. It is CC0 (see ``examples/README.md``): its strip may be committed.
- ``esl-cups``: all 8 frames of ``../shared/data/real/esl-cups`` (DAVIS346, eSL-Net data).
- ``davis346``: a few APS frames of ``../shared/data/recordings/davis346.aedat4`` (needs
  ``pip install 'trmd[formats]'``), spread over the frames whose exposure holds events. Its
  exposures are 0.5 ms of a static camera: the frames are sharp already, and the strips show
  that deblurring leaves them alone.

**Licences: strips rendered from the real recordings (``esl-cups``, ``davis346``) must never be
committed.** Their licences do not allow redistribution, so the pictures derived from them stay
on your machine. ``OUT`` defaults to ``./gallery``, which ``.gitignore`` lists; if you choose
another folder inside the repository, keep it out of git yourself.

The TRMD column appears only when weights are available: ``--weights``, else the shipped
default (``trmd_cli/weights/trmd_default.safetensors``). Without them the column is left out and
the script says so. EDI estimates its contrast threshold per frame (as ``trmd deblur`` does),
and the value used is written in the column's label.

The strips show each method's frame nearest to mid-exposure. The output folder is written
whole or not at all; an existing one is replaced only with ``--overwrite``. ``OUT/README.md``
lists what was rendered, from which source, and which strips may be shared.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
SOURCES = ("example", "esl-cups", "davis346")


@dataclass(frozen=True)
class Source:
    """One thing to render: the positional inputs ``trmd deblur`` would take."""

    name: str
    inputs: list[Path]
    shareable: bool  # derived pictures may be committed (simulated / CC0 data)
    truth: Path | None = None  # a ground-truth image shown as the last column
    pick: int | None = None  # render this many frames, spread evenly (None = all)


def _sources(shared: Path, davis_frames: int) -> dict[str, Source]:
    ex = REPO / "examples"
    cups = shared / "real" / "esl-cups"
    return {
        "example": Source("example", [ex / "blurry.png", ex / "events.npz"], True,
                          truth=ex / "sharp.png"),
        "esl-cups": Source("esl-cups", [cups / "images", cups / "mat"], False),
        "davis346": Source("davis346", [shared / "recordings" / "davis346.aedat4"], False,
                           pick=davis_frames),
    }


def _methods(weights: Path | None, threads: int | None, notes: list[str]):
    """EDI always; TRMD when weights can be found and loaded (else a note)."""
    from trmd_cli.errors import TrmdError
    from trmd_cli.methods import MethodConfig, make_method
    from trmd_cli.models.weights import default_weights_path

    methods = [("EDI", make_method(MethodConfig(method="edi")))]
    path = weights if weights is not None else default_weights_path()
    if not Path(path).exists():
        notes.append(f"TRMD column skipped: no weights at {path} (the shipped default is not "
                     "installed yet; pass --weights W.safetensors, e.g. a run's best.safetensors)")
        return methods
    try:
        methods.append(("TRMD", make_method(MethodConfig(method="trmd", weights=path,
                                                         device="auto", threads=threads))))
    except TrmdError as e:
        notes.append(f"TRMD column skipped: {e}")
    return methods


def _label(name: str, result) -> str:
    c = result.estimate.contrast
    if result.passthrough:
        return f"{name} (no events)"
    return f"{name} c={c:.2f}" if name == "EDI" and c is not None else name


def render_source(src: Source, methods, out: Path, limit: int | None,
                  notes: list[str]) -> list[str]:
    """Write one strip per frame of ``src`` into ``out``; return the file names written."""
    from trmd_cli.deblur import deblur_frames
    from trmd_cli.read import read_image
    from trmd_cli.read.inputs import open_inputs
    from trmd_cli.viz import strip
    from trmd_cli.write import write_image

    truth = read_image(src.truth) if src.truth is not None and src.truth.exists() else None
    written: list[str] = []
    with open_inputs(src.inputs) as ins:
        notes.extend(f"{src.name}: {w}" for w in ins.warnings)
        source = ins.source
        if src.pick is not None and len(source) > src.pick:
            source = source.subset(_spread(source, src.pick))
        count = len(source) if limit is None else min(limit, len(source))
        for i, item in enumerate(source):
            if i >= count:
                break
            tiles, labels = [item.frame.image], ["blurry"]
            for name, method in methods:
                res = next(deblur_frames([item], method))
                notes.extend(f"{src.name}: {w}" for w in res.warnings)
                tiles.append(res.middle)
                labels.append(_label(name, res))
            if truth is not None:
                tiles.append(truth)
                labels.append("ground truth")
            file = f"{src.name}_{_safe(item.frame.name)}.png"
            write_image(out / file, strip(tiles, labels))
            written.append(file)
            print(f"{src.name}: {file}", flush=True)
    return written


def _spread(source, k: int) -> list[int]:
    """``k`` frame positions spread evenly, over the frames whose windows hold events when
    the recording can tell (short APS exposures of a static scene often hold none)."""
    positions = list(range(len(source)))
    rec = source.recording
    if rec is not None:
        busy = [i for i, w in enumerate(source.exposures())
                if len(rec.events(w.start_us, w.end_us + 1)) > 0]
        positions = busy or positions
    if len(positions) <= k:
        return positions
    return [positions[int(round(j))] for j in np.linspace(0, len(positions) - 1, k)]


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in Path(name).stem) or "frame"


def _readme(rendered: dict[str, list[str]], sources: dict[str, Source], notes: list[str]) -> str:
    lines = ["# trmd gallery (rendered locally by docs/gallery.py)", "",
             "Each strip: blurry | EDI | TRMD (when weights were available) "
             "[| ground truth]; the frame nearest to mid-exposure.", ""]
    for name, files in rendered.items():
        src = sources[name]
        rule = ("simulated CC0 data: may be shared" if src.shareable else
                "REAL RECORDING: its licence does not allow redistribution. Do not commit or "
                "publish these strips.")
        lines += [f"## {name}: {len(files)} strip(s), {rule}", "",
                  *(f"- {f}" for f in files), ""]
    if notes:
        lines += ["## Notes", "", *(f"- {n}" for n in notes), ""]
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", type=Path, default=Path("gallery"),
                    help="output folder (default ./gallery, ignored by git)")
    ap.add_argument("--weights", type=Path, default=None,
                    help="TRMD weights (default: the shipped ones, if installed)")
    ap.add_argument("--only", default=",".join(SOURCES),
                    help=f"comma-separated sources (default: {','.join(SOURCES)})")
    ap.add_argument("--davis-frames", type=int, default=4,
                    help="frames of davis346.aedat4 to render, spread evenly (default 4)")
    ap.add_argument("--limit", type=int, default=None, help="at most K frames per source")
    ap.add_argument("--shared", type=Path, default=SHARED,
                    help="the shared data folder (default ../shared/data beside the repo)")
    ap.add_argument("--threads", type=int, default=None, help="CPU threads for TRMD")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing OUT")
    args = ap.parse_args(argv)

    from trmd_cli.errors import TrmdError
    from trmd_cli.write import atomic_dir, check_output, write_text

    wanted = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = sorted(set(wanted) - set(SOURCES))
    if unknown or not wanted:
        print(f"error: unknown source(s) {', '.join(unknown) or '(none)'}; choose from "
              f"{', '.join(SOURCES)}", file=sys.stderr)
        return 2
    if args.davis_frames < 1 or (args.limit is not None and args.limit < 1):
        print("error: --davis-frames and --limit must be ≥ 1", file=sys.stderr)
        return 2
    sources = _sources(args.shared, args.davis_frames)
    notes: list[str] = []
    rendered: dict[str, list[str]] = {}
    try:
        check_output(args.out, args.overwrite)
        methods = _methods(args.weights, args.threads, notes)
        with atomic_dir(args.out) as tmp:
            for name in wanted:
                src = sources[name]
                missing = [p for p in src.inputs if not p.exists()]
                if missing:
                    notes.append(f"{name} skipped: {missing[0]} not found")
                    continue
                try:
                    rendered[name] = render_source(src, methods, tmp, args.limit, notes)
                except TrmdError as e:  # e.g. an optional reader not installed
                    notes.append(f"{name} skipped: {e}")
            if not rendered:
                raise SystemExit("error: nothing rendered: " + "; ".join(notes))
            # the same warning comes from the inputs and again from each frame: say it once
            notes = list(dict.fromkeys(notes))
            write_text(tmp / "README.md", _readme(rendered, sources, notes))
    except TrmdError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    total = sum(len(f) for f in rendered.values())
    print(f"wrote {args.out}: {total} strip(s)")
    if any(not sources[n].shareable for n in rendered):
        print("reminder: strips of real recordings must not be committed (licences)",
              file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
