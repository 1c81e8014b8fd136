"""Read throughput of the camera-native readers (EVT 2.0, EVT 3.0, .dat, AEDAT4, .mat).

Run: python bench/bench_read_camera.py [--events 10000000] [--keep DIR]

The shared recordings (../shared/data/recordings) are repeated end to end, with their clocks
shifted so time keeps increasing, until each file holds ≥ --events events. AEDAT4 packets are
compressed and cannot be shifted without re-encoding, so the AEDAT4 figure repeats the read of
the shared file instead. Each measurement runs in a fresh subprocess so its peak memory is its
own. Modes:

* ``open+all``: open (one indexing pass) and take every event into memory;
* ``stream``: cache disabled, iterate 50 ms windows over the whole file with ``iter_windows``
  (memory bounded by one window + one chunk);
* ``ref``: the third-party decoder alone (expelliarmus / evt3 / aedat / scipy), for comparison.

Modules are imported before the clock starts (importing a decoder is not decoding). ``open s``
is the part of the time spent opening (the index pass); ``% ref`` compares the event rate with
the ``ref`` line of the same format, measured in the same run, by wall-clock time and by the
process's CPU time (``cpu s``: what other processes on a shared machine disturb least). Run it
several times and compare ratios.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine  # noqa: E402

from trmd_cli.read.chunked import CACHE_MAX_EVENTS  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
REC = SHARED / "recordings"

CHILD = r"""
import json, sys, time
from pathlib import Path
import numpy as np
mode, fmt, path, repeat = {mode!r}, {fmt!r}, {path!r}, {repeat}
# every module is imported before the clock starts: importing expelliarmus alone takes longer
# than decoding 10M events with it, and would hide the decoding being compared
DECODER = {{"evt2": "expelliarmus", "dat": "expelliarmus", "evt3": "evt3", "aedat4": "aedat",
           "mat": "scipy.io"}}[fmt]
import importlib
importlib.import_module(DECODER)
if mode != "ref":
    from trmd_cli.read import open_events, ReadOptions
    from trmd_cli.read import chunked
    from trmd_cli.events import Exposure
    opts = ReadOptions(sensor=(346, 260)) if fmt == "mat" else ReadOptions()
t0, c0 = time.perf_counter(), time.process_time()
n = 0
opened = 0.0
if mode == "ref":
    for _ in range(repeat):
        if fmt in ("evt2", "dat"):
            import expelliarmus
            n += len(expelliarmus.Wizard(encoding=fmt.upper(), fpath=path).read())
        elif fmt == "evt3":
            import evt3
            n += len(evt3.decode_file(path))
        elif fmt == "aedat4":
            import aedat
            n += sum(len(p["events"]) for p in aedat.Decoder(path) if "events" in p)
        elif fmt == "mat":
            import scipy.io
            n += scipy.io.loadmat(path)["section_event_x"].size
else:
    for _ in range(repeat):
        if mode == "stream":
            chunked.CACHE_MAX_EVENTS = 0
            t1 = time.perf_counter()
            with open_events(path, opts) as r:
                opened += time.perf_counter() - t1
                a, b = r.time_range_us()
                # closed windows that tile the recording: every event counted once
                wins = [Exposure(s, s + 49_999) for s in range(a, b + 1, 50_000)]
                n += sum(len(w) for w in r.iter_windows(wins))
        else:
            t1 = time.perf_counter()
            with open_events(path, opts) as r:
                opened += time.perf_counter() - t1
                n += len(r.events())
secs, cpu = time.perf_counter() - t0, time.process_time() - c0
# VmHWM belongs to this process image alone (ru_maxrss would include the parent's at fork)
hwm = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM"))
print(json.dumps({{"events": n, "seconds": secs, "cpu_s": cpu, "open_s": opened,
                  "peak_mib": hwm / 1024}}))
