"""Whole-recording cost per frame against the bare network, measured in the same process.

    python bench/bench_recording.py [INPUTS …] [--method trmd] [--threads T] [--precision P]
                                    [--repeat R] [--profile] [--contrast C] [--keep-pattern]

What `trmd deblur INPUTS -o OUT` does per frame after start-up — the sensor's fixed pattern
and the recording's contrast threshold (each estimated once, the threshold on its busiest
frames; ``--contrast-scope frame``: per frame, as ``--contrast frame``; ``--keep-pattern``: no
pattern), read the frame and its events, voxels and timing levels, the network,
the reconstruction, writing the result folder (the next frame deblurred while the last is
written) — timed over the whole recording (the best of ``--repeat`` passes), against the
shipped network's bare forward pass on a frame of the same size (median of 10, after 2 warm-up
passes) and against the network's own time inside that pass (what it spent per frame there,
under whatever else ran: on a shared machine the steadier ratio); the process's CPU time is
given beside each wall time. OpenMP threads wait passively, as `trmd` sets them. The start-up
(imports, loading the weights) is reported apart.

``--contrast C`` gives the threshold (no estimate): what the rest of the run costs.
``--heap-defaults``: the process's memory as glibc and numpy set it up, not as `trmd` tunes
it (:mod:`trmd_cli.heap`; ``NUMPY_MADVISE_HUGEPAGE=1`` in the environment keeps numpy's
huge-page advice alone).

``--profile`` adds one pass without the overlap, each stage timed on its own (median over the
frames, ms of wall time, and in brackets of the thread's CPU time, which other work on the
machine does not inflate): the recording's pattern and threshold (their whole cost shared out
over the frames), reading, the per-pixel sort, the hot-pixel mask, the isolated events left out, the
EDI table, the threshold search, the voxels and their timing levels, the network's forward
pass, the rest of the method (checks, reconstruction, conversions) and writing the result
folder.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _timed(table: dict, key: str, fn):
    """``fn`` adding its wall time to ``table[key]`` and the calling thread's CPU time to
    ``table[key + " cpu"]`` (what a single-threaded stage costs whatever else runs)."""
    def run(*args, **kwargs):
        t, c = time.perf_counter(), time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            table[key] += time.perf_counter() - t
            table[key + " cpu"] += time.thread_time() - c
    return run


class _Timed:
    """A method whose calls add their wall time to ``table["method"]``."""

    def __init__(self, method, table: dict) -> None:
        self._method, self._table = method, table

    def __getattr__(self, name):
        return getattr(self._method, name)

    def __call__(self, *args, **kwargs):
        return _timed(self._table, "method", self._method)(*args, **kwargs)


def profile(ins, est, config, tmp: Path) -> str:
    """One sequential pass with every stage timed: ``stage ms`` pairs, medians over frames."""
    from trmd_cli import methods, voxel
    from trmd_cli.deblur import deblur_frames, settle
    from trmd_cli.write import write_result_folder

    per_frame: dict[str, list[float]] = defaultdict(list)
    now: dict[str, float] = defaultdict(float)
    patches = [(getattr(methods, "PixelEvents", None), "build", "sort"),
               (methods, "hot_pixel_mask", "hot pixels"),
               (methods, "without_isolated", "isolated"),
               (methods.EdiEvents, "build", "EDI table"),
               (methods, "search_contrast", "threshold"),
               (voxel, "scer_voxels", "voxels"), (voxel, "scer_levels", "levels")]
    # code without one of these stages (an older checkout on PYTHONPATH) times the others
    patches = [(o, n, k) for o, n, k in patches if o is not None and n in o.__dict__]
    saved = [(owner, name, owner.__dict__[name]) for owner, name, _ in patches]
    net = getattr(getattr(est, "model", None), "model", None)
    try:
        for owner, name, key in patches:
            timed = _timed(now, key, getattr(owner, name))
            if isinstance(owner.__dict__[name], classmethod):
                timed = classmethod(lambda cls, *a, f=timed, **k: f(*a, **k))
            setattr(owner, name, timed)
        if net is not None:
            net.forward = _timed(now, "network", net.forward)
        t, c = time.perf_counter(), time.thread_time()
        est, _ = settle(est, ins.source, config)
        settled = ((time.perf_counter() - t) / len(ins.source),
                   (time.thread_time() - c) / len(ins.source))
        frames = iter(deblur_frames(ins.source, _Timed(est, now)))
        stages = [k for _, _, k in patches] + ["network"]
        for i in range(len(ins.source)):
            now.clear()
            t0, c0 = time.perf_counter(), time.thread_time()
            res = next(frames)
            now["reading"] = time.perf_counter() - t0
            now["reading cpu"] = time.thread_time() - c0
            folder = tmp / f"p{i:06d}"
            folder.mkdir()
            # writing encodes in threads of its own, and nothing else runs now: process time
            t1, c1 = time.perf_counter(), time.process_time()
            write_result_folder(folder, res, meta={})
            now["writing"] = time.perf_counter() - t1
            now["writing cpu"] = time.process_time() - c1
            for suffix in ("", " cpu"):
                method = now.pop("method" + suffix, 0.0)
                now["reading" + suffix] -= method  # the frame source and the loop's checks
                inner = sum(now.get(k + suffix, 0.0) for k in stages)
                now["rest of method" + suffix] = method - inner
            now["pattern and c"], now["pattern and c cpu"] = settled
            for k, v in now.items():
                per_frame[k].append(v)
    finally:
        for owner, name, value in saved:
            setattr(owner, name, value)
        if net is not None:
            del net.forward
    order = ["pattern and c", "reading", "sort", "hot pixels", "isolated", "EDI table",
             "threshold", "voxels", "levels", "network", "rest of method", "writing"]

    def ms(key: str) -> float:
        return 1e3 * float(np.median(per_frame[key]))

    # the network's CPU time is not its calling thread's: its wall time alone
    return ", ".join(f"{k} {ms(k):.1f}" + ("" if k == "network" else f" ({ms(k + ' cpu'):.1f})")
                     for k in order if k in per_frame)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="*", type=Path,
                    default=[SHARED / "recordings" / "davis346.aedat4"],
                    help="what `trmd deblur` takes: a recording, or frames and events")
    ap.add_argument("--method", default="trmd", choices=["trmd", "edi"])
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--precision", default="auto", choices=["auto", "fp32", "bf16"],
                    help="the network's arithmetic (auto: bfloat16 where the CPU has it)")
    ap.add_argument("--repeat", type=int, default=1, help="passes over the recording; the best")
    ap.add_argument("--profile", action="store_true", help="also time each stage")
    ap.add_argument("--contrast", type=float, default=None,
                    help="a given threshold c: no estimate (what the rest of the run costs)")
    ap.add_argument("--heap-defaults", action="store_true",
                    help="leave the process's memory settings at glibc's and numpy's defaults "
                         "(trmd raises the heap's thresholds, and turns numpy's huge-page "
                         "advice off where the kernel would stall on it)")
    ap.add_argument("--contrast-scope", default="recording", choices=["recording", "frame"],
                    help="one threshold for the recording (trmd's default) or one per frame")
    ap.add_argument("--keep-pattern", action="store_true",
                    help="leave the sensor's fixed pattern in the frames (no estimate)")
    args = ap.parse_args()

    t0 = time.perf_counter()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `trmd` sets it before torch loads
    if not args.heap_defaults:
        from trmd_cli.heap import tune_memory

        tune_memory()  # as `trmd` does when it starts
    import torch

    from trmd_cli.deblur import deblur_frames, settle
    from trmd_cli.methods import MethodConfig, make_method
    from trmd_cli.overlap import ahead
    from trmd_cli.read import ReadOptions
    from trmd_cli.read.inputs import open_inputs
    from trmd_cli.write import write_result_folder

    config = MethodConfig(method=args.method, threads=args.threads, precision=args.precision,
                          contrast=args.contrast, contrast_scope=args.contrast_scope,
                          fixed_pattern=not args.keep_pattern)
    est = make_method(config)
    start_s = time.perf_counter() - t0
    whole, inside, cpu = float("inf"), float("nan"), float("nan")
    net = est.model.model if args.method == "trmd" else None
    spent: dict[str, float] = defaultdict(float)
    if net is not None:  # the network's own time inside the run: the contention it saw too
        net.forward = _timed(spent, "network", net.forward)
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            with open_inputs(args.inputs, ReadOptions()) as ins:
                frames = len(ins.source)
                spent.clear()
                t1, c1 = time.perf_counter(), time.process_time()
                settled, _ = settle(est, ins.source, config)
                for i, res in enumerate(ahead(deblur_frames(ins.source, settled))):
                    folder = Path(tmp) / f"{r}_{i:06d}"
                    folder.mkdir()
                    write_result_folder(folder, res, meta={})
                per_frame = (time.perf_counter() - t1) / frames
                if per_frame < whole:
                    whole, inside = per_frame, spent["network"] / frames
                    cpu = (time.process_time() - c1) / frames
                h, w = ins.source.height, ins.source.width
        if net is not None:
            del net.forward
        stages = None
        if args.profile:
            with open_inputs(args.inputs, ReadOptions()) as ins:
                stages = profile(ins, est, config, Path(tmp))
    scope = f"c = {args.contrast:g} given" if args.contrast else f"c per {args.contrast_scope}"
    line = (f"{' '.join(p.name for p in args.inputs)}: {frames} frames {w}x{h}, {args.method}, "
            f"{torch.get_num_threads()} threads, {scope}; "
            f"start-up {start_s:.2f} s; "
            f"whole recording {whole * 1e3:.0f} ms per frame ({1 / whole:.1f} frames/s, "
            f"CPU {cpu * 1e3:.0f} ms)")
    if args.method == "trmd":
        from trmd_cli.models.inputs import RENetInputs
        from trmd_cli.precision import autocast

        m = 2 * est.n
        g = torch.Generator().manual_seed(0)
        x = RENetInputs(torch.rand(1, 1, h, w, generator=g), torch.randn(1, m, h, w, generator=g),
                        levels=torch.randn(1, m, h, w, generator=g), contrast=0.25)
        times, cpus = [], []
        with torch.inference_mode(), autocast(est.model.device, est.model.amp_dtype):
            for k in range(12):
                t, c = time.perf_counter(), time.process_time()
                net(x)
                if k >= 2:
                    times.append(time.perf_counter() - t)
                    cpus.append(time.process_time() - c)
        fwd, fwd_cpu = float(np.median(times)), float(np.median(cpus))
        line += (f"; bare network ({est.precision}) {fwd * 1e3:.0f} ms (CPU "
                 f"{fwd_cpu * 1e3:.0f} ms): whole / network = {whole / fwd:.2f}× (CPU "
                 f"{cpu / fwd_cpu:.2f}×); the network inside the run {inside * 1e3:.0f} ms per "
                 f"frame: whole / that = {whole / inside:.2f}×")
    print(line)
    if stages is not None:
        print(f"  per frame, ms (median, no overlap): {stages}")


if __name__ == "__main__":
    main()
