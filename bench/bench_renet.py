"""RE-Net variants: parameters, MACs and CPU forward time at DAVIS346 size; end-to-end timing.

Usage::

    python bench/bench_renet.py                      # all registered variants, 2 threads
    python bench/bench_renet.py --variants trmd_small --repeats 10 --threads 2
    python bench/bench_renet.py --precisions fp32 bf16   # bf16: mixed precision (autocast)
    python bench/bench_renet.py --layouts contiguous channels_last   # weight memory layouts

Per variant: parameters, MACs (count_macs, at the padded 352×272 grid), median and minimum
wall time of one forward pass of the network alone (torch.inference_mode, after warm-up), and
the minimum process CPU time (summed over threads; with --threads 1 it hardly depends on other
load) — once per precision (default: fp32, plus bf16 on CPUs with native bfloat16). End to
end (one variant, the last precision): SCER voxels from ~300k synthetic events, the
TrmdEstimator call (numpy in → 2N+1 frames out, weights loaded from a safetensors file), and
the two together. Wall times depend on what else runs on the machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from trmd_cli.events import EventStream, Exposure
from trmd_cli.methods import TrmdMethod
from trmd_cli.models import RENetInputs, count_macs, count_params, create_model, list_models
from trmd_cli.models.estimator import TrmdEstimator
from trmd_cli.models.weights import save_weights
from trmd_cli.precision import autocast, cpu_has_native_bf16, resolve_precision
from trmd_cli.voxel import scer_levels, scer_voxels


def _median_time(fn, repeats: int, warmup: int) -> tuple[float, float, float]:
    """Median and minimum wall time, and minimum process CPU time (all threads), in s."""
    for _ in range(warmup):
        fn()
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(times), min(times), min(cpu)


def _events(width: int, height: int, count: int, exposure: Exposure, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(exposure.start_us, exposure.end_us + 1, count)).astype(np.int64)
    return EventStream(x=rng.integers(0, width, count).astype(np.uint16),
                       y=rng.integers(0, height, count).astype(np.uint16), t=t,
                       p=rng.choice(np.array([-1, 1], np.int8), count), width=width,
                       height=height)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", nargs="*", default=None, help="default: all registered")
    ap.add_argument("--n", type=int, default=3)
    ap.add_argument("--width", type=int, default=346)
    ap.add_argument("--height", type=int, default=260)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--end-to-end", default="trmd_small_prior",
                    help="variant for the end-to-end run (default: the shipped one)")
    ap.add_argument("--precisions", nargs="*", default=None,
                    help="fp32 / bf16 (default: fp32, and bf16 where the CPU has it natively)")
    ap.add_argument("--layouts", nargs="*", default=["channels_last"],
                    choices=["channels_last", "contiguous"],
                    help="weight memory layouts to time (the estimator uses channels_last)")
    ap.add_argument("--args", default="{}",
                    help="JSON constructor overrides for the variants, e.g. "
                    "'{\"widths\": [48, 96, 192, 384]}'")
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    h, w, n = args.height, args.width, args.n
    names = args.variants or list_models()
    precisions = args.precisions or (["fp32", "bf16"] if cpu_has_native_bf16() else ["fp32"])
    over = json.loads(args.args)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {w}x{h}, N={n}, "
          f"native bfloat16: {cpu_has_native_bf16()}")
    print(f"{'variant':22s} {'prec':>5s} {'layout':>8s} {'params':>9s} {'GMACs':>7s} "
          f"{'median ms':>10s} {'min ms':>8s} {'CPU ms':>8s}")
    g = torch.Generator().manual_seed(0)
    blurry = torch.rand(1, 1, h, w, generator=g)
    counts = torch.randn(1, 2 * n, h, w, generator=g)
    # every optional input: networks ignore what they do not take
    levels = counts + 0.5 * torch.rand(counts.shape, generator=g)
    inputs = RENetInputs(blurry, counts, levels=levels, contrast=0.25)
    cpu_dev = torch.device("cpu")
    for name in names:
        for layout in args.layouts:
            model = create_model(name, n=n, **over).eval()
            if layout == "channels_last":  # how TrmdEstimator holds the weights
                model = model.to(memory_format=torch.channels_last)
            for prec in precisions:
                dtype = resolve_precision(prec, cpu_dev)

                def run(m=model, dtype=dtype):
                    with autocast(cpu_dev, dtype):
                        return m(inputs)

                with torch.inference_mode():
                    med, best, cpu = _median_time(run, args.repeats, args.warmup)
                tag = "nhwc" if layout == "channels_last" else "nchw"
                print(f"{name:22s} {prec:>5s} {tag:>8s} {count_params(model) / 1e6:8.2f}M "
                      f"{count_macs(model, h, w) / 1e9:7.2f} {med * 1e3:10.1f} "
                      f"{best * 1e3:8.1f} {cpu * 1e3:8.1f}", flush=True)

    exposure = Exposure(0, 20_000)
    stream = _events(w, h, 300_000, exposure)
    frame = np.random.default_rng(1).random((h, w)).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        path = save_weights(Path(tmp) / "bench.safetensors",
                            create_model(args.end_to_end, n=n, **over), meta={})
        t0 = time.perf_counter()
        est = TrmdEstimator.load(path, device="cpu", threads=args.threads,
                                 precision=precisions[-1])
        load_s = time.perf_counter() - t0
        method = TrmdMethod(n, path, device="cpu", threads=args.threads,
                            precision=precisions[-1])
    vox_med, *_ = _median_time(lambda: scer_voxels(stream, exposure, n), args.repeats, 1)
    vox = scer_voxels(stream, exposure, n)
    lev_med, *_ = _median_time(lambda: scer_levels(stream, exposure, n), args.repeats, 1)
    lev = scer_levels(stream, exposure, n) if est.needs_timing else None
    est_med, *_ = _median_time(lambda: est(frame, vox, 0.25, lev), args.repeats, args.warmup)

    def inputs_and_network():
        levels = scer_levels(stream, exposure, n) if est.needs_timing else None
        return est(frame, scer_voxels(stream, exposure, n), 0.25, levels)

    all_med, *_ = _median_time(inputs_and_network, args.repeats, 1)
    rgb = np.repeat(frame[..., None], 3, axis=2)
    rgb_med, *_ = _median_time(lambda: est(rgb, vox, 0.25, lev), max(args.repeats // 2, 1), 1)
    # what `trmd deblur --method trmd` does per frame: hot pixels, the threshold (estimated
    # when the network takes one), voxels, the network
    pipe_med, *_ = _median_time(lambda: method(frame, stream, exposure), args.repeats, 1)
    print(f"end to end ({args.end_to_end}, gray model, {est.precision}): "
          f"load {load_s * 1e3:.0f} ms, "
          f"voxels (300k events) {vox_med * 1e3:.1f} ms, timing levels {lev_med * 1e3:.1f} ms, "
          f"estimator {est_med * 1e3:.1f} ms, "
          f"voxels (+ levels) + estimator {all_med * 1e3:.1f} ms, RGB frame (3 channels) "
          f"{rgb_med * 1e3:.1f} ms, whole pipeline per frame (auto c) {pipe_med * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
