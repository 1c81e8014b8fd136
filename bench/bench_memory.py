"""Peak memory of `trmd deblur` over every frame of a long HDF5 recording: it must stay flat.

Run::

    python bench/bench_memory.py                   # recordings of 1/8, 1/4, 1/2, 1 × 1.2 GB
    python bench/bench_memory.py --size-gb 2.4     # the largest recording; halves below it
    python bench/bench_memory.py --quick           # ~50 MB: a quick correctness check
    python bench/bench_memory.py --dir /work/runs  # where the recordings go (default: $TMPDIR)

For each size a synthetic recording in the trmd HDF5 layout is written with
:class:`trmd_cli.write.H5Writer`, a few frames' events at a time (memory bounded while writing
too): 240×180 float32 blurry frames, a 10 ms exposure every 20 ms, and events all the time
(``--events-per-frame`` per 20 ms, half of them inside each exposure). Then
``trmd deblur REC.h5 -o OUT --method edi`` runs in a child process, which writes its own peak
resident memory (``VmHWM`` of ``/proc/self/status``) when it exits. Not ``ru_maxrss`` from
``wait4``/``RUSAGE_CHILDREN``: Linux carries the high-water mark of the address space a child
was spawned from (this process, which has just written the recording) across ``exec``, so it
would report the parent's peak. ``VmRSS`` of the child is also sampled while it runs, to show
memory over time.

``--readers`` measures the readers instead: one recording of ``--events`` events as an
uncompressed ``.npz`` and as an HDF5 file, and one of ``--text-events`` as text (the same
240×180 sensor and event rate), each given to ``trmd info``, ``trmd voxelize`` on one 10 ms
window, ``trmd deblur BLURRY.png EVENTS`` on that window, and ``trmd voxelize`` with no window
(the whole span). ``--trmd-src DIR`` runs another copy of trmd's sources (e.g. the previous
version, unpacked with ``git archive``) for a before/after comparison::

    python bench/bench_memory.py --readers --events 50e6 --text-events 20e6

The claim (issue: bounded memory): the peak does not grow with the file. Expect the same figure,
within a few MiB, for every size past a warm-up: HDF5's chunk caches and free lists take a fixed
~30 MiB over the first ~200 windows, then stay put (so ``--quick``, whose recordings are shorter
than that, shows a little growth). Everything is written under a fresh
temporary folder, removed at the end unless ``--keep``. Timings are only meaningful on a quiet
machine.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import PEAK_CHILD, machine, peak_env, run_peak  # noqa: E402

W, H = 240, 180
EXPOSURE_US = 10_000
INTERVAL_US = 20_000
#: frames whose events go to H5Writer in one call (bounds memory while writing)
PIECE_FRAMES = 32


def bytes_per_frame(events_per_frame: int) -> int:
    """Stored bytes per frame: float32 pixels + x, y (uint16), t (int64), p (int8) per event."""
    return W * H * 4 + events_per_frame * (2 + 2 + 8 + 1)


def write_recording(path: Path, frames: int, events_per_frame: int, seed: int = 0) -> None:
    """A trmd-layout recording of ``frames`` exposures, written a piece at a time."""
    from trmd_cli.events import Exposure, make_stream
    from trmd_cli.write import H5Writer

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    # smooth texture with edges: a plausible frame that PNG compresses like a real one
    base = (0.2 + 0.6 * (((xx // 16) + (yy // 16)) % 2) + 0.1 * np.sin(xx / 9.0)).astype(
        np.float32)
    with H5Writer(path, W, H) as w:
        for p0 in range(0, frames, PIECE_FRAMES):
            ks = range(p0, min(frames, p0 + PIECE_FRAMES))
            n = events_per_frame * len(ks)
            t = np.concatenate([k * INTERVAL_US + np.sort(rng.integers(0, INTERVAL_US,
                                                                          events_per_frame))
                                for k in ks])
            w.add_events(make_stream(rng.integers(0, W, n, dtype=np.uint16),
                                     rng.integers(0, H, n, dtype=np.uint16), t,
                                     rng.integers(0, 2, n, dtype=np.int8), W, H))
            for k in ks:
                start = k * INTERVAL_US + (INTERVAL_US - EXPOSURE_US) // 2
                w.add_frame(np.roll(base, k, axis=1), Exposure(start, start + EXPOSURE_US))


def vm_rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def run_trmd(args: list[str], hwm: Path, src: Path | None = None) -> tuple[float, float]:
    """``trmd ARGS`` in a child: (peak RSS MiB, wall s). ``src``: the trmd sources to run."""
    peak, wall, _ = run_peak(args, hwm, src)
    return peak, wall


def write_flat_recording(work: Path, events: int, seed: int = 0):
    """``events`` events at 2 M/s on 240×180 (40 000 per 20 ms): the same stream as .npz
    (uncompressed) and .h5, written a piece at a time."""
    from trmd_cli.events import make_stream
    from trmd_cli.write import H5Writer, write_events_npz

    rng = np.random.default_rng(seed)
    rate = 2  # events per µs
    t = np.sort(rng.integers(0, events // rate, events)).astype(np.int64)
    x = rng.integers(0, W, events, dtype=np.uint16)
    y = rng.integers(0, H, events, dtype=np.uint16)
    p = rng.integers(0, 2, events).astype(np.int8) * 2 - 1
    write_events_npz(work / "rec.npz", make_stream(x, y, t, p, W, H))
    with H5Writer(work / "rec.h5", W, H) as w:
        step = 1 << 24
        for i in range(0, events, step):
            w.add_events(make_stream(x[i:i + step], y[i:i + step], t[i:i + step],
                                     p[i:i + step], W, H))
    return int(t[-1])


def write_text_recording(path: Path, events: int, seed: int = 1) -> int:
    """``events`` text events (t in seconds, 2 M/s) written a million lines at a time."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, events // 2, events)).astype(np.int64)
    with open(path, "w") as fh:
        fh.write(f"{W} {H}\n")
        for i in range(0, events, 1 << 20):
            s, us = np.divmod(t[i:i + (1 << 20)], 1_000_000)
            n = len(s)
            cols = np.stack([s, us, rng.integers(0, W, n), rng.integers(0, H, n),
                             rng.integers(0, 2, n)], 1).tolist()
            fh.write("".join(f"{a}.{b:06d} {c} {d} {e}\n" for a, b, c, d, e in cols))
    return int(t[-1])


