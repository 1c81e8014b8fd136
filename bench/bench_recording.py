"""Whole-recording cost per frame against the bare network, measured in the same process.

    python bench/bench_recording.py [INPUTS …] [--method trmd] [--threads T]

What `trmd deblur INPUTS -o OUT` does per frame after start-up — read the frame and its
events, the threshold, voxels and timing levels, the network, the reconstruction, writing the
result folder (the next frame deblurred while the last is written) — timed over the whole
recording, against the shipped network's bare forward pass on a frame of the same size (median
of 10, after 2 warm-up passes). The start-up (imports, loading the weights) is reported apart.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="*", type=Path,
                    default=[SHARED / "recordings" / "davis346.aedat4"],
                    help="what `trmd deblur` takes: a recording, or frames and events")
    ap.add_argument("--method", default="trmd", choices=["trmd", "edi"])
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()

    t0 = time.perf_counter()
    import torch

    from trmd_cli.deblur import deblur_frames
    from trmd_cli.methods import MethodConfig, make_method
    from trmd_cli.overlap import ahead
    from trmd_cli.read import ReadOptions
    from trmd_cli.read.inputs import open_inputs
    from trmd_cli.write import write_result_folder

    est = make_method(MethodConfig(method=args.method, threads=args.threads))
    start_s = time.perf_counter() - t0
    with open_inputs(args.inputs, ReadOptions()) as ins, \
            tempfile.TemporaryDirectory() as tmp:
        frames = len(ins.source)
        t1 = time.perf_counter()
        for i, res in enumerate(ahead(deblur_frames(ins.source, est))):
            folder = Path(tmp) / f"{i:06d}"
            folder.mkdir()
            write_result_folder(folder, res, meta={})
        whole = (time.perf_counter() - t1) / frames
        h, w = ins.source.height, ins.source.width
    line = (f"{' '.join(p.name for p in args.inputs)}: {frames} frames {w}x{h}, {args.method}, "
            f"{torch.get_num_threads()} threads; start-up {start_s:.2f} s; "
            f"whole recording {whole * 1e3:.0f} ms per frame ({1 / whole:.1f} frames/s)")
    if args.method == "trmd":
        from trmd_cli.models.inputs import RENetInputs

        net = est.model.model
        m = 2 * est.n
        g = torch.Generator().manual_seed(0)
        x = RENetInputs(torch.rand(1, 1, h, w, generator=g), torch.randn(1, m, h, w, generator=g),
                        levels=torch.randn(1, m, h, w, generator=g), contrast=0.25)
        from trmd_cli.precision import autocast

        times = []
        with torch.inference_mode(), autocast(est.model.device, est.model.amp_dtype):
            for k in range(12):
                t = time.perf_counter()
                net(x)
                if k >= 2:
                    times.append(time.perf_counter() - t)
        fwd = float(np.median(times))
        line += (f"; bare network ({est.precision}) {fwd * 1e3:.0f} ms: whole / network = "
                 f"{whole / fwd:.2f}×")
    print(line)


if __name__ == "__main__":
    main()
