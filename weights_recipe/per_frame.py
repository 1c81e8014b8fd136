"""Per latent frame k: PSNR of EDI (given the true c) and of TRMD (c estimated) on a set with
ground truth, and of their residuals R(k) = L(k) − L(N).

    python weights_recipe/per_frame.py ../runs/valset_kodak24.h5 [--weights FILE] [--every 2]

Frame PSNR is the mean over frames of each frame's PSNR (as ``trmd eval``); residual PSNR pools
the squared error over all frames (the middle frame's residual is zero by definition).
"""

from __future__ import annotations

import argparse

import numpy as np

from trmd_cli.evaluate import PSNR_CAP_DB
from trmd_cli.methods import EdiMethod, TrmdMethod
from trmd_cli.metrics import psnr
from trmd_cli.read.dataset import open_dataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("--weights", default=None, help="default: the shipped weights")
    ap.add_argument("--every", type=int, default=1, help="use every k-th frame of the set")
    ap.add_argument("--n", type=int, default=3)
    args = ap.parse_args()
    n, m = args.n, 2 * args.n + 1
    trmd = TrmdMethod(n, args.weights)
    frame_psnr = {"edi": [], "trmd": []}
    res_err = {"edi": np.zeros(m), "trmd": np.zeros(m)}
    pixels = 0
    for i, fr in enumerate(open_dataset(args.data, n=n).frames()):
        if i % args.every:
            continue
        truth = fr.truth
        outs = {"edi": EdiMethod(n, fr.contrast, hot_pixels=True)(fr.blurry, fr.events,
                                                                  fr.exposure).frames,
                "trmd": trmd(fr.blurry, fr.events, fr.exposure).frames}
        for name, frames in outs.items():
            frame_psnr[name].append([min(psnr(np.clip(frames[k], 0, 1), truth[k]), PSNR_CAP_DB)
                                     for k in range(m)])
            res_err[name] += [np.square((frames[k] - frames[n]) - (truth[k] - truth[n])).sum()
                              for k in range(m)]
        pixels += truth[0].size
    print("k              " + " ".join(f"{k:>6d}" for k in range(m)) + "    mean")
    means = {name: np.mean(v, axis=0) for name, v in frame_psnr.items()}
    for name, v in means.items():
        print(f"{name:5s} frame   " + " ".join(f"{x:6.2f}" for x in v) + f"  {v.mean():6.2f}")
    gain = means["trmd"] - means["edi"]
    print("gain          " + " ".join(f"{x:+6.2f}" for x in gain) + f"  {gain.mean():+6.2f}")
    for name, e in res_err.items():
        r = [10 * np.log10(pixels / e[k]) if k != n else float("nan") for k in range(m)]
        print(f"{name:5s} resid.  " + " ".join(f"{x:6.2f}" for x in r))


if __name__ == "__main__":
    main()
