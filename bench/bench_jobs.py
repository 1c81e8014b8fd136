"""`trmd deblur --jobs K`: frames per second on a multi-frame recording, K = 1 vs 2 (or more,
or auto).

    python bench/bench_jobs.py                      # 200 frames of 346×260, EDI, K = 1, 2
    python bench/bench_jobs.py --frames 100 --jobs 1 2 4 --method trmd
    python bench/bench_jobs.py --inputs REC.h5 --method fused --jobs 1 auto --repeat 3

Each run is the whole command (reading, deblurring, writing PNGs, starting the workers) on a
trmd HDF5 recording made here (a checkerboard under random events: nothing for the motion
methods to find), or on ``--inputs`` (what `trmd deblur` takes), so the figures include the
fixed cost of spawning K processes. With K > 1 each worker gets cores // K threads. With
``--repeat`` the K values take turns, pass after pass (the machine's speed drifts), and the
median is printed. No target: the gain depends on the cores the machine leaves free.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import machine


def make_recording(path: Path, frames: int, width: int = 346, height: int = 260,
                   events_per_frame: int = 20_000) -> Path:
    """A 10 ms exposure every 20 ms, a moving checkerboard, events all the time."""
    from trmd_cli.events import Exposure, make_stream
    from trmd_cli.write import H5Writer

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:height, 0:width]
    base = (0.2 + 0.6 * (((xx // 16) + (yy // 16)) % 2)).astype(np.float32)
    with H5Writer(path, width, height) as w:
        t = np.concatenate([k * 20_000 + np.sort(rng.integers(0, 20_000, events_per_frame))
                            for k in range(frames)])
        n = len(t)
        w.add_events(make_stream(rng.integers(0, width, n), rng.integers(0, height, n), t,
                                 rng.integers(0, 2, n), width, height))
        for k in range(frames):
            w.add_frame(np.roll(base, 2 * k, axis=1),
                        Exposure(k * 20_000 + 5_000, k * 20_000 + 15_000))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--jobs", nargs="+", default=["1", "2"], help="K values (or auto)")
    ap.add_argument("--method", default="edi")
    ap.add_argument("--inputs", type=Path, nargs="+", help="a recording (or frames and events) "
                    "instead of the one made here; its threshold is estimated")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    print(machine())
    with tempfile.TemporaryDirectory() as tmp:
        if args.inputs:
            inputs, contrast = [str(p) for p in args.inputs], []
            from trmd_cli.read import ReadOptions
            from trmd_cli.read.inputs import open_inputs

            with open_inputs(args.inputs, ReadOptions()) as ins:
                frames = len(ins.source)
        else:
            inputs = [str(make_recording(Path(tmp) / "rec.h5", args.frames))]
            contrast, frames = ["--contrast", "0.2"], args.frames
        times: dict[str, list[float]] = {k: [] for k in args.jobs}
        for r in range(args.repeat):
            for k in args.jobs:
                out = Path(tmp) / f"out{k}_{r}"
                cmd = [sys.executable, "-m", "trmd_cli", "deblur", *inputs, "-o", str(out),
                       "--method", args.method, *contrast, "--jobs", k]
                t0 = time.perf_counter()
                subprocess.run(cmd, check=True, capture_output=True)
                times[k].append(time.perf_counter() - t0)
                print(f"--jobs {k}: {frames} frames in {times[k][-1]:.1f} s = "
                      f"{frames / times[k][-1]:.2f} frames/s ({args.method})", flush=True)
        if args.repeat > 1:
            for k, ts in times.items():
                dt = float(np.median(ts))
                print(f"median --jobs {k}: {dt:.1f} s, {dt / frames:.2f} s per frame "
                      f"({min(ts):.1f}–{max(ts):.1f} s)")


if __name__ == "__main__":
    main()
