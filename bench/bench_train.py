"""Training speed on this machine: one optimiser step (forward, paper loss, backward, Adam) of a
model at a crop and batch size, for torch thread counts, memory layouts and precisions (float32;
bfloat16 autocast where the CPU has it natively, as ``train.amp`` does); plus the cost of
simulating a training sample on the fly (what DataLoader workers would compete with).

    python bench/bench_train.py [--model trmd_small_prior] [--crop 96] [--batch 14]

Prints seconds per step and samples per second. Keep it short: the cores are shared.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine  # noqa: E402


def step_time(model_name: str, crop: int, batch: int, steps: int, threads: int,
              channels_last: bool, precision: str = "fp32") -> float:
    import torch

    from trmd_cli.precision import autocast, resolve_precision
    from trmd_cli.reconstruct import reconstruct
    from trmd_cli.train.loop import build_model, forward
    from trmd_cli.train.losses import total_loss
    from trmd_cli.train.recipe import Recipe, apply_overrides

    torch.set_num_threads(threads)
    r = apply_overrides(Recipe(), [f"model.name={model_name!r}"])
    torch.manual_seed(0)
    model = build_model(r)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4, foreach=False)
    g = torch.Generator().manual_seed(0)
    sharp = torch.rand(batch, 7, 1, crop, crop, generator=g)
    b = {"blurry": sharp.mean(1), "voxels": torch.randn(batch, 6, crop, crop, generator=g),
         "levels": torch.randn(batch, 6, crop, crop, generator=g), "sharp": sharp,
         "contrast": torch.full((batch,), 0.25)}
    if channels_last:
        b = {k: (v.contiguous(memory_format=torch.channels_last) if v.ndim == 4 else v)
             for k, v in b.items()}

    dtype = resolve_precision(precision, torch.device("cpu"))

    def one() -> None:
        with autocast(torch.device("cpu"), dtype):
            res = forward(model, b, needs=model.needs)
        res = res.float()
        loss, _ = total_loss({"residuals": res, "latent": reconstruct(b["blurry"], res)}, b, r)
        opt.zero_grad()
        loss.backward()
        opt.step()

    one()  # warm-up (allocations, oneDNN kernels)
    t0 = time.perf_counter()
    for _ in range(steps):
        one()
    return (time.perf_counter() - t0) / steps


def simulate_time(crop: int, count: int) -> float:
    import numpy as np

    from trmd_cli.simulate.dataset import SimulatedDataset

    rng = np.random.default_rng(0)
    img = np.clip(rng.random((512, 768)).astype(np.float32), 0, 1)
    ds = SimulatedDataset([img], crop=crop, length=count, seed=0)
    ds[0]
    t0 = time.perf_counter()
    for i in range(1, count):
        ds[i]
    return (time.perf_counter() - t0) / max(count - 1, 1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default="trmd_small_prior")
    ap.add_argument("--crop", type=int, default=96)
    ap.add_argument("--batch", type=int, default=14)
    ap.add_argument("--steps", type=int, default=5)
    args = ap.parse_args()
    print(machine())
    print(f"{args.model}, crop {args.crop}, batch {args.batch}: seconds per training step")
    from trmd_cli.precision import cpu_has_native_bf16

    precisions = ["fp32", "bf16"] if cpu_has_native_bf16() else ["fp32"]
    for threads in (1, 2):
        for cl in (False, True):
            for prec in precisions:
                s = step_time(args.model, args.crop, args.batch, args.steps, threads, cl, prec)
                print(f"  threads {threads}  channels_last {cl!s:5}  {prec:4s}  {s:.3f} s/step  "
                      f"{args.batch / s:.1f} samples/s")
    s = simulate_time(args.crop, 12)
    print(f"simulating one {args.crop}x{args.crop} sample on the fly: {s * 1000:.0f} ms "
          f"({1 / s:.1f} samples/s on one core)")


if __name__ == "__main__":
    main()
