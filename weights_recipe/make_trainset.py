"""Pre-generate the simulated training set of the shipped weights (so simulation does not
compete with training for the two cores).

Sources: every still under ``shared/data/images`` except ``kodak24`` (held out for validation):
wikimedia, skimage, sklearn, scipy, matplotlib photos, and a subsample of the video frames
(sam2-bedroom every 10th, cutie every 5th, vimeo septuplets' middle frames) used as stills.
Samples follow ``SimulatedDataset``'s default training ranges (sensor noise, thresholds,
motion, exposure, gain, read noise), drawn per sample.

    python weights_recipe/make_trainset.py -o ../runs/train_128.h5 --count 10000 --workers 2
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

DEFAULT_IMAGES = Path(__file__).resolve().parents[2] / "shared" / "data" / "images"
EXT = (".png", ".jpg", ".jpeg")


def training_images(root: Path) -> list[Path]:
    def files(sub: str) -> list[Path]:
        return sorted(p for p in (root / sub).rglob("*") if p.suffix.lower() in EXT)

    out: list[Path] = []
    for sub in ("wikimedia", "skimage", "sklearn", "scipy", "matplotlib"):
        out += files(sub)
    out += files("sam2-bedroom")[::10]
    out += files("cutie")[::5]
    out += [p for p in files("vimeo-septuplets") if p.stem in ("im4", "4")] or \
        files("vimeo-septuplets")[3::7]
    assert not any("kodak" in str(p) for p in out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", nargs="?", type=Path, default=DEFAULT_IMAGES)
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--count", type=int, default=10000)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--motion-px", type=float, default=None,
                    help="largest camera translation per exposure (default: DATASET_MOTION's 70)")
    ap.add_argument("--zoom", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="source pixels per output pixel (default: SimulatedDataset's 1 2)")
    ap.add_argument("--exposure-ms", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="exposure time range (default: SimulatedDataset's 10 100)")
    ap.add_argument("--gain", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="brightness factor range (default: SimulatedDataset's 0.25 1)")
    ap.add_argument("--read-noise", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="σ range of the blurry frame's read noise (default: 0 0.02)")
    ap.add_argument("--sensor-range", nargs=3, action="append", default=[],
                    metavar=("FIELD", "LO", "HI"),
                    help="override one SensorRanges field, e.g. --sensor-range leak_hz 0 0.1")
    args = ap.parse_args()
    from trmd_cli.simulate.pregen import pregenerate

    images = training_images(args.images)
    print(f"{len(images)} source images", flush=True)
    t0 = time.time()

    def progress(done: int, total: int) -> None:
        if done % 200 == 0 or done == total:
            el = time.time() - t0
            print(f"{done}/{total} samples, {done / el:.1f}/s, {el / 60:.1f} min", flush=True)

    extra: dict = {}
    if args.motion_px is not None:
        from dataclasses import asdict, replace

        from trmd_cli.simulate.dataset import DATASET_MOTION

        extra["motion"] = asdict(replace(DATASET_MOTION, translation_px=args.motion_px))
    if args.zoom is not None:
        extra["zoom"] = tuple(args.zoom)
    for name in ("exposure_ms", "gain", "read_noise"):
        if getattr(args, name) is not None:
            extra[name] = tuple(getattr(args, name))
    if args.sensor_range:
        extra["sensor_ranges"] = {f: (float(lo), float(hi)) for f, lo, hi in args.sensor_range}
    pregenerate(images, args.output, args.count, workers=args.workers, compression="gzip",
                progress=progress, crop=args.crop, seed=args.seed, **extra)
    print(f"wrote {args.output} in {(time.time() - t0) / 60:.1f} min")


if __name__ == "__main__":
    main()