def bench_readers(args, work: Path) -> None:
    from trmd_cli.write import write_image

    print(f"readers: {args.events:.0f} events (.npz, .h5), {args.text_events:.0f} (text); "
          f"sources: {args.trmd_src or 'this checkout'}")
    write_image(work / "blurry.png", np.full((H, W), 0.5, np.float32))
    t0 = time.perf_counter()
    end = write_flat_recording(work, int(args.events))
    text_end = write_text_recording(work / "rec.txt", int(args.text_events)) \
        if args.text_events else None
    print(f"written in {time.perf_counter() - t0:.0f} s")
    print(f"{'file':>8} {'command':<28} {'peak RSS MiB':>13} {'wall s':>8}")
    hwm = work / "hwm"
    for name, last in (("rec.npz", end), ("rec.h5", end), ("rec.txt", text_end)):
        if last is None:
            continue
        f = str(work / name)
        mid = last // 2
        win = ["--exposure", str(mid), str(mid + 10_000)]
        if name.endswith(".txt"):  # text times are seconds: the window in the file's unit
            win = ["--exposure", f"{mid / 1e6:.6f}", f"{(mid + 10_000) / 1e6:.6f}"]
        runs = [("info", ["info", f]),
                ("voxelize (one window)", ["voxelize", f, "-o", str(work / "v.npz"), *win,
                                           "--overwrite"]),
                ("deblur (one window)", ["deblur", str(work / "blurry.png"), f, "-o",
                                         str(work / "d"), *win, "--method", "edi",
                                         "--contrast", "0.2", "--overwrite"]),
                ("voxelize (whole span)", ["voxelize", f, "-o", str(work / "v.npz"), "--n",
                                           "1", "--overwrite"])]
        for what, cmd in runs:
            peak, wall = run_trmd(cmd, hwm, args.trmd_src)
            print(f"{name:>8} {what:<28} {peak:13.0f} {wall:8.1f}", flush=True)


def run_deblur(rec: Path, out: Path, contrast: str) -> dict:
    """Run the CLI in a child; its peak RSS (MiB), RSS samples over time, wall time."""
    hwm = out.with_name(out.name + ".hwm")
    env = peak_env(hwm)
    cmd = [sys.executable, "-c", PEAK_CHILD, "deblur", str(rec), "-o", str(out), "--method", "edi",
           "--contrast", contrast]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    samples: list[float] = []
    while proc.poll() is None:
        rss = vm_rss_mib(proc.pid)
        if rss is not None:
            samples.append(rss)
        time.sleep(0.25)
    wall = time.perf_counter() - t0
    stdout, stderr = (s.read().decode() for s in (proc.stdout, proc.stderr))
    proc.stdout.close()
    proc.stderr.close()
    if proc.returncode != 0:
        raise SystemExit(f"deblur failed (exit {proc.returncode}): {stderr.strip()}")
    peak = int(hwm.read_text()) / 1024
    hwm.unlink()
    return {"peak_mib": peak, "samples": samples, "wall_s": wall, "stdout": stdout.strip()}


