"""What a run records of its validation set: the file's name and SHA-256, never the path it had
on the training machine — in the weights' metadata and the run's recipe.json; the checkpoint
keeps the path, since resuming reads the set again."""

from __future__ import annotations

import hashlib
import json

import pytest
from safetensors import safe_open

from tests.helpers.training import make_gopro_h5, make_image_folder, recipe
from trmd_cli.models.weights import read_metadata
from trmd_cli.train.checkpoint import read_checkpoint_state
from trmd_cli.train.data import build_data, data_record
from trmd_cli.train.loop import train


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _raw_metadata(path) -> dict[str, str]:
    with safe_open(str(path), framework="numpy") as f:
        return dict(f.metadata())


def test_weights_and_run_record_the_validation_file_by_name_and_sha256(tmp_path):
    data = make_gopro_h5(tmp_path / "train.h5", k=8)
    sets = tmp_path / "sets"
    sets.mkdir()
    val = make_gopro_h5(sets / "valset.h5", k=3, seed=4)
    r = recipe(f"data.val_data={str(val)!r}", "train.steps=4", "train.val_every=2")
    run = tmp_path / "run"
    first = train([data], recipe=r, run_dir=run, stop_after_steps=2)
    assert first.stopped == "step_limit"
    # resuming reads the set again from the path the checkpoint keeps
    assert read_checkpoint_state(run / "checkpoint.safetensors")["recipe"]["data"][
        "val_data"] == str(val)
    res = train(None, run_dir=run, resume=True)
    assert res.steps == 4 and res.val_psnr_mid is not None
    record = {"file": "valset.h5", "sha256": _sha(val)}
    assert len(record["sha256"]) == 64
    for weights in (res.final_weights, res.best_weights):
        meta = read_metadata(weights)
        assert meta["figures"]["validation"] == record
        assert meta["recipe"]["data"]["val_data"] == "valset.h5"
        raw = _raw_metadata(weights)
        assert not any(str(sets) in v for v in raw.values())
    saved = json.loads((run / "recipe.json").read_text())
    assert saved["validation"] == record and saved["recipe"]["data"]["val_data"] == "valset.h5"
    assert str(sets) not in json.dumps(saved)


def test_a_validation_folder_is_recorded_by_its_files(tmp_path):
    folder = make_image_folder(tmp_path / "val", 3)
    data = make_gopro_h5(tmp_path / "train.h5", k=4)
    r = recipe(f"data.val_data={str(folder)!r}", "data.val_samples=2", "data.crop=16")
    plan = build_data([data], r)
    lines = sorted(f"{p.name}\t{_sha(p)}\n" for p in folder.iterdir())
    assert plan.val_record == {"folder": "val", "files": 3,
                               "sha256": hashlib.sha256("".join(lines).encode()).hexdigest()}
    assert plan.val_source == str(folder)  # what people are told: where it is


@pytest.mark.parametrize("overrides, expected", [
    ((), "held out 25% of the training data"),
    (("data.val_fraction=0.0",), "none"),
])
def test_without_a_validation_file_the_record_says_where_it_came_from(gopro, overrides,
                                                                     expected):
    plan = build_data([gopro], recipe(*overrides))
    assert plan.val_record == plan.val_source == expected


def test_data_record_of_a_file(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"abc")
    assert data_record(p, [p]) == {
        "file": "x.bin",
        "sha256": "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"}
