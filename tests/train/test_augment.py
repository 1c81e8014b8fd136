"""Training augmentations keep the physics: time reversal of events == reversed SCER channels."""

from __future__ import annotations

import numpy as np
import torch

from trmd_cli.events import Exposure, make_stream
from trmd_cli.train.data import augment_item
from trmd_cli.voxel import scer_voxels


def test_time_reversal_equals_reversed_voxel_channels(rng):
    n, T = 3, 6000
    # avoid exact bin edges (multiples of 1000), where "[lo, hi)" flips side under reversal
    t = np.sort(rng.integers(0, T, 4000))
    t = t[t % (T // (2 * n)) != 0]
    x, y, p = (rng.integers(0, s, len(t)) for s in (9, 7, 2))
    fwd = make_stream(x, y, t, p, 9, 7)
    rev = make_stream(x[::-1], y[::-1], T - t[::-1], 1 - p[::-1], 9, 7)
    v, vr = scer_voxels(fwd, Exposure(0, T), n), scer_voxels(rev, Exposure(0, T), n)
    np.testing.assert_array_equal(vr, v[::-1])


def test_augment_item_consistent_across_keys(rng):
    item = {"blurry": torch.rand(1, 8, 8), "voxels": torch.rand(6, 8, 8),
            "sharp": torch.rand(7, 1, 8, 8)}
    seen = set()
    for seed in range(40):
        out = augment_item(item, np.random.default_rng(seed))
        # the mapping applied to blurry must be the one applied to every sharp frame: find it
        geom = (item["blurry"][0], out["blurry"][0])
        reversed_time = torch.equal(out["voxels"][0], _same_geom(item["voxels"][5], *geom))
        seen.add(reversed_time)
        # middle frame stays the middle frame; the set of frames is the same up to order
        assert torch.equal(out["sharp"][3, 0], _same_geom(item["sharp"][3, 0], *geom))
    assert seen == {True, False}


def _same_geom(src: torch.Tensor, ref_in: torch.Tensor, ref_out: torch.Tensor) -> torch.Tensor:
    """Apply to ``src`` whichever flip/transpose maps ``ref_in`` to ``ref_out``."""
    for tr in (False, True):
        for hf in (False, True):
            for vf in (False, True):
                def f(a, hf=hf, vf=vf, tr=tr):
                    a = a.flip(-1) if hf else a
                    a = a.flip(-2) if vf else a
                    return a.transpose(-1, -2) if tr else a
                if torch.equal(f(ref_in), ref_out):
                    return f(src)
    raise AssertionError("no geometric mapping found")
