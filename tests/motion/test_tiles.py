"""Tiles vote for a velocity: the background's motion apart from what moves on its own."""

from __future__ import annotations

import numpy as np

from trmd_cli.events import EventStream, Exposure
from trmd_cli.motion import GlobalMotion
from trmd_cli.motion.cmax import window_points
from trmd_cli.motion.tiles import (
    background_motion,
    disputed_tiles,
    outvoted_tiles,
    tile_velocities,
)

from ..helpers.data import texture

W, H = 160, 120


def test_outvoted_tiles_by_hand():
    """Nine tiles at (4, 0), two at (20, 0) and one at (8, 3) (within 6 px of (4, 0)): the two
    are out, exactly their rectangles of the 4×3 grid."""
    votes = {(i, j): (4.0, 0.0) for i in range(4) for j in range(3)}
    votes[(1, 1)] = (20.0, 0.0)
    votes[(2, 1)] = (20.0, 1.0)
    votes[(3, 2)] = (8.0, 3.0)
    mask = outvoted_tiles(votes, W, H)
    expected = np.zeros((H, W), bool)
    expected[40:80, 40:120] = True
    assert np.array_equal(mask, expected)


def test_outvoted_tiles_needs_a_disagreement_and_three_votes():
    assert outvoted_tiles({(i, 0): (1.0, 2.0) for i in range(4)}, W, H) is None
    assert outvoted_tiles({(0, 0): (0.0, 0.0), (1, 0): (30.0, 0.0)}, W, H) is None


def _translated_events(velocity, img, seed, region=None, other=None):
    """Events of ``img`` translated by ``velocity`` px per exposure over [0, 10 000] µs, a
    threshold of 0.2 on log intensity crossed by sampling 40 instants; inside ``region``
    (slices) the texture moves by ``other`` instead."""
    import cv2

    rng = np.random.default_rng(seed)
    xs, ys, ts, ps = [], [], [], []
    u = np.linspace(0.0, 1.0, 41)
    ref = None
    def shifted(v, f):
        m = np.float32([[1, 0, v[0] * (f - 0.5)], [0, 1, v[1] * (f - 0.5)]])
        return cv2.warpAffine(img, m, (W, H), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REFLECT)

    for f in u:
        frame = shifted(velocity, f)
        if region is not None:
            frame[region] = shifted(other, f)[region]
        logf = np.log(frame + 0.05)
        if ref is None:
            ref = logf
            continue
        n = np.trunc((logf - ref) / 0.2).astype(np.int64)
        y, x = np.nonzero(n)
        count = np.abs(n[y, x])
        xs.append(np.repeat(x, count))
        ys.append(np.repeat(y, count))
        ps.append(np.repeat(np.sign(n[y, x]), count))
        ts.append(((f - rng.uniform(0, 1 / 40, int(count.sum()))) * 10_000).astype(np.int64))
        ref = ref + 0.2 * n
    t = np.clip(np.concatenate(ts), 0, 10_000)
    order = np.argsort(t, kind="stable")
    return EventStream(np.concatenate(xs)[order].astype(np.uint16),
                       np.concatenate(ys)[order].astype(np.uint16), t[order],
                       np.concatenate(ps)[order].astype(np.int8), W, H), Exposure(0, 10_000)


def test_tiles_vote_the_translation_they_see():
    """A texture translated by (12, −6) px over the exposure: ten of the twelve tiles vote
    within 1 px of it (measured: 11; the worst, a tile of little texture, 5.6 px off), and no
    tile is outvoted."""
    ev, ex = _translated_events((12.0, -6.0), texture(H, W, seed=1), seed=0)
    votes = tile_velocities(ev, ex)
    assert len(votes) == 12
    near = [np.hypot(vx - 12.0, vy + 6.0) <= 1.0 for vx, vy in votes.values()]
    assert sum(near) >= 10
    assert outvoted_tiles(votes, W, H) is None
    assert background_motion(ev, ex) is None


