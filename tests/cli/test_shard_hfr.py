"""`trmd hfr` in several processes (--jobs, torchrun ranks), resumed, over several recordings:
every output — frames folders, MP4, GIF — equals a one-process run's file for file."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.cli.test_interrupt_deblur import write_recording
from tests.cli.test_shard_deblur import _free_port, assert_same, files, no_stage
from tests.helpers.cli import assert_one_error_line
from trmd_cli.batch import ShardError, Stage, prepare_stage
from trmd_cli.cli.app import app
from trmd_cli.hfr_batch import HfrSettings, make_hfr_plan, run_hfr_share
from trmd_cli.methods import MethodConfig
from trmd_cli.read.base import ReadOptions

runner = CliRunner()
#: the same arithmetic in every process: EDI, float32, one thread
SAME = ("--method", "edi", "--precision", "fp32", "--threads", "1")
#: write_recording: a 10 ms exposure every 20 ms, so 7 frames a step of 10/6 ms apart each and
#: floor(10 / (10/6) − 0.5) = 5 frames in each gap
PER_EXPOSURE, PER_GAP = 7, 5


@pytest.fixture(scope="module")
def recs(tmp_path_factory) -> Path:
    """A folder of four tiny recordings (64x48) of 4, 3, 1 and 2 exposures."""
    folder = tmp_path_factory.mktemp("recs")
    for name, frames in (("a", 4), ("b", 3), ("c", 1), ("d", 2)):
        write_recording(folder / f"{name}.h5", frames)
    return folder


def hfr(*args):
    """``trmd hfr ARGS`` with the same arithmetic everywhere; it must succeed."""
    r = runner.invoke(app, ["hfr", *map(str, args), *SAME])
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def alone(recs, tmp_path_factory) -> Path:
    """Each recording run alone by today's one-process path: a frames folder and an MP4."""
    out = tmp_path_factory.mktemp("alone")
    for name in "abcd":
        hfr(recs / f"{name}.h5", "-o", out / name)
        hfr(recs / f"{name}.h5", "-o", out / f"{name}.mp4")
    return out


def test_stream_of_the_reference_is_what_the_timing_says(alone):
    """The reference itself, against the recording's timing: 4 exposures, 3 gaps."""
    meta = json.loads((alone / "a" / "meta.json").read_text())
    assert meta["frames"] == {"exposure": 4 * PER_EXPOSURE, "gap": 3 * PER_GAP}
    rows = [ln.split() for ln in (alone / "a" / "timestamps.txt").read_text().splitlines()[1:]]
    assert [r[2] for r in rows] == (["exposure"] * 7 + ["gap"] * 5) * 3 + ["exposure"] * 7
    np.testing.assert_allclose(np.diff([float(r[1]) for r in rows]), 10_000 / 6, rtol=1e-6)


