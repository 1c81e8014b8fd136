"""Every Python block in the documentation runs as written.

docs/quickstart.md runs on the bundled example from the repository's root. Blocks that stand for
a user's files run on stand-ins: the paths they name are mapped to shared recordings or to small
files made here, and the sample counts that size a real job are scaled down (listed below).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from tests.helpers.data import ROOT

BLOCK = re.compile(r"^( *)```python\n(.*?)^\1```", re.S | re.M)


def blocks(doc: str) -> list[str]:
    text = (ROOT / "docs" / doc).read_text()
    out = []
    for indent, body in BLOCK.findall(text):
        out.append("\n".join(line[len(indent):] for line in body.splitlines()))
    return out


def test_every_python_block_is_covered_here():
    """A new block in the docs must be added to a test below."""
    found = {doc: len(blocks(doc)) for doc in
             sorted(p.name for p in (ROOT / "docs").glob("*.md"))}
    assert {d: k for d, k in found.items() if k} == {"quickstart.md": 2, "training.md": 1}


@pytest.mark.parametrize("k", [0, 1])
def test_quickstart_blocks_run_on_the_bundled_example(k, monkeypatch):
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    exec(compile(blocks("quickstart.md")[k], f"quickstart.md block {k}", "exec"), scope)
    if k == 0:
        assert scope["voxels"].shape == (6, 260, 346)
        assert scope["edi"].shape == (7, 260, 346)
        frames = scope["frames"]
        assert frames.shape == (2 * scope["est"].n + 1, 260, 346)
        # the reconstruction keeps the blur model: the frames average to the blurry input
        np.testing.assert_allclose(frames.mean(0), scope["blurry"], atol=2e-3)


def test_training_pregenerate_block_runs_on_stand_in_photos(tmp_path, monkeypatch):
    import cv2

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        img = cv2.GaussianBlur((rng.random((160, 160)) * 255).astype(np.uint8), (5, 5), 2)
        cv2.imwrite(str(photos / f"{i}.png"), img)
    code = blocks("training.md")[0]
    # a real set holds 10,000 samples of 128 px on 2 workers; two of 32 px show that it runs
    code = code.replace("10000", "2").replace("crop=128", "crop=32").replace("workers=2",
                                                                               "workers=0")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "training.md block 0", "exec"), {})
    from trmd_cli.read import open_events

    with open_events(tmp_path / "train.h5") as rec:
        assert rec.num_frames == 2 and rec.num_events() > 0


def test_the_estimator_docstring_example_runs(monkeypatch):
    import doctest

    from trmd_cli.models import estimator

    monkeypatch.chdir(ROOT)
    finder = doctest.DocTestFinder()
    tests = [t for t in finder.find(estimator.TrmdEstimator) if t.examples]
    assert tests, "the example is gone"
    runner = doctest.DocTestRunner()
    for t in tests:
        runner.run(t)
    assert runner.failures == 0
