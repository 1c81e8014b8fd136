"""Contrast-threshold estimation (trmd_cli.threshold) on simulated data with a known threshold:
auto-c must land within 0.5 dB (mean) of the EDI result obtained with the true c."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.data import SHARED
from trmd_cli.edi import EdiBins, EdiEvents
from trmd_cli.events import Exposure, make_stream
from trmd_cli.threshold import (
    DEFAULT_CONTRAST,
    ContrastObjective,
    estimate_contrast,
    search_contrast,
)
from trmd_cli.voxel import event_bins

IMAGES = ["skimage/camera.png", "skimage/coffee.png", "skimage/astronaut.png",
          "skimage/brick.png", "wikimedia/013.png", "wikimedia/039.png"]
CONTRASTS = [0.2, 0.3, 0.15, 0.2, 0.3, 0.15]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - b) ** 2)))


def scene(k: int) -> np.ndarray:
    """A shared-data image, or (without the shared data) a procedural one with edges and
    texture."""
    from trmd_cli.read.frames import read_image

    path = SHARED / "images" / IMAGES[k]
    if path.exists():
        return read_image(path)
    import cv2

    rng = np.random.default_rng(k)
    img = cv2.GaussianBlur(rng.uniform(0, 1, (400, 520)).astype(np.float32), (0, 0), 6)
    img = (img - img.min()) / (img.max() - img.min()) * 0.6 + 0.1
    for _ in range(25):
        x, y = rng.integers(0, 480), rng.integers(0, 360)
        cv2.rectangle(img, (int(x), int(y)), (int(x + rng.integers(10, 80)),
                      int(y + rng.integers(10, 80))), float(rng.uniform(0.05, 0.95)), -1)
    return img


@pytest.fixture(scope="module")
def samples():
    from trmd_cli.simulate import SensorConfig, make_sample

    rng = np.random.default_rng(7)
    return [make_sample(scene(k), rng=rng, sensor=SensorConfig.clean(c))
            for k, c in enumerate(CONTRASTS)]


def test_auto_contrast_within_half_a_db_of_the_true_one(samples):
    gaps = []
    for s in samples:
        prep = EdiEvents.build(s.events, s.exposure)
        est = search_contrast(s.blurry, prep)
        assert est.reliable

        def mid(c, prep=prep, s=s):
            return psnr(prep.latent(s.blurry, np.array([0.5]), c)[0], s.sharp[3])

        gaps.append(mid(s.contrast) - mid(est.contrast))
    assert np.mean(gaps) <= 0.5, gaps
    assert max(gaps) <= 1.5, gaps


def test_energy_prefers_the_true_threshold_to_half_or_double(samples):
    for s in samples[:3]:
        obj = ContrastObjective.from_events(EdiEvents.build(s.events, s.exposure), s.blurry)
        e = obj(s.contrast)
        assert e < obj(0.5 * s.contrast) and e < obj(2.0 * s.contrast)


def test_bins_auto_contrast_within_half_a_db(samples):
    gaps = []
    for s in samples[:4]:
        model = EdiBins.build(event_bins(s.events, s.exposure, 18))
        est = search_contrast(s.blurry, model)

        def mid(c, model=model, s=s):
            return psnr(model.latent(s.blurry, [0.5], c)[0], s.sharp[3])

        gaps.append(mid(s.contrast) - mid(est.contrast))
    assert np.mean(gaps) <= 0.5, gaps


def test_too_few_events_falls_back_to_the_default():
    ev = make_stream([1, 2, 3], [1, 1, 1], [10, 20, 30], [1, 1, 0], 32, 32)
    b = np.full((32, 32), 0.5, np.float32)
    assert estimate_contrast(b, ev, Exposure(0, 100)) == DEFAULT_CONTRAST
    est = search_contrast(b, EdiEvents.build(ev, Exposure(0, 100)))
    assert not est.reliable and est.evaluations == 0


def test_colour_frame_is_estimated_from_its_luma(samples):
    s = samples[0]
    rgb = np.repeat(s.blurry[..., None], 3, axis=2)
    assert estimate_contrast(rgb, s.events, s.exposure) == pytest.approx(
        estimate_contrast(s.blurry, s.events, s.exposure), rel=1e-3)


def test_the_fallback_says_why():
    ev = make_stream([1, 2, 3], [1, 1, 1], [10, 20, 30], [1, 1, 0], 32, 32)
    b = np.full((32, 32), 0.5, np.float32)
    est = search_contrast(b, EdiEvents.build(ev, Exposure(0, 100)))
    assert not est.at_bound and "too few events (3" in est.reason


def test_a_threshold_beyond_the_search_range_is_flagged(samples):
    """Searched over a range that excludes the true c, the estimate sits on the range's edge
    and says so; searched over the default range, it does not."""
    s = samples[0]
    prep = EdiEvents.build(s.events, s.exposure)
    inside = search_contrast(s.blurry, prep)
    assert inside.reliable and not inside.at_bound and inside.reason is None
    low = search_contrast(s.blurry, prep, bounds=(0.3 * s.contrast, 0.6 * s.contrast))
    assert low.at_bound and low.contrast == pytest.approx(0.6 * s.contrast, rel=1e-6)
