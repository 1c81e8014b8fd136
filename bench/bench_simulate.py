"""Event simulator throughput, training-sample throughput, and realism against a real DAVIS346.

Run: python bench/bench_simulate.py [--samples 40] [--skip-real]

Prints:
1. sensor frames/s at 346×260 (clean and DAVIS-like noise) on a moving natural image;
2. make_sample/s at 346×260 (30 px motion);
3. SimulatedDataset samples/s at 128×128 with the default training ranges, and pregenerate;
4. events per pixel per exposure, share of silent pixels and hot pixels: real esl-cups frames
   (DAVIS346, 104 ms) vs the default sensor on Kodak images with similar blur.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import best_of, machine, peak_rss_mib  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def moving_frames(image: np.ndarray, count: int, w: int = 346, h: int = 260) -> np.ndarray:
    """``count`` frames of ``image`` panned by 0.7 px per frame and slightly rotated."""
    import cv2

    cx, cy = image.shape[1] / 2, image.shape[0] / 2
    out = np.empty((count, h, w), np.float32)
    for k in range(count):
        m = cv2.getRotationMatrix2D((cx, cy), 0.02 * k, 1.0)
        m[0, 2] += 0.7 * k - (cx - w / 2)
        m[1, 2] += -(cy - h / 2)
        out[k] = cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_REFLECT101)
    return out


def bench_sensor(image: np.ndarray) -> None:
    from trmd_cli.simulate import SensorConfig, simulate_events

    frames = moving_frames(image, 200)
    times = np.arange(200, dtype=np.int64) * 500
    print("\n1. sensor, 346×260, 200 frames (0.7 px/frame pan)")
    print(f"   {'config':<10} {'frames/s':>9} {'events':>9} {'Mev/s':>7}")
    for name, cfg in (("clean 0.2", SensorConfig.clean(0.2)), ("DAVIS", SensorConfig())):
        n_ev = len(simulate_events(frames, times, cfg, np.random.default_rng(0)))
        secs = best_of(lambda cfg=cfg: simulate_events(frames, times, cfg,
                                                       np.random.default_rng(0)), 3)
        print(f"   {name:<10} {200 / secs:>9.0f} {n_ev:>9} {n_ev / secs / 1e6:>7.2f}")


def bench_sample(image: np.ndarray, count: int) -> None:
    from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample

    motion = MotionRanges(translation_px=30.0)
    t0 = time.perf_counter()
    events = 0
    for i in range(count):
        s = make_sample(image, rng=np.random.default_rng(i), sensor=SensorConfig(),
                        motion=motion, zoom=None)
        events += len(s.events)
    secs = time.perf_counter() - t0
    print(f"\n2. make_sample 346×260, motion ≤ 30 px: {count / secs:.1f} samples/s "
          f"({events / count / 1000:.0f}k events/sample)")


def bench_dataset(images: list[Path], count: int) -> None:
    from trmd_cli.simulate.dataset import SimulatedDataset, pregenerate

    ds = SimulatedDataset(images, crop=128, length=count, seed=0)
    for i in range(len(images)):  # decode the images once, as a long training run would
        ds.images.get(i)
    t0 = time.perf_counter()
    n_ev = 0
    for i in range(count):
        n_ev += len(ds.sample(i).events)
    secs = time.perf_counter() - t0
    t1 = time.perf_counter()
    for i in range(count):
        _ = ds[i]
    secs_items = time.perf_counter() - t1
    print(f"\n3. SimulatedDataset 128×128, default ranges ({len(images)} images): "
          f"{count / secs:.1f} samples/s raw, {count / secs_items:.1f} items/s with voxels "
          f"({n_ev / count / 1000:.0f}k events/sample)")
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "train.h5"
        t0 = time.perf_counter()
        pregenerate(images, out, count, crop=128, seed=0)
        secs = time.perf_counter() - t0
        print(f"   pregenerate {count} → HDF5: {count / secs:.1f} samples/s, "
              f"{out.stat().st_size / count / 1e6:.2f} MB/sample")


def real_stats() -> list[tuple[float, float, float, int]]:
    import scipy.io as sio

    rows = []
    for mat in sorted((SHARED / "real" / "esl-cups" / "mat").glob("*.mat")):
        m = sio.loadmat(mat)
        x = m["section_event_x"].ravel().astype(np.int64)
        y = m["section_event_y"].ravel().astype(np.int64)
        p = m["section_event_polarity"].ravel()
        rows.append(_stats(x, y, p > 0, 346, 260))
    return rows


def _stats(x, y, on, w, h) -> tuple[float, float, float, int]:
    from scipy.ndimage import uniform_filter

    cnt = np.bincount(y * w + x, minlength=w * h).reshape(h, w).astype(np.float64)
    neighbours = (uniform_filter(cnt, 3, mode="constant") * 9 - cnt) / 8
    hot = int(((cnt >= 8) & (cnt > 6 * np.maximum(neighbours, 1))).sum())
    return float(cnt.mean()), float(np.mean(cnt == 0)), float(np.mean(on)), hot


def bench_realism() -> None:
    from trmd_cli.read import read_image
    from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample

    real = real_stats()
    print("\n4. realism: one 104 ms exposure, 346×260 (hot = pixels ≥ 8 events and 6× their "
          "neighbours)")
    print(f"   {'source':<28} {'ev/px':>6} {'silent':>7} {'ON':>5} {'hot':>4}")
    r = np.array(real)
    print(f"   {'real esl-cups (8 frames)':<28} {r[:, 0].mean():>6.2f} {r[:, 1].mean():>7.2f} "
          f"{r[:, 2].mean():>5.2f} {r[:, 3].mean():>4.1f}   "
          f"(range {r[:, 0].min():.2f}–{r[:, 0].max():.2f} ev/px)")
    sims = []
    kodak = sorted((SHARED / "images" / "kodak24").glob("*.png"))[:8]
    for i, path in enumerate(kodak):
        img = read_image(path)
        img = img.mean(-1) if img.ndim == 3 else img
        # dark like the esl-cups frames (mean ≈ 65/255), ≈ 25 px of blur
        s = make_sample(img * (0.25 / max(float(img.mean()), 1e-3)),
                        rng=np.random.default_rng(i), sensor=SensorConfig(),
                        exposure_us=104_000, zoom=None,
                        motion=MotionRanges(translation_px=30.0, rotation_deg=2.0))
        sims.append(_stats(s.events.x.astype(np.int64), s.events.y.astype(np.int64),
                           s.events.p > 0, 346, 260))
    m = np.array(sims)
    print(f"   {'simulated DAVIS (8 Kodak)':<28} {m[:, 0].mean():>6.2f} {m[:, 1].mean():>7.2f} "
          f"{m[:, 2].mean():>5.2f} {m[:, 3].mean():>4.1f}   "
          f"(range {m[:, 0].min():.2f}–{m[:, 0].max():.2f} ev/px)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=40, help="samples for 2. and 3.")
    ap.add_argument("--skip-real", action="store_true", help="skip the realism comparison")
    args = ap.parse_args()
    from trmd_cli.read import read_image

    print(machine())
    cam_path = SHARED / "images" / "skimage" / "camera.png"
    if cam_path.exists():
        camera = read_image(cam_path)
    else:  # a synthetic texture when ../shared/data is absent
        import cv2

        camera = cv2.GaussianBlur(np.random.default_rng(0).random((512, 512)).astype(np.float32),
                                  (0, 0), 2.0) * 3 - 1
        camera = np.clip(camera, 0, 1)
    bench_sensor(camera)
    bench_sample(camera, max(4, args.samples // 4))
    kodak = sorted((SHARED / "images" / "kodak24").glob("*.png"))
    if kodak:
        bench_dataset(kodak, args.samples)
    if not args.skip_real and (SHARED / "real" / "esl-cups").exists():
        bench_realism()
    print(f"\npeak memory {peak_rss_mib():.0f} MiB")


if __name__ == "__main__":
    main()