def test_two_jobs_on_a_folder_equal_one_process(recs, alone, tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    hfr(recs, "-o", one, "--jobs", "1")
    r = hfr(recs, "-o", two, "--jobs", "2")
    assert "from 4 recordings" in r.stdout
    assert sorted(p.name for p in two.iterdir()) == ["a", "b", "c", "d"]
    assert_same(one, two)
    for name in "abcd":
        assert_same(alone / name, two / name)
    no_stage(two)


def test_two_jobs_videos_equal_one_process(recs, alone, tmp_path):
    out = tmp_path / "videos"
    hfr(recs, "-o", out, "--jobs", "2", "--format", "mp4")
    assert sorted(p.name for p in out.iterdir()) == ["a.mp4", "b.mp4", "c.mp4", "d.mp4"]
    for name in "abcd":
        assert (out / f"{name}.mp4").read_bytes() == (alone / f"{name}.mp4").read_bytes()
    no_stage(out)


@pytest.mark.parametrize("extra", [
    ["-o", "slowmo.gif"],
    ["-o", "frames", "--max-gap-frames", "2"],  # capped gaps
    ["-o", "frames", "--no-fill-gaps", "--per-exposure", "4", "--bit-depth", "16"],
], ids=["gif", "capped", "no-gaps"])
def test_one_recording_in_two_jobs_equals_one_process(recs, tmp_path, extra):
    _, target, *opts = extra
    ref, out = tmp_path / "ref" / target, tmp_path / "out" / target
    ref.parent.mkdir()
    out.parent.mkdir()
    hfr(recs / "a.h5", "-o", ref, *opts)
    r = hfr(recs / "a.h5", "-o", out, *opts, "--jobs", "2")
    assert files(ref) == files(out) if ref.is_dir() else ref.read_bytes() == out.read_bytes()
    assert ("gaps between exposures are long" in r.stderr) == ("--max-gap-frames" in opts)
    no_stage(out)


def test_trmd_in_two_jobs_equals_one_process(recs, tmp_path):
    """A network in every worker, with in-between instants and c settled for the gaps."""
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights

    w = save_weights(tmp_path / "w.safetensors", create_model("test_trmd", n=2), meta={})
    args = ["hfr", str(recs / "b.h5"), "--method", "trmd", "--weights", str(w),
            "--per-exposure", "6",
            "--precision", "fp32", "--threads", "1"]
    for out, extra in (("ref", []), ("out", ["--jobs", "2"])):
        r = runner.invoke(app, [*args, "-o", str(tmp_path / out), *extra])
        assert r.exit_code == 0, r.output
    assert_same(tmp_path / "ref", tmp_path / "out")
    meta = json.loads((tmp_path / "out" / "meta.json").read_text())
    assert meta["method"] == "trmd" and len(meta["contrast"]) == 3


def test_colour_images_and_events_gif_in_two_jobs(tmp_path):
    """BLURRY… EVENTS with RGB frames into a GIF: the units' PNGs come back as RGB."""
    from trmd_cli.simulate import SensorConfig, make_sequence
    from trmd_cli.write import write_events_npz, write_image

    yy, xx = np.mgrid[0:200, 0:200]
    scene = (0.15 + 0.7 * ((xx // 20 + yy // 28) % 2)).astype(np.float32)
    seq = make_sequence(scene, n=3, size=(32, 24), exposure_us=10_000, frames=3,
                        frame_interval_us=20_000, rng=np.random.default_rng(1),
                        sensor=SensorConfig.clean(0.2))
    names = []
    for k, g in enumerate(seq.blurry):
        names.append(tmp_path / f"{k:04d}.png")
        write_image(names[-1], np.stack([g, 0.7 * g, 0.2 + 0.5 * g], -1), 8)
    events = write_events_npz(tmp_path / "ev.npz", seq.events, seq.exposures)
    hfr(*names, events, "--contrast", "0.2", "-o", tmp_path / "ref.gif")
    r = hfr(*names, events, "--contrast", "0.2", "-o", tmp_path / "out.gif", "--jobs", "2")
    assert "21 from exposures, 10 filling gaps" in r.stdout
    assert (tmp_path / "ref.gif").read_bytes() == (tmp_path / "out.gif").read_bytes()
    import imageio.v3 as iio

    video = iio.imread(tmp_path / "out.gif")
    assert video.shape[0] == 31 and video.shape[-1] == 3
    assert (video[..., 0].astype(int) - video[..., 1]).mean() > 5  # red above green


def test_two_torchrun_ranks_equal_one_process(recs, alone, tmp_path):
    """Two real processes with torchrun's variables, as on two machines sharing a disk."""
    out = tmp_path / "out"
    port = _free_port()
    procs = []
    for rank in range(2):
        env = {**os.environ, "RANK": str(rank), "WORLD_SIZE": "2", "LOCAL_RANK": str(rank),
               "LOCAL_WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "trmd_cli", "hfr", str(recs / "a.h5"), "-o", str(out),
             *SAME], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    said = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], said
    # exposures 1, 3 of 0..3, then gap 1 of 0..2
    assert "rank 1: made 3 parts" in said[1][0]
    assert_same(alone / "a", out)
    no_stage(out)


def settings() -> HfrSettings:
    return HfrSettings(MethodConfig(method="edi", precision="fp32", threads=1,
                                    settle_contrast=True), ReadOptions())


def test_resume_completes_a_partial_run(recs, alone, tmp_path):
    """Rank 0 of 2 finished its exposures, rank 1 died: one after its exposure's folder was
    renamed in but before its record, leaving a temporary of a process that is gone."""
    out = tmp_path / "out"
    plan = make_hfr_plan([[str(recs / "a.h5")]], [""], settings())
    assert len(plan.phases()) == 2 and len(plan.units()) == 4 + 3
    stage, _ = prepare_stage(plan, out, resume=False)
    exposures = plan.phases()[0]
    assert run_hfr_share(plan, stage, plan.share(0, 2, exposures)).frames == 2
    shutil.copytree(stage.root / "parts" / "0" / "x0", stage.root / "parts" / "0" / "x1")
    (stage.root / "parts" / "0" / ".x3.trmd-999999999-x.tmp").mkdir()
    assert len(stage.pending(plan)) == 5

    r = runner.invoke(app, ["hfr", str(recs / "a.h5"), "-o", str(out), *SAME, "--resume"])
    assert r.exit_code == 0, r.output
    assert "resuming: 2 of 7 parts" in r.stdout
    assert_same(alone / "a", out)
    no_stage(out)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals as on Linux")
def test_ctrl_c_then_resume(tmp_path):
    """Ctrl-C (to the whole process group, as a terminal sends it) in the middle of a --jobs 2
    run: exit 130, no output, no worker left running, the finished parts kept; --resume then
    ends with the one-process output."""
    import signal

    from tests.helpers.procs import finish, group_gone, launch, wait_until

    rec = write_recording(tmp_path / "long.h5", 200)
    out = tmp_path / "out"
    stage = Stage(out)
    proc = launch("hfr", str(rec), "-o", str(out), *SAME, "--contrast", "0.2", "--jobs", "2",
                  new_session=True)
    def records() -> int:
        # a record being written is a hidden temporary beside the records: not one of them
        return sum(1 for p in stage.done.iterdir() if not p.name.startswith("."))

    wait_until(proc, lambda: stage.done.is_dir() and records() >= 10, "ten parts were made")
    os.killpg(proc.pid, signal.SIGINT)
    err = finish(proc)
    assert proc.returncode == 130, err
    assert "rerun with --resume" in err and "Traceback" not in err
    assert not out.exists()
    assert group_gone(proc.pid), "a worker outlived the run"
    kept = records()
    assert 10 <= kept < 399

    r = runner.invoke(app, ["hfr", str(rec), "-o", str(out), *SAME, "--contrast", "0.2",
                            "--resume"])
    assert r.exit_code == 0, r.output
    assert f"resuming: {kept} of 399 parts" in r.stdout
    hfr(rec, "-o", tmp_path / "ref", "--contrast", "0.2")
    assert_same(tmp_path / "ref", out)
    no_stage(out)


def test_failed_share_keeps_its_parts_for_resume(recs, alone, tmp_path, monkeypatch):
    """A share failing midway stops the run: no output, the finished parts stay for --resume
    (the CLI says so), which then completes it."""
    import trmd_cli.hfr_batch as hb

    out = tmp_path / "out"
    real = hb.run_hfr_share

    def fail_after_two(plan, stage, share, tick=lambda: None):
        real(plan, stage, share[:2], tick)
        raise hb.ShardError("stand-in failure of a share")

    r = runner.invoke(app, ["hfr", str(recs / "a.h5"), "-o", str(out), *SAME, "--resume"])
    assert_one_error_line(r, "out", "nothing to resume")
    monkeypatch.setattr(hb, "run_hfr_share", fail_after_two)
    r = runner.invoke(app, ["hfr", str(recs), "-o", str(out), *SAME, "--format", "mp4"])
    assert r.exit_code == 2 and "stand-in failure" in r.stderr
    assert "--resume" in r.stderr and not out.exists()
    assert len(list(Stage(out).done.iterdir())) == 2
    monkeypatch.setattr(hb, "run_hfr_share", real)
    r = runner.invoke(app, ["hfr", str(recs), "-o", str(out), *SAME, "--format", "mp4",
                            "--resume"])
    assert r.exit_code == 0, r.output
    # 10 exposures, 6 gaps
    assert "resuming: 2 of 16 parts" in r.stdout
    for name in "abcd":
        assert (out / f"{name}.mp4").read_bytes() == (alone / f"{name}.mp4").read_bytes()
    no_stage(out)


def test_gap_before_its_exposures_is_refused(recs, tmp_path):
    plan = make_hfr_plan([[str(recs / "d.h5")]], [""], settings())
    stage, _ = prepare_stage(plan, tmp_path / "out", resume=False)
    with pytest.raises(ShardError, match="exposure 0 .* is not complete"):
        run_hfr_share(plan, stage, plan.phases()[1])


def test_resume_with_other_settings_is_refused(recs, tmp_path):
    out = tmp_path / "out"
    prepare_stage(make_hfr_plan([[str(recs / "d.h5")]], [""], settings()), out, resume=False)
    r = runner.invoke(app, ["hfr", str(recs / "d.h5"), "-o", str(out), *SAME,
                            "--fps", "12", "--resume"])
    assert_one_error_line(r, "out", "other inputs or settings")
    assert Stage(out).plan_file.is_file()
    # a deblur stage is not an hfr one, even of the same inputs
    r = runner.invoke(app, ["deblur", str(recs / "d.h5"), "-o", str(out), *SAME, "--resume"])
    assert_one_error_line(r, "out", "other inputs or settings")
    r = runner.invoke(app, ["hfr", str(recs / "d.h5"), "-o", str(out), *SAME, "--jobs", "2"])
    assert r.exit_code == 0, r.output
    assert "unfinished run" in r.stderr and "discarded" in r.stderr
    no_stage(out)


def test_binned_events_in_two_jobs_equal_one_process(tmp_path):
    """No event times: one phase (exposures only), fractions in timestamps.txt."""
    from tests.helpers.bins import write_bins
    from trmd_cli.write import write_image

    rng = np.random.default_rng(3)
    (tmp_path / "blurry").mkdir()
    for k in range(3):
        write_image(tmp_path / "blurry" / f"{k + 1:04d}.png",
                    rng.uniform(0.2, 0.8, (48, 64)).astype(np.float32), 16)
    bins = write_bins(tmp_path / "bins.npy",
                      rng.integers(-2, 3, (3 * 12, 48, 64)).astype(np.int16))
    args = [tmp_path / "blurry", bins, "--contrast", "0.2"]
    hfr(*args, "-o", tmp_path / "ref")
    r = hfr(*args, "-o", tmp_path / "out", "--jobs", "2")
    assert sum("binned events" in ln for ln in r.stderr.splitlines()) == 1
    assert_same(tmp_path / "ref", tmp_path / "out")
    assert json.loads((tmp_path / "out" / "meta.json").read_text())["fill_gaps"] is False


@pytest.mark.parametrize("name, extra, needle", [
    ("out", ["--jobs", "0"], "--jobs must be at least 1"),
    ("out.mp4", [], "several recordings give one output each"),
    ("out", ["--format", "webm"], "--format 'webm' is not one of frames, mp4, gif"),
])
def test_bad_combinations_one_line(recs, tmp_path, name, extra, needle):
    out = tmp_path / name
    r = runner.invoke(app, ["hfr", str(recs), *SAME, "-o", str(out), *extra])
    assert_one_error_line(r, needle.split()[0] if extra else name, needle)
    assert not out.exists()
    no_stage(out)


def test_format_must_agree_with_one_output(recs, tmp_path):
    out = tmp_path / "slowmo.mp4"
    r = runner.invoke(app, ["hfr", str(recs / "a.h5"), "-o", str(out), *SAME, "--format",
                            "gif"])
    assert_one_error_line(r, "slowmo.mp4", "--format gif disagrees")
    assert not out.exists()


def test_two_recordings_of_one_name_one_line(recs, tmp_path):
    (tmp_path / "x").mkdir()
    shutil.copy(recs / "d.h5", tmp_path / "x" / "d.h5")
    out = tmp_path / "out"
    r = runner.invoke(app, ["hfr", str(recs / "d.h5"), str(tmp_path / "x" / "d.h5"), "-o",
                            str(out), *SAME, "--format", "gif"])
    assert_one_error_line(r, "d.gif", "two recordings would both write 'd.gif'")
    assert not out.exists()
    no_stage(out)
