"""What local motion could give on scenes with an independent mover: the exact motions, noise-free.

    python bench/bench_oracle_movers.py [SAMPLES]

Kodak images (../shared/data/images) through the simulator with a noise-free sensor (c = 0.2
exactly) and one foreground layer moving on its own over a moving camera. The middle frame
from: the blurry frame; EDI given the true c; the deconvolution of B along the camera's true
path (anchored to EDI, with B's unexplained pixels down-weighted, as the motion method solves;
no guard): right on the background, wrong on the layer; the same along the layer's own true
path: right on the layer only; the camera path's frame with EDI's on the layer, by the layer's
true mask at mid-exposure (a perfect guard, no local motion); the two paths put together by
that mask (what a perfect local motion and segmentation would reach, up to the occlusion
edges, where neither path explains the blur); the motion method along the camera's true path
as `trmd eval` runs it (the guard falls back to EDI where that path fails); and the motion
method itself (motion estimated from the events). PSNR on the interior (16 px border left out)
and, in brackets, on the layer's pixels alone.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from trmd_cli.deconv import DeconvConfig, deconvolve
from trmd_cli.methods import EdiMethod, MotionMethod
from trmd_cli.metrics import psnr
from trmd_cli.motion import SampledMotion
from trmd_cli.oracle import TruePathMethod
from trmd_cli.read.frames import read_image
from trmd_cli.simulate import MotionRanges, run_exposures, to_gray
from trmd_cli.simulate.blur import grid_blocks
from trmd_cli.simulate.sample import MOTION_SAMPLES, plan_sequence
from trmd_cli.simulate.sensor import EventSensor, SensorConfig

IMAGES = Path(__file__).resolve().parents[2] / "shared" / "data" / "images"
NOISE_FREE = SensorConfig(contrast_on=0.2, contrast_off=0.2, contrast_sigma=0.0,
                          refractory_us=0.0, shot_noise_hz=0.0, leak_hz=0.0,
                          hot_pixel_fraction=0.0)
MOTION = MotionRanges(translation_px=20, rotation_deg=1, scale=0.02, perspective=0,
                      curvature=0.3, foreground_prob=1.0, max_layers=1,
                      layer_translation_px=30.0, layer_size=(0.3, 0.45))
ANCHORED = DeconvConfig(iterations=30).for_contrast(0.2).for_noise(0.0)


def _affine3(a: np.ndarray) -> np.ndarray:
    out = np.zeros((len(a), 3, 3))
    out[:, :2] = a
    out[:, 2, 2] = 1.0
    return out


def simulate(image: np.ndarray, seed: int):
    """(blurry, sharp middle, events, exposure, camera motion, layer motion, layer mask)."""
    plan = plan_sequence(image, n=3, rng=np.random.default_rng(seed), motion=MOTION)
    sensor = EventSensor(NOISE_FREE, 346, 260, plan.sensor_rng)
    events, result = [], None
    for item in run_exposures(grid_blocks(plan.grid_us, plan.scene.render), plan.exposures, 3,
                              sensor, read_noise=0.0, noise_rng=plan.noise_rng):
        if hasattr(item, "blurry"):
            result = item
        else:
            events.append(item)
    from trmd_cli.events import EventStream

    stream = EventStream.concatenate(events)
    scene, e = plan.scene, plan.exposures[0]
    f = np.linspace(0.0, 1.0, MOTION_SAMPLES)
    camera = scene.exposure_motion(e.start_us, e.end_us, f)
    layer = scene.layers[0]
    u = scene._u(np.append(e.start_us + f * e.duration_us, e.mid_us))
    a = _affine3(layer.affines(u))
    # a layer point seen at y in the middle frame is at A(u) · A(mid)⁻¹ · y at time u
    moves = a[:-1] @ np.linalg.inv(a[-1])[None]
    mask = cv2.warpAffine(layer.mask, layer.affines(u[-1:])[0], (346, 260),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return (result.blurry, result.sharp[3], stream, e, SampledMotion(camera),
            SampledMotion(moves), mask)


def main(samples: int = 4) -> None:
    names = ["blurry", "EDI (true c)", "camera path", "layer path", "camera path, EDI on the layer",
             "both, by the mask",
             "motion method on the camera path", "motion method"]
    rows, layer_rows = [], []
    for k, path in enumerate(sorted(IMAGES.rglob("kodim*.png"))[:samples]):
        blurry, gt, ev, ex, camera, moves, mask = simulate(to_gray(read_image(path)), 400 + k)
        edi = EdiMethod(contrast=0.2)(blurry, ev, ex).frames[3]
        # each path anchored to EDI, pixels of B it does not explain down-weighted: the solver
        # the motion method runs, so the misfit of the other layer does not spread
        cam = deconvolve(blurry, camera, ANCHORED, start=edi, anchor=edi).frames([0.5])[0]
        lay = deconvolve(blurry, moves, ANCHORED, start=edi, anchor=edi).frames([0.5])[0]
        both = mask * lay + (1.0 - mask) * cam
        segmented = mask * edi + (1.0 - mask) * cam
        guarded = TruePathMethod(motion=camera, contrast=0.2)(blurry, ev, ex).frames[3]
        estimated = MotionMethod(contrast=0.2)(blurry, ev, ex).frames[3]
        h, w = gt.shape
        inner = (slice(16, h - 16), slice(16, w - 16))
        on_layer = mask[inner] > 0.5
        frames = (blurry, edi, cam, lay, segmented, both, guarded, estimated)
        rows.append([psnr(x[inner], gt[inner]) for x in frames])
        layer_rows.append([psnr(x[inner][on_layer], gt[inner][on_layer]) for x in frames])
        print(f"{path.name} (layer {100 * on_layer.mean():.0f} % of the frame): " + ", ".join(
            f"{n} {v:.2f} ({lv:.2f})" for n, v, lv in zip(names, rows[-1], layer_rows[-1],
                                                        strict=True)), flush=True)
    a, b = np.mean(rows, axis=0), np.mean(layer_rows, axis=0)
    print("mean, dB (on the layer): " + ", ".join(
        f"{n} {v:.2f} ({lv:.2f})" for n, v, lv in zip(names, a, b, strict=True)))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 4)