"""


def _header_end(data: bytes) -> int:
    from trmd_cli.read.prophesee import parse_header

    return parse_header(data[:1 << 16]).data_offset


def make_evt2(src: Path, dst: Path, copies: int) -> None:
    data = src.read_bytes()
    off = _header_end(data)
    words = np.frombuffer(data[off:], "<u4")
    is_th = (words >> 28) == 0x8
    th = words[is_th] & 0x0FFFFFFF
    shift = int(th.max() - th.min()) + 100  # in 64 µs units: one copy's span plus a gap
    parts = []
    for k in range(copies):
        w = words.copy()
        w[is_th] = (0x8 << 28) | ((th - th.min() + k * shift) & 0x0FFFFFFF)
        parts.append(w)
    dst.write_bytes(data[:off] + np.concatenate(parts).tobytes())


def make_dat(src: Path, dst: Path, copies: int) -> None:
    data = src.read_bytes()
    off = _header_end(data) + 2
    rec = np.frombuffer(data[off:], [("t", "<u4"), ("d", "<u4")])
    span = int(rec["t"].max()) + 1000
    parts = []
    for k in range(copies):
        r = rec.copy()
        r["t"] = r["t"] + k * span
        parts.append(r)
    dst.write_bytes(data[:off] + np.concatenate(parts).tobytes())


def make_evt3(src: Path, dst: Path, copies: int) -> None:
    # EVT 3.0 times are 24-bit and the decoder unwraps them: copies laid end to end keep
    # increasing as long as each copy starts "later" modulo 2**24 µs than the last one ended,
    # which the reader checks (it raises if time went back).
    data = src.read_bytes()
    off = _header_end(data)
    dst.write_bytes(data[:off] + data[off:] * copies)


def make_mat(dst: Path, n: int) -> None:
    import scipy.io

    rng = np.random.default_rng(0)
    t = 1_615_007_563.0 + np.sort(rng.random(n)) * 0.104
    scipy.io.savemat(dst, {"section_event_timestamp": t[None],
                           "section_event_x": rng.integers(0, 346, n)[None],
                           "section_event_y": rng.integers(0, 260, n)[None],
                           "section_event_polarity": rng.integers(0, 2, n)[None],
                           "start_timestamp": np.array([[t[0]]]),
                           "end_timestamp": np.array([[t[-1]]])})


def run(mode: str, fmt: str, path: Path, repeat: int = 1) -> dict:
    code = CHILD.format(mode=mode, fmt=fmt, path=str(path), repeat=repeat)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if out.returncode:
        return {"error": out.stderr.strip().splitlines()[-1]}
    return json.loads(out.stdout)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--events", type=int, default=10_000_000)
    ap.add_argument("--keep", type=Path, help="write the big files here (else a temp dir)")
    ap.add_argument("--formats", default="evt2,evt3,dat,aedat4,mat",
                    help="comma-separated formats to measure")
    args = ap.parse_args()
    if not REC.exists():
        sys.exit(f"shared recordings not found at {REC}")
    print(machine())
    print(f"in-memory cache up to {CACHE_MAX_EVENTS:,} events; bigger files are decoded on demand")
    with tempfile.TemporaryDirectory() as tmp:
        d = args.keep or Path(tmp)
        d.mkdir(parents=True, exist_ok=True)
        files = {
            "evt2": (d / "big_evt2.raw", 521_252, make_evt2, REC / "evt2.raw"),
            "evt3": (d / "big_evt3.raw", 1_218_618, make_evt3, REC / "evt3.raw"),
            "dat": (d / "big.dat", 1_218_618, make_dat, REC / "gen4.dat"),
        }
        wanted = set(args.formats.split(","))
        plan = []
        for fmt, (dst, per_copy, maker, src) in files.items():
            if fmt in wanted:
                maker(src, dst, -(-args.events // per_copy))
                plan.append((fmt, dst, 1))
        if "aedat4" in wanted:
            plan.append(("aedat4", REC / "davis346.aedat4", -(-args.events // 78_830)))
        if "mat" in wanted:
            mat = d / "big.mat"
            make_mat(mat, min(args.events, 4_000_000))  # 32 bytes/event on disk: keep it modest
            plan.append(("mat", mat, 1))

        print(f"{'format':<7} {'mode':<9} {'events':>12} {'seconds':>8} {'cpu s':>7} "
              f"{'open s':>7} {'Mev/s':>7} {'% ref':>6} {'cpu %':>6} {'peak MiB':>9} "
              f"{'file MiB':>9}")
        for fmt, path, repeat in plan:
            size = path.stat().st_size / 2**20
            results = {}
            for mode in ("ref", "open+all", "stream"):
                if fmt == "mat" and mode == "stream":
                    continue  # read whole by scipy: nothing to stream
                results[mode] = run(mode, fmt, path, repeat)
            ref = results["ref"]
            for mode, r in results.items():
                if "error" in r:
                    print(f"{fmt:<7} {mode:<9} failed: {r['error']}")
                    continue
                rate = r["events"] / r["seconds"]
                if mode == "ref" or "error" in ref:
                    share = cpu_share = f"{'':>6}"
                else:
                    share = f"{rate / (ref['events'] / ref['seconds']):>6.0%}"
                    cpu_rate = r['events'] / r['cpu_s']
                    cpu_share = f"{cpu_rate / (ref['events'] / ref['cpu_s']):>6.0%}"
                print(f"{fmt:<7} {mode:<9} {r['events']:>12,} {r['seconds']:>8.3f} "
                      f"{r['cpu_s']:>7.3f} {r['open_s']:>7.3f} {rate / 1e6:>7.1f} {share} "
                      f"{cpu_share} {r['peak_mib']:>9.0f} {size:>9.1f}"
                      + (f"  (file read {repeat}×)" if repeat > 1 else ""))


if __name__ == "__main__":
    main()
