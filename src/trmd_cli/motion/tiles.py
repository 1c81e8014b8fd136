"""The background's motion where something else moves on its own: tiles vote for a velocity.

One global contrast maximisation over all of an exposure's events can follow a foreground
object instead of the camera: a mover that sweeps fast over a textured patch fires dense
events, and its sharpening outweighs the background's even where it covers a tenth of the
frame (the rotation, zoom and acceleration then bend to fit it). Each tile of a coarse grid
estimates its own velocity on its own events instead; the velocity most tiles share is the
background's, and the tiles that disagree are left out of a second, global estimate.
"""

from __future__ import annotations

import numpy as np

from ..events import EventStream, Exposure
from ..threads import map_shared
from .cmax import (
    MIN_EVENTS,
    MotionSearch,
    _ascend,
    _Level,
    _start,
    _votes,
    estimate_motion,
    warped_image,
    window_points,
)
from .model import GlobalMotion

__all__ = ["tile_velocities", "outvoted_tiles", "disputed_tiles", "background_motion",
           "follows_votes", "votes_and_background", "TileEvidence", "AGREE_PX",
           "DISPUTE_GAIN", "GRID"]

#: tiles across × down
GRID = (4, 3)
#: two tiles' velocities (pixels per exposure) this close are the same motion
AGREE_PX = 6.0
#: least events for a tile to vote
TILE_EVENTS = 300
#: how much more a tile's own velocity must sharpen its events than a global motion does
#: (ratio of the variances of their images of warped events) for the tile to dispute it
DISPUTE_GAIN = 1.15
#: events per tile used to vote (a fixed random subset when there are more)
TILE_MAX_EVENTS = 4000
#: about this many of them rank the first, coarsest velocity grid
ROUGH_EVENTS = 1000


