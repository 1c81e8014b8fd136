"""The motion method where something moves on its own: the background's motion and the events' test.

    python bench/bench_mover_guard.py [SAMPLES]

The samples of ``bench_oracle_movers.py`` (Kodak, noise-free sensor, c = 0.2 exactly, a moving
camera and one foreground layer moving on its own). Over the exposure the events give each
pixel's change of log intensity, ``c · S(1)``; a deconvolution along a motion predicts it,
``log L(1) − log L(0)`` of its frames carried to the exposure's ends. Where the two disagree
the motion does not hold and EDI is kept. The middle frame's PSNR on the interior, in dB, from:

* EDI given the true c;
* ``--method motion`` (global motion from the events, the guard; where tiles dispute that
  motion (``motion.tiles.disputed_tiles``) or it explains under half the frame, the
  background's motion from the tiles that move together, kept where it predicts the events:
  ``deconv.change_agreement``, the local RMS of the difference within one threshold);
* ``motion-true-path`` (the camera's true path through the same method);
* the background's motion (``motion.tiles.background_motion``) with the signed test instead:
  the difference smoothed by the same σ = 4 px Gaussian, within 0.06 (log units);
* the background's motion with the RMS test (what the method does on those frames);
* the camera's true path with the RMS test alone (no global gain, no half-frame rule).

Then each sample's largest displacement of the camera's path, of the global estimate and of
the background's motion, to see which one an estimate followed, and the seconds
``--method motion`` took (run the script alone: the figure is the machine's; the method runs
once untimed first, so the first frame does not carry the process's start-up; the C heap is
tuned as `trmd` tunes it, :mod:`trmd_cli.heap`).
"""

from __future__ import annotations

import sys
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_oracle_movers import IMAGES, simulate  # noqa: E402

from trmd_cli.deconv import (  # noqa: E402
    DeconvConfig,
    change_agreement,
    change_of_log,
    deconvolve,
    explained,
    noise_level,
    predicted_change,
)
from trmd_cli.heap import tune_memory  # noqa: E402
from trmd_cli.methods import EdiMethod, MotionMethod  # noqa: E402
from trmd_cli.metrics import psnr  # noqa: E402
from trmd_cli.motion import estimate_motion  # noqa: E402
from trmd_cli.motion.tiles import background_motion  # noqa: E402
from trmd_cli.oracle import TruePathMethod  # noqa: E402
from trmd_cli.read.frames import read_image  # noqa: E402
from trmd_cli.simulate import to_gray  # noqa: E402

C = 0.2


def signed_test(solved, *, change: np.ndarray, sigma: float = 4.0, tau: float = 0.06
                ) -> np.ndarray:
    """(H, W) in [0, 1]: the difference of the predicted and measured changes smoothed by a
    σ = ``sigma`` Gaussian, rejected beyond ``tau`` (the rejection spread the same way)."""
    miss = np.abs(cv2.GaussianBlur((predicted_change(solved) - change).astype(np.float32),
                                   (0, 0), sigma))
    rejected = cv2.GaussianBlur((miss > tau).astype(np.float32), (0, 0), sigma)
    return (1.0 - np.clip(2.0 * rejected, 0.0, 1.0)).astype(np.float32)


def blend(blurry, edi, cfg, motion, test) -> np.ndarray:
    """The middle frame deconvolved along ``motion`` where ``test`` and re-blurring keep it,
    EDI's elsewhere (EDI's alone when there is no motion)."""
    if motion is None:
        return edi
    d = deconvolve(blurry, motion, cfg, start=edi, anchor=edi)
    wgt = test(d) * explained(d.data_weight)
    return wgt * d.frames([0.5])[0] + (1.0 - wgt) * edi


def main(samples: int = 8) -> None:
    names = ["EDI (true c)", "motion", "motion-true-path", "background, signed test",
             "background, RMS test", "true path, RMS test"]
    rows, seconds = [], []
    tune_memory()  # as `trmd` does when it starts: temporaries reuse the heap's pages
    for k, path in enumerate(sorted(IMAGES.rglob("kodim*.png"))[:samples]):
        blurry, gt, ev, ex, camera, _, _ = simulate(to_gray(read_image(path)), 400 + k)
        if k == 0:
            # once untimed: the process's first call pays for imports and thread pools
            # (≈ 1 s, which the first frame's time showed before)
            MotionMethod(contrast=C)(blurry, ev, ex)
        h, w = gt.shape
        inner = (slice(16, h - 16), slice(16, w - 16))
        edi = EdiMethod(contrast=C)(blurry, ev, ex).frames[3]
        change = change_of_log(ev, ex, w, h, C)
        cfg = DeconvConfig().for_contrast(C).for_noise(noise_level(blurry))

        background = background_motion(ev, ex)
        t0 = time.perf_counter()
        shipped = MotionMethod(contrast=C)(blurry, ev, ex).frames[3]
        seconds.append(time.perf_counter() - t0)
        frames = [edi, shipped,
                  TruePathMethod(motion=camera, contrast=C)(blurry, ev, ex).frames[3],
                  blend(blurry, edi, cfg, background, partial(signed_test, change=change)),
                  blend(blurry, edi, cfg, background, partial(change_agreement, change=change,
                                                              contrast=C)),
                  blend(blurry, edi, cfg, camera, partial(change_agreement, change=change,
                                                          contrast=C))]
        rows.append([psnr(f[inner], gt[inner]) for f in frames])
        moved = [m.max_displacement_px(w, h) if m is not None else float("nan")
                 for m in (camera, estimate_motion(ev, ex), background)]
        print(f"{path.name}: " + ", ".join(f"{n} {v:.2f}" for n, v in zip(names, rows[-1],
                                                                          strict=True))
              + "; largest displacement (px): camera {:.1f}, global estimate {:.1f}, "
              "background {:.1f}".format(*moved) + f"; motion took {seconds[-1]:.2f} s",
              flush=True)
    print("mean, dB: " + ", ".join(f"{n} {v:.2f}" for n, v in zip(names, np.mean(rows, axis=0),
                                                                   strict=True))
          + f"; motion {np.median(seconds):.2f} s per frame (median)")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 8)
