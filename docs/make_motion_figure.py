"""Make docs/images/motion_example.png: the motion method on one simulated frame.

    python docs/make_motion_figure.py            # writes docs/images/motion_example.png
    python docs/make_motion_figure.py -o X.png   # elsewhere

Only simulated data: the CC0 "camera" photograph of scikit-image (Lav Varshney; read from
../shared/data/images/skimage/camera.png beside the repository, else a synthetic texture),
moved along a random camera path by `trmd_cli.simulate`, clean sensor with c = 0.2. Top row:
the blurry frame, EDI, the motion method, the motion method along the true camera path, the
ground truth (middle frames, PSNR against the truth). Bottom row: what `trmd motion` writes —
the estimated motion's flow (hue = direction, saturation = length, legend = the colour wheel
and its scale), the guard's weight (white: deconvolution, black: EDI) and the events as
recorded and carried to mid-exposure by the estimated motion.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
PHOTO = HERE.parents[1] / "shared" / "data" / "images" / "skimage" / "camera.png"
SIZE = (160, 120)
SEED = 3


def _image() -> tuple[np.ndarray, str]:
    from trmd_cli.read.frames import read_image

    if PHOTO.is_file():
        return read_image(PHOTO), "camera.png (CC0)"
    rng = np.random.default_rng(0)
    import cv2

    tex = cv2.GaussianBlur(rng.random((300, 400)).astype(np.float32), (0, 0), 2.0)
    return (tex - tex.min()) / np.ptp(tex), "synthetic texture"


def make_figure() -> tuple[np.ndarray, dict[str, float]]:
    """The figure (uint8 RGB) and the middle frames' PSNR (dB) by method."""
    from trmd_cli.methods import EdiMethod, MotionMethod
    from trmd_cli.metrics import psnr
    from trmd_cli.motion import SampledMotion
    from trmd_cli.motion_views import motion_views
    from trmd_cli.oracle import TruePathMethod
    from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample
    from trmd_cli.viz import event_picture, flow_picture, strip, to_rgb8, weight_picture

    img, _ = _image()
    s = make_sample(img, n=3, size=SIZE, rng=np.random.default_rng(SEED),
                    motion=MotionRanges(translation_px=24, rotation_deg=2, scale=0.03,
                                        perspective=0.0),
                    sensor=SensorConfig.clean(0.2), read_noise=0.0, zoom=None)
    truth = s.sharp[3]
    mids = {"blurry": s.blurry}
    w, h = SIZE
    true_path = SampledMotion(s.motion, centre=((w - 1) / 2, (h - 1) / 2))
    for name, method in (("EDI", EdiMethod(3)), ("motion", MotionMethod(3)),
                         ("true path", TruePathMethod(3, true_path))):
        mids[name] = method(s.blurry, s.events, s.exposure).frames[3]
    scores = {k: psnr(np.clip(v, 0, 1), truth) for k, v in mids.items()}
    top = strip([*mids.values(), truth],
                [f"{k} {scores[k]:.1f} dB" for k in mids] + ["ground truth"])
    v = motion_views(s.blurry, s.events, s.exposure)
    ev = event_picture([v.events_before, v.events_after], ["events", "compensated"])
    bottom = strip([flow_picture(v.displacement), weight_picture(v.weight), to_rgb8(truth)],
                   ["flow", "guard weight", ""])
    # the bottom row: flow | weight | the two event images (the truth tile only pads)
    bottom = np.concatenate([bottom[:, : 2 * w + 4], np.full((h, 4, 3), 255, np.uint8), ev],
                            axis=1)
    width = max(top.shape[1], bottom.shape[1])
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255)
            for r in (top, bottom)]
    fig = np.concatenate([rows[0], np.full((4, width, 3), 255, np.uint8), rows[1]], axis=0)
    return fig, scores


def main() -> None:
    import cv2

    from trmd_cli.write import write_bytes

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=HERE / "images" / "motion_example.png")
    args = ap.parse_args()
    fig, scores = make_figure()
    # the strongest PNG compression keeps the picture small enough for the repository
    ok, png = cv2.imencode(".png", np.ascontiguousarray(fig[..., ::-1]),
                           [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    write_bytes(args.output, png.tobytes())
    print(f"wrote {args.output} ({args.output.stat().st_size // 1024} KB, source: "
          f"{_image()[1]}): " + ", ".join(f"{k} {v:.2f} dB" for k, v in scores.items()))


if __name__ == "__main__":
    main()
