"""SCER voxels against hand-computed cases, numpy vs torch, and invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers.data import random_stream
from trmd_cli.edi import PixelEvents
from trmd_cli.errors import InputError
from trmd_cli.events import Exposure, make_stream
from trmd_cli.voxel import (
    event_bins,
    resample_bins,
    scer_from_bins,
    scer_levels,
    scer_voxels,
    scer_voxels_torch,
    voxel_instants,
)


def _one_pixel(times, pols, width=2, height=1):
    return make_stream(np.zeros(len(times), int), np.zeros(len(times), int), times, pols,
                       width, height)


def test_hand_computed_n2():
    # exposure 0..400 µs, N=2 → 4 bins of 100 µs; the event at t=400 clamps into the last bin
    ev = _one_pixel([50, 150, 250, 350, 400], [1, 0, 1, 1, 1])
    bins = event_bins(ev, Exposure(0, 400), 4)
    assert bins[:, 0, 0].tolist() == [1, -1, 1, 2]
    assert bins[:, 0, 1].tolist() == [0, 0, 0, 0]
    v = scer_voxels(ev, Exposure(0, 400), n=2)
    # V(0) = -(b0+b1) = 0, V(1) = -b1 = 1, V(3) = b2 = 1, V(4) = b2+b3 = 3
    assert v[:, 0, 0].tolist() == [0, 1, 1, 3]
    assert voxel_instants(2) == [0, 1, 3, 4]


def test_events_outside_window_ignored_and_edges():
    ev = _one_pixel([99, 100, 199, 200, 300, 301], [1, 1, 1, 1, 1, 1])
    bins = event_bins(ev, Exposure(100, 300), 2)  # bins [100,200) [200,300]
    assert bins[:, 0, 0].tolist() == [2, 2]


def test_n3_shapes_and_sign_convention():
    # a pixel that only brightens: voxels before the middle are negative, after positive
    ev = _one_pixel(np.arange(0, 600, 10), np.ones(60, int))
    v = scer_voxels(ev, Exposure(0, 600), n=3)
    assert v.shape == (6, 1, 2) and v.dtype == np.float32
    # 10 events per 100 µs bin: V(k) = 10·(k−3)
    assert v[:, 0, 0].tolist() == [-30, -20, -10, 10, 20, 30]


def test_torch_twin_matches_numpy(rng):
    torch = pytest.importorskip("torch")
    ev = random_stream(rng, n=20000)
    win = Exposure(10_000, 90_001)
    ref = scer_voxels(ev, win, 3)
    got = scer_voxels_torch(torch.from_numpy(ev.x.astype(np.int64)),
                            torch.from_numpy(ev.y.astype(np.int64)), torch.from_numpy(ev.t.copy()),
                            torch.from_numpy(ev.p.copy()), win, 3, ev.height, ev.width)
    np.testing.assert_array_equal(got.numpy(), ref)
    np.testing.assert_array_equal(scer_from_bins(torch.from_numpy(event_bins(ev, win, 6))).numpy(),
                                  ref)


def test_inputs_not_mutated(rng):
    ev = random_stream(rng)
    before = [getattr(ev, k).copy() for k in "xytp"]
    scer_voxels(ev, Exposure(0, 100_000), 3)
    for k, b in zip("xytp", before):
        np.testing.assert_array_equal(getattr(ev, k), b)


def test_bad_n():
    ev = _one_pixel([1], [1])
    with pytest.raises(InputError):
        scer_voxels(ev, Exposure(0, 10), n=0)
    with pytest.raises(InputError):
        scer_from_bins(np.zeros((3, 1, 1), np.float32))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 999), st.integers(0, 3), st.integers(0, 2),
                          st.booleans()), max_size=200),
       st.integers(1, 4))
def test_property_voxels_equal_bruteforce(events, n):
    events = sorted(events)
    t = np.array([e[0] for e in events], np.int64)
    x = np.array([e[1] for e in events], np.int64)
    y = np.array([e[2] for e in events], np.int64)
    p = np.array([e[3] for e in events], bool)
    ev = make_stream(x, y, t, p, 4, 3)
    win = Exposure(0, 1000)
    v = scer_voxels(ev, win, n)
    # brute force from the definition: V(k) = sgn(k−N) · Σ events between instants N and k
    inst = np.arange(2 * n + 1) * 1000 / (2 * n)
    expect = np.zeros((2 * n, 3, 4))
    for c, k in enumerate(voxel_instants(n)):
        lo, hi = sorted((inst[k], inst[n]))
        for ti, xi, yi, pi in zip(t, x, y, p):
            # bins are half-open [lo, hi); the exposure end belongs to the last bin
            inside = lo <= ti < hi or (ti == 1000 and hi == 1000)
            if inside:
                expect[c, yi, xi] += (1 if pi else -1) * np.sign(k - n)
    np.testing.assert_allclose(v, expect)
    # the sum of |channel| is monotone away from the middle for one-signed data
    assert v.shape == (2 * n, 3, 4)


def test_resample_bins_sums_whole_bins_or_splits_evenly():
    b = np.array([3, -1, 4, 1, -5, 9], np.int16).reshape(6, 1, 1)
    # 2 divides 6: sums of whole bins, exact
    np.testing.assert_array_equal(resample_bins(b, 2).ravel(), [6, 5])
    np.testing.assert_array_equal(resample_bins(b, 6).ravel(), b.ravel())
    # 4 does not: new bin i spans old bins [1.5·i, 1.5·(i+1)); straddling bins split by overlap
    np.testing.assert_allclose(resample_bins(b, 4).ravel(),
                               [3 - 0.5, -0.5 + 4, 1 - 2.5, -2.5 + 9])
    # fewer bins than asked: each split evenly
    np.testing.assert_allclose(resample_bins(b[:2], 4).ravel(), [1.5, 1.5, -0.5, -0.5])
    # the total is kept
    assert resample_bins(b, 5).sum() == pytest.approx(b.sum())


def test_resample_bins_of_events_equals_binning_them_coarser(rng):
    ev = random_stream(rng)
    win = Exposure(0, 100_000)
    np.testing.assert_array_equal(resample_bins(event_bins(ev, win, 18), 6),
                                  event_bins(ev, win, 6))


def test_a_sorted_window_gives_the_same_voxels_and_levels(rng):
    # events on a coarse clock: many exactly at bin edges, latent instants and the window's end
    n = 6000
    t = np.sort(rng.choice(np.arange(0, 60_001, 500), n))
    ev = make_stream(rng.integers(0, 19, n), rng.integers(0, 13, n), t, rng.integers(0, 2, n),
                     19, 13)
    for win in (Exposure(0, 60_000), Exposure(7_000, 43_000)):
        sorted_ = PixelEvents.build(ev, win)
        for n_ in (1, 3):
            np.testing.assert_array_equal(scer_voxels(ev, win, n_, window=sorted_),
                                          scer_voxels(ev, win, n_))
        np.testing.assert_array_equal(event_bins(ev, win, 5, window=sorted_),
                                      event_bins(ev, win, 5))
        np.testing.assert_array_equal(scer_levels(ev, win, 3, window=sorted_),
                                      scer_levels(ev, win, 3))
    with pytest.raises(InputError, match="window"):
        scer_levels(ev, Exposure(0, 50_000), 3, window=PixelEvents.build(ev, Exposure(0, 60_000)))


def test_levels_interpolate_between_events_by_hand():
    # one pixel, exposure 0..600 µs, N = 1 (instants 0, 300, 600): events +1 at 100, +1 at 400.
    # Λ(0) = half-way to the first event = 0.5; Λ(300) = 1 + (300−100)/(400−100) = 1.667;
    # Λ(600) = 2 (stays at the level reached). Output: Λ(0) − Λ(300), Λ(600) − Λ(300)
    ev = _one_pixel([100, 400], [1, 1])
    lv = scer_levels(ev, Exposure(0, 600), n=1)
    np.testing.assert_allclose(lv[:, 0, 0], [0.5 - (1 + 2 / 3), 2 - (1 + 2 / 3)], rtol=1e-6)
    np.testing.assert_array_equal(lv[:, 0, 1], [0, 0])


def test_spread_bins_puts_each_count_evenly_inside_its_bin_and_bins_back_exactly():
    from trmd_cli.voxel import spread_bins

    bins = np.zeros((3, 2, 2), np.int16)
    bins[1, 0, 1] = -4  # four OFF events in the middle bin of pixel (x=1, y=0)
    bins[2, 1, 0] = 1
    events, exposure = spread_bins(bins, bin_us=1000)
    assert (exposure.start_us, exposure.end_us) == (0, 3000)
    # by hand: (j + ½)/k of the bin, j = 0..3 of k = 4 → 1125, 1375, 1625, 1875; k = 1 → 2500
    assert events.t.tolist() == [1125, 1375, 1625, 1875, 2500]
    assert events.p.tolist() == [-1, -1, -1, -1, 1]
    assert events.x.tolist() == [1, 1, 1, 1, 0] and events.y.tolist() == [0, 0, 0, 0, 1]
    rng = np.random.default_rng(3)
    many = rng.integers(-6, 7, (18, 9, 11)).astype(np.int16)
    ev, ex = spread_bins(many)
    np.testing.assert_array_equal(event_bins(ev, ex, 18), many)
    with pytest.raises(InputError, match="whole numbers"):
        spread_bins(many.astype(np.float32) + 0.5)
