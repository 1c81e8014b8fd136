"""Train the fusion network (``trmd_cli.models.fusion``) on a set from ``make_fusionset.py``.

Random 128×128 crops (flipped and turned at random) of random instants, MSE against the sharp
frame, Adam with a cosine schedule, stopped by a step count or a time budget. The last
``--holdout`` samples are never trained on: the motion method and the fused frames are scored
on them, whole, at the end (the network's frames: the fused method then keeps EDI's where
nothing fired and the motion method's where its guard trusts them above c = 0.65,
``trmd_cli.fusion``, which needs the events the set does not store). Weights are written
(safetensors) every ``--save-every`` steps and at the end; ``--init`` resumes from a file
written here.

    python weights_recipe/train_fusion.py ../runs/fusion_346.h5 -o ../runs/fusion.safetensors
    python weights_recipe/train_fusion.py --ship ../runs/fusion.safetensors \
        -o src/trmd_cli/weights/fusion_default.safetensors
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from trmd_cli.metrics import psnr
from trmd_cli.models.fusion import FusionNet, fusion_planes, load_fusion, save_fusion

PLANES_FROM = ("motion", "trmd", "edi")


def load(path: Path) -> dict[str, np.ndarray]:
    import h5py

    with h5py.File(path, "r") as f:
        data = {k: f[k][()] for k in ("truth", "edi", "trmd", "motion", "weight", "events",
                                      "blurry")}
        data["n"] = int(f.attrs["n"])
    return data


def batch(data, idx: np.ndarray, rng: np.random.Generator, size: int):
    n = data["n"]
    h, w = data["blurry"].shape[1:]
    xs, ys = [], []
    for i in idx:
        k = int(rng.integers(2 * n + 1))
        y0, x0 = int(rng.integers(h - size + 1)), int(rng.integers(w - size + 1))
        sl = (slice(y0, y0 + size), slice(x0, x0 + size))
        planes = fusion_planes(*(data[m][i, k:k + 1][:, sl[0], sl[1]].astype(np.float32)
                                 for m in PLANES_FROM),
                               data["blurry"][i][sl].astype(np.float32),
                               data["weight"][i, k:k + 1][:, sl[0], sl[1]].astype(np.float32),
                               data["events"][i, k:k + 1][:, sl[0], sl[1]].astype(np.float32), n)
        # the instant plane must say k, not 0: fusion_planes numbers its K = 1 frame 0
        planes[:, 6] = (k - n) / n
        gt = torch.from_numpy(data["truth"][i, k][sl].astype(np.float32))[None, None]
        t = int(rng.integers(8))
        if t & 1:
            planes, gt = planes.flip(-1), gt.flip(-1)
        if t & 2:
            planes, gt = planes.flip(-2), gt.flip(-2)
        if t & 4:
            planes, gt = planes.transpose(-1, -2), gt.transpose(-1, -2)
        xs.append(planes)
        ys.append(gt)
    return torch.cat(xs), torch.cat(ys)


@torch.no_grad()
def score(model: FusionNet | None, data, idx) -> tuple[float, float]:
    """Mean PSNR (middle, sequence) of the fused frames (None: the motion method's)."""
    n = data["n"]
    mids, seqs = [], []
    for i in idx:
        gt = data["truth"][i].astype(np.float32)
        if model is None:
            out = data["motion"][i].astype(np.float32)
        else:
            planes = fusion_planes(*(data[m][i].astype(np.float32) for m in PLANES_FROM),
                                   data["blurry"][i].astype(np.float32),
                                   data["weight"][i].astype(np.float32),
                                   data["events"][i].astype(np.float32), n)
            out = model(planes)[:, 0].numpy()
        p = [psnr(np.clip(o, 0, 1), g) for o, g in zip(out, gt)]
        mids.append(p[n])
        seqs.append(float(np.mean(p)))
    return float(np.mean(mids)), float(np.mean(seqs))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, nargs="?", help="the set (not with --ship)")
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--minutes", type=float, default=30.0, help="time budget")
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--holdout", type=int, default=48)
    ap.add_argument("--save-every", type=int, default=500)
    ap.add_argument("--init", type=Path, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ship", type=Path, default=None,
                    help="convert these trained weights to the package's float16 file "
                         "(-o names it) and stop")
    args = ap.parse_args()
    if args.ship is not None:
        model, meta = load_fusion(args.ship)
        save_fusion(args.output, model, {k: v for k, v in meta.items()
                                         if k not in ("format", "width")}, torch.float16)
        print(f"wrote {args.output}")
        return
    if args.data is None:
        ap.error("give the training set")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    data = load(args.data)
    count = len(data["blurry"])
    train = np.arange(count - args.holdout)
    held = np.arange(count - args.holdout, count)
    model = load_fusion(args.init)[0].train() if args.init else FusionNet(args.width)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    print(f"{len(train)} training samples, {len(held)} held out; "
          f"{sum(p.numel() for p in model.parameters())} parameters", flush=True)
    base = score(None, data, held)
    print(f"held out, motion method: {base[0]:.2f} / {base[1]:.2f} dB", flush=True)
    if args.init:
        first = score(model.eval(), data, held)
        model.train()
        print(f"held out, the weights it starts from: {first[0]:.2f} / {first[1]:.2f} dB",
              flush=True)
    meta = {"trained_on": args.data.name, "samples": int(len(train)), "crop": args.crop,
            "batch": args.batch, "lr": args.lr}
    t0 = time.time()
    step, avg = 0, None
    while step < args.steps and time.time() - t0 < args.minutes * 60:
        lr = args.lr * 0.5 * (1 + math.cos(math.pi * step / args.steps))
        for g in opt.param_groups:
            g["lr"] = lr
        x, y = batch(data, rng.choice(train, args.batch), rng, args.crop)
        loss = torch.mean((model(x) - y) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        avg = loss.item() if avg is None else 0.98 * avg + 0.02 * loss.item()
        if step % 100 == 0:
            print(f"step {step} loss {avg:.3e} ({-10 * math.log10(avg):.2f} dB) lr {lr:.1e} "
                  f"{(time.time() - t0) / 60:.1f} min", flush=True)
        if step % args.save_every == 0:
            save_fusion(args.output, model, {**meta, "steps": step})
    model.eval()
    fused = score(model, data, held)
    print(f"held out after {step} steps: motion {base[0]:.2f} / {base[1]:.2f}, fused "
          f"{fused[0]:.2f} / {fused[1]:.2f} dB (middle / sequence)", flush=True)
    save_fusion(args.output, model, {**meta, "steps": step,
                                     "held_out_psnr": {"motion": base, "fused": fused}})
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