def quartiles(samples: list[float]) -> str:
    """VmRSS at 25 / 50 / 75 / 100 % of the run (MiB)."""
    if len(samples) < 4:
        return "–"
    idx = [len(samples) // 4, len(samples) // 2, 3 * len(samples) // 4, len(samples) - 1]
    return " / ".join(f"{samples[i]:.0f}" for i in idx)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size-gb", type=float, default=1.2,
                    help="size of the largest recording, GB (10^9 bytes)")
    ap.add_argument("--steps", type=int, default=4,
                    help="recordings measured: the largest and its halves (default 4 → 1/8..1)")
    ap.add_argument("--events-per-frame", type=int, default=40_000,
                    help="events per 20 ms frame interval (half inside each exposure)")
    ap.add_argument("--contrast", default="0.2", help="--contrast for deblur (or 'auto')")
    ap.add_argument("--quick", action="store_true",
                    help="largest recording ~50 MB, 3 sizes: a quick correctness check")
    ap.add_argument("--dir", type=Path, default=None,
                    help="where to put the temporary folder (default: $TMPDIR or /tmp)")
    ap.add_argument("--keep", action="store_true", help="keep the recordings and outputs")
    ap.add_argument("--readers", action="store_true",
                    help="measure info / voxelize / deblur on .npz, .h5 and text instead")
    ap.add_argument("--events", type=float, default=50e6, help="--readers: .npz/.h5 events")
    ap.add_argument("--text-events", type=float, default=20e6,
                    help="--readers: text events (0: no text file)")
    ap.add_argument("--trmd-src", type=Path, default=None,
                    help="--readers: run the trmd found here (a src/ folder) instead")
    args = ap.parse_args()
    if args.quick:
        args.size_gb, args.steps = 0.05, 3
    if args.dir is not None:
        args.dir.mkdir(parents=True, exist_ok=True)
    repo = Path(__file__).resolve().parents[1]
    work = Path(tempfile.mkdtemp(prefix="trmd-bench-memory-", dir=args.dir))
    if repo in work.resolve().parents:
        shutil.rmtree(work)
        raise SystemExit(f"refusing to write recordings inside the repository ({work})")

    print(machine())
    if args.readers:
        try:
            bench_readers(args, work)
        finally:
            if not args.keep:
                shutil.rmtree(work, ignore_errors=True)
        return
    print(f"trmd deblur REC.h5 -o OUT --method edi --contrast {args.contrast}; frames {W}x{H} "
          f"float32, {args.events_per_frame} events per {INTERVAL_US // 1000} ms; in {work}")
    per_frame = bytes_per_frame(args.events_per_frame)
    sizes = [args.size_gb * 1e9 / 2 ** i for i in reversed(range(args.steps))]
    print(f"{'file MB':>9} {'frames':>7} {'events':>11} {'write s':>8} {'deblur s':>9} "
          f"{'s/frame':>8} {'peak RSS MiB':>13}  RSS over the run (25/50/75/100 %)")
    peaks: list[float] = []
    try:
        for size in sizes:
            frames = max(2, int(round(size / per_frame)))
            rec, out = work / f"rec-{frames}.h5", work / f"out-{frames}"
            t0 = time.perf_counter()
            write_recording(rec, frames, args.events_per_frame)
            t_write = time.perf_counter() - t0
            res = run_deblur(rec, out, args.contrast)
            # correctness: one output folder per frame, each with its 7 latent frames
            made = sorted(p for p in out.iterdir() if p.is_dir())
            if len(made) != frames or len(list(made[-1].glob("frame_*.png"))) != 7:
                raise SystemExit(f"expected {frames} frame folders in {out}, got {len(made)}")
            peaks.append(res["peak_mib"])
            print(f"{rec.stat().st_size / 1e6:9.0f} {frames:7d} "
                  f"{frames * args.events_per_frame:11d} {t_write:8.1f} {res['wall_s']:9.1f} "
                  f"{res['wall_s'] / frames:8.3f} {res['peak_mib']:13.0f}  "
                  f"{quartiles(res['samples'])}", flush=True)
            if not args.keep:
                rec.unlink()
                shutil.rmtree(out)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    if len(peaks) < 2:
        return
    # the first ~200 windows warm up HDF5's chunk caches and free lists (a fixed ~30 MiB):
    # judge flatness on the last doubling, and show the whole span too
    last = peaks[-1] - peaks[-2]
    verdict = "flat" if abs(last) < 0.1 * peaks[-2] else "NOT flat"
    print(f"peak RSS: {last:+.0f} MiB over the last doubling of the file ({verdict} by the "
          f"±10 % rule); {peaks[-1] - peaks[0]:+.0f} MiB while the file grew "
          f"{sizes[-1] / sizes[0]:.0f}×")


if __name__ == "__main__":
    main()
