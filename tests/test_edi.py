"""EDI (trmd_cli.edi): analytic single-pixel cases, the defining mean property, binned events,
event propagation, hot pixels, colour, and PSNR on simulated frames with known threshold."""

from __future__ import annotations

import numpy as np
import pytest

from trmd_cli.edi import (
    EdiBins,
    EdiEvents,
    PixelEvents,
    cumsum_rows,
    edi_from_bins,
    edi_latent,
    hot_pixel_mask,
    propagate,
    signed_counts,
)
from trmd_cli.errors import InputError, ShapeError
from trmd_cli.events import EventStream, Exposure, make_stream

LN2 = float(np.log(2.0))


def one_pixel(times, pols, width=1, height=1, x=0, y=0) -> EventStream:
    n = len(times)
    return make_stream(np.full(n, x), np.full(n, y), np.asarray(times, np.int64),
                       np.asarray(pols), width, height)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - b) ** 2)))


# --------------------------------------------------------------------------------------------
# analytic


def test_single_pixel_steps_match_hand_computation():
    # +1 at 25, +1 at 50, −1 at 75 in [0, 100] with c = ln 2: exp(c·S) = 2^S = 1, 2, 4, 2 over
    # four quarter-intervals, so J = (1 + 2 + 4 + 2) / 4 = 2.25 and L(t) = B · 2^S(t) / 2.25
    ev = one_pixel([25, 50, 75], [1, 1, -1])
    b = np.array([[0.45]], np.float32)
    lat = edi_latent(b, ev, Exposure(0, 100), [0, 24, 25, 60, 75, 100], LN2)
    expected = 0.45 / 2.25 * np.array([1, 1, 2, 4, 2, 2])
    np.testing.assert_allclose(lat[:, 0, 0], expected, rtol=1e-6)


def test_fired_pixels_integral_by_hand():
    # pixel (0, 0): the steps of the test above, J = 2.25 at c = ln 2; pixel (2, 1): one +1 at
    # 50 of [0, 100], J = (1 + 2) / 2 = 1.5; every other pixel is silent, J = 1
    ev = make_stream(np.array([0, 0, 2, 0]), np.array([0, 0, 1, 0]),
                     np.array([25, 50, 50, 75]), np.array([1, 1, 1, 0]), 3, 2)
    model = EdiEvents.build(ev, Exposure(0, 100))
    fired = model.fired_integral(LN2)
    np.testing.assert_allclose(fired, [2.25, 1.5], rtol=1e-12)
    full = model.integral(LN2)
    np.testing.assert_array_equal(full.reshape(-1)[[0, 5]], fired)
    np.testing.assert_array_equal(np.delete(full.reshape(-1), [0, 5]), 1.0)


def test_reference_free_and_mean_equals_blurry(rng):
    # the defining property: the latent frames average back to the blurry frame
    ev = make_stream(rng.integers(0, 5, 400), rng.integers(0, 4, 400),
                     np.sort(rng.integers(0, 10_000, 400)), rng.integers(0, 2, 400), 5, 4)
    b = rng.uniform(0.1, 0.9, (4, 5)).astype(np.float32)
    exposure = Exposure(0, 10_000)
    t = (np.arange(20_000) + 0.5) * 0.5  # midpoints of 0.5 µs cells; events sit on whole µs
    lat = edi_latent(b, ev, exposure, t, 0.3)
    np.testing.assert_allclose(lat.mean(axis=0), b, rtol=2e-3)


def test_no_events_gives_the_blurry_frame():
    ev = EventStream.empty(3, 2)
    b = np.full((2, 3), 0.3, np.float32)
    lat = edi_latent(b, ev, Exposure(0, 50), [0, 25, 50], 0.2)
    np.testing.assert_allclose(lat, np.broadcast_to(b, (3, 2, 3)))


def test_events_outside_the_window_are_ignored():
    inside = one_pixel([40, 60], [1, -1])
    around = one_pixel([5, 40, 60, 95], [1, 1, -1, -1])
    b = np.array([[0.5]], np.float32)
    w = Exposure(10, 90)
    np.testing.assert_allclose(edi_latent(b, inside, w, [10, 50, 90], 0.4),
                               edi_latent(b, around, w, [10, 50, 90], 0.4))


