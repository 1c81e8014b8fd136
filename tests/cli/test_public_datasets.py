"""The public DAVIS layouts through every command that reads recordings: an AEDAT 3.1 file, a
ROS 1 bag and an RPG folder, each with two frames, through info, convert, voxelize, deblur,
hfr and eval."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers import aedat as A
from tests.helpers.rosbag import BagBuilder
from tests.read.test_rpg import rpg_folder
from trmd_cli.cli.app import app

runner = CliRunner()
W, H = 40, 30


def _aedat3(tmp, rng):
    n = 4000
    t = np.sort(rng.integers(0, 400_000, n))
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    p = np.where(rng.integers(0, 2, n) == 1, 1, -1)
    img = (rng.random((H, W)) * 40_000 + 10_000).astype(np.uint16)
    path = tmp / "rec.aedat"
    path.write_bytes(A.aedat3_header("Camera") + A.polarity_packet(x, y, t, p)
                     + A.frame_packet(img, (50_000, 80_000))
                     + A.frame_packet(img, (250_000, 280_000)))
    return path, ["--sensor", f"{W}x{H}"]


def _bag(tmp, rng):
    b = BagBuilder(False)
    t0 = 1_600_000_000_000_000_000
    n = 4000
    t = t0 + np.sort(rng.integers(0, 400_000, n)) * 1000
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    p = np.where(rng.integers(0, 2, n) == 1, 1, -1)
    for i in range(0, n, 500):
        b.events("/dvs/events", t[i:i + 500], x[i:i + 500], y[i:i + 500], p[i:i + 500], W, H)
    for k in range(2):
        img = (rng.random((H, W)) * 200 + 20).astype(np.uint8)
        b.image("/dvs/image_raw", t0 + (65_000 + 200_000 * k) * 1000, img)
        b.int32("/dvs/exposure", 30_000, t0 + (65_001 + 200_000 * k) * 1000)
    return b.write(tmp / "rec.bag"), ["--stamp", "middle"]


def _rpg(tmp, rng):
    d, _, _, _ = rpg_folder(tmp, rng, n=4000, frames=2)
    return d, ["--exposure-length", "30ms", "--stamp", "middle"]


@pytest.mark.parametrize("make", [_aedat3, _bag, _rpg], ids=["aedat3", "rosbag1", "rpg"])
def test_every_command_reads_it(tmp_path, rng, make):
    src, opts = make(tmp_path, rng)
    r = runner.invoke(app, ["info", str(src), "--json", *opts])
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    assert info["events"] == 4000 and len(info["frames"]) == 2
    windows = [(f["start_us"], f["end_us"]) for f in info["frames"]]

    r = runner.invoke(app, ["convert", str(src), "-o", str(tmp_path / "c.h5"), *opts])
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "c.h5") as f:
        assert len(f["events/t"]) == 4000
        assert list(zip(f["frames/exposure_start"][:], f["frames/exposure_end"][:],
                        strict=True)) == windows

    r = runner.invoke(app, ["voxelize", str(src), "-o", str(tmp_path / "v.npz"), *opts])
    assert r.exit_code == 0, r.output
    with np.load(tmp_path / "v.npz") as z:
        assert z["exposure"].tolist() == [list(w) for w in windows]

    r = runner.invoke(app, ["deblur", str(src), "-o", str(tmp_path / "d"), "--method", "edi",
                            "--contrast", "0.2", *opts])
    assert r.exit_code == 0, r.output
    meta = json.loads((tmp_path / "d" / "meta.json").read_text())
    assert len(meta["frames"]) == 2

    r = runner.invoke(app, ["hfr", str(src), "-o", str(tmp_path / "h"), "--method", "edi",
                            "--contrast", "0.2", "--per-exposure", "3", *opts])
    assert r.exit_code == 0, r.output

    r = runner.invoke(app, ["eval", str(src), "--methods", "blurry,edi", "--json",
                            str(tmp_path / "e.json"), *opts])
    assert r.exit_code == 0, r.output
    report = json.loads((tmp_path / "e.json").read_text())
    scored = report["datasets"][0]
    assert scored["frames"] == 2 and not scored["methods"]["edi"]["skipped"]
