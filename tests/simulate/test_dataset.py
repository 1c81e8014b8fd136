"""Training datasets: simulated on the fly, pre-generated to HDF5 and read back."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tests.helpers.data import texture  # noqa: E402
from trmd_cli.errors import FormatError, InputError, OutputExistsError  # noqa: E402
from trmd_cli.simulate import MotionRanges  # noqa: E402
from trmd_cli.simulate.dataset import (  # noqa: E402
    H5SampleDataset,
    SensorRanges,
    SimulatedDataset,
    pregenerate,
)
from trmd_cli.voxel import scer_voxels  # noqa: E402

CROP = 48


@pytest.fixture(scope="module")
def images():
    return [texture(150, 200, seed=s) for s in range(3)]


@pytest.fixture(scope="module")
def dataset(images):
    return SimulatedDataset(images, n=2, crop=CROP, length=6, seed=5,
                            motion={"translation_px": 20.0})


def test_items_have_the_documented_shapes(dataset):
    item = dataset[0]
    assert set(item) == {"blurry", "voxels", "sharp", "contrast"}
    assert item["blurry"].shape == (1, CROP, CROP)
    assert item["voxels"].shape == (4, CROP, CROP)
    assert item["sharp"].shape == (5, 1, CROP, CROP)
    assert item["contrast"].shape == ()
    assert all(v.dtype == torch.float32 for v in item.values())
    assert 0.1 <= float(item["contrast"]) <= 0.5


def test_items_are_a_function_of_seed_and_index(dataset, images):
    a, b = dataset[3], dataset[3]
    for k in a:
        assert torch.equal(a[k], b[k])
    assert not torch.equal(dataset[3]["blurry"], dataset[4]["blurry"])
    other = SimulatedDataset(images, n=2, crop=CROP, length=6, seed=6,
                             motion={"translation_px": 20.0})
    assert not torch.equal(other[3]["blurry"], a["blurry"])


def test_voxels_are_scer_of_the_sample_events(dataset):
    s = dataset.sample(2)
    np.testing.assert_array_equal(dataset[2]["voxels"].numpy(), scer_voxels(s.events,
                                                                           s.exposure, 2))
    assert s.exposure.duration_us % 4 == 0  # 2N equal integer bins
    np.testing.assert_allclose(dataset[2]["sharp"].numpy()[:, 0], s.sharp)


def test_sensor_ranges_are_drawn_per_sample():
    ranges = SensorRanges(contrast=(0.2, 0.3), clean_prob=0.0)
    rng = np.random.default_rng(0)
    configs = [ranges.draw(rng) for _ in range(200)]
    means = np.array([c.mean_contrast for c in configs])
    assert means.min() >= 0.2 - 1e-9 and means.max() <= 0.3 + 1e-9
    assert abs(means.mean() - 0.25) < 0.01
    assert not any(c.is_clean for c in configs)
    shot = np.array([c.shot_noise_hz for c in configs])
    assert 0 <= shot.min() and shot.max() <= 1.0 and shot.std() > 0.2
    always_clean = SensorRanges(clean_prob=1.0)
    assert always_clean.draw(rng).is_clean


def test_bad_settings_are_input_errors(images):
    with pytest.raises(InputError, match="unknown key"):
        SimulatedDataset(images, sensor_ranges={"contrst": (0.1, 0.2)})
    with pytest.raises(InputError):
        SimulatedDataset(images, channels=3)
    with pytest.raises(InputError):
        SensorRanges(contrast=(0.5, 0.1))
    with pytest.raises(InputError):
        SimulatedDataset([])


def test_dicts_from_recipes_are_accepted(images):
    ds = SimulatedDataset(images, n=1, crop=32, length=2,
                          sensor_ranges={"contrast": [0.2, 0.2], "clean_prob": 1.0},
                          motion={"translation_px": 5.0, "layer_size": [0.2, 0.3]})
    assert ds.sensor_ranges.contrast == (0.2, 0.2)
    assert isinstance(ds.motion, MotionRanges) and ds.motion.layer_size == (0.2, 0.3)
    assert float(ds[0]["contrast"]) == pytest.approx(0.2)


def test_pregenerated_file_reads_back_the_same_items(tmp_path, images, dataset):
    out = tmp_path / "train.h5"
    seen = []
    pregenerate(images, out, 4, n=2, crop=CROP, seed=5, motion={"translation_px": 20.0},
                progress=lambda done, total: seen.append((done, total)))
    assert seen[-1] == (4, 4)
    h5 = H5SampleDataset(out)
    assert len(h5) == 4 and h5.n == 2
    for i in range(4):
        got, want = h5[i], dataset[i]
        assert set(got) == set(want)
        for k in want:
            torch.testing.assert_close(got[k], want[k], rtol=0, atol=0)
    with pytest.raises(OutputExistsError):
        pregenerate(images, out, 1, n=2, crop=CROP)


def test_h5_dataset_rejects_other_files(tmp_path):
    import h5py

    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(FormatError):
        H5SampleDataset(p)


def test_h5_dataset_survives_pickling(tmp_path, images):
    import pickle

    out = tmp_path / "t.h5"
    pregenerate(images, out, 2, n=1, crop=32, seed=1)
    ds = H5SampleDataset(out)
    _ = ds[0]
    clone = pickle.loads(pickle.dumps(ds))  # what DataLoader workers receive
    torch.testing.assert_close(clone[1]["voxels"], ds[1]["voxels"])


def test_training_motion_covers_small_and_heavy_blur():
    from trmd_cli.simulate.dataset import DATASET_MOTION
    from trmd_cli.simulate.trajectory import CameraPath

    rng = np.random.default_rng(0)
    extents = []
    for _ in range(400):
        path = CameraPath(128, 128, DATASET_MOTION, 1.0, rng, centre=0.5)
        centre = np.array([63.5, 63.5, 1.0])
        g = path.homographies(np.array([0.0, 1.0])) @ centre
        extents.append(np.linalg.norm(g[1, :2] / g[1, 2] - g[0, :2] / g[0, 2]))
    extents = np.array(extents)
    # log-uniform 3.5–70 px (bent paths wander a little either way)
    assert 0.3 < np.mean(extents > 20) < 0.55
    assert np.mean(extents > 45) > 0.08
    assert np.mean(extents < 8) > 0.15


def test_pregenerate_with_workers_writes_the_same_samples(tmp_path, images):
    one, two = tmp_path / "one.h5", tmp_path / "two.h5"
    kw = dict(n=1, crop=32, seed=3, motion={"translation_px": 10.0})
    pregenerate(images, one, 3, **kw)
    pregenerate(images, two, 3, workers=2, compression="gzip", **kw)
    a, b = H5SampleDataset(one), H5SampleDataset(two)
    for i in range(3):
        for k in ("blurry", "voxels", "sharp", "contrast"):
            assert torch.equal(a[i][k], b[i][k])


@pytest.mark.parametrize("kw, needle", [
    ({"gain": [1, 0.5]}, "gain = \\[1, 0.5\\] is not a range 0 < low ≤ high"),
    ({"gain": [0, 0]}, "gain"),
    ({"zoom": [-1, -1]}, "zoom"),
    ({"read_noise": [-1, -1]}, "read_noise = \\[-1, -1\\] is not a range 0 ≤ low"),
    ({"exposure_ms": [0, 0]}, "exposure_ms"),
    ({"sensor_ranges": {"contrast": 0.3}}, "sensor_ranges.contrast = 0.3 is not a range"),
])
def test_simulator_ranges_that_cannot_be_are_refused(kw, needle):
    """Each names its key (was: a numpy ValueError, a 'float is not iterable', or a run on
    black images for a gain of 0)."""
    from trmd_cli.errors import InputError
    from trmd_cli.simulate.dataset import SimulatedDataset

    with pytest.raises(InputError, match=needle):
        SimulatedDataset([np.zeros((64, 64), np.float32)], crop=32, **kw)