def test_colour_frame_uses_the_same_ratio_per_channel(rng):
    ev = make_stream(rng.integers(0, 6, 300), rng.integers(0, 4, 300),
                     np.sort(rng.integers(0, 1000, 300)), rng.integers(0, 2, 300), 6, 4)
    rgb = rng.uniform(0, 1, (4, 6, 3)).astype(np.float32)
    lat = edi_latent(rgb, ev, Exposure(0, 1000), [0, 500, 1000], 0.25)
    assert lat.shape == (3, 4, 6, 3)
    for ch in range(3):
        mono = edi_latent(rgb[..., ch], ev, Exposure(0, 1000), [0, 500, 1000], 0.25)
        np.testing.assert_allclose(lat[..., ch], mono, rtol=1e-6)


def test_size_and_contrast_errors():
    ev = one_pixel([1], [1], width=4, height=3)
    with pytest.raises(InputError, match="4x3"):
        edi_latent(np.zeros((3, 5), np.float32), ev, Exposure(0, 10), [5], 0.2)
    with pytest.raises(ShapeError):
        edi_latent(np.zeros((3, 4, 2), np.float32), ev, Exposure(0, 10), [5], 0.2)
    for c in (0.0, -0.1, float("nan")):
        with pytest.raises(InputError, match="contrast"):
            edi_latent(np.zeros((3, 4), np.float32), ev, Exposure(0, 10), [5], c)


# --------------------------------------------------------------------------------------------
# the per-pixel sort and the sparse evaluation


def _stream_with_ties(rng, n=4000, width=23, height=17):
    # coarse times (many events at one instant, some exactly at the window's ends and at the
    # latent instants) and pixels that fire many times
    t = np.sort(rng.choice(np.arange(0, 12_001, 250), n))
    return make_stream(rng.integers(0, width, n), rng.integers(0, height, n), t,
                       rng.integers(0, 2, n), width, height)


def test_pixel_events_are_sorted_by_pixel_in_time_order(rng):
    ev = _stream_with_ties(rng)
    w = Exposure(1_000, 11_000)
    win = PixelEvents.build(ev, w)
    inside = (ev.t >= 1_000) & (ev.t <= 11_000)
    flat = ev.y.astype(np.int64)[inside] * ev.width + ev.x[inside]
    order = np.argsort(flat, kind="stable")  # the definition: by pixel, ties in time order
    np.testing.assert_array_equal(win.pix, flat[order])
    np.testing.assert_array_equal(win.t_rel, ev.t[inside][order] - 1_000)
    np.testing.assert_array_equal(win.p, ev.p[inside][order])
    np.testing.assert_array_equal(win.pixels, np.unique(flat))
    np.testing.assert_array_equal(win.pixels[win.group], win.pix)
    assert len(PixelEvents.build(ev, Exposure(20_000, 30_000))) == 0


def test_levels_at_counts_the_events_up_to_each_instant(rng):
    ev = _stream_with_ties(rng)
    w = Exposure(1_000, 11_000)
    prep = EdiEvents.build(ev, w)
    # unsorted, repeated, outside [0, 1], and exactly on event times (an event at an instant
    # counts there)
    fr = np.array([0.5, 0.0, 1.0, 0.25, 0.5, -0.3, 1.7, 0.4321])
    got = prep.levels_at(fr)
    inside = (ev.t >= 1_000) & (ev.t <= 11_000)
    t, x, y, p = ev.t[inside], ev.x[inside], ev.y[inside], ev.p[inside].astype(float)
    for k, f in enumerate(np.clip(fr, 0, 1)):
        expect = np.zeros((ev.height, ev.width))
        sel = (t - 1_000) / 10_000 <= f
        np.add.at(expect, (y[sel], x[sel]), p[sel])
        np.testing.assert_array_equal(got[k], expect)
    pixels, sparse = prep.sparse_levels(fr)
    np.testing.assert_array_equal(got.reshape(len(fr), -1)[:, pixels], sparse)


def test_latent_is_the_dense_formula(rng):
    # exp(c·S)/J evaluated densely, with J summed interval by interval per pixel
    ev = _stream_with_ties(rng, n=1500)
    w = Exposure(1_000, 11_000)
    prep = EdiEvents.build(ev, w)
    c = 0.27
    j = np.ones(ev.height * ev.width)
    for pix in np.unique(prep.pix):
        sel = prep.pix == pix
        j[pix] = prep.lead[pix] + np.sum(prep.dur[sel] * np.exp(c * prep.level[sel]))
    np.testing.assert_allclose(prep.integral(c).ravel(), j, rtol=1e-12)
    fr = np.array([0.0, 0.3, 1.0])
    b = rng.uniform(0.1, 0.9, (ev.height, ev.width)).astype(np.float32)
    expect = b * np.exp(c * prep.levels_at(fr)) / j.reshape(ev.height, ev.width)
    lat = prep.latent(b, fr, c)
    assert lat.dtype == np.float32
    np.testing.assert_allclose(lat, expect, rtol=1e-6)


