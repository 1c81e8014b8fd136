"""The fused method where the camera stands still, and on binned events: simulated Kodak frames.

    python bench/bench_still_camera.py [--fusion-weights FILE]

Six Kodak images (../shared/data/images) at 240×180 through the simulator's DAVIS-like sensor
(threshold mismatch σ = c/10, read noise 0.005 on B), one foreground layer moving up to 30 px
on its own over each exposure, each run through ``EdiMethod``, ``TrmdMethod``,
``MotionMethod`` and ``FusedMethod`` as ``trmd deblur`` runs them (c settled per frame):

* **tripod**: the camera shakes by at most 0.3 px (c = 0.2 and 0.75), events with their
  times. The motion method finds no global motion, or only the mover's, and falls back to
  EDI (at c = 0.75 the fused method uses its network only where it fell back).
* **binned**: the camera moves up to 4 px (c = 0.2) or 15 px (c = 0.75) and the events are
  given as 18 bins per exposure (and each frame's mirror image, 12 frames): no event times,
  so the fused method reads EDI's frames in the motion method's place.

Printed: PSNR against the simulator's sharp frames at each of the 2N+1 instants (mean over
the frames), and the mean over all of them. ``--fusion-weights``: the fusion network to use
instead of the shipped one (to compare two).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.helpers.bins import binned_frames  # noqa: E402

from trmd_cli.methods import EdiMethod, FusedMethod, MotionMethod, TrmdMethod  # noqa: E402
from trmd_cli.metrics import psnr  # noqa: E402
from trmd_cli.read.frames import read_image  # noqa: E402
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample, to_gray  # noqa: E402

IMAGES = Path(__file__).resolve().parents[2] / "shared" / "data" / "images"


def samples(contrast: float, camera_px: float, count: int = 6):
    """``count`` simulated exposures (240×180, N = 3) with one layer moving on its own."""
    motion = MotionRanges(translation_px=camera_px, rotation_deg=0.5 if camera_px > 1 else 0.0,
                          scale=0.01 if camera_px > 1 else 0.0, perspective=0,
                          foreground_prob=1.0, max_layers=1, layer_translation_px=30.0)
    sensor = replace(SensorConfig().with_contrast(contrast), contrast_sigma=0.1 * contrast)
    for k, path in enumerate(sorted(IMAGES.rglob("kodim*.png"))[:count]):
        yield make_sample(to_gray(read_image(path)), size=(240, 180),
                          rng=np.random.default_rng(900 + k), sensor=sensor, motion=motion,
                          read_noise=0.005)


def report(title: str, rows: dict[str, list[list[float]]]) -> None:
    print(title)
    for name, per in rows.items():
        a = np.array(per)
        print(f"  {name:7s} " + " ".join(f"{v:5.2f}" for v in a.mean(0))
              + f"   all {a.mean():.2f}   ({len(a)} frames)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fusion-weights", type=Path, default=None)
    args = ap.parse_args()
    if not IMAGES.is_dir():
        sys.exit(f"no images at {IMAGES}")
    fused = FusedMethod(3, fusion_weights=args.fusion_weights)
    methods = {"edi": EdiMethod(3), "trmd": TrmdMethod(3),
               "motion": MotionMethod(3), "fused": fused}
    for c in (0.2, 0.75):
        rows: dict[str, list[list[float]]] = {m: [] for m in methods}
        for s in samples(c, 0.3):
            for name, m in methods.items():
                est = m(s.blurry, s.events, s.exposure)
                rows[name].append([psnr(np.clip(a, 0, 1), b)
                                   for a, b in zip(est.frames, s.sharp)])
        report(f"tripod, c = {c}, PSNR at instants 0…6 (dB):", rows)
    for c, camera in ((0.2, 4.0), (0.75, 15.0)):
        rows = {m: [] for m in ("edi", "trmd", "fused")}
        for s in samples(c, camera):
            for f in binned_frames(s, 18):
                for name in rows:
                    est = methods[name].from_bins(f.blurry, f.bins)
                    rows[name].append([psnr(np.clip(a, 0, 1), b)
                                       for a, b in zip(est.frames, f.sharp)])
        report(f"binned (18 bins), c = {c}, camera up to {camera:g} px:", rows)


if __name__ == "__main__":
    main()
