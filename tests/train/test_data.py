"""Training data: which reader for which path, the GOPRO-layout reader, splits, the sampler.

``make_gopro_h5`` is also used by the other training tests: a tiny, physically consistent set
(blur = mean of the sharp frames, voxels = rounded log-intensity changes / c).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.helpers.training import make_gopro_h5, make_image_folder, write_trmd_h5
from trmd_cli.errors import FormatError, InputError
from trmd_cli.train.data import (
    GOPRO_LUMA,
    EpochSampler,
    GoproH5Dataset,
    build_data,
    detect_kind,
    gather,
)
from trmd_cli.train.recipe import Recipe, apply_overrides

N = 3


def recipe(*overrides: str) -> Recipe:
    base = ["model.name='test_trmd'", "data.crop=32", "data.batch_size=2"]
    return apply_overrides(Recipe(), base + list(overrides))


# --------------------------------------------------------------------------------------------
# GOPRO layout


def test_gopro_gray_item_matches_the_file(tmp_path):
    path = make_gopro_h5(tmp_path / "g.h5", k=3)
    ds = GoproH5Dataset(path, n=N, channels=1, crop=0)
    item = ds[1]
    assert item["blurry"].shape == (1, 40, 48)
    assert item["voxels"].shape == (2 * N, 40, 48)
    assert item["sharp"].shape == (2 * N + 1, 1, 40, 48)
    assert torch.isnan(item["contrast"])
    import h5py

    with h5py.File(path) as f:
        rgb = f["sharp_images"][1, 2].astype(np.float64) / 255
        expected = rgb @ np.asarray(GOPRO_LUMA)  # skimage rgb2gray weights
        assert np.allclose(item["sharp"][2, 0].numpy(), expected, atol=1e-6)
        assert np.array_equal(item["voxels"].numpy(), f["voxel"][1])


def test_gopro_rgb_and_crops(tmp_path):
    path = make_gopro_h5(tmp_path / "g.h5", k=4)
    full = GoproH5Dataset(path, n=N, channels=3, crop=0)[2]
    assert full["blurry"].shape == (3, 40, 48)
    ds = GoproH5Dataset(path, n=N, channels=3, crop=16, random_crop=True, seed=5)
    a = ds[2]
    assert a["blurry"].shape == (3, 16, 16) and a["sharp"].shape == (7, 3, 16, 16)
    # the crop is a window of the full frame, the same for every key
    ys, xs = ds._window(2)
    assert torch.equal(a["blurry"], full["blurry"][:, ys, xs])
    assert torch.equal(a["voxels"], full["voxels"][:, ys, xs])
    # a pure function of (seed, epoch, index): equal again, different in another epoch
    assert torch.equal(ds[2]["blurry"], a["blurry"])
    windows = set()
    for e in range(6):
        ds.set_epoch(e)
        ys, xs = ds._window(2)
        windows.add((ys.start, xs.start))
    assert len(windows) > 1
    centre = GoproH5Dataset(path, n=N, channels=1, crop=16, random_crop=False)
    assert centre._window(0) == (slice(12, 28), slice(16, 32))


def test_gopro_wrong_n_and_oversized_crop(tmp_path):
    path = make_gopro_h5(tmp_path / "g.h5", k=2)
    with pytest.raises(FormatError, match="N=2"):
        GoproH5Dataset(path, n=2)
    with pytest.raises(InputError, match="crop 64"):
        GoproH5Dataset(path, n=N, crop=64)


# --------------------------------------------------------------------------------------------
# Which reader


def test_detect_kind(tmp_path):
    assert detect_kind(make_gopro_h5(tmp_path / "g.h5", k=1)) == "gopro_h5"
    assert detect_kind(write_trmd_h5(tmp_path / "t.h5")) == "trmd_h5"
    assert detect_kind(tmp_path / "x.png") == "images"
    import h5py

    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["data"] = np.zeros(3)
    with pytest.raises(FormatError, match="layout not recognised"):
        detect_kind(tmp_path / "other.h5")
    (tmp_path / "v.mp4").write_bytes(b"")
    with pytest.raises(InputError, match="extract its frames"):
        detect_kind(tmp_path / "v.mp4")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(InputError, match="not training data"):
        detect_kind(tmp_path / "notes.txt")
    (tmp_path / "broken.h5").write_bytes(b"not hdf5")
    with pytest.raises(FormatError, match="not a readable HDF5"):
        detect_kind(tmp_path / "broken.h5")


def test_gather_folders_and_errors(tmp_path):
    import cv2

    (tmp_path / "imgs" / "sub").mkdir(parents=True)
    for i, where in enumerate(["imgs/a.png", "imgs/sub/b.png"]):
        cv2.imwrite(str(tmp_path / where), np.full((20, 20), 40 * i, np.uint8))
    (tmp_path / "sets").mkdir()
    make_gopro_h5(tmp_path / "sets" / "g1.h5", k=1)
    write_trmd_h5(tmp_path / "sets" / "t.h5")
    groups = gather([tmp_path / "imgs", tmp_path / "sets"])
    assert groups[0] == ("images", [tmp_path / "imgs/a.png", tmp_path / "imgs/sub/b.png"])
    assert sorted(k for k, _ in groups[1:]) == ["gopro_h5", "trmd_h5"]
    with pytest.raises(InputError, match="not found"):
        gather([tmp_path / "missing"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images and no .h5"):
        gather([tmp_path / "empty"])
    with pytest.raises(InputError, match="no training data"):
        gather([])


# --------------------------------------------------------------------------------------------
# Training / validation split


def test_build_data_holds_out_the_tail_of_an_h5(tmp_path):
    path = make_gopro_h5(tmp_path / "g.h5", k=8)
    plan = build_data([path], recipe("data.val_fraction=0.25", "data.val_crop=0"))
    assert len(plan.train) == 6 and len(plan.val) == 2
    # validation = the last two samples, whole frames, deterministic
    full = GoproH5Dataset(path, n=N, crop=0)
    assert torch.equal(plan.val[0]["sharp"], full[6]["sharp"])
    assert torch.equal(plan.val[1]["blurry"], full[7]["blurry"])
    assert plan.train[0]["blurry"].shape == (1, 32, 32)


def test_build_data_val_data_and_no_validation(tmp_path):
    train_path = make_gopro_h5(tmp_path / "g.h5", k=6)
    (tmp_path / "val").mkdir()
    make_gopro_h5(tmp_path / "val" / "v.h5", k=5, seed=3)
    (tmp_path / "r.toml").write_text("[data]\nval_data = \"val/v.h5\"\nval_samples = 3\n"
                                     "val_crop = 16\ncrop = 32\n[model]\nname = \"test_trmd\"\n")
    from trmd_cli.train.recipe import load_recipe

    plan = build_data([train_path], load_recipe(tmp_path / "r.toml"))
    assert len(plan.train) == 6  # nothing held out when val_data is given
    assert len(plan.val) == 3 and plan.val_source.endswith("v.h5")
    assert plan.val[0]["blurry"].shape == (1, 16, 16)
    none = build_data([train_path], recipe("data.val_fraction=0.0"))
    assert none.val is None and any("no validation" in n for n in none.notes)


def test_build_data_trmd_h5_and_supervision_check(tmp_path):
    labelled = write_trmd_h5(tmp_path / "t.h5", k=4)
    plan = build_data([labelled], recipe("data.crop=16", "data.val_fraction=0.25"))
    item = plan.train[0]
    assert item["blurry"].shape == (1, 16, 16) and item["sharp"].shape == (7, 1, 16, 16)
    assert float(item["contrast"]) == pytest.approx(0.2)
    unlabelled = write_trmd_h5(tmp_path / "u.h5", sharp=False, k=4)
    with pytest.raises(InputError, match="no ground-truth sharp frames"):
        build_data([unlabelled], recipe("data.crop=16", "data.val_fraction=0.0"))
    r = recipe("data.crop=16", "data.val_fraction=0.0", "loss.residual=0", "loss.middle=0",
               "loss.event_consistency=1")
    plan = build_data([unlabelled], r, supervised=False)
    assert "sharp" not in plan.train[0]
    with pytest.raises(InputError, match="some `data` sets"):
        build_data([unlabelled, labelled], r, supervised=False)
    both = build_data([labelled, make_gopro_h5(tmp_path / "g.h5", k=2)],
                      recipe("data.crop=16", "data.val_fraction=0.0"))
    assert len(both.train) == 6 and torch.isnan(both.train[5]["contrast"])
    with pytest.raises(FormatError, match="for N=3"):
        build_data([make_gopro_h5(tmp_path / "g2.h5", k=2, n=2)],
                   recipe("model.n=3", "data.val_fraction=0.0"))


def test_a_crop_larger_than_the_frames_is_refused(tmp_path):
    """Whole frames of another size would train on what the recipe does not say."""
    labelled = write_trmd_h5(tmp_path / "t.h5", k=4)
    with pytest.raises(InputError, match="sample 0 is 24x24, smaller than the crop 1000"):
        build_data([labelled], recipe("data.crop=1000", "data.val_fraction=0.0")).train[0]


def test_build_data_image_folder_uses_the_simulator(tmp_path):
    make_image_folder(tmp_path / "imgs", 4)
    r = recipe("data.length=10", "data.val_fraction=0.25", "data.val_samples=3",
               "data.crop=24")
    plan = build_data([tmp_path / "imgs"], r)
    assert len(plan.train) == 10 and len(plan.val) == 3
    assert "3 image(s)" in plan.sources[0]  # one of four images held out
    a, b = plan.train[4], plan.train[4]
    assert a["sharp"].shape == (7, 1, 24, 24)
    assert torch.equal(a["voxels"], b["voxels"])  # deterministic per (seed, index)
    with pytest.raises(InputError, match="data.simulator"):
        build_data([tmp_path / "imgs"], recipe("data.simulator.no_such_knob=1"))


# --------------------------------------------------------------------------------------------
# Sampler


def test_sampler_shares_an_epoch_without_overlap_and_resumes():
    length, world = 23, 2
    parts = []
    for rank in range(world):
        s = EpochSampler(length, seed=4, rank=rank, world=world)
        s.set_position(3)
        parts.append(list(s))
        assert len(s) == length // world
    assert not set(parts[0]) & set(parts[1])
    assert len(parts[0]) + len(parts[1]) == 22
    # resuming mid-epoch continues the same order
    s = EpochSampler(length, seed=4, rank=1, world=world)
    s.set_position(3, skip=5)
    assert list(s) == parts[1][5:] and len(s) == len(parts[1]) - 5
    # another epoch, another order; the same epoch, the same order
    s.set_position(4)
    assert list(s) != parts[1]
    s.set_position(3)
    assert list(s) == parts[1]
    with pytest.raises(InputError):
        EpochSampler(1, seed=0, world=2)
