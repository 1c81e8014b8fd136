"""The shipped weights: found, self-describing, the default method, and good on the bundled
example (simulated, with ground truth)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import ROOT
from trmd_cli.cli.app import app
from trmd_cli.models.weights import default_weights_path, read_metadata
from trmd_cli.read import open_events, read_image

EX = ROOT / "examples"

pytestmark = pytest.mark.skipif(not default_weights_path().is_file(),
                                reason="no shipped weights in this installation")


def _psnr(a, b):
    return float(10 * np.log10(1.0 / np.mean((np.asarray(a, np.float64) - b) ** 2)))


def test_metadata_records_architecture_recipe_and_figures():
    # the shipped file must come from the recipe committed beside it
    from trmd_cli.models import canonical_name, create_model
    from trmd_cli.train.recipe import load_recipe

    recipe = load_recipe(ROOT / "weights_recipe" / "recipe.toml")
    meta = read_metadata(None)
    # the same architecture, whichever of its names (an old one: models.renet.ALIASES) each uses
    assert canonical_name(meta["architecture"]) == canonical_name(recipe.model.name)
    built = create_model(recipe.model.name, n=recipe.model.n, channels=recipe.model.channels,
                         **recipe.model.args)
    assert meta["args"] == json.loads(json.dumps(built.args))
    assert meta["n"] == 3 and meta["channels"] == 1
    assert meta["recipe"]["name"] == recipe.name
    val = meta["validation"]
    assert val["frames"] == 48 and val["trmd"]["psnr_mid"] > val["blurry"]["psnr_mid"]


def test_default_deblur_is_fused_and_sharpens_the_example(tmp_path):
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["deblur", str(EX / "blurry.png"), str(EX / "events.npz"),
                                 "-o", str(out), "--threads", "2"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "meta.json").read_text())
    assert meta["method"] == "fused" and meta.get("weights_hash")
    gt = np.load(EX / "ground_truth.npz")["sharp"].astype(np.float32) / 255
    blurry = read_image(EX / "blurry.png")
    frames = [read_image(out / f"frame_{k:03d}.png") for k in range(7)]
    # measured: blurry 23.5 / 21.6, TRMD 31.8 / 30.7, fused 34.1 / 36.0 dB (middle / sequence)
    assert _psnr(frames[3], gt[3]) > _psnr(blurry, gt[3]) + 8.0
    seq = np.mean([_psnr(f, g) for f, g in zip(frames, gt)])
    assert seq > np.mean([_psnr(blurry, g) for g in gt]) + 10.0
    # the frames re-blur to the blurry frame closely (measured 0.006 mean absolute)
    assert np.abs(np.mean(frames, 0) - blurry).mean() < 0.01


def test_trmd_keeps_the_blur_average(tmp_path):
    """Eq. 11: TRMD's 8-bit frames of the clipped frames still average to the blurry frame."""
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["deblur", str(EX / "blurry.png"), str(EX / "events.npz"),
                                 "-o", str(out), "--method", "trmd", "--threads", "2"])
    assert r.exit_code == 0, r.output
    blurry = read_image(EX / "blurry.png")
    frames = [read_image(out / f"frame_{k:03d}.png") for k in range(7)]
    # measured 0.0004: 8-bit rounding
    assert np.abs(np.mean(frames, 0) - blurry).mean() < 0.002
    assert open_events(EX / "events.npz").num_events() > 0
