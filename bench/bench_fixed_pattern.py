"""The sensor's fixed pattern kept and removed, on simulated camera pans with a known one.

    python bench/bench_fixed_pattern.py [--methods edi-true-c,edi,trmd,motion,fused]

Each pan is 8 consecutive exposures of one camera path (`trmd_cli.simulate.make_sequence`,
read noise 0.003) with a pattern added to every blurry frame: σ = 0.012 per pixel and 0.006
per column (about esl-cups'). The pans: the project's `examples/sharp.png` at 160×120, and
kodim05 and kodim15 of ../shared/data/images/kodak24 at 346×260 when that folder is beside the
repository. Every method is scored by `trmd_cli.evaluate` against the simulator's sharp frames
with the pattern kept and removed: PSNR middle / sequence, dB.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KODAK = ROOT.parent / "shared" / "data" / "images" / "kodak24"


def pans() -> list[tuple[str, Path, tuple[int, int], int]]:
    """(name, image, size, seed) of every pan this machine has the image of."""
    out = [("example", ROOT / "examples" / "sharp.png", (160, 120), 1)]
    for name, seed in (("kodim05", 1), ("kodim15", 2)):
        if (KODAK / f"{name}.png").is_file():
            out.append((name, KODAK / f"{name}.png", (346, 260), seed))
    return out


def write_pan(path: Path, image: Path, size: tuple[int, int], seed: int) -> Path:
    """The pan as a trmd HDF5 file with its sharp frames and true c."""
    from trmd_cli.read.frames import read_image
    from trmd_cli.simulate import aps_pattern, make_sequence, to_gray
    from trmd_cli.write import H5Writer

    w, h = size
    seq = make_sequence(to_gray(read_image(image)), frames=8, size=size,
                        rng=np.random.default_rng(seed), read_noise=0.003)
    pattern = aps_pattern(np.random.default_rng(99), w, h)
    with H5Writer(path, w, h) as writer:
        writer.add_events(seq.events)
        for blurry, exposure, sharp in zip(seq.blurry, seq.exposures, seq.sharp, strict=True):
            writer.add_frame(np.clip(blurry + pattern, 0, 1), exposure, sharp=sharp,
                             contrast=seq.contrast)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default="edi-true-c,edi,trmd,motion,fused")
    args = ap.parse_args()
    from trmd_cli.evaluate import evaluate

    with tempfile.TemporaryDirectory() as tmp:
        for name, image, size, seed in pans():
            h5 = write_pan(Path(tmp) / f"{name}.h5", image, size, seed)
            rows = {}
            for removed in (False, True):
                report = evaluate([h5], args.methods, fixed_pattern=removed, lpips=False)
                for m in report.datasets[0].methods:
                    rows.setdefault(m.method, []).append((m.mean("psnr_mid"),
                                                        m.mean("psnr_seq")))
            print(f"{name} ({size[0]}x{size[1]}), PSNR middle / sequence, kept -> removed:")
            for method, ((a, b), (c, d)) in rows.items():
                print(f"  {method:12s} {a:.2f} / {b:.2f} -> {c:.2f} / {d:.2f}")


if __name__ == "__main__":
    main()