def test_background_motion_leaves_a_mover_out():
    """The same background with a patch of two tiles sliding (−30, 10) px on its own: those
    tiles are outvoted and the background's motion is the background's translation within
    1 px (its displacement at the exposure's end)."""
    img = texture(H, W, seed=2)
    ev, ex = _translated_events((12.0, -6.0), img, seed=1,
                                region=(slice(40, 80), slice(40, 120)), other=(-30.0, 10.0))
    out = outvoted_tiles(tile_velocities(ev, ex), W, H)
    assert out is not None and out[60, 80] and not out[10, 10]
    m = background_motion(ev, ex)
    assert m is not None
    x, y = m.positions(1.0, np.array([20.0, 140.0]), np.array([20.0, 100.0]))
    assert np.allclose(x - [20.0, 140.0], 6.0, atol=1.0)
    assert np.allclose(y - [20.0, 100.0], -3.0, atol=1.0)


def test_disputed_tiles_are_the_movers_not_the_bad_votes():
    """The background translating (12, −6) px with a patch of two tiles sliding (−30, 10):
    against the background's own translation exactly those two tiles are disputed. Given
    a vote 30 px off on a tile of background (as coarse grids give on a textureless tile),
    that tile is not: carrying its events by the vote blurs them. Against the patch's
    motion, the patch's tiles are not disputed and most of the ten background tiles are
    (measured: nine; the other sharpens less than 1.15× over no motion at all)."""
    img = texture(H, W, seed=2)
    ev, ex = _translated_events((12.0, -6.0), img, seed=1,
                                region=(slice(40, 80), slice(40, 120)), other=(-30.0, 10.0))
    centre = ((W - 1) / 2, (H - 1) / 2)
    points = window_points(ev, ex)
    background = GlobalMotion((12.0, -6.0), centre=centre)
    votes = {(i, j): (-30.0, 10.0) if (i, j) in ((1, 1), (2, 1)) else (12.0, -6.0)
             for i in range(4) for j in range(3)}
    assert sorted(disputed_tiles(votes, background, points, W, H)) == [(1, 1), (2, 1)]
    votes[(0, 0)] = (-18.0, 0.0)
    assert sorted(disputed_tiles(votes, background, points, W, H)) == [(1, 1), (2, 1)]
    patch = GlobalMotion((-30.0, 10.0), centre=centre)
    del votes[(0, 0)]
    got = disputed_tiles(votes, patch, points, W, H)
    assert len(got) >= 7 and not {(1, 1), (2, 1)} & set(got), got
    # the tiles' own votes put the patch's two near rest (measured (−4, 0) and (−2, 0)):
    # a velocity that sharpens a tile no more than no motion does disputes nothing (noise
    # events and hot pixels collapse at rest; a mover's events do not)
    votes = tile_velocities(ev, ex)
    assert max(np.hypot(*votes[k]) for k in ((1, 1), (2, 1))) < 6.0
    assert disputed_tiles(votes, background, points, W, H) == []


def test_votes_do_not_depend_on_the_thread_count():
    """The tiles shared out over two or three threads vote exactly as one thread does, in the
    same order (their event subsets are drawn before they are shared out)."""
    import torch

    img = texture(H, W, seed=2)
    ev, ex = _translated_events((12.0, -6.0), img, seed=1,
                                region=(slice(40, 80), slice(40, 120)), other=(-30.0, 10.0))
    before = torch.get_num_threads()
    try:
        got = []
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            got.append(tile_velocities(ev, ex))
    finally:
        torch.set_num_threads(before)
    assert len(got[0]) == 12
    assert list(got[0].items()) == list(got[1].items()) == list(got[2].items())


