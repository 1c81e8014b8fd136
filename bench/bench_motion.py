"""Time and quality of `--method motion` on 346×260 simulated frames (fixed seed).

    python bench/bench_motion.py [FRAMES]

Per frame: motion estimation (contrast maximisation), deconvolution, total; PSNR of the middle
frame against the ground truth for the blurry frame, EDI at the true c, and motion at the true c.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from trmd_cli.deconv import deconvolve
from trmd_cli.edi import hot_pixel_mask
from trmd_cli.methods import EdiMethod, MotionMethod
from trmd_cli.metrics import psnr
from trmd_cli.motion import estimate_motion
from trmd_cli.read.frames import read_image
from trmd_cli.simulate import MotionRanges, make_sample, to_gray

SOURCE = Path(__file__).resolve().parents[2] / "shared/data/images/skimage/camera.png"


def main(frames: int = 3) -> None:
    img = to_gray(read_image(SOURCE))
    motion = MotionRanges(translation_px=20, rotation_deg=1, scale=0.02, perspective=0,
                          curvature=0.3)
    rows = []
    for seed in range(frames):
        s = make_sample(img, rng=np.random.default_rng(100 + seed), motion=motion,
                        read_noise=0.005)
        t0 = time.perf_counter()
        m = estimate_motion(s.events, s.exposure, hot_pixel_mask(s.events, s.exposure))
        t1 = time.perf_counter()
        deconvolve(s.blurry, m)
        t2 = time.perf_counter()
        mot = MotionMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
        t3 = time.perf_counter()
        edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
        gt = s.sharp[3]
        rows.append((psnr(s.blurry, gt), psnr(edi.frames[3], gt), psnr(mot.frames[3], gt),
                     t1 - t0, t2 - t1, t3 - t2))
        print(f"seed {100 + seed}: blurry {rows[-1][0]:.2f}  EDI {rows[-1][1]:.2f}  "
              f"motion {rows[-1][2]:.2f} dB   cmax {rows[-1][3]:.2f} s  deconv "
              f"{rows[-1][4]:.2f} s  method total {rows[-1][5]:.2f} s")
    a = np.mean(rows, axis=0)
    print(f"mean: blurry {a[0]:.2f}  EDI {a[1]:.2f}  motion {a[2]:.2f} dB   cmax {a[3]:.2f} s  "
          f"deconv {a[4]:.2f} s  total {a[5]:.2f} s per 346×260 frame")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
