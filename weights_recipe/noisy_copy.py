"""A copy of a trmd HDF5 set whose blurry frames carry more sensor noise.

The pinned set's frames are nearly clean (σ ≈ 0.002); a real APS frame is not (esl-cups
measures σ ≈ 0.01, growing with intensity). This adds Gaussian noise of variance
``read² + shot · B`` to every ``frames/blurry`` (B the stored frame, [0, 1]); the events, the
sharp frames and everything else are copied unchanged, so `trmd eval` on the copy and on the
original differ only in B's noise.

    python weights_recipe/noisy_copy.py valset_motion.h5 -o valset_read10.h5 --read 0.01
    python weights_recipe/noisy_copy.py valset_motion.h5 -o valset_shot.h5 \
        --read 0.0063 --shot 1.2e-4
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import h5py
import numpy as np


def noisy_copy(src: Path, out: Path, read: float, shot: float, seed: int = 0) -> Path:
    """Copy ``src`` to ``out`` with noise of σ² = read² + shot·B added to its blurry frames."""
    if out.exists():
        raise SystemExit(f"{out} exists: choose another name or remove it")
    if not src.is_file():
        raise SystemExit(f"{src}: no such file")
    try:
        with h5py.File(src, "r") as f:
            found = "frames/blurry" in f
    except OSError as e:
        raise SystemExit(f"{src}: not an HDF5 file h5py can read ({e})") from None
    if not found:
        raise SystemExit(f"{src}: no frames/blurry to add noise to")
    tmp = out.with_name(out.name + ".part")
    shutil.copyfile(src, tmp)
    rng = np.random.default_rng(seed)
    with h5py.File(tmp, "r+") as f:
        frames = f["frames/blurry"]
        for k in range(frames.shape[0]):
            b = frames[k].astype(np.float32)
            sigma = np.sqrt(read * read + shot * np.clip(b, 0.0, None))
            frames[k] = b + (sigma * rng.standard_normal(b.shape)).astype(np.float32)
    tmp.replace(out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--read", type=float, default=0.0, help="σ of signal-independent noise")
    ap.add_argument("--shot", type=float, default=0.0,
                    help="variance per unit intensity (shot noise)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    print(f"wrote {noisy_copy(a.src, a.output, a.read, a.shot, a.seed)}")


if __name__ == "__main__":
    main()
