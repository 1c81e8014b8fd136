"""Build the pinned validation set the shipped weights are judged on.

24 Kodak images (never used for training) × 2 samples, 346×260, the simulator's default
DAVIS-like sensor (``SensorConfig()``) and default motion (``MotionRanges()``), 20 ms exposures,
seed 2024. The figures in weights_recipe/README.md mean the same thing every time this is run:
the output is identical for the same trmd version.

    python weights_recipe/make_valset.py [KODAK_DIR] -o ../runs/valset_kodak24.h5 [--with-motion]

``--with-motion`` also stores each sample's true camera path (``frames/motion``), so that
``trmd eval … --methods motion,motion-true-path`` can score the motion method against its
oracle; the events, frames and ground truth are the same, but the file (and its SHA-256, by
which the shipped weights name their validation set) is not.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from trmd_cli.read.frames import read_image
from trmd_cli.simulate import DEFAULT_EXPOSURE_US, MotionRanges, SensorConfig, make_sample
from trmd_cli.write import H5Writer

SEED = 2024
SIZE = (346, 260)
PER_IMAGE = 2
GAP_US = 5_000
DEFAULT_KODAK = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "kodak24"


def build(kodak: Path, out: Path, n: int = 3, per_image: int = PER_IMAGE,
          with_motion: bool = False) -> Path:
    paths = sorted(p for p in kodak.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not paths:
        raise SystemExit(f"no images in {kodak}")
    rng = np.random.default_rng(SEED)
    t0 = 0
    attrs = {"valset": "kodak24", "seed": SEED, "n": n, "per_image": per_image,
             "sensor": "SensorConfig() defaults", "motion": "MotionRanges() defaults"}
    with H5Writer(out, *SIZE, compression="gzip", attrs=attrs) as w:
        for path in paths:
            image = read_image(path)
            for _ in range(per_image):
                s = make_sample(image, n=n, size=SIZE, exposure_us=DEFAULT_EXPOSURE_US, rng=rng,
                                sensor=SensorConfig(), motion=MotionRanges())
                ev = s.events
                shifted = type(ev)(ev.x, ev.y, ev.t + t0, ev.p, ev.width, ev.height)
                w.add_events(shifted)
                w.add_frame(s.blurry, s.exposure.shifted(t0), sharp=s.sharp, contrast=s.contrast,
                            motion=s.motion if with_motion else None)
                t0 += s.exposure.duration_us + GAP_US
            print(f"{path.name}: done", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kodak", nargs="?", type=Path, default=DEFAULT_KODAK)
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--n", type=int, default=3)
    ap.add_argument("--with-motion", action="store_true",
                    help="also store the true camera paths (for motion-true-path)")
    args = ap.parse_args()
    build(args.kodak, args.output, args.n, with_motion=args.with_motion)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
