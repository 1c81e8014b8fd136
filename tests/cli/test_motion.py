"""`trmd deblur --method motion` on the bundled example: at least as good as EDI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from trmd_cli.cli.app import app
from trmd_cli.metrics import psnr
from trmd_cli.read.frames import read_image

runner = CliRunner()
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_motion_on_the_example_is_not_worse_than_edi(tmp_path):
    gt = np.load(EXAMPLES / "ground_truth.npz")["sharp"][3].astype(np.float32) / 255
    scores = {}
    for method in ("edi", "motion"):
        out = tmp_path / method
        r = runner.invoke(app, ["deblur", str(EXAMPLES / "blurry.png"),
                                str(EXAMPLES / "events.npz"), "-o", str(out),
                                "--method", method])
        assert r.exit_code == 0, r.output
        img = read_image(out / "sharp.png")
        img = img.mean(-1) if img.ndim == 3 else img
        scores[method] = psnr(img, gt)
        meta = json.loads((out / "meta.json").read_text())
        if method == "motion":
            # the estimated c (0.351) refitted to the deconvolution for EDI's frames: 0.308,
            # the true mean threshold 0.30
            truth = float(np.load(EXAMPLES / "ground_truth.npz")["contrast"])
            assert abs(meta["fallback_contrast"] - truth) < abs(meta["contrast"] - truth)
        else:
            assert "fallback_contrast" not in meta
    # measured: EDI 30.20 dB, motion 33.41 dB
    assert scores["motion"] >= scores["edi"] + 2, scores