def test_a_sorted_window_gives_what_the_stream_gives(rng):
    ev = _stream_with_ties(rng)
    w = Exposure(1_000, 11_000)
    win = PixelEvents.build(ev, w)
    hot = np.zeros((ev.height, ev.width), bool)
    hot[3, 5] = hot[10, 0] = True
    np.testing.assert_array_equal(hot_pixel_mask(ev, w, window=win), hot_pixel_mask(ev, w))
    a, b = EdiEvents.build(ev, w, hot), EdiEvents.build(ev, w, hot, window=win)
    for name in ("pix", "time", "step", "level", "dur", "lead"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.isin(a.pix, [3 * ev.width + 5, 10 * ev.width]).any()
    with pytest.raises(InputError, match="window"):
        EdiEvents.build(ev, Exposure(0, 11_000), window=win)


def test_cumsum_rows_is_cumsum_along_the_first_axis(rng):
    a = rng.integers(-5, 5, (7, 33))
    np.testing.assert_array_equal(cumsum_rows(a.copy()), np.cumsum(a, axis=0))


# --------------------------------------------------------------------------------------------
# bins


def test_bins_single_bin_matches_the_linear_model_integral():
    # one bin, +2 events: log L rises linearly by 2c, J = (e^{2c} − 1) / (2c)
    c = 0.3
    bins = np.full((1, 1, 1), 2.0)
    b = np.array([[0.6]], np.float32)
    lat = edi_from_bins(b, bins, [0.0, 0.5, 1.0], c)
    j = np.expm1(2 * c) / (2 * c)
    np.testing.assert_allclose(lat[:, 0, 0], 0.6 / j * np.exp(c * np.array([0, 1, 2])),
                               rtol=1e-6)


def test_bins_mean_equals_blurry_and_partial_exposure(rng):
    bins = rng.integers(-3, 4, (6, 3, 4)).astype(np.float64)
    b = rng.uniform(0.1, 0.9, (3, 4)).astype(np.float32)
    t = (np.arange(6000) + 0.5) / 6000
    np.testing.assert_allclose(edi_from_bins(b, bins, t, 0.2).mean(0), b, rtol=1e-4)
    # the blurry frame integrates only [1/6, 5/6] of the span
    inner = (1 / 6) + (np.arange(4000) + 0.5) / 4000 * (4 / 6)
    lat = edi_from_bins(b, bins, inner, 0.2, exposure=(1 / 6, 5 / 6))
    np.testing.assert_allclose(lat.mean(0), b, rtol=1e-4)


def test_bins_agree_with_events_when_events_sit_mid_bin():
    # events exactly at bin centres vs the linear model: the same to first order in c
    ev = one_pixel([150, 450, 750], [1, 1, -1])
    bins = np.array([0, 1, 0, 0, 1, 0, 0, -1, 0, 0], np.float64).reshape(10, 1, 1)
    b = np.array([[0.5]], np.float32)
    a = edi_latent(b, ev, Exposure(0, 1000), [0, 500, 1000], 0.05)
    z = edi_from_bins(b, bins, [0.0, 0.5, 1.0], 0.05)
    np.testing.assert_allclose(a, z, rtol=1e-4)


def test_bins_shape_errors():
    with pytest.raises(ShapeError):
        EdiBins.build(np.zeros((4, 5)))
    with pytest.raises(InputError):
        EdiBins.build(np.zeros((4, 5, 6)), exposure=(0.5, 0.2))


# --------------------------------------------------------------------------------------------
# propagation, hot pixels


def test_signed_counts_forward_and_backward():
    ev = one_pixel([10, 20, 30, 40], [1, 1, -1, 1])
    s = signed_counts(ev, 20, [5, 10, 20, 25, 30, 45])
    # S(t) − S(20): S = 0 before 10, 1 at 10, 2 at 20, 1 at 30, 2 at 40
    np.testing.assert_allclose(s[:, 0, 0], [-2, -1, 0, 0, -1, 0])


def test_propagate_matches_edi_inside_the_window(rng):
    ev = make_stream(rng.integers(0, 8, 600), rng.integers(0, 6, 600),
                     np.sort(rng.integers(0, 5000, 600)), rng.integers(0, 2, 600), 8, 6)
    b = rng.uniform(0.2, 0.8, (6, 8)).astype(np.float32)
    w = Exposure(0, 5000)
    lat = edi_latent(b, ev, w, [1000, 2500, 4000], 0.2)
    fwd = propagate(lat[0], ev, 1000, [2500, 4000], 0.2)
    back = propagate(lat[2], ev, 4000, [1000, 2500], 0.2)
    np.testing.assert_allclose(fwd, lat[1:], rtol=1e-5)
    np.testing.assert_allclose(back, lat[:2], rtol=1e-5)


def test_hot_pixel_is_found_and_ignored(rng):
    n = 3000
    x = rng.integers(0, 40, n)
    y = rng.integers(0, 30, n)
    p = rng.integers(0, 2, n)
    # a hot pixel: 300 ON events, drifting one way
    x = np.concatenate([x, np.full(300, 7)])
    y = np.concatenate([y, np.full(300, 11)])
    p = np.concatenate([p, np.ones(300, int)])
    t = np.concatenate([np.sort(rng.integers(0, 10_000, n)), np.linspace(0, 9999, 300)])
    order = np.argsort(t, kind="stable")
    ev = make_stream(x[order], y[order], t[order].astype(np.int64), p[order], 40, 30)
    w = Exposure(0, 10_000)
    mask = hot_pixel_mask(ev, w)
    assert mask[11, 7] and mask.sum() == 1
    b = np.full((30, 40), 0.5, np.float32)
    prep = EdiEvents.build(ev, w, mask)
    assert prep.count == n - int(((x[:n] == 7) & (y[:n] == 11)).sum())
    np.testing.assert_allclose(prep.latent(b, np.array([0.0, 1.0]), 0.3)[:, 11, 7], 0.5)


# --------------------------------------------------------------------------------------------
# simulated frames with known threshold


def test_edi_with_the_true_threshold_sharpens_a_simulated_frame():
    from tests.helpers.data import SHARED
    from trmd_cli.read.frames import read_image
    from trmd_cli.simulate import SensorConfig, make_sample

    path = SHARED / "images" / "skimage" / "camera.png"
    if path.exists():
        img = read_image(path)
    else:  # a synthetic scene keeps the test meaningful without the shared data
        yy, xx = np.mgrid[0:256, 0:256]
        img = (0.2 + 0.6 * ((xx // 32 + yy // 32) % 2)).astype(np.float32)
    s = make_sample(img, size=(160, 120), rng=np.random.default_rng(3),
                    sensor=SensorConfig.clean(0.2))
    lat = edi_latent(s.blurry, s.events, s.exposure, s.exposure.instants_us(3), s.contrast)
    gain = [psnr(lat[k], s.sharp[k]) - psnr(s.blurry, s.sharp[k]) for k in range(7)]
    assert min(gain) > 3.0, gain
    assert gain[3] > 5.0, gain


@pytest.mark.parametrize("n_pix", [7, 1 << 16, (1 << 16) + 1, 1280 * 720, (1 << 32) + 5])
def test_pixel_order_is_the_stable_sort_by_pixel(n_pix):
    from trmd_cli.edi import _pixel_order

    rng = np.random.default_rng(n_pix % 1000)
    for n in (0, 1, 2, 999, 40_000):
        flat = rng.integers(0, n_pix, n).astype(np.int64)
        flat[: n // 3] = flat[0] if n else 0  # many ties: their time order must be kept
        np.testing.assert_array_equal(_pixel_order(flat, n_pix),
                                      np.argsort(flat, kind="stable"))


def test_the_hot_pixel_statistics_are_numpys_medians():
    """The median and the median absolute deviation of whole counts from their histogram equal
    numpy's (odd and even sizes, half-integer medians, wide ranges)."""
    from trmd_cli.edi import _median_and_deviation

    rng = np.random.default_rng(7)
    cases = [rng.integers(0, hi, n) for n in (1, 2, 3, 16, 17, 1000) for hi in (1, 3, 40, 5000)]
    cases += [rng.poisson(2.5, 999), np.array([0, 10**9]), np.array([5, 5, 5, 6])]
    for counts in cases:
        med = np.median(counts)
        assert _median_and_deviation(counts) == (med, np.median(np.abs(counts - med)))
