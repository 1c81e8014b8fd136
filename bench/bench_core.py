"""Read throughput (npz, HDF5, text) and SCER voxelization throughput on ≥ 10M events.

Peak memory of each reader is the child's own VmHWM (ru_maxrss would carry the parent's).

Run: python bench/bench_core.py [--events 10000000]
Each reader runs in a fresh subprocess so its peak memory is its own.
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
from _common import best_of, machine, peak_rss_mib  # noqa: E402

CHILD = r"""
import json, sys, time
sys.path.insert(0, {bench!r})
from _common import best_of, peak_rss_mib
from trmd_cli.read import open_events
path = {path!r}
def run():
    with open_events(path) as r:
        s = r.events()
    return s
secs = best_of(run, {repeat})
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")]
peak = int(hwm[0].split()[1]) / 1024 if hwm else peak_rss_mib()
print(json.dumps({{"seconds": secs, "peak_mib": peak}}))
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--events", type=int, default=10_000_000)
    args = ap.parse_args()
    from trmd_cli.events import Exposure, make_stream
    from trmd_cli.voxel import scer_voxels
    from trmd_cli.write import write_events_npz, write_events_text, write_h5

    print(machine())
    n = args.events
    rng = np.random.default_rng(0)
    w, h = 346, 260
    stream = make_stream(rng.integers(0, w, n), rng.integers(0, h, n),
                         np.sort(rng.integers(0, 10_000_000, n)), rng.integers(0, 2, n), w, h)
    with tempfile.TemporaryDirectory() as d:
        files = {"npz": Path(d) / "e.npz", "hdf5": Path(d) / "e.h5", "text": Path(d) / "e.txt"}
        write_events_npz(files["npz"], stream)
        write_h5(files["hdf5"], stream)
        write_events_text(files["text"], stream)
        print(f"{'reader':<8} {'events':>12} {'seconds':>8} {'Mev/s':>8} {'peak MiB':>9} "
              f"{'file MiB':>9}")
        for fmt, path in files.items():
            code = CHILD.format(bench=str(Path(__file__).parent), path=str(path),
                                repeat=1 if fmt == "text" else 3)
            out = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True,
                                            text=True, check=True).stdout)
            print(f"{fmt:<8} {n:>12,} {out['seconds']:>8.3f} {n / out['seconds'] / 1e6:>8.1f} "
                  f"{out['peak_mib']:>9.0f} {path.stat().st_size / 2**20:>9.0f}")
    win = Exposure(0, 10_000_000)
    secs = best_of(lambda: scer_voxels(stream, win, 3))
    print(f"voxelize (N=3, one core, numpy): {n:,} events in {secs:.3f} s = "
          f"{n / secs / 1e6:.1f} Mev/s; peak RSS of this process {peak_rss_mib():.0f} MiB")
    try:
        import torch

        torch.set_num_threads(1)
        from trmd_cli.voxel import scer_voxels_torch

        xs = torch.from_numpy(stream.x.astype(np.int64))
        ys = torch.from_numpy(stream.y.astype(np.int64))
        ts, ps = torch.from_numpy(stream.t), torch.from_numpy(stream.p)
        secs = best_of(lambda: scer_voxels_torch(xs, ys, ts, ps, win, 3, h, w))
        print(f"voxelize (N=3, one thread, torch): {n / secs / 1e6:.1f} Mev/s")
    except ImportError:
        pass


if __name__ == "__main__":
    main()
