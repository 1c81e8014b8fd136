"""`trmd deblur`, `hfr` and `eval` remove the sensor's fixed pattern of a recording: a
simulated camera pan over the project's example image with a pattern added to every frame,
scored against the simulator's sharp frames (which hold no pattern)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.cli.test_shard_deblur import assert_same, no_stage
from trmd_cli.cli.app import app
from trmd_cli.metrics import psnr
from trmd_cli.read.frames import read_image
from trmd_cli.simulate import aps_pattern, make_sequence
from trmd_cli.write import H5Writer

runner = CliRunner()
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "sharp.png"
W, H = 160, 120


@pytest.fixture(scope="module")
def panned(tmp_path_factory):
    """8 exposures of a moving camera with a pattern of σ = 0.012 per pixel and 0.006 per
    column (about esl-cups' 2.4 grey levels) added: (recording, sharp frames, pattern, c)."""
    seq = make_sequence(read_image(EXAMPLE), frames=8, size=(W, H),
                        rng=np.random.default_rng(1), read_noise=0.003)
    pattern = aps_pattern(np.random.default_rng(99), W, H)
    path = tmp_path_factory.mktemp("fp") / "pan.h5"
    with H5Writer(path, W, H) as w:
        w.add_events(seq.events)
        for blurry, exposure, sharp in zip(seq.blurry, seq.exposures, seq.sharp, strict=True):
            w.add_frame(np.clip(blurry + pattern, 0, 1), exposure, sharp=sharp,
                        contrast=seq.contrast)
    return path, seq.sharp, pattern, seq.contrast


def _middles(out: Path) -> list[np.ndarray]:
    folders = sorted(p for p in out.iterdir() if p.is_dir())
    return [read_image(f / "sharp.png") for f in folders]


def _psnr(out: Path, sharp: np.ndarray) -> float:
    inner = (slice(8, H - 8), slice(8, W - 8))
    return float(np.mean([psnr(m[inner], s[3][inner])
                          for m, s in zip(_middles(out), sharp, strict=True)]))


def _removed_and_kept(rec: Path, method: str, c: float, tmp_path: Path
                      ) -> tuple[Path, Path, list[str]]:
    """`trmd deblur REC --method METHOD` with the pattern removed and kept (16-bit frames):
    the two outputs and what each run printed."""
    common = ["--method", method, "--contrast", f"{c:.6f}", "--bit-depth", "16", "--jobs", "1"]
    outs, said = (tmp_path / "removed", tmp_path / "kept"), []
    for out, extra in zip(outs, ([], ["--keep-pattern"]), strict=True):
        r = runner.invoke(app, ["deblur", str(rec), "-o", str(out), *common, *extra])
        assert r.exit_code == 0, r.output
        said.append(r.output)
    return *outs, said


def test_deblur_removes_the_pattern_and_gains(panned, tmp_path):
    rec, sharp, _, c = panned
    removed, kept, (said_removed, said_kept) = _removed_and_kept(rec, "edi", c, tmp_path)
    assert "removed the sensor's fixed pattern" in said_removed and "--keep-pattern keeps it" \
        in said_removed
    assert "fixed pattern" not in said_kept
    # EDI copies the pattern into every frame; without it the middle frames are nearer the
    # sharp ones (measured: 28.80 → 29.38 dB)
    assert _psnr(removed, sharp) > _psnr(kept, sharp) + 0.3
    meta = json.loads((removed / "meta.json").read_text())["fixed_pattern"]
    assert meta["removed"] and meta["agreement"] > 0.5 and meta["scene_correlation"] < 0.5
    # the pattern's RMS is 0.0134; its smooth part stays (the σ = 1 px blur holds it)
    assert 0.008 < meta["rms"] < 0.0134 and len(meta["frames"]) == 8
    meta = json.loads((kept / "meta.json").read_text())["fixed_pattern"]
    assert meta == {"removed": False, "reason": "kept as asked (`fixed_pattern=False`)"}


def test_motion_method_gains_too(panned, tmp_path):
    rec, sharp, _, c = panned
    removed, kept, _ = _removed_and_kept(rec, "motion", c, tmp_path)
    # measured: 30.80 → 30.93 dB (the prior weighed halfway between the frame's noise as
    # recorded and without the pattern; as recorded it lost 0.36 dB here)
    assert _psnr(removed, sharp) > _psnr(kept, sharp) + 0.05


def test_split_run_removes_the_same_pattern(panned, tmp_path):
    """Every worker of `--jobs 2` removes the pattern settled once for the plan."""
    rec, _, _, c = panned
    common = ["--method", "edi", "--contrast", f"{c:.6f}", "--threads", "1"]
    one, two = tmp_path / "one", tmp_path / "two"
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(one), *common, "--jobs", "1"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(two), *common, "--jobs", "2"])
    assert r.exit_code == 0, r.output
    assert "removed the sensor's fixed pattern" in r.output
    assert json.loads((two / "meta.json").read_text())["fixed_pattern"]["removed"]
    assert_same(one, two)
    no_stage(two)


