"""Build the training set of the fusion network (``trmd_cli.models.fusion``): simulated
346×260 exposures with what the three methods make of them.

Each sample stores the blurry frame, its 2N+1 sharp frames, and at the same instants the frames
of EDI, of the shipped TRMD weights and of the motion method (with its guard's weights), the
events between the middle and each instant, and the c EDI settled — everything the fusion
network reads, computed exactly as ``trmd deblur`` computes it. Sources: the same stills as
``make_trainset.py`` (Kodak is never used). Half the samples use the simulator's default
DAVIS-like sensor and motion over 20 ms, half a sensor, exposure and motion drawn from the
training ranges (foreground layers in a third of those: the network must see the motion's guard
at work).

With ``--still-every K`` every K-th sample is instead a still camera (under 1 px of shake)
with objects moving on their own in most: the scene a camera on a tripod sees, where the
motion method finds no global motion and falls back to EDI. A network that never saw one
smoothed the texture B holds sharp (3 dB below EDI on a still scene, ``tests/test_fusion.py``).
Their sensors alternate between the DAVIS-like default and one drawn with a threshold of up
to 0.8. ``--max-contrast`` raises the largest threshold of the moving cameras' drawn sensors
(0.5 by default, the training ranges').

    python weights_recipe/make_fusionset.py -o ../runs/fusion_346.h5 --count 480 --workers 2
"""

from __future__ import annotations

import argparse
import time
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from make_trainset import DEFAULT_IMAGES, training_images

N = 3
SIZE = (346, 260)
FIELDS = ("truth", "edi", "trmd", "motion", "weight", "events")
#: the still camera's samples: shake under 1 px, objects moving on their own in most
STILL_CAMERA = dict(translation_px=1.0, rotation_deg=0.2, scale=0.005, perspective=0.0,
                    curvature=0.5, foreground_prob=0.85, max_layers=2,
                    layer_translation_px=60.0, layer_size=(0.15, 0.5), margin=0.45)


def _draw(images: list[Path], seed: int, index: int, still_every: int = 0,
          max_contrast: float = 0.5):
    from trmd_cli.read.frames import read_image
    from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample
    from trmd_cli.simulate.dataset import DATASET_MOTION, SensorRanges

    rng = np.random.default_rng([seed, index])
    image = read_image(images[int(rng.integers(len(images)))])
    if still_every and index % still_every == still_every - 1:
        drawn = (index // still_every) % 2 == 1
        sensor = SensorRanges(contrast=(0.1, 0.8)).draw(rng) if drawn else SensorConfig()
        exposure = int(round(rng.uniform(10.0, 60.0) * 1000 / (2 * N))) * 2 * N if drawn \
            else 20_000
        return make_sample(image * np.float32(rng.uniform(0.4, 1.0)), n=N, size=SIZE,
                           exposure_us=exposure, rng=rng, sensor=sensor,
                           motion=MotionRanges(**STILL_CAMERA),
                           read_noise=float(rng.uniform(0.0, 0.01)), zoom=(1.0, 2.0))
    if index % 2 == 0:
        return make_sample(image, n=N, size=SIZE, exposure_us=20_000, rng=rng,
                           sensor=SensorConfig(), motion=MotionRanges())
    gain = float(rng.uniform(0.4, 1.0))
    sensor = SensorRanges(contrast=(0.1, max_contrast)).draw(rng)
    exposure = int(round(rng.uniform(10.0, 60.0) * 1000 / (2 * N))) * 2 * N
    return make_sample(image * np.float32(gain), n=N, size=SIZE, exposure_us=exposure, rng=rng,
                       sensor=sensor, motion=DATASET_MOTION,
                       read_noise=float(rng.uniform(0.0, 0.01)), zoom=(1.0, 2.0))


_STATE: dict = {}


def _init(images: list[Path], seed: int, still_every: int = 0,
          max_contrast: float = 0.5) -> None:
    import torch

    from trmd_cli.methods import MethodConfig, make_method

    torch.set_num_threads(1)
    _STATE.update(images=images, seed=seed, still_every=still_every, max_contrast=max_contrast,
                  trmd=make_method(MethodConfig("trmd", n=N, threads=1)))


def _one(index: int) -> dict[str, np.ndarray]:
    from trmd_cli.fusion import fusion_inputs

    s = _draw(_STATE["images"], _STATE["seed"], index, _STATE["still_every"],
              _STATE["max_contrast"])
    ins = fusion_inputs(s.blurry, s.events, s.exposure, _STATE["trmd"], N)
    out = {k: np.asarray(getattr(ins, k), np.float16) for k in FIELDS if k != "truth"}
    out["truth"] = np.asarray(s.sharp, np.float16)
    out["blurry"] = np.asarray(s.blurry, np.float16)
    out["contrast"] = np.float32(ins.contrast)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", nargs="?", type=Path, default=DEFAULT_IMAGES)
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--count", type=int, default=480)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--still-every", type=int, default=0,
                    help="every K-th sample a still camera with objects moving on their own "
                         "(0: none)")
    ap.add_argument("--max-contrast", type=float, default=0.5,
                    help="largest threshold of the drawn sensors of the moving cameras")
    args = ap.parse_args()
    import h5py

    images = training_images(args.images)
    print(f"{len(images)} source images", flush=True)
    t0 = time.time()
    w, h = SIZE
    k = 2 * N + 1
    part = args.output.with_suffix(".part.h5")
    with h5py.File(part, "w") as f, get_context("spawn").Pool(
            args.workers, _init, (images, args.seed, args.still_every,
                                  args.max_contrast)) as pool:
        ds = {name: f.create_dataset(name, (args.count, k, h, w), np.float16, chunks=(1, k, h, w))
              for name in FIELDS}
        ds["blurry"] = f.create_dataset("blurry", (args.count, h, w), np.float16)
        ds["contrast"] = f.create_dataset("contrast", (args.count,), np.float32)
        f.attrs.update(n=N, seed=args.seed, count=args.count, still_every=args.still_every,
                       max_contrast=args.max_contrast)
        for i, item in enumerate(pool.imap(_one, range(args.count))):
            for name, v in item.items():
                ds[name][i] = v
            if (i + 1) % 40 == 0 or i + 1 == args.count:
                el = time.time() - t0
                print(f"{i + 1}/{args.count} samples, {el / 60:.1f} min", flush=True)
    part.replace(args.output)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
