"""GOPRO-style HDF5 (trmd_cli.read.gopro) and the evaluation datasets made from it
(trmd_cli.read.dataset): recognised by content, frames in [0, 1], voxels back to bin counts,
layouts that do not fit refused."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from tests.helpers.training import make_gopro_h5, write_trmd_h5
from trmd_cli.errors import FormatError, InputError
from trmd_cli.read.dataset import open_dataset
from trmd_cli.read.gopro import GoproFile, is_gopro_h5
from trmd_cli.voxel import scer_from_bins

N = 3


@pytest.fixture(scope="module")
def gopro_h5(tmp_path_factory):
    return make_gopro_h5(tmp_path_factory.mktemp("g") / "g.h5", k=3)


def test_recognised_by_its_datasets(gopro_h5, tmp_path):
    assert is_gopro_h5(gopro_h5)
    assert not is_gopro_h5(write_trmd_h5(tmp_path / "t.h5"))
    (tmp_path / "x.h5").write_bytes(b"not hdf5 at all")
    assert not is_gopro_h5(tmp_path / "x.h5")


def test_frames_truth_and_bins(gopro_h5):
    with h5py.File(gopro_h5, "r") as f:
        blur, sharp, vox = f["blur_images"][1], f["sharp_images"][1], f["voxel"][1]
    with GoproFile(gopro_h5, N) as g:
        assert len(g) == 3 and (g.width, g.height, g.n) == (48, 40, N)
        assert g.has_sharp and g.sharp_count == 2 * N + 1
        np.testing.assert_array_equal(g.blurry(1), blur.astype(np.float32) / 255)
        np.testing.assert_array_equal(g.sharp(1), sharp.astype(np.float32) / 255)
        np.testing.assert_array_equal(scer_from_bins(g.bins(1).astype(np.float32)), vox)


def test_dataset_frames_carry_bins_not_events(gopro_h5):
    with open_dataset(gopro_h5, N) as src:
        assert src.kind == "gopro-h5" and not src.has_raw_events and src.has_ground_truth
        frames = list(src.frames(limit=2))
    assert len(frames) == 2 and frames[0].events is None and frames[0].exposure is None
    assert frames[0].bins.shape == (2 * N, 40, 48)
    np.testing.assert_array_equal(frames[0].instants_us, np.linspace(0, 1, 2 * N + 1))


def test_layouts_that_do_not_fit(gopro_h5, tmp_path):
    with pytest.raises(InputError, match="not 2N = 4.*`n=3`"):
        GoproFile(gopro_h5, 2)
    bad = tmp_path / "b.h5"
    with h5py.File(bad, "w") as f:
        f["blur_images"] = np.zeros((2, 8, 8), np.uint8)
        f["voxel"] = np.zeros((3, 6, 8, 8), np.float32)
    with pytest.raises(FormatError, match="do not fit"):
        GoproFile(bad)
