"""Make docs/images/fixed_pattern.png: the sensor's fixed pattern, found and removed.

    python docs/make_pattern_figure.py            # writes docs/images/fixed_pattern.png
    python docs/make_pattern_figure.py -o X.png   # elsewhere

Only simulated data: the CC0 "camera" photograph of scikit-image (Lav Varshney; read from
../shared/data/images/skimage/camera.png beside the repository, else a synthetic texture),
8 consecutive exposures of one camera path (`trmd_cli.simulate.make_sequence`), with a fixed
pattern added to every blurry frame (σ = 0.012 per pixel, 0.006 per column: the size of
esl-cups'). Top row, for exposure 3: the blurry frame with the pattern, EDI and the motion
method on it as recorded (`--keep-pattern`), and with the pattern removed. Bottom row: the
ground truth, the pattern added and the one estimated from the 8 frames (both ×10 around
grey), and what is left of it after the removal (×10). PSNR of the middle frames against the
truth is printed under each.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
PHOTO = HERE.parents[1] / "shared" / "data" / "images" / "skimage" / "camera.png"
SIZE = (160, 120)
FRAME = 3


def _image() -> np.ndarray:
    from trmd_cli.read.frames import read_image

    if PHOTO.is_file():
        return read_image(PHOTO)
    import cv2

    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.random((300, 400)).astype(np.float32), (0, 0), 2.0)
    return (tex - tex.min()) / np.ptp(tex)


def make_figure() -> tuple[np.ndarray, dict[str, float]]:
    """The figure (uint8 RGB) and the middle frames' PSNR (dB) by panel."""
    from trmd_cli.fixed_pattern import estimate_fixed_pattern
    from trmd_cli.methods import EdiMethod, MotionMethod
    from trmd_cli.metrics import psnr
    from trmd_cli.simulate import aps_pattern, make_sequence
    from trmd_cli.viz import strip

    w, h = SIZE
    seq = make_sequence(_image(), frames=8, size=SIZE, rng=np.random.default_rng(1),
                        read_noise=0.003)
    added = aps_pattern(np.random.default_rng(99), w, h)
    frames = [np.clip(b + added, 0, 1) for b in seq.blurry]
    pattern = estimate_fixed_pattern(frames, [str(k) for k in range(len(frames))])
    c, e = seq.contrast, seq.exposures[FRAME]
    truth = seq.sharp[FRAME][3]
    b = frames[FRAME]
    panels = {"blurry": b}
    for tag, method in (("EDI", EdiMethod(3, c)), ("motion", MotionMethod(3, c))):
        panels[f"{tag}, pattern kept"] = method(b, seq.events, e).frames[3]
        panels[f"{tag}, pattern removed"] = method.for_pattern(pattern)(b, seq.events, e).frames[3]
    inner = (slice(8, h - 8), slice(8, w - 8))
    scores = {k: psnr(np.clip(v, 0, 1)[inner], truth[inner]) for k, v in panels.items()}

    def grey(x):
        return np.clip(0.5 + 10 * x, 0, 1)

    top = strip(list(panels.values()), [f"{k} {scores[k]:.1f} dB" for k in panels])
    bottom = strip([truth, grey(added), grey(pattern.offsets), grey(added - pattern.offsets)],
                   ["ground truth", "pattern added x10", "estimated x10", "left x10"])
    pad = np.full((bottom.shape[0], top.shape[1] - bottom.shape[1], 3), 255, np.uint8)
    return np.concatenate([top, np.concatenate([bottom, pad], axis=1)], axis=0), scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=HERE / "images" / "fixed_pattern.png")
    args = ap.parse_args()
    from trmd_cli.write import write_image

    fig, scores = make_figure()
    write_image(args.output, fig)
    print(f"wrote {args.output}: " + ", ".join(f"{k} {v:.2f} dB" for k, v in scores.items()))


if __name__ == "__main__":
    main()
