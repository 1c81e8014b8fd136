"""`trmd deblur` in several processes (--jobs, torchrun ranks), resumed, over several
recordings: the output equals a one-process run's file for file."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from tests.cli.test_interrupt_deblur import write_recording
from tests.helpers.cli import assert_one_error_line
from trmd_cli.batch import Settings, Stage, make_plan, prepare_stage, run_share
from trmd_cli.cli.app import app
from trmd_cli.methods import MethodConfig
from trmd_cli.read.base import ReadOptions

runner = CliRunner()
#: the same arithmetic in every process: EDI, float32, one thread
SAME = ("--method", "edi", "--precision", "fp32", "--threads", "1")


@pytest.fixture(scope="module")
def recs(tmp_path_factory) -> Path:
    """A folder of two tiny recordings (5 and 3 frames of 64x48)."""
    folder = tmp_path_factory.mktemp("recs")
    write_recording(folder / "a.h5", 5)
    write_recording(folder / "b.h5", 3)
    return folder


@pytest.fixture(scope="module")
def reference(recs, tmp_path_factory) -> Path:
    """One process, today's path: the output every other run must equal."""
    out = tmp_path_factory.mktemp("ref") / "out"
    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(out), *SAME])
    assert r.exit_code == 0, r.output
    return out


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def assert_same(a: Path, b: Path) -> None:
    fa, fb = files(a), files(b)
    assert sorted(fa) == sorted(fb)
    assert [k for k in fa if fa[k] != fb[k]] == []


def no_stage(out: Path) -> None:
    assert sorted(p.name for p in out.parent.iterdir() if p.name.startswith(".")) == []


def test_two_jobs_equal_one_process(recs, reference, tmp_path):
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(out), *SAME, "--jobs", "2"])
    assert r.exit_code == 0, r.output
    assert_same(reference, out)
    no_stage(out)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_torchrun_ranks_equal_one_process(recs, reference, tmp_path):
    """Two real processes with torchrun's variables, as on two machines sharing a disk."""
    out = tmp_path / "out"
    port = _free_port()
    procs = []
    for rank in range(2):
        env = {**os.environ, "RANK": str(rank), "WORLD_SIZE": "2", "LOCAL_RANK": str(rank),
               "LOCAL_WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "trmd_cli", "deblur", str(recs / "a.h5"), "-o", str(out),
             *SAME], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    said = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], said
    assert "rank 1: deblurred 2 frames" in said[1][0]  # frames 1 and 3 of 0..4
    assert_same(reference, out)
    no_stage(out)


def test_resume_completes_a_partial_run(recs, reference, tmp_path):
    """Rank 0 of 2 finished, rank 1 died: one after its frame folder was renamed in but
    before its record, leaving a temporary of a process that is gone."""
    out = tmp_path / "out"
    s = Settings(MethodConfig(method="edi", precision="fp32", threads=1), ReadOptions())
    plan = make_plan([[str(recs / "a.h5")]], [""], s)
    stage, _ = prepare_stage(plan, out, resume=False)
    assert run_share(plan, stage, plan.share(0, 2)).frames == 3
    shutil.copytree(reference / "a.h5_frame1", stage.out / "a.h5_frame1")  # no record: redone
    (stage.out / ".a.h5_frame3.trmd-999999999-x.tmp").mkdir()
    assert len(stage.pending(plan)) == 2

    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(out), *SAME, "--resume"])
    assert r.exit_code == 0, r.output
    assert "resuming: 3 of 5 frames are done already" in r.stdout
    assert_same(reference, out)
    no_stage(out)


def test_failed_share_keeps_its_frames_for_resume(recs, reference, tmp_path, monkeypatch):
    """A share failing midway stops the run: no output, the finished frames stay for --resume
    (the CLI says so), which then completes it."""
    import trmd_cli.batch as batch

    out = tmp_path / "out"
    real = batch.run_share

    def fail_after_two(plan, stage, share, tick=lambda: None):
        real(plan, stage, share[:2], tick)
        raise batch.ShardError("stand-in failure of a share")

    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(out), *SAME, "--resume"])
    assert_one_error_line(r, "out", "nothing to resume")
    monkeypatch.setattr(batch, "run_share", fail_after_two)
    r = runner.invoke(app, ["deblur", str(recs), "-o", str(out), *SAME])
    assert r.exit_code == 2 and "stand-in failure" in r.stderr
    assert "--resume" in r.stderr and not out.exists()
    assert len(list(Stage(out).done.iterdir())) == 2
    monkeypatch.setattr(batch, "run_share", real)
    r = runner.invoke(app, ["deblur", str(recs), "-o", str(out), *SAME, "--resume"])
    assert r.exit_code == 0, r.output
    assert "resuming: 2 of 8 frames are done already" in r.stdout
    assert_same(reference, out / "a")
    no_stage(out)


def test_folder_of_recordings_one_folder_each(recs, tmp_path):
    """Each recording's folder equals that recording deblurred alone."""
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(recs), "-o", str(out), *SAME, "--jobs", "2"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["a", "b"]
    for name in ("a", "b"):
        alone = tmp_path / f"alone_{name}"
        r = runner.invoke(app, ["deblur", str(recs / f"{name}.h5"), "-o", str(alone), *SAME])
        assert r.exit_code == 0, r.output
        assert_same(alone, out / name)
    listed = tmp_path / "listed"
    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), str(recs / "b.h5"), "-o",
                            str(listed), *SAME])
    assert r.exit_code == 0, r.output
    assert_same(out, listed)


def test_resume_with_other_settings_is_refused(recs, tmp_path):
    out = tmp_path / "out"
    s = Settings(MethodConfig(method="edi", precision="fp32", threads=1), ReadOptions())
    plan = make_plan([[str(recs / "a.h5")]], [""], s)
    prepare_stage(plan, out, resume=False)
    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(out), *SAME,
                            "--contrast", "0.3", "--resume"])
    assert_one_error_line(r, "out", "other inputs or settings")
    assert Stage(out).plan_file.is_file()  # nothing of it was removed
    # without --resume the unfinished run is discarded, and said so
    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(out), *SAME,
                            "--contrast", "0.3", "--jobs", "2"])
    assert r.exit_code == 0, r.output
    assert "unfinished run" in r.stderr and "discarded" in r.stderr
    no_stage(out)


@pytest.mark.parametrize("extra, needle", [
    (["--jobs", "0"], "--jobs must be at least 1"),
    (["--jobs", "2", "--video", "v.mp4"], "--video needs every frame in order"),
])
def test_bad_combinations_one_line(recs, tmp_path, extra, needle):
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(out), *SAME, *extra])
    assert_one_error_line(r, needle.split()[0], needle)
    assert not out.exists()
    no_stage(out)


def test_one_image_has_nothing_to_share(tmp_path):
    from tests.helpers.data import ROOT

    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(ROOT / "examples" / "blurry.png"),
                            str(ROOT / "examples" / "events.npz"), "-o", str(out), *SAME,
                            "--jobs", "2"])
    assert_one_error_line(r, "blurry.png", "nothing to share out")
    no_stage(out)


def test_rank_out_of_range_one_line(recs, tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "2")
    r = runner.invoke(app, ["deblur", str(recs / "a.h5"), "-o", str(tmp_path / "o"), *SAME])
    assert_one_error_line(r, "RANK", "must be in 0..1")
