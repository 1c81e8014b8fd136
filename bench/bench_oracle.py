"""The ceiling of motion-aware deblurring: exact camera path, exact c, noise-free events.

    python bench/bench_oracle.py [SAMPLES]

Kodak images (../shared/data/images) through the simulator with a noise-free sensor (c = 0.2
exactly, no threshold mismatch, shot noise, leak or hot pixels; no read noise; camera motion
only), then the middle frame from: the blurry frame, EDI given the true c, the deconvolution
of B along the simulator's own camera path with no guard (``deconv.deconvolve`` with
``SampledMotion``, no anchor, 60 iterations per round), and the motion method along that path
as ``trmd eval`` runs it (``TruePathMethod`` at the true c: the anchored solver's defaults and
the guard against EDI), so the guard's cost on an exact motion is one column. PSNR on the
interior (16 px border left out: what moved into view).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from trmd_cli.deconv import DeconvConfig, deconvolve
from trmd_cli.methods import EdiMethod
from trmd_cli.metrics import psnr
from trmd_cli.motion import SampledMotion
from trmd_cli.oracle import TruePathMethod
from trmd_cli.read.frames import read_image
from trmd_cli.simulate import MotionRanges, make_sample, to_gray
from trmd_cli.simulate.sensor import SensorConfig

IMAGES = Path(__file__).resolve().parents[2] / "shared" / "data" / "images"
NOISE_FREE = SensorConfig(contrast_on=0.2, contrast_off=0.2, contrast_sigma=0.0,
                          refractory_us=0.0, shot_noise_hz=0.0, leak_hz=0.0,
                          hot_pixel_fraction=0.0)
MOTION = MotionRanges(translation_px=20, rotation_deg=1, scale=0.02, perspective=0,
                      curvature=0.3, foreground_prob=0.0)


def main(samples: int = 4) -> None:
    rows = []
    for k, path in enumerate(sorted(IMAGES.rglob("kodim*.png"))[:samples]):
        s = make_sample(to_gray(read_image(path)), rng=np.random.default_rng(200 + k),
                        motion=MOTION, read_noise=0.0, sensor=NOISE_FREE)
        gt = s.sharp[3]
        edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
        t0 = time.perf_counter()
        d = deconvolve(s.blurry, SampledMotion(s.motion),
                       DeconvConfig(penalty=2e-4, rounds=3, iterations=60), start=edi.frames[3])
        took = time.perf_counter() - t0
        mid = d.frames([0.5])[0]
        guarded = TruePathMethod(motion=SampledMotion(s.motion), contrast=s.contrast)(
            s.blurry, s.events, s.exposure).frames[3]
        h, w = gt.shape
        inner = (slice(16, h - 16), slice(16, w - 16))
        rows.append([psnr(x[inner], gt[inner]) for x in (s.blurry, edi.frames[3], mid, guarded)])
        print(f"{path.name}: blurry {rows[-1][0]:.2f}  EDI (true c) {rows[-1][1]:.2f}  "
              f"deconvolution along the true path {rows[-1][2]:.2f} dB  ({took:.1f} s)  "
              f"the guarded method along it {rows[-1][3]:.2f} dB", flush=True)
    a = np.mean(rows, axis=0)
    print(f"mean: blurry {a[0]:.2f}  EDI {a[1]:.2f}  true path {a[2]:.2f} dB  "
          f"(+{a[2] - a[1]:.2f} dB over EDI)  guarded method {a[3]:.2f} dB "
          f"(+{a[3] - a[1]:.2f})")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 4)
