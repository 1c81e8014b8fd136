"""Isolated events (trmd_cli.isolated): hand-placed events with the expected verdict worked out
by hand, the binned twin, and EDI's frames on a simulated noisy sensor with a known ground
truth."""

from __future__ import annotations

import numpy as np
import pytest

from trmd_cli.edi import PixelEvents
from trmd_cli.events import Exposure, make_stream
from trmd_cli.isolated import bins_without_isolated, corroborated, without_isolated
from trmd_cli.methods import EdiMethod, window_model
from trmd_cli.metrics import psnr

W, H = 12, 10
SPAN = Exposure(0, 1600)  # 16 slices of 100 µs


def _window(events: list[tuple[int, int, int, int]]) -> PixelEvents:
    """``events``: (x, y, t µs, polarity 0/1), in any order."""
    x, y, t, p = (list(c) for c in zip(*sorted(events, key=lambda e: e[2]), strict=True))
    return PixelEvents.build(make_stream(x, y, t, p, W, H), SPAN)


def _verdicts(events) -> dict[tuple[int, int, int], bool]:
    """(x, y, t) → corroborated, whatever the window's order."""
    w = _window(events)
    keep = corroborated(w)
    ys, xs = np.divmod(w.pix, W)
    return {(int(a), int(b), int(c)): bool(k) for a, b, c, k in zip(xs, ys, w.t_rel, keep,
                                                                     strict=True)}


def test_a_lone_event_is_isolated_and_a_neighbour_in_the_same_slice_keeps_both():
    v = _verdicts([(5, 5, 250, 1), (9, 1, 300, 1), (6, 5, 320, 0)])
    # slice 2 (200–299 µs) and slice 3: one apart, and (6, 5) is (5, 5)'s neighbour
    assert v == {(5, 5, 250): True, (6, 5, 320): True, (9, 1, 300): False}


def test_diagonal_neighbours_count_and_two_slices_apart_do_not():
    v = _verdicts([(2, 2, 0, 1), (3, 3, 99, 1),       # slice 0 and 0, diagonal
                   (8, 6, 100, 1), (9, 7, 350, 1)])   # slice 1 and 3: two apart
    assert v == {(2, 2, 0): True, (3, 3, 99): True, (8, 6, 100): False, (9, 7, 350): False}


def test_a_pixel_does_not_corroborate_itself_and_a_pixel_two_away_is_no_neighbour():
    v = _verdicts([(4, 4, 10, 1), (4, 4, 20, 0), (4, 4, 30, 1), (6, 4, 15, 1)])
    assert not any(v.values())


def test_sensor_corners_and_the_window_end():
    # (0, 0) and (1, 1) fire at the end of the window: the last slice, both kept; the corner
    # (11, 9) has its only neighbour (10, 8) in slice 0, far from its own slice 15
    v = _verdicts([(10, 8, 0, 1), (0, 0, 1600, 1), (1, 1, 1550, 0), (11, 9, 1600, 1)])
    assert v == {(10, 8, 0): False, (0, 0, 1600): True, (1, 1, 1550): True,
                 (11, 9, 1600): False}


def test_the_filtered_window_keeps_time_order_within_each_pixel_and_a_clean_one_is_itself():
    w = _window([(5, 5, 250, 1), (6, 5, 260, 0), (5, 5, 270, 0), (0, 9, 900, 1)])
    out = without_isolated(w)
    assert out.pix.tolist() == [5 * W + 5, 5 * W + 5, 5 * W + 6]
    assert out.t_rel.tolist() == [250, 270, 260] and out.p.tolist() == [1, -1, -1]
    clean = _window([(5, 5, 250, 1), (6, 5, 260, 0)])
    assert without_isolated(clean) is clean
    with pytest.raises(Exception, match="slices"):
        corroborated(clean, slices=32)


def test_bins_keep_a_count_whose_neighbour_fired_in_that_bin_or_the_next():
    bins = np.zeros((4, H, W), np.int16)
    bins[1, 3, 3] = 2      # neighbour (4, 4) fires in bin 2: kept
    bins[2, 4, 4] = -1     # neighbour (3, 3) in bin 1: kept
    bins[0, 8, 1] = 1      # alone: dropped
    bins[3, 8, 2] = 1      # (1, 8) is its neighbour but three bins earlier: dropped
    out = bins_without_isolated(bins)
    want = np.zeros_like(bins)
    want[1, 3, 3], want[2, 4, 4] = 2, -1
    np.testing.assert_array_equal(out, want)
    assert out.dtype == bins.dtype and bins[0, 8, 1] == 1  # the input is left as it was


@pytest.fixture(scope="module")
def noisy():
    """A moving texture seen by the simulator's DAVIS-like sensor (threshold mismatch, shot
    noise, leak)."""
    import cv2

    from trmd_cli.simulate import make_sample

    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.uniform(0, 1, (300, 400)).astype(np.float32), (0, 0), 5)
    img = (img - img.min()) / (img.max() - img.min()) * 0.7 + 0.15
    return make_sample(img, size=(160, 120), rng=rng)


def test_edi_frames_gain_when_isolated_events_are_dropped(noisy):
    s = noisy
    inst = s.exposure.instants_us(3)
    kept = EdiMethod(3, s.contrast, drop_isolated=False)(s.blurry, s.events, s.exposure, inst)
    dropped = EdiMethod(3, s.contrast)(s.blurry, s.events, s.exposure, inst)
    # scored as `trmd eval` scores them: clipped to [0, 1]
    before = np.mean([psnr(np.clip(f, 0, 1), g) for f, g in zip(kept.frames, s.sharp,
                                                                 strict=True)])
    after = np.mean([psnr(np.clip(f, 0, 1), g) for f, g in zip(dropped.frames, s.sharp,
                                                                strict=True)])
    # measured 27.82 → 28.00 dB
    assert after > before + 0.1, (before, after)


def test_a_still_scene_with_background_activity_comes_back_as_it_was():
    """Nothing moves, so every event is noise and every latent frame should be B: with the
    isolated events dropped it is, but at the few pixels where two noise events happen to
    fall side by side close in time."""
    rng = np.random.default_rng(5)
    w, h, n = 160, 120, 400
    b = rng.uniform(0.2, 0.8, (h, w)).astype(np.float32)
    t = np.sort(rng.integers(0, 20_000, n))
    ev = make_stream(rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n),
                     w, h)
    span = Exposure(0, 20_000)
    inst = span.instants_us(3)
    kept = EdiMethod(3, 0.3, hot_pixels=False, drop_isolated=False)(b, ev, span, inst).frames
    dropped = EdiMethod(3, 0.3, hot_pixels=False)(b, ev, span, inst).frames
    changed = lambda frames: np.any(frames != b, axis=0).sum()  # noqa: E731
    # 400 events on 19,200 pixels: each has ~8 · 400 · 3/16 / 19,200 ≈ 3 % odds of a neighbour
    assert changed(kept) > 350
    assert changed(dropped) < 0.1 * changed(kept)


def test_the_window_keeps_every_event_and_each_setting_has_its_own_model(noisy):
    s = noisy
    a, _, window = window_model(s.events, s.exposure, False, True)
    b, _, window_b = window_model(s.events, s.exposure, False, False)
    assert a is not b and len(window_b) == len(window)
    assert a.count < b.count == len(window)
    assert window_model(s.events, s.exposure, False, False)[0] is b  # kept for the stream