def tile_velocities(events: EventStream, exposure: Exposure,
                    hot_mask: np.ndarray | None = None, grid: tuple[int, int] = GRID,
                    search: MotionSearch | None = None
                    ) -> dict[tuple[int, int], tuple[float, float]]:
    """Each tile's own velocity, pixels per exposure: ``{(column, row): (vx, vy)}`` for the
    tiles with at least :data:`TILE_EVENTS` events (the others do not vote).

    The velocity grid of :func:`~trmd_cli.motion.estimate_motion` on the tile's events, each
    grid's translations scored at once (:func:`_translation_gains`): step 8 on an 8× coarser
    image (from about :data:`ROUGH_EVENTS` of them), then the step-4 neighbours of the best
    three on 4× (on tiles under 80 px, half those steps and scales; under 40, a quarter);
    then the velocity ascended at full resolution on the tile's box.
    """
    search = MotionSearch() if search is None else search
    w, h = events.width, events.height
    x, y, u = window_points(events, exposure, hot_mask)
    centre, radius = ((w - 1) / 2, (h - 1) / 2), 0.5 * max(w, h)
    cols, rows = grid
    tile = _tile_index(x, y, w, h, grid)
    order = np.argsort(tile, kind="stable")
    bounds = np.searchsorted(tile[order], np.arange(cols * rows + 1))
    vmax = search.max_velocity_px
    # the first grid's cells: 8 px on tiles of ≥ 80 px (ten cells or more a side), finer on
    # smaller ones, where 8 px cells blur a tile's texture into a few values
    side = min(w / cols, h / rows)
    scale = 8.0 if side >= 80 else 4.0 if side >= 40 else 2.0
    steps = np.arange(-vmax, vmax + 1e-9, scale)
    cands = np.array([(a, b) for a in steps for b in steps])
    half = scale / 2
    # each voting tile's events, drawn in tile order (the same subsets however the tiles are
    # then shared out)
    rng = np.random.default_rng(search.seed)
    voters: list[tuple[int, np.ndarray]] = []
    for k in range(cols * rows):
        idx = order[bounds[k]:bounds[k + 1]]
        if len(idx) < TILE_EVENTS:
            continue
        if len(idx) > TILE_MAX_EVENTS:
            idx = np.sort(rng.choice(idx, TILE_MAX_EVENTS, replace=False))
        voters.append((k, idx))

    def vote(idx: np.ndarray) -> tuple[float, float]:
        tau = u[idx] - 0.5
        # the coarsest grid from about ROUGH_EVENTS events: its cells need few to rank
        few = slice(None, None, max(len(idx) // ROUGH_EVENTS, 1))
        gains = _translation_gains(x[idx][few], y[idx][few], tau[few], cands, w, h, scale)
        seeds = cands[np.argsort(-gains, kind="stable")[:3]]
        near = np.array(sorted({(a + dx, b + dy) for a, b in seeds.tolist()
                                for dx in (-half, 0.0, half) for dy in (-half, 0.0, half)}))
        gains = _translation_gains(x[idx], y[idx], tau, near, w, h, half)
        vx, vy = near[int(np.argmax(gains))]
        # then the velocity alone, ascended at full resolution (the grids' cells bias a small
        # tile's optimum towards slow motion), on the tile's box widened by its events' reach:
        # the same image of warped events as on the whole sensor, a tenth of the pixels
        reach = 0.5 * np.hypot(vx, vy) + 2 * half + 4.0
        x0 = max(int(x[idx].min() - reach), 0)
        y0 = max(int(y[idx].min() - reach), 0)
        bw = min(int(x[idx].max() + reach) + 1, w) - x0
        bh = min(int(y[idx].max() + reach) + 1, h) - y0
        fine = _Level(x[idx] - x0, y[idx] - y0, u[idx], bw, bh, 1.0, centre, radius)
        q = _ascend(fine, _start(vx, vy), 2, (0.0, 0.0, 0.0), 10, 0.5)
        return float(q[0]), float(q[1])

    # the tiles on the process's threads (their candidate grids are arrays of 10⁵ entries,
    # whose passes release the interpreter)
    velocities = map_shared(vote, [idx for _, idx in voters])
    return {(k // rows, k % rows): v for (k, _), v in zip(voters, velocities, strict=True)}


def _tile_index(x: np.ndarray, y: np.ndarray, width: int, height: int,
                grid: tuple[int, int] = GRID) -> np.ndarray:
    """The tile (``column · rows + row``) each point (x, y) (pixels) lies in: column
    ``⌊x · cols / W⌋``, row ``⌊y · rows / H⌋``."""
    cols, rows = grid
    return np.minimum((x * cols / width).astype(np.int64), cols - 1) * rows + \
        np.minimum((y * rows / height).astype(np.int64), rows - 1)


def outvoted_tiles(votes: dict[tuple[int, int], tuple[float, float]], width: int, height: int,
                   grid: tuple[int, int] = GRID, agree_px: float = AGREE_PX) -> np.ndarray | None:
    """(H, W) bool: the tiles whose velocity is not the one most tiles share (within
    ``agree_px``; ties: the first tile in column order). None when every voting tile agrees,
    or fewer than three voted (nothing to tell apart)."""
    if len(votes) < 3:
        return None
    keys = list(votes)
    v = np.array([votes[k] for k in keys])
    near = np.hypot(v[:, None, 0] - v[None, :, 0], v[:, None, 1] - v[None, :, 1]) <= agree_px
    best = int(np.argmax(near.sum(1)))
    if near[best].all():
        return None
    cols, rows = grid
    mask = np.zeros((height, width), bool)
    for (i, j), agrees in zip(keys, near[best], strict=True):
        if not agrees:
            mask[j * height // rows:(j + 1) * height // rows,
                 i * width // cols:(i + 1) * width // cols] = True
    return mask


def disputed_tiles(votes: dict[tuple[int, int], tuple[float, float]], motion: GlobalMotion,
                   points: tuple[np.ndarray, np.ndarray, np.ndarray], width: int, height: int,
                   grid: tuple[int, int] = GRID, agree_px: float = AGREE_PX,
                   min_gain: float = DISPUTE_GAIN) -> list[tuple[int, int]]:
    """The voting tiles (column, row) that something else moves: their velocity is more than
    ``agree_px`` (pixels per exposure) off ``motion``'s displacement at their centre, *and*
    carrying their events by it sharpens them more than ``min_gain`` times as much as
    ``motion`` does (the variance of the σ = 1 px blurred image of the tile's warped events).

    The second test is what makes the first usable: a tile's vote comes from coarse grids on
    a few thousand events, and on textureless or noisy tiles it lands tens of pixels off a
    right global motion (on the pinned set's 48 frames, with their DAVIS-like noise events,
    a tile 6–56 px off in 37 of them), while carrying its events by that vote sharpens them
    less than the global motion does: only four of those frames had a tile above 1.15. On
    the mover bench's, the movers' tiles reach 1.2–2.3.

    Args:
        votes: :func:`tile_velocities`' output.
        points: the window's events as :func:`~trmd_cli.motion.cmax.window_points` gives
            them (x, y pixels; u exposure fractions).
    """
    import cv2

    x, y, u = points
    rows = grid[1]
    keys = list(votes)
    out = []
    tile = None
    for (i, j), off in zip(keys, _vote_offsets(motion, votes, keys, width, height, grid),
                           strict=True):
        if off <= agree_px:
            continue
        if tile is None:
            tile = _tile_index(x, y, width, height, grid)
        # the events the tile voted with (a busy window holds 10⁵–10⁶: each drawn once)
        sel = np.flatnonzero(tile == i * rows + j)
        xs, ys, us = x[sel], y[sel], u[sel]
        vx, vy = votes[(i, j)]
        own = GlobalMotion((vx, vy), centre=motion.centre)
        # (the events as recorded: no motion to carry them by)
        var = [float(cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0).var())
               for img in (warped_image(own, xs, ys, us, width, height),
                           warped_image(motion, xs, ys, us, width, height),
                           _votes(xs, ys, width, height))]
        if var[0] > min_gain * max(var[1], var[2]):
            out.append((i, j))
    return out


def background_motion(events: EventStream, exposure: Exposure,
                      hot_mask: np.ndarray | None = None,
                      search: MotionSearch | None = None,
                      votes: dict[tuple[int, int], tuple[float, float]] | None = None
                      ) -> GlobalMotion | None:
    """The global motion of the events of the tiles that move with the majority
    (``votes``, by default :func:`tile_velocities`'; :func:`outvoted_tiles`), by
    :func:`~trmd_cli.motion.estimate_motion`; None when every tile agrees (the first estimate
    already is the background's), the kept tiles hold fewer than
    :data:`~trmd_cli.motion.MIN_EVENTS` events, or the estimate does not move those tiles as
    they voted (see :func:`follows_votes`)."""
    w, h = events.width, events.height
    if votes is None:
        votes = tile_velocities(events, exposure, hot_mask, search=search)
    out = outvoted_tiles(votes, w, h)
    if out is None:
        return None
    ignore = out if hot_mask is None else (out | hot_mask)
    motion = estimate_motion(events, exposure, ignore, search,
                             start=_majority_velocity(votes, out, w, h))
    if motion.events < MIN_EVENTS or not follows_votes(motion, votes, out, w, h):
        return None
    return motion


def votes_and_background(events: EventStream, exposure: Exposure,
                         hot_mask: np.ndarray | None = None):
    """Yields :func:`tile_velocities`' votes, then the :func:`background_motion` made from
    them (a generator: the votes are ready before the longer second estimate)."""
    votes = tile_velocities(events, exposure, hot_mask)
    yield votes
    yield background_motion(events, exposure, hot_mask, votes=votes)


class TileEvidence:
    """One exposure's tile votes and the background's motion from them, neither of which
    depends on the global estimate: begun in the process's helper
    (:mod:`trmd_cli.helper_process`) while the caller makes that estimate, when one is ready;
    else each computed here when first asked for (the background's only if asked for). The
    same values either way. Call :meth:`drop` when done.

    Args:
        events, exposure, hot_mask: as :func:`tile_velocities` takes them.
    """

    def __init__(self, events: EventStream, exposure: Exposure,
                 hot_mask: np.ndarray | None = None) -> None:
        from ..helper_process import ahead

        self._args = (events, exposure, hot_mask)
        self._votes: dict[tuple[int, int], tuple[float, float]] | None = None
        self._background: tuple[GlobalMotion | None] | None = None
        # only the exposure's events travel to the helper
        self._ahead = ahead(votes_and_background, events.within(exposure), exposure, hot_mask)

    def votes(self) -> dict[tuple[int, int], tuple[float, float]]:
        """:func:`tile_velocities`' votes."""
        if self._votes is None:
            ok, votes = self._ahead.take(0)
            self._votes = votes if ok else tile_velocities(*self._args)
        return self._votes

    def background(self) -> GlobalMotion | None:
        """:func:`background_motion` from :meth:`votes`."""
        if self._background is None:
            votes = self.votes()
            ok, motion = self._ahead.take(1)
            self._background = (motion if ok else
                                background_motion(*self._args, votes=votes),)
        return self._background[0]

    def drop(self) -> None:
        """Nothing more is wanted: the helper's job is cancelled or stopped."""
        self._ahead.drop()


def _majority_velocity(votes: dict[tuple[int, int], tuple[float, float]], outvoted: np.ndarray,
                       width: int, height: int, grid: tuple[int, int] = GRID
                       ) -> tuple[float, float]:
    """The mean velocity (pixels per exposure) of the tiles not ``outvoted``."""
    keys = _majority(votes, outvoted, width, height, grid)
    v = np.array([votes[k] for k in keys]).mean(0)
    return float(v[0]), float(v[1])


def _majority(votes: dict[tuple[int, int], tuple[float, float]], outvoted: np.ndarray,
              width: int, height: int, grid: tuple[int, int] = GRID) -> list[tuple[int, int]]:
    """The voting tiles (column, row) that are not ``outvoted``, (H, W) bool."""
    cols, rows = grid
    return [k for k in votes
            if not outvoted[(2 * k[1] + 1) * height // (2 * rows),
                            (2 * k[0] + 1) * width // (2 * cols)]]


def follows_votes(motion: GlobalMotion, votes: dict[tuple[int, int], tuple[float, float]],
                  outvoted: np.ndarray, width: int, height: int,
                  grid: tuple[int, int] = GRID, agree_px: float = AGREE_PX) -> bool:
    """Whether ``motion`` moves the majority's tiles (those not ``outvoted``, (H, W) bool) as
    they voted: its displacement over the exposure at their centres is within twice
    ``agree_px`` of their velocities, in the median (each of them is within ``agree_px`` of
    one tile's, so within twice that of each other's). The estimate on their events can still
    bend to a mover's events left inside them (on a noisy scene whose tiles agreed on a few
    pixels, rotation and zoom went to their bounds and the motion was 12 px off the camera's
    path at both ends, 18 px off the votes in the median)."""
    keys = _majority(votes, outvoted, width, height, grid)
    if not keys:
        return False
    off = _vote_offsets(motion, votes, keys, width, height, grid)
    return bool(np.median(off) <= 2.0 * agree_px)


def _vote_offsets(motion: GlobalMotion, votes: dict[tuple[int, int], tuple[float, float]],
                  keys: list[tuple[int, int]], width: int, height: int,
                  grid: tuple[int, int] = GRID) -> np.ndarray:
    """(len(keys),) pixels: how far ``motion``'s displacement over the exposure at each
    tile's centre is from the velocity the tile voted."""
    cols, rows = grid
    cx = np.array([(i + 0.5) * width / cols for i, _ in keys])
    cy = np.array([(j + 0.5) * height / rows for _, j in keys])
    x0, y0 = motion.positions(0.0, cx, cy)
    x1, y1 = motion.positions(1.0, cx, cy)
    voted = np.array([votes[k] for k in keys]).reshape(-1, 2)
    return np.hypot(x1 - x0 - voted[:, 0], y1 - y0 - voted[:, 1])


def _translation_gains(x: np.ndarray, y: np.ndarray, tau: np.ndarray, velocities: np.ndarray,
                       width: int, height: int, scale: float) -> np.ndarray:
    """The contrast of the events ``(x, y)`` (pixels; ``tau``: exposure fraction − 0.5)
    carried to the middle by each pure translation of ``velocities`` (K, 2) (pixels per
    exposure), all at once: (K,) variances of their images of warped events on a grid
    ``scale`` times coarser, bilinear votes blurred by a σ = 1 cell Gaussian (as
    :class:`~trmd_cli.motion.cmax._Level` makes them; the unwarped image's variance, the
    same for every candidate, is left out).

    The images are drawn on the part of the grid the votes and their blur can reach (a
    tile's events: a fifth to a half of the sensor's cells), and the variance is taken over
    the whole grid from the sums over that part: the cells beyond it hold zeros."""
    from scipy.ndimage import gaussian_filter

    w, h = int(np.ceil(width / scale)), int(np.ceil(height / scale))
    k = len(velocities)
    if not len(x):
        return np.zeros(k)
    f32 = np.float32
    v = (velocities / scale).astype(f32)
    # cells of the reach of the farthest carried event, its bilinear votes and the blur's
    # taps (4 cells, as ``truncate=4``), with one to spare
    reach = float(np.abs(v).max(initial=0.0)) * float(np.abs(tau).max(initial=0.0)) + 6.0
    bx0 = max(int(np.floor(x.min() / scale - reach)), 0)
    by0 = max(int(np.floor(y.min() / scale - reach)), 0)
    bw = min(int(np.ceil(x.max() / scale + reach)), w) - bx0
    bh = min(int(np.ceil(y.max() / scale + reach)), h) - by0
    stride, rows = bw + 4, bh + 4
    xs = (x / scale).astype(f32)[None, :] - v[:, :1] * tau.astype(f32)[None, :]
    ys = (y / scale).astype(f32)[None, :] - v[:, 1:] * tau.astype(f32)[None, :]
    # clipped into a two-cell margin of the sensor's grid, cropped away: an event carried
    # off the grid votes nowhere that counts (see cmax._Taps)
    np.clip(xs, -2.0, w + 0.5, out=xs)
    np.clip(ys, -2.0, h + 0.5, out=ys)
    x0, y0 = np.floor(xs), np.floor(ys)
    fx, fy = xs - x0, ys - y0
    gx, gy = 1 - fx, 1 - fy
    base = (np.arange(k)[:, None] * rows + y0.astype(np.intp) + (2 - by0)) * stride + \
        x0.astype(np.intp) + (2 - bx0)
    acc = np.bincount(np.concatenate([base.ravel(), (base + 1).ravel(),
                                      (base + stride).ravel(), (base + stride + 1).ravel()]),
                      np.concatenate([(gx * gy).ravel(), (fx * gy).ravel(),
                                      (gx * fy).ravel(), (fx * fy).ravel()]),
                      minlength=k * rows * stride)
    img = acc.reshape(k, rows, stride)[:, 2:-2, 2:-2].astype(np.float32)
    img = gaussian_filter(img, (0, 1.0, 1.0), mode="constant", truncate=4.0)
    flat = img.reshape(k, -1).astype(np.float64)
    cells = w * h
    mean = flat.sum(axis=1) / cells
    return np.einsum("ij,ij->i", flat, flat) / cells - mean * mean
