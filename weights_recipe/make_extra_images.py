"""Source images for an extra training set of new content, none of it Kodak.

Tried in an A/B run (docs/experiments.md, "new content"); not in the shipped weights.

- 140 synthetic **dead-leaves** images (768×512): occluding disks with power-law radii
  (r^-3, 3–300 px, the scale-invariant choice), each flat, striped or shaded, in random colours,
  slightly blurred. Unlimited and licence-free content with edges at every scale and contrast.
- every 12th frame of the five ``shared/data/images/sam2-videos`` clips (1280×720, 120
  frames): scenes the other sets never saw.

They land in ``OUT/wikimedia/`` so that ``make_trainset.py OUT`` picks them up as stills:

    python weights_recipe/make_extra_images.py ../runs/extra_root
    python weights_recipe/make_trainset.py ../runs/extra_root -o ../runs/train_128_extra.h5 \\
        --count 6000 --seed 5 --workers 2 --exposure-ms 10 40 --gain 0.6 1.0 --read-noise 0 0.005
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

VIDEOS = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "sam2-videos"


def dead_leaves(rng: np.random.Generator, h: int = 512, w: int = 768, rmin: float = 3.0,
                rmax: float = 300.0, alpha: float = 3.0, max_disks: int = 200_000) -> np.ndarray:
    """(h, w, 3) float32 in [0, 1]. Disks are laid front to back (each only fills what is still
    empty) until 99.9 % of the canvas is covered."""
    img = np.zeros((h, w, 3), np.float32)
    filled = np.zeros((h, w), bool)
    yy, xx = np.mgrid[0:h, 0:w]
    a1 = 1.0 - alpha  # inverse CDF of a power law r^-alpha on [rmin, rmax]
    radii = (rmin ** a1 + rng.random(max_disks) * (rmax ** a1 - rmin ** a1)) ** (1.0 / a1)
    for i, r in enumerate(radii):
        cx, cy = rng.uniform(-r, w + r), rng.uniform(-r, h + r)
        x0, x1 = int(max(cx - r, 0)), int(min(cx + r + 1, w))
        y0, y1 = int(max(cy - r, 0)), int(min(cy + r + 1, h))
        if x0 >= x1 or y0 >= y1:
            continue
        X, Y = xx[y0:y1, x0:x1], yy[y0:y1, x0:x1]
        inside = ((X - cx) ** 2 + (Y - cy) ** 2 <= r * r) & ~filled[y0:y1, x0:x1]
        if not inside.any():
            continue
        colour = np.clip(rng.uniform(0.03, 1.0) ** 1.5 * (1 + 0.25 * rng.standard_normal(3)),
                         0, 1)
        patch = np.broadcast_to(colour, (y1 - y0, x1 - x0, 3)).copy()
        kind = rng.integers(0, 3)
        if kind == 1:  # stripes
            f, th = rng.uniform(0.05, 0.6), rng.uniform(0, np.pi)
            patch *= (1 + rng.uniform(0.1, 0.5) * np.sin(f * (np.cos(th) * X + np.sin(th) * Y))
                      )[..., None]
        elif kind == 2:  # shading
            g = (X - cx) * rng.normal() + (Y - cy) * rng.normal()
            patch *= np.clip(1 + 0.5 * g / max(r, 1.0), 0.2, 2.0)[..., None]
        img[y0:y1, x0:x1][inside] = patch[inside]
        filled[y0:y1, x0:x1] |= inside
        if i % 500 == 0 and filled.mean() > 0.999:
            break
    return np.clip(cv2.GaussianBlur(img, (0, 0), 0.7), 0, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--dead-leaves", type=int, default=140)
    ap.add_argument("--every", type=int, default=12, help="video frame step")
    args = ap.parse_args()
    out = args.out / "wikimedia"
    out.mkdir(parents=True, exist_ok=True)
    for i in range(args.dead_leaves):
        group, k = 1 + i // 70, i % 70  # the seeds of the images the A/B run used
        im = dead_leaves(np.random.default_rng(group * 100003 + k))
        cv2.imwrite(str(out / f"dl_{group}_{k:04d}.png"),
                    (im[..., ::-1] * 255 + 0.5).astype(np.uint8))
    frames = 0
    for video in sorted(VIDEOS.glob("*.mp4")):
        cap = cv2.VideoCapture(str(video))
        k = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            if k % args.every == 0:
                cv2.imwrite(str(out / f"v_{video.stem}_{k:04d}.png"), frame)
                frames += 1
            k += 1
    print(f"{args.dead_leaves} dead-leaves images and {frames} video frames in {out}")


if __name__ == "__main__":
    main()
