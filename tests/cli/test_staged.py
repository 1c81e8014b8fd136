"""The one driver of runs through a stage (`batch.run_staged`), as deblur and hfr use it: what
it refuses before anything is opened, and what it tells the processes that did not finish."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from tests.cli.test_interrupt_deblur import write_recording
from tests.cli.test_shard_deblur import no_stage
from tests.helpers.cli import assert_one_error_line
from trmd_cli.batch import Ranks, Settings, make_plan, nothing_to_resume, run_staged, staged
from trmd_cli.cli.app import app
from trmd_cli.methods import MethodConfig
from trmd_cli.read.base import ReadOptions

runner = CliRunner()
SAME = ("--method", "edi", "--precision", "fp32", "--threads", "1")


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    return write_recording(tmp_path_factory.mktemp("rec") / "a.h5", 3)


@pytest.mark.parametrize("command, target", [("deblur", "out"), ("hfr", "out"),
                                             ("hfr", "slowmo.mp4")])
def test_an_output_of_the_other_kind_is_refused_even_with_overwrite(rec, tmp_path, command,
                                                                    target):
    """A stage swapped in over a file would replace it with a folder (and a video over a
    folder): refused, the old output kept, no stage left."""
    out = tmp_path / target
    if out.suffix:
        out.mkdir()
    else:
        out.write_bytes(b"keep")
    r = runner.invoke(app, [command, str(rec), "-o", str(out), *SAME, "--jobs", "2",
                            "--overwrite"])
    kind = "a folder" if out.is_dir() else "not a folder"
    assert_one_error_line(r, target, f"the output exists and is {kind}")
    assert out.is_dir() if out.suffix else out.read_bytes() == b"keep"
    no_stage(out)


def test_nothing_to_resume_says_whether_the_output_looks_complete(tmp_path):
    def hint(path, folder):
        return nothing_to_resume(path, folder).hint

    out = tmp_path / "out"
    assert hint(out, True) == hint(out, False) == "run it without --resume"
    out.mkdir()
    assert hint(out, True) == "run it without --resume"  # empty: nothing was written
    (out / "meta.json").write_text("{}")
    assert hint(out, True) == "the output is complete already"
    assert hint(out, False) == "run it without --resume"  # a folder is no video
    video = tmp_path / "v.mp4"
    video.write_bytes(b"x")
    assert hint(video, False) == "the output is complete already"
    assert hint(video, True) == "run it without --resume"


def test_which_runs_go_through_a_stage(tmp_path):
    one, two = Ranks(), Ranks(1, 2, 2)
    assert not staged(1, False, one, None)
    assert staged(2, False, one, None) and staged(1, True, one, None)
    assert staged(1, False, two, None) and staged(1, False, one, [tmp_path])


def test_the_driver_speaks_through_its_callers_functions(rec, tmp_path):
    """Nothing printed: a resume's count goes to ``say``, the shares' contrast notes to
    ``warn`` (told once for the frames made here), the bar gets the plan's label and what is
    left to do here, and ticks once a unit."""
    import contextlib

    from trmd_cli.batch import prepare_stage, run_share

    settings = Settings(MethodConfig(method="edi", precision="fp32", threads=1), ReadOptions())
    out = tmp_path / "out"
    plan = make_plan([[rec]], [""], settings)
    stage, _ = prepare_stage(plan, out, resume=False)
    assert run_share(plan, stage, [(0, 1)]).frames == 1
    said: list[str] = []
    warned: list[str] = []
    bars: list[tuple[str, int]] = []
    ticks: list[int] = []

    @contextlib.contextmanager
    def progress(label, total):
        bars.append((label, total))
        yield lambda: ticks.append(1)

    run = run_staged(make_plan, [rec], None, settings, out, ranks=Ranks(), resume=True,
                     warn=warned.append, say=said.append, progress=progress)
    assert said == ["resuming: 1 of 3 frames are done already"]
    assert len(warned) == 1 and warned[0].startswith("2 of 2 frames (the first, a.h5#frame0)")
    assert bars == [("deblurring", 2)] and len(ticks) == 2
    assert run.main and [r.frames for r in run.reports] == [2] and len(run.summary) == 3
    assert sorted(p.name for p in out.iterdir()) == [
        "a.h5_frame0", "a.h5_frame1", "a.h5_frame2", "meta.json"]
    no_stage(out)
