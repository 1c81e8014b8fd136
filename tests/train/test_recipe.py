"""Recipes: the shipped default, TOML → validated Recipe, errors that name key and fix."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from trmd_cli.errors import InputError
from trmd_cli.train.recipe import (
    Recipe,
    apply_overrides,
    default_recipe_path,
    load_recipe,
    recipe_diff,
    recipe_from_dict,
)


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "r.toml"
    p.write_text(text)
    return p


def test_default_recipe_ships_and_has_the_paper_loss():
    assert default_recipe_path().is_file()
    r = load_recipe()
    assert r.loss.weights == {"residual": 1.0, "middle": 1.0}
    assert r.loss.penalty == "mse"
    assert r.model.n == 3 and r.model.channels == 1
    assert r.optim.lr == pytest.approx(1e-3)


def test_empty_recipe_gives_the_dataclass_defaults(tmp_path):
    r = load_recipe(write(tmp_path, ""))
    assert dataclasses.replace(r, base_dir="") == Recipe()


def test_values_are_read_and_typed(tmp_path):
    r = load_recipe(write(tmp_path, """
name = "x"
seed = 7
[model]
name = "test_trmd"
n = 2
[model.args]
feat_width = 8
[optim]
lr = 1       # an integer is a fine float
betas = [0.8, 0.99]
[loss]
residual = 0.5
event_consistency = 0.1
penalty = "charbonnier"
"""))
    assert r.name == "x" and r.seed == 7
    assert r.model.n == 2 and r.model.args == {"feat_width": 8}
    assert isinstance(r.optim.lr, float) and r.optim.lr == 1.0
    assert r.optim.betas == (0.8, 0.99)
    # a recipe that names weights replaces the default weights, it does not add to them
    assert r.loss.weights == {"residual": 0.5, "event_consistency": 0.1}
    assert r.loss.penalty == "charbonnier"


@pytest.mark.parametrize("text, words", [
    ("[optim]\nlrr = 1e-3", ["optim.lrr", "did you mean 'lr'"]),
    ("[optimizer]\nlr = 1e-3", ["unknown recipe key 'optimizer'"]),
    ("[loss]\nresidul = 1.0", ["loss.residul", "residual"]),
    ("[train]\nsteps = 1.5", ["train.steps", "expected an integer"]),
    ("[train]\namp = 1", ["train.amp", "true or false"]),
    ("[data]\nbatch_size = true", ["data.batch_size", "integer"]),
    ("[optim]\nlr = -1.0", ["optim.lr", "> 0"]),
    ("[optim]\nbetas = [0.9]", ["optim.betas", "2 numbers"]),
    ("[optim]\nschedule = \"linear\"", ["optim.schedule", "cosine or constant"]),
    ("[model]\nchannels = 2", ["model.channels", "1 (gray) or 3 (RGB)"]),
    ("[loss]\nresidual = 0.0\nmiddle = 0.0", ["no loss has a positive weight"]),
    ("[loss]\npenalty = \"huber\"", ["loss.penalty"]),
    ("model = 3", ["'model' must be a table"]),
    ("name = \"a/b\"", ["name"]),
    ("[optim\nlr = 1", ["not valid TOML"]),
])
def test_bad_recipes_name_the_key(tmp_path, text, words):
    path = write(tmp_path, text)
    with pytest.raises(InputError) as e:
        load_recipe(path)
    msg = str(e.value)
    assert str(path) in msg
    for w in words:
        assert w in msg


def test_missing_recipe_file(tmp_path):
    with pytest.raises(InputError, match="recipe not found"):
        load_recipe(tmp_path / "nope.toml")


def test_overrides_parse_toml_values_and_bare_words(tmp_path):
    r = load_recipe(write(tmp_path, ""), overrides=[
        "optim.lr=5e-4", "model.name=test_trmd", "train.amp=false", "optim.betas=[0.5, 0.6]",
        "model.args.feat_width=4", "loss.sequence=2"])
    assert r.optim.lr == 5e-4 and r.model.name == "test_trmd" and r.train.amp is False
    assert r.optim.betas == (0.5, 0.6)
    assert r.model.args == {"feat_width": 4}
    # the file names no weights, so the override's is the only one (the rule of [loss] tables)
    assert r.loss.weights == {"sequence": 2.0}
    # on the shipped recipe, which names residual and middle, an override adds to them
    d = load_recipe(None, overrides=["loss.sequence=2"])
    assert d.loss.weights == {"residual": 1.0, "middle": 1.0, "sequence": 2.0}
    with pytest.raises(InputError, match="KEY=VALUE"):
        apply_overrides(r, ["optim.lr"])
    with pytest.raises(InputError, match="train.steps"):
        apply_overrides(r, ["train.steps=0"])


def test_a_bad_override_is_blamed_on_the_override_not_the_file(tmp_path):
    path = write(tmp_path, "")
    with pytest.raises(InputError, match=r"train.steps = 'abc'.*after the overrides "
                       r"train.steps=abc") as e:
        load_recipe(path, overrides=["train.steps=abc"])
    assert e.value.path is None
    with pytest.raises(InputError, match="after the overrides optim.lr=nan"):
        apply_overrides(load_recipe(path), ["optim.lr=nan"])
    with pytest.raises(InputError) as e:  # the file's own fault still names the file
        load_recipe(write(tmp_path, "[train]\nsteps = -5\n"), overrides=["optim.lr=1e-3"])
    assert e.value.path is not None and "overrides" not in str(e.value)


def test_to_dict_round_trips_through_json(tmp_path):
    r = load_recipe(write(tmp_path, "[loss]\nmiddle = 2.0\n[data.simulator]\nnoise = 0.1"))
    back = recipe_from_dict(json.loads(json.dumps(r.to_dict())), base_dir=r.base_dir)
    assert back == r
    assert recipe_diff(r, back) == []
    other = apply_overrides(r, ["optim.lr=0.1", "loss.middle=1.0"])
    assert recipe_diff(r, other) == ["loss.middle", "optim.lr"]


def test_relative_val_data_resolves_beside_the_recipe(tmp_path):
    r = load_recipe(write(tmp_path, "[data]\nval_data = \"sets/val.h5\""))
    assert r.resolve_path(r.data.val_data) == tmp_path / "sets" / "val.h5"
    assert r.resolve_path("/abs/x.h5") == Path("/abs/x.h5")


def test_recipe_is_frozen():
    r = Recipe()
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.seed = 3  # type: ignore[misc]
