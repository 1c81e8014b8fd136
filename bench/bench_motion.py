"""Time and quality of `--method motion` and `--method fused` on 346×260 simulated frames
(fixed seed).

    python bench/bench_motion.py [FRAMES] [REPEATS] [--no-helper]

Per frame: motion estimation (contrast maximisation), deconvolution (from and anchored to
EDI's middle frame, as the method runs it), the whole method (EDI's contrast and frames, motion,
deconvolution, guard); the fused method (TRMD, the motion method and the fusion network, with
the shipped weights; skipped when none ship); each the fastest of REPEATS runs (default 3; the
machine is shared). PSNR of the middle frame against the ground truth for the blurry frame, EDI
at the true c, motion and fused at the true c, and the motion estimate's mean end-point error
against the simulator's camera path (pixels). The C heap is tuned as `trmd` tunes it
(:mod:`trmd_cli.heap`). ``--no-helper``: the motion method without its helper process
(:mod:`trmd_cli.helper_process`; the same frames), to time one against the other.
"""

from __future__ import annotations

import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

from trmd_cli.deconv import deconvolve
from trmd_cli.edi import hot_pixel_mask
from trmd_cli.heap import tune_memory
from trmd_cli.methods import EdiMethod, FusedMethod, MethodConfig, MotionMethod, unavailable
from trmd_cli.metrics import psnr
from trmd_cli.motion import SampledMotion, estimate_motion
from trmd_cli.read.frames import read_image
from trmd_cli.simulate import MotionRanges, make_sample, to_gray

SOURCE = Path(__file__).resolve().parents[2] / "shared/data/images/skimage/camera.png"


def _fastest(fn, repeats: int):
    """(result, seconds) of the fastest of ``repeats`` calls of ``fn``."""
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def main(frames: int = 3, repeats: int = 3) -> None:
    tune_memory()  # as `trmd` does when it starts: temporaries reuse the heap's pages
    img = to_gray(read_image(SOURCE))
    motion = MotionRanges(translation_px=20, rotation_deg=1, scale=0.02, perspective=0,
                          curvature=0.3)
    rows = []
    with_fused = unavailable(MethodConfig("fused")) is None
    for seed in range(frames):
        s = make_sample(img, rng=np.random.default_rng(100 + seed), motion=motion,
                        read_noise=0.005)
        edi = EdiMethod(contrast=s.contrast)(s.blurry, s.events, s.exposure)
        hot = hot_pixel_mask(s.events, s.exposure)
        m, t_cmax = _fastest(partial(estimate_motion, s.events, s.exposure, hot), repeats)
        prep = EdiMethod(contrast=s.contrast).prepare(s.blurry, s.events, s.exposure)
        start = prep.model.latent(s.blurry, np.array([0.5]), prep.contrast)[0]
        _, t_dec = _fastest(partial(deconvolve, s.blurry, m, start=start, anchor=start),
                            repeats)
        mot, t_all = _fastest(partial(MotionMethod(contrast=s.contrast), s.blurry, s.events,
                                      s.exposure), repeats)
        h, w = s.blurry.shape[:2]
        epe = m.end_point_error_px(SampledMotion(s.motion, centre=m.centre), w, h)
        gt = s.sharp[3]
        p_fu, t_fu = np.nan, np.nan
        if with_fused:
            fu, t_fu = _fastest(partial(FusedMethod(3, contrast=s.contrast), s.blurry,
                                        s.events, s.exposure), repeats)
            p_fu = psnr(np.clip(fu.frames[3], 0, 1), gt)
        rows.append((psnr(s.blurry, gt), psnr(edi.frames[3], gt), psnr(mot.frames[3], gt), epe,
                     t_cmax, t_dec, t_all, p_fu, t_fu))
        r = rows[-1]
        print(f"seed {100 + seed}: blurry {r[0]:.2f}  EDI {r[1]:.2f}  motion {r[2]:.2f}  fused "
              f"{r[7]:.2f} dB  EPE {r[3]:.3f} px   cmax {r[4]:.2f} s  deconv {r[5]:.2f} s  "
              f"motion total {r[6]:.2f} s  fused total {r[8]:.2f} s", flush=True)
    a = np.mean(rows, axis=0)
    print(f"mean: blurry {a[0]:.2f}  EDI {a[1]:.2f}  motion {a[2]:.2f}  fused {a[7]:.2f} dB  "
          f"EPE {a[3]:.3f} px   cmax {a[4]:.2f} s  deconv {a[5]:.2f} s  motion {a[6]:.2f} s  "
          f"fused {a[8]:.2f} s per 346×260 frame")


if __name__ == "__main__":
    if "--no-helper" in sys.argv:
        from trmd_cli.helper_process import allow

        allow(False)
    main(*(int(v) for v in sys.argv[1:] if not v.startswith("--")))
