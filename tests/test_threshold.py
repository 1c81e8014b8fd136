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
    _minimise,
    estimate_contrast,
    explained_share,
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


# --------------------------------------------------------------------------------------------
# the search on energies known in closed form


class _Energy:
    """An energy on log c, recording where it was evaluated."""

    def __init__(self, f) -> None:
        self.f, self.points = f, []

    def __call__(self, x: float) -> float:
        self.points.append(x)
        return self.f(x)


def test_search_finds_the_minimum_of_a_parabola_exactly():
    # a parabola in log c: the final parabola through three of its points is the curve itself
    lo, hi = np.log(0.05), np.log(1.0)
    for c_true in (0.07, 0.2, 0.31, 0.8):
        e = _Energy(lambda x, m=np.log(c_true): 0.4 + (x - m) ** 2)
        x, f, at_bound = _minimise(e, lo, hi)
        assert np.exp(x) == pytest.approx(c_true, rel=1e-9) and not at_bound
        # 5 coarse points and two rounds of two: 9 evaluations, each point once, none outside
        # the range (near an end, 0.07 and 0.8, a half step beyond it is left out)
        assert len(e.points) == (9 if c_true in (0.2, 0.31) else 8) == len(set(e.points))
        assert all(lo <= p <= hi for p in e.points)
        assert f == pytest.approx(0.4 + min((p - np.log(c_true)) ** 2 for p in e.points))


def test_search_on_a_skewed_energy_lands_near_its_minimum():
    # |x − m|^1.5 is not a parabola: the refinement must still come within a few per cent
    lo, hi = np.log(0.05), np.log(1.0)
    for c_true in (0.12, 0.33, 0.5):
        x, _, _ = _minimise(lambda x, m=np.log(c_true): abs(x - m) ** 1.5 + 0.1 * (x - m),
                            lo, hi)
        assert abs(x - np.log(c_true)) < 0.06


def test_search_keeps_the_lower_of_two_basins_the_coarse_grid_sees():
    # two dips: a shallow one near c = 0.08, the deeper one near c = 0.45
    lo, hi = np.log(0.05), np.log(1.0)

    def two_basins(x):
        return 1.0 - 0.5 * np.exp(-((x - np.log(0.08)) / 0.4) ** 2) \
            - 0.8 * np.exp(-((x - np.log(0.45)) / 0.4) ** 2)

    x, _, _ = _minimise(two_basins, lo, hi)
    assert np.exp(x) == pytest.approx(0.45, rel=0.05)


def test_a_minimum_at_the_end_of_the_range_is_flagged():
    lo, hi = np.log(0.05), np.log(1.0)
    e = _Energy(lambda x: x)  # falls towards the low end
    x, f, at_bound = _minimise(e, lo, hi)
    assert x == lo and f == lo and at_bound
    assert len(e.points) == 7  # the half steps below the range are not evaluated


def test_search_spends_nine_evaluations_on_a_frame(samples):
    s = samples[1]
    est = search_contrast(s.blurry, EdiEvents.build(s.events, s.exposure))
    assert est.reliable and est.evaluations == 9


def test_explained_share_of_edis_frame_is_one_minus_its_energy(samples):
    """The figure `trmd eval` reports, on EDI's middle frame, is the threshold energy's
    complement at that frame's c, measured at mid-exposure alone (two code paths: the
    objective takes logs of the fired pixels only)."""
    s = samples[0]
    model = EdiEvents.build(s.events, s.exposure)
    obj = ContrastObjective.from_events(model, s.blurry, np.array([0.5]))
    middle = model.latent(s.blurry, np.array([0.5]), s.contrast)[0]
    near = np.abs(model.time - 0.5) <= 0.03  # the objective's window
    counts = np.bincount(model.pix[near], weights=model.step[near],
                         minlength=model.width * model.height).reshape(model.height, model.width)
    assert explained_share(middle, counts) == pytest.approx(1.0 - obj(s.contrast), abs=1e-5)


def test_explained_share_by_construction():
    """Counts that are a fixed mix of the frame's central-difference log gradients are
    explained whole; the frame blurred along x explains less of them; counts unrelated to the
    frame hardly any; no counts: nan; a flat frame has no gradient to explain with."""
    import cv2

    rng = np.random.default_rng(4)
    img = cv2.GaussianBlur(rng.uniform(0.1, 0.9, (96, 128)).astype(np.float32), (0, 0), 2)
    log = np.log(img + 0.02).astype(np.float32)
    diff = np.array([[-0.5, 0.0, 0.5]], np.float32)
    gx = cv2.filter2D(log, -1, diff, borderType=cv2.BORDER_REFLECT_101)
    gy = cv2.filter2D(log, -1, diff.T, borderType=cv2.BORDER_REFLECT_101)
    counts = 40.0 * gx - 25.0 * gy
    # (not exactly 1: at the borders the reflected difference image is not the difference of
    # the reflected image, measured 0.991)
    assert explained_share(img, counts) > 0.98
    smeared = cv2.blur(img, (15, 1))
    assert explained_share(smeared, counts) < explained_share(img, counts) - 0.2
    assert explained_share(img, rng.normal(0, 1, img.shape)) < 0.1
    assert np.isnan(explained_share(img, np.zeros_like(img)))
    assert explained_share(np.full_like(img, 0.5), counts) == 0.0


def test_a_pixel_whose_events_sum_past_float32_leaves_the_energy_finite(samples):
    """A pixel that fired 300 times one way (a flicker the hot-pixel test missed) sums c·S
    past float32's exp at c = 1: the energy stays a number, within a block's share of the
    energy without that pixel, with event times and with bins."""
    import warnings

    s = samples[0]
    n = 300
    e = s.events
    t = np.linspace(s.exposure.start_us + 1, s.exposure.end_us - 1, n).astype(np.int64)
    order = np.argsort(np.concatenate([e.t, t]), kind="stable")
    burst = make_stream(np.concatenate([e.x, np.full(n, 60)])[order],
                        np.concatenate([e.y, np.full(n, 40)])[order],
                        np.concatenate([e.t, t])[order],
                        np.concatenate([e.p, np.ones(n, e.p.dtype)])[order], e.width, e.height)
    bins = event_bins(e, s.exposure, 6)
    flicker = bins.copy()
    flicker[:, 40, 60] += n / 6
    for plain, with_burst in (
            (ContrastObjective.from_events(EdiEvents.build(e, s.exposure), s.blurry),
             ContrastObjective.from_events(EdiEvents.build(burst, s.exposure), s.blurry)),
            (ContrastObjective.from_bins(EdiBins.build(bins), s.blurry),
             ContrastObjective.from_bins(EdiBins.build(flicker), s.blurry))):
        for c in (0.2, 1.0):
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                got = with_burst(c)
            assert np.isfinite(got)
            assert got == pytest.approx(plain(c), abs=0.05)
