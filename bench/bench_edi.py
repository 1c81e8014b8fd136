"""EDI speed and auto-contrast accuracy.

    python bench/bench_edi.py            # speed: 346×260 frame, 100k events, auto-c included
    python bench/bench_edi.py --quality  # + auto-c vs true-c PSNR on simulated frames

Speed target (issue): ≤ 0.2 s per frame on 2 CPU cores, contrast estimation included.
Quality target: the frame EDI makes with the estimated c within 0.5 dB (mean) of the one made
with the true c.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
IMAGES = ["skimage/camera.png", "skimage/coffee.png", "skimage/astronaut.png",
          "skimage/brick.png", "wikimedia/013.png", "wikimedia/025.png", "wikimedia/039.png",
          "wikimedia/001.png"]


def load(name: str) -> np.ndarray:
    from trmd_cli.read.frames import read_image

    path = SHARED / "images" / name
    if path.exists():
        return read_image(path)
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    import cv2

    img = cv2.GaussianBlur(rng.uniform(0, 1, (400, 520)).astype(np.float32), (0, 0), 4)
    return (img - img.min()) / (np.ptp(img) + 1e-6)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - b) ** 2)))


def speed(repeats: int) -> None:
    import cv2

    from trmd_cli.edi import EdiEvents, hot_pixel_mask
    from trmd_cli.events import EventStream
    from trmd_cli.simulate import SensorConfig, make_sample
    from trmd_cli.threshold import search_contrast

    cv2.setNumThreads(2)
    s = make_sample(load(IMAGES[0]), rng=np.random.default_rng(0), sensor=SensorConfig())
    ev = s.events
    rng = np.random.default_rng(1)
    if len(ev) > 100_000:  # exactly 100k events, still sorted and spread over the exposure
        keep = np.sort(rng.choice(len(ev), 100_000, replace=False))
        ev = ev.take(keep)
    elif len(ev) < 100_000:
        extra = 100_000 - len(ev)
        t = np.sort(rng.integers(s.exposure.start_us, s.exposure.end_us, extra))
        pad = EventStream(rng.integers(0, 346, extra).astype(np.uint16),
                          rng.integers(0, 260, extra).astype(np.uint16), t,
                          rng.choice([-1, 1], extra).astype(np.int8), 346, 260)
        merged = EventStream.concatenate([ev, pad])
        ev = merged.take(np.argsort(merged.t, kind="stable"))
    inst = s.exposure.instants_us(3)
    fr = (inst - s.exposure.start_us) / s.exposure.duration_us
    stages = {"hot pixels": [], "sort/prepare": [], "auto contrast": [], "7 latent frames": [],
              "total": []}
    for _ in range(repeats):
        t0 = time.perf_counter()
        hot = hot_pixel_mask(ev, s.exposure)
        t1 = time.perf_counter()
        prep = EdiEvents.build(ev, s.exposure, hot)
        t2 = time.perf_counter()
        est = search_contrast(s.blurry, prep)
        t3 = time.perf_counter()
        prep.latent(s.blurry, fr, est.contrast)
        t4 = time.perf_counter()
        for key, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0), strict=True):
            stages[key].append(dt)
    print(f"EDI on {s.blurry.shape[1]}x{s.blurry.shape[0]}, {len(ev):,} events, "
          f"{repeats} runs ({est.evaluations} energy evaluations per estimate):")
    for key, v in stages.items():
        print(f"  {key:16s} median {1000 * statistics.median(v):7.1f} ms   "
              f"best {1000 * min(v):7.1f} ms")
    print("  target: total ≤ 200 ms on 2 cores")


def quality() -> None:
    from trmd_cli.edi import EdiEvents
    from trmd_cli.simulate import SensorConfig, make_sample
    from trmd_cli.threshold import search_contrast

    rng = np.random.default_rng(7)
    for label, sensors in (("clean", [SensorConfig.clean(c) for c in (0.15, 0.2, 0.3)]),
                           ("DAVIS-like", [SensorConfig()])):
        gaps = []
        for name in IMAGES:
            img = load(name)
            for sensor in sensors:
                s = make_sample(img, rng=rng, sensor=sensor)
                prep = EdiEvents.build(s.events, s.exposure)
                est = search_contrast(s.blurry, prep)

                def mid(c, prep=prep, s=s):
                    return psnr(prep.latent(s.blurry, np.array([0.5]), c)[0], s.sharp[3])

                gaps.append(mid(s.contrast) - mid(est.contrast))
        print(f"auto-c vs true-c, {label} sensor, {len(gaps)} frames: mean loss "
              f"{np.mean(gaps):+.2f} dB, worst {max(gaps):+.2f} dB, "
              f"share within 0.5 dB {np.mean(np.array(gaps) <= 0.5):.0%}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--quality", action="store_true", help="also measure auto-c accuracy")
    args = ap.parse_args()
    speed(args.repeats)
    if args.quality:
        quality()


if __name__ == "__main__":
    main()