def test_hfr_and_eval_remove_it_as_deblur_does(panned, tmp_path):
    rec, _, _, c = panned
    out = tmp_path / "hfr"
    r = runner.invoke(app, ["hfr", str(rec), "-o", str(out), "--method", "edi", "--contrast",
                            f"{c:.6f}", "--no-fill-gaps", "--jobs", "1"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "meta.json").read_text())["fixed_pattern"]["removed"]
    scores, said = {}, {}
    for flag in ("--remove-pattern", "--keep-pattern"):
        js = tmp_path / f"{flag}.json"
        r = runner.invoke(app, ["eval", str(rec), "--methods", "blurry,edi-true-c", "--json",
                                str(js), flag])
        assert r.exit_code == 0, r.output
        said[flag] = "removed the sensor's fixed pattern" in r.output.replace("\n", " ")
        scores[flag] = json.loads(js.read_text())["datasets"][0]["methods"]
    assert said == {"--remove-pattern": True, "--keep-pattern": False}
    # the blurry floor is the input as it is; EDI gets the frames without the pattern
    on, off = scores["--remove-pattern"], scores["--keep-pattern"]
    assert {k: v for k, v in on["blurry"]["mean"].items() if k != "seconds"} == \
        {k: v for k, v in off["blurry"]["mean"].items() if k != "seconds"}
    assert on["edi-true-c"]["mean"]["psnr_mid"] > off["edi-true-c"]["mean"]["psnr_mid"] + 0.3


def test_still_camera_and_single_frames_keep_their_pixels(tmp_path):
    """A recording whose scene hardly moves: nothing removed, and the reason recorded."""
    from tests.cli.test_interrupt_deblur import write_recording

    rec = write_recording(tmp_path / "still.h5", 8)
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(out), "--method", "edi",
                            "--contrast", "0.2", "--jobs", "1"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "meta.json").read_text())["fixed_pattern"]
    assert not meta["removed"] and "hardly moved" in meta["reason"]
    assert "no fixed pattern removed: the scene hardly moved" in r.output.replace("\n", " ")


def test_finetune_sees_the_frames_deblur_gives_the_network(panned):
    """Fine-tuning's windows hold the frames without the pattern, as the network gets them in
    use; with `fixed_pattern=False`, as recorded."""
    from trmd_cli.train.finetune import FinetuneConfig, prepare_windows

    rec, _, added, c = panned

    def windows(**kw):
        config = FinetuneConfig(losses={"reblur": 1.0}, contrast=c, max_windows=3, **kw)
        return prepare_windows([[rec]], 3, timing=False, config=config)

    (on, notes), (off, _) = windows(), windows(fixed_pattern=False)
    assert any("removed the sensor's fixed pattern" in n for n in notes)
    for a, b in zip(on, off, strict=True):
        removed = b.blurry - a.blurry
        # what left the frame is the pattern's fine part (away from clipped pixels)
        assert np.corrcoef(removed.ravel(), added.ravel())[0, 1] > 0.8
        assert np.sqrt(np.mean(removed ** 2)) > 0.008