def test_translation_gains_equal_the_searchs_own_gain():
    """All candidates at once score each translation as contrast maximisation's own level
    does, one at a time (its gain times the unwarped image's variance)."""
    from trmd_cli.motion.cmax import _Level, _start
    from trmd_cli.motion.tiles import _translation_gains

    rng = np.random.default_rng(4)
    n = 2000
    x, y = rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)
    u = rng.uniform(0, 1, n)
    velocities = np.array([[0.0, 0.0], [8.0, -4.0], [-16.0, 12.0], [30.0, 2.0], [3.5, 0.25]])
    for scale in (8.0, 4.0, 1.0):
        level = _Level(x, y, u, W, H, scale, ((W - 1) / 2, (H - 1) / 2), 0.5 * W, sigma=1.0)
        expected = [level.gain(_start(vx, vy)) * level.base for vx, vy in velocities]
        got = _translation_gains(x, y, u - 0.5, velocities, W, H, scale)
        np.testing.assert_allclose(got, expected, rtol=2e-4)
    # a tile's events, drawn on the part of the grid they reach: in a corner (some carried
    # off the sensor) and inside (the part's edges all within the sensor)
    for x0, y0 in ((0.0, 0.0), (50.0, 40.0)):
        cx, cy = x0 + rng.uniform(0, 60, 600), y0 + rng.uniform(0, 50, 600)
        cu = rng.uniform(0, 1, 600)
        for scale in (8.0, 4.0):
            level = _Level(cx, cy, cu, W, H, scale, ((W - 1) / 2, (H - 1) / 2), 0.5 * W,
                           sigma=1.0)
            expected = [level.gain(_start(vx, vy)) * level.base for vx, vy in velocities]
            got = _translation_gains(cx, cy, cu - 0.5, velocities, W, H, scale)
            np.testing.assert_allclose(got, expected, rtol=2e-4)


def test_follows_votes_by_hand():
    """Nine tiles voted (4, 0) px, three (30, 0) (outvoted): a translation of (4.5, 0.5)
    moves the nine as they voted; one of (20, −10) does not (16 px off each, over twice the
    6 px agreement); nor does a rotation that moves the frame's edges tens of pixels, though
    it leaves the centre still."""
    from trmd_cli.motion import GlobalMotion
    from trmd_cli.motion.tiles import follows_votes

    votes = {(i, j): (4.0, 0.0) for i in range(4) for j in range(3)}
    for k in ((1, 1), (2, 1), (2, 2)):
        votes[k] = (30.0, 0.0)
    out = outvoted_tiles(votes, W, H)
    assert out is not None
    centre = ((W - 1) / 2, (H - 1) / 2)
    assert follows_votes(GlobalMotion((4.5, 0.5), centre=centre), votes, out, W, H)
    assert not follows_votes(GlobalMotion((20.0, -10.0), centre=centre), votes, out, W, H)
    assert not follows_votes(GlobalMotion((4.0, 0.0), rotation=0.5, centre=centre), votes,
                             out, W, H)


def test_estimate_from_a_start_velocity():
    """Contrast maximisation started from a given velocity, 3 px off, instead of its grid
    finds the translation within 0.2 px at the exposure's end."""
    from trmd_cli.motion import estimate_motion

    ev, ex = _translated_events((12.0, -6.0), texture(H, W, seed=1), seed=0)
    m = estimate_motion(ev, ex, start=(15.0, -4.0))
    x, y = m.positions(1.0, np.array([40.0, 120.0]), np.array([30.0, 90.0]))
    assert np.allclose(x - [40.0, 120.0], 6.0, atol=0.2)
    assert np.allclose(y - [30.0, 90.0], -3.0, atol=0.2)


def test_tile_index_by_hand():
    """A 346×260 sensor in 4 × 3 tiles: columns split at x = 86.5, 173 and 259.5, rows at
    y = 86.67 and 173.33 (pixel coordinates), the tile numbered column · 3 + row; the tiles
    the votes are cast in are those a dispute reads."""
    from trmd_cli.motion.tiles import _tile_index

    x = np.array([0.0, 86.0, 87.0, 172.0, 173.0, 259.0, 260.0, 345.0, 345.0])
    y = np.array([0.0, 86.0, 87.0, 173.0, 174.0, 0.0, 259.0, 0.0, 259.0])
    expected = [0 * 3 + 0, 0 * 3 + 0, 1 * 3 + 1, 1 * 3 + 1, 2 * 3 + 2, 2 * 3 + 0, 3 * 3 + 2,
                3 * 3 + 0, 3 * 3 + 2]
    assert _tile_index(x, y, 346, 260, (4, 3)).tolist() == expected
