"""Every weights file written so far still loads and computes what it computed, and every old
variant name still builds its network (``models.renet.ALIASES``).

``data/old_<name>.safetensors`` were written, before the network was restructured, by the code
of the time: ``create_model(name, n=1, feat_width=2, widths=(2, 4, 4, 4), num_res_blocks=1)``
(``refine_width=2`` for the refining variants), weights moved away from their initialisation,
BatchNorm statistics set, saved by ``save_weights`` (fp16, the metadata layout of the time:
``architecture`` = the old name, ``args`` = the constructor's arguments).
``data/old_outputs.safetensors`` holds the inputs and what that code computed from each file:
the network's residuals and the estimator's frames.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from tests.helpers.training import make_image_folder, recipe
from trmd_cli.models import (
    ALIASES,
    RENet,
    RENetInputs,
    canonical_name,
    create_model,
    is_model,
    list_aliases,
    list_models,
    variant_args,
)
from trmd_cli.models.estimator import TrmdEstimator
from trmd_cli.models.grow import load_grown
from trmd_cli.models.weights import load_weights, read_metadata

DATA = Path(__file__).parent / "data"
OLD_NAMES = ("trmd_paper", "trmd_base", "trmd_small", "trmd_small_edi", "trmd_small_edi_c",
             "trmd_small_edi_c_fr", "trmd_small_edi_c_fr_t", "test_trmd")
_SMALL = dict(feat_width=16, widths=(32, 64, 128, 256), num_res_blocks=2, norm="batch",
              attn_norm="spatial")
#: the variant table as it was before the stage names became aliases
OLD_VARIANT_ARGS = {
    "trmd_paper": dict(feat_width=32, widths=(64, 128, 256, 512), num_res_blocks=2,
                       norm="batch", attn_norm="none"),
    "trmd_base": dict(feat_width=24, widths=(48, 96, 192, 384), num_res_blocks=2,
                      norm="batch", attn_norm="spatial"),
    "trmd_small": dict(_SMALL),
    "trmd_small_edi": dict(_SMALL, prior="edi"),
    "trmd_small_edi_c": dict(_SMALL, prior="edi_c"),
    "trmd_small_edi_c_fr": dict(_SMALL, prior="edi_c", refine=3, refine_width=24),
    "trmd_small_edi_c_fr_t": dict(_SMALL, prior="edi_c", refine=3, refine_width=24,
                                  timing=True),
    "test_trmd": dict(feat_width=4, widths=(4, 8, 8, 8), num_res_blocks=1, norm="batch",
                      attn_norm="spatial"),
}


@pytest.fixture(scope="module")
def expected() -> dict[str, torch.Tensor]:
    return load_file(str(DATA / "old_outputs.safetensors"))


def _path(name: str) -> Path:
    return DATA / f"old_{name}.safetensors"


def test_the_fixtures_have_the_old_metadata_layout():
    assert sum(p.stat().st_size for p in DATA.iterdir()) < 200_000
    for name in OLD_NAMES:
        with safe_open(str(_path(name)), framework="numpy") as f:
            raw = f.metadata()
        assert raw["architecture"] == name and raw["format_version"] == "1"
        args = json.loads(raw["args"])
        assert args["n"] == 1 and args["widths"] == [2, 4, 4, 4]


@pytest.mark.parametrize("name", OLD_NAMES)
def test_each_old_weights_file_loads_and_computes_what_it_computed(name, expected):
    net, meta = load_weights(_path(name))
    assert meta["architecture"] == name  # the file's metadata is read as it is
    assert net.variant == canonical_name(name) and is_model(net.variant)
    x = RENetInputs(expected["blurry"], expected["counts"], levels=expected["levels"],
                    contrast=expected["contrast"])
    with torch.no_grad():
        got = net(x)
    want = expected[f"residuals/{name}"]
    assert want.abs().max() > 1.0  # a non-trivial output is compared
    # float32 sums in another order on another CPU's kernels differ by a few 1e-6 on outputs
    # above 1; a misread weight moves them by far more
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    est = TrmdEstimator.load(_path(name), device="cpu", expect_n=1)
    frames = est(expected["blurry"][0, 0].numpy(), expected["counts"][0].numpy(), 0.2,
                 expected["levels"][0].numpy())
    np.testing.assert_allclose(frames, expected[f"frames/{name}"].numpy(), rtol=1e-4,
                               atol=1e-5)
    old = OLD_VARIANT_ARGS[name]
    assert est.needs_contrast == (old.get("prior") == "edi_c")
    assert est.needs_timing == bool(old.get("timing"))


@pytest.mark.parametrize("name", OLD_NAMES)
def test_each_old_name_builds_the_network_it_built(name):
    old = OLD_VARIANT_ARGS[name]
    assert variant_args(name) == old
    net = create_model(name, n=1)
    assert net.args == RENet(n=1, **old).args
    assert net.variant == canonical_name(name) in list_models()


def test_the_alias_table():
    # stages on the way to the shipped network are aliases, not architectures
    assert list_aliases() == {old: ALIASES[old] for old in sorted(ALIASES)}
    assert set(ALIASES) == {"trmd_small_edi", "trmd_small_edi_c", "trmd_small_edi_c_fr",
                            "trmd_small_edi_c_fr_t"}
    assert not set(ALIASES) & set(list_models())
    assert set(list_models()) == {"trmd_paper", "trmd_base", "trmd_small", "trmd_small_prior",
                                  "test_trmd"}
    for old, (name, _) in ALIASES.items():
        assert name in list_models() and is_model(old) and canonical_name(old) == name
    assert canonical_name("trmd_small_edi_c_fr_t") == "trmd_small_prior"
    assert canonical_name("custom") == "custom"  # other names pass as they are
    # overrides still apply over an alias's arguments
    assert create_model("trmd_small_edi", n=1, prior="edi_c").args["prior"] == "edi_c"


def test_a_recipe_naming_an_old_variant_trains(tmp_path):
    from trmd_cli.train.data import wants_levels
    from trmd_cli.train.loop import train

    imgs = make_image_folder(tmp_path / "imgs", 3)
    r = recipe("model.name='trmd_small_edi_c_fr_t'", "model.n=1",
               "model.args={feat_width=2, widths=[2, 4, 4, 4], num_res_blocks=1, "
               "refine_width=2}", "data.length=4", "data.crop=16", "data.batch_size=2",
               "data.val_fraction=0.0", "train.steps=1", "loss.contrast=0.25")
    assert wants_levels(r)  # the old name says timing through the alias
    res = train([imgs], recipe=r, run_dir=tmp_path / "run")
    meta = read_metadata(res.final_weights)
    assert meta["architecture"] == "trmd_small_prior"
    assert meta["args"]["timing"] is True and meta["args"]["refine"] == 3


def test_an_old_stage_file_grows_into_the_shipped_architecture(expected):
    # what weights_recipe's stages did: trmd_small_edi_c weights → refinement and timing grown
    old, _ = load_weights(_path("trmd_small_edi_c"))
    new = create_model("trmd_small_prior", n=1, feat_width=2, widths=(2, 4, 4, 4),
                       num_res_blocks=1, refine_width=2).eval()
    grown = load_grown(new, old.state_dict())
    assert grown.identity and all(k.startswith("refine.") for k in grown.identity)
    assert len(grown.timing) == 3 and not grown.widened
    x = RENetInputs(expected["blurry"], expected["counts"], levels=expected["levels"],
                    contrast=expected["contrast"])
    with torch.no_grad():
        torch.testing.assert_close(new(x), expected["residuals/trmd_small_edi_c"], rtol=1e-5,
                                   atol=1e-5)
