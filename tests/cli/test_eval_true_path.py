"""`trmd eval --methods motion,motion-true-path`: the motion method along the simulator's true
camera path beside the estimated one, and the one-line refusal on sets without a path."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.cli import assert_one_error_line
from tests.helpers.data import texture
from trmd_cli.cli.app import app
from trmd_cli.errors import InputError
from trmd_cli.evaluate import evaluate_dataset
from trmd_cli.oracle import TRUE_PATH
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sequence
from trmd_cli.write import H5Writer

runner = CliRunner()
W, H = 112, 84


@pytest.fixture(scope="module")
def seq():
    """2 clean exposures, up to 25 px of camera translation with some rotation."""
    return make_sequence(texture(240, 300, seed=2), n=3, size=(W, H), exposure_us=20_000,
                         frames=2, rng=np.random.default_rng(1),
                         sensor=SensorConfig.clean(0.2, eps=0.001),
                         motion=MotionRanges(translation_px=25, rotation_deg=2, scale=0.02,
                                             perspective=0.0))


def _write(path, seq, motion=True):
    with H5Writer(path, W, H) as w:
        w.add_events(seq.events)
        for k, e in enumerate(seq.exposures):
            w.add_frame(seq.blurry[k], e, sharp=seq.sharp[k], contrast=seq.contrast,
                        motion=seq.motion[k] if motion else None)
    return path


@pytest.fixture(scope="module")
def sets(seq, tmp_path_factory):
    d = tmp_path_factory.mktemp("truepath")
    return _write(d / "sim.h5", seq), _write(d / "nopath.h5", seq, motion=False)


@pytest.fixture(scope="module")
def report(sets):
    return evaluate_dataset(sets[0], f"blurry,edi,motion,{TRUE_PATH}", 3, lpips=False)


def _mid(report, method):
    return next(m for m in report.methods if m.method == method).mean("psnr_mid")


def test_true_path_is_a_row_beside_the_estimate(report):
    names = [m.method for m in report.methods]
    assert names == ["blurry", "edi", "motion", TRUE_PATH]
    assert all(len(m.frames) == 2 and m.skipped is None for m in report.methods)
    blurry, edi = _mid(report, "blurry"), _mid(report, "edi")
    est, true = _mid(report, "motion"), _mid(report, TRUE_PATH)
    # measured (mean of the 2 frames): blurry 32.0, EDI 31.1, motion 36.5, true path 39.0 dB
    assert true > edi + 5 and true > blurry + 5
    # a perfect motion is at least as good as the estimate (a little noise in the guard aside)
    assert true >= est - 0.2, (est, true)


def test_cli_prints_the_row_and_the_json_says_what_it_is(sets, tmp_path):
    out = tmp_path / "r.json"
    r = runner.invoke(app, ["eval", str(sets[0]), "--methods", f"blurry,{TRUE_PATH}",
                            "--limit", "1", "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "motion-true" in r.stdout  # the table may cut the name to its column
    data = json.loads(out.read_text())
    assert "true camera path" in data["protocol"]["methods"][TRUE_PATH]
    rows = data["datasets"][0]["methods"]
    assert list(rows) == ["blurry", TRUE_PATH]


def test_a_set_without_a_path_is_refused_in_one_line(sets, tmp_path):
    out = tmp_path / "r.json"
    r = runner.invoke(app, ["eval", str(sets[1]), "--methods", f"edi,{TRUE_PATH}",
                            "--json", str(out)])
    assert_one_error_line(r, "nopath.h5", r"no true camera path \(frames/motion\)")
    assert not out.exists()
    with pytest.raises(InputError, match="frames/motion"):
        evaluate_dataset(sets[1], TRUE_PATH, 3, lpips=False)
