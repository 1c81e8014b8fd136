"""The true camera path in trmd HDF5: written by `trmd simulate` and pregenerate, read back by
HDF5Recording and open_dataset; files without it keep reading as before."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import texture
from trmd_cli.cli.app import app
from trmd_cli.deconv import BlurOperator
from trmd_cli.errors import InputError
from trmd_cli.events import Exposure, make_stream
from trmd_cli.metrics import psnr
from trmd_cli.motion import SampledMotion
from trmd_cli.read import open_events
from trmd_cli.read.base import ReadOptions
from trmd_cli.read.dataset import open_dataset
from trmd_cli.simulate.dataset import H5SampleDataset, SimulatedDataset, pregenerate
from trmd_cli.write import H5Writer, write_image

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def sim_h5(tmp_path_factory):
    d = tmp_path_factory.mktemp("truepath")
    write_image(d / "tex.png", texture(200, 260, seed=5))
    out = d / "sim.h5"
    r = run("simulate", d / "tex.png", "-o", out, "--size", "96x72", "--count", "2",
            "--frames", "2", "--exposure-ms", "10", "--clean", "--seed", "4", "--motion-px",
            "20")
    assert r.exit_code == 0, r.output
    return out


def test_simulate_stores_each_exposures_path(sim_h5):
    with h5py.File(sim_h5, "r") as f:
        mot = f["frames/motion"][...]
        sharp = f["frames/sharp"][...]
    assert mot.shape == (4, 33, 3, 3) and mot.dtype == np.float64
    # every path is the identity at its own mid-exposure and H[2, 2] = 1 throughout
    np.testing.assert_allclose(mot[:, 16], np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-9)
    np.testing.assert_allclose(mot[..., 2, 2], 1.0)
    inner = (slice(12, -12), slice(12, -12))
    for k in range(4):
        op = BlurOperator(SampledMotion(mot[k]), 96, 72)
        end = op.warp(op.pad_frame(sharp[k, 3]), [1.0]).numpy()[0, 0]
        # 15–17 dB unwarped; warped, what is left is the second bilinear resampling of a
        # texture with detail down to the pixel (measured 35–44 dB)
        assert psnr(sharp[k, 3][inner], sharp[k, 6][inner]) < 20
        assert psnr(end[inner], sharp[k, 6][inner]) > 33, k


def test_readers_hand_out_the_path(sim_h5):
    with open_events(sim_h5) as rec:
        assert rec.has_true_motion
        assert rec.true_motion(3).shape == (33, 3, 3)
    with open_dataset(sim_h5, 3) as src:
        assert src.has_true_motion
        frames = list(src.frames())
    assert all(isinstance(f.motion, SampledMotion) for f in frames)
    assert frames[0].motion.centre == (47.5, 35.5)


def _old_file(path):
    ev = make_stream(np.arange(100) % 32, np.arange(100) % 24, np.arange(100) * 10,
                     np.where(np.arange(100) % 2, 1, -1), 32, 24)
    with H5Writer(path, 32, 24) as w:
        w.add_events(ev)
        w.add_frame(np.full((24, 32), 0.5, np.float32), Exposure(0, 1_000),
                    sharp=np.zeros((7, 24, 32), np.float32), contrast=0.2)
    return path


def test_files_without_a_path_read_as_before(tmp_path):
    p = _old_file(tmp_path / "old.h5")
    with open_events(p) as rec:
        assert not rec.has_true_motion and rec.true_motion(0) is None
    with open_dataset(p, 3, ReadOptions()) as src:
        assert not src.has_true_motion
        assert next(iter(src.frames())).motion is None


def test_writer_refuses_inconsistent_paths(tmp_path):
    b = np.zeros((24, 32), np.float32)
    eye = np.broadcast_to(np.eye(3), (5, 3, 3))
    with pytest.raises(InputError, match="expected"), H5Writer(tmp_path / "a.h5", 32, 24) as w:
        w.add_frame(b, Exposure(0, 10), motion=np.eye(3))
    with pytest.raises(InputError, match="first frame"), H5Writer(tmp_path / "b.h5", 32, 24) as w:
        w.add_frame(b, Exposure(0, 10), motion=eye)
        w.add_frame(b, Exposure(20, 30))
    with pytest.raises(InputError, match="shape"), H5Writer(tmp_path / "c.h5", 32, 24) as w:
        w.add_frame(b, Exposure(0, 10), motion=eye)
        w.add_frame(b, Exposure(20, 30), motion=eye[:3])
    assert not any(tmp_path.iterdir())  # nothing half-written


def test_damaged_path_is_a_format_error(tmp_path):
    p = _old_file(tmp_path / "bad.h5")
    with h5py.File(p, "a") as f:
        f["frames"].create_dataset("motion", data=np.full((1, 4, 3, 3), np.nan))
    from trmd_cli.errors import FormatError

    with open_events(p) as rec, pytest.raises(FormatError, match="frames/motion"):
        rec.true_motion(0)


def test_pregenerated_sets_store_the_samples_paths(tmp_path):
    images = [texture(120, 160, seed=7)]
    out = tmp_path / "train.h5"
    pregenerate(images, out, 2, n=1, crop=32, seed=3)
    ds = SimulatedDataset(images, n=1, crop=32, length=2, seed=3)
    with h5py.File(out, "r") as f:
        mot = f["frames/motion"][...]
    for i in range(2):
        np.testing.assert_allclose(mot[i], ds.sample(i).motion)
    assert len(H5SampleDataset(out)) == 2  # the training reader does not mind the extra data
