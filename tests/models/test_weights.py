"""Weights files (safetensors + metadata) and the inference wrapper that loads them."""

from __future__ import annotations

import json
import os
import pickle
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from trmd_cli.errors import InputError, ShapeError, WeightsError
from trmd_cli.models import RENetInputs, create_model
from trmd_cli.models.estimator import TrmdEstimator
from trmd_cli.models.weights import (
    load_weights,
    read_metadata,
    save_weights,
    weights_hash,
)
from trmd_cli.reconstruct import reconstruct

RECIPE = {"data": "synthetic", "steps": 10, "lr": 3e-4}
FIGURES = {"val_psnr_db": 31.5, "steps": 10}


def _trained_like(**kwargs):
    """A test model whose BatchNorm statistics differ from their defaults, as after training."""
    torch.manual_seed(0)
    m = create_model("test_trmd", **kwargs)
    for mod in m.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.5, 0.5)
            mod.running_var.uniform_(0.5, 2.0)
    return m.eval()


@pytest.fixture
def saved(tmp_path: Path):
    m = _trained_like()
    p = save_weights(tmp_path / "w.safetensors", m, meta={"recipe": RECIPE, "figures": FIGURES,
                                                           "seed": 7}, half=False)
    return m, p


def _run(m, h=19, w=23, seed=0):
    g = torch.Generator().manual_seed(seed)
    b = torch.rand(1, m.channels, h, w, generator=g)
    v = torch.randn(1, 2 * m.n, h, w, generator=g)
    with torch.no_grad():
        return m(RENetInputs(b, v))


# --------------------------------------------------------------------------------------------
# round trips


def test_round_trip_fp32_exact(saved):
    m, p = saved
    loaded, meta = load_weights(p)
    for (k, a), (k2, b) in zip(m.state_dict().items(), loaded.state_dict().items(), strict=True):
        assert k == k2
        assert torch.equal(a, b), k
    assert not loaded.training
    torch.testing.assert_close(_run(loaded), _run(m), atol=0, rtol=0)
    assert meta["architecture"] == "test_trmd" and meta["model_class"] == "RENet"
    assert meta["n"] == 3 and meta["channels"] == 1 and meta["dtype"] == "float32"
    assert meta["recipe"] == RECIPE and meta["figures"] == FIGURES and meta["seed"] == 7
    assert meta["args"] == m.args


def test_round_trip_fp16(tmp_path):
    m = _trained_like(n=2, channels=3, attn_norm="l2")
    p32 = save_weights(tmp_path / "a.safetensors", m, meta={}, half=False)
    p16 = save_weights(tmp_path / "b.safetensors", m, meta={})
    assert p16.stat().st_size < 0.7 * p32.stat().st_size
    loaded, meta = load_weights(p16)
    assert meta["dtype"] == "float16" and meta["args"]["attn_norm"] == "l2"
    assert (loaded.n, loaded.channels) == (2, 3)
    for k, a in m.state_dict().items():
        b = loaded.state_dict()[k]
        assert b.dtype == a.dtype  # loaded back into float32 parameters
        if k.endswith(("running_mean", "running_var")):
            assert torch.equal(a, b)  # statistics are stored in float32
        elif a.is_floating_point():
            torch.testing.assert_close(b, a, atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(_run(loaded), _run(m), atol=1e-3, rtol=1e-2)


def test_metadata_readable_without_loading(saved):
    _, p = saved
    meta = read_metadata(p)
    assert meta["format"] == "trmd-weights" and meta["args"]["widths"] == [4, 8, 8, 8]


def test_metadata_is_read_without_torch(saved):
    import subprocess
    import sys

    _, p = saved
    code = ("import sys; from trmd_cli.models.weights import describe_weights, read_metadata; "
            f"d = describe_weights({str(p)!r}); m = read_metadata({str(p)!r}); "
            "print(d['architecture'], m['n'], 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["test_trmd", "3", "False"]


def test_hash_is_content_hash(saved, tmp_path):
    m, p = saved
    h = weights_hash(p)
    assert len(h) == 12 and int(h, 16) >= 0
    same = save_weights(tmp_path / "again.safetensors", m, meta={"recipe": RECIPE,
                                                                 "figures": FIGURES, "seed": 7},
                        half=False)
    assert weights_hash(same) == h  # deterministic bytes for the same model + metadata
    other = save_weights(tmp_path / "o.safetensors", m, meta={"seed": 8}, half=False)
    assert weights_hash(other) != h


def test_save_is_atomic_and_leaves_no_temp(tmp_path):
    m = _trained_like()
    save_weights(tmp_path / "w.safetensors", m, meta={})
    assert [f.name for f in tmp_path.iterdir()] == ["w.safetensors"]


def test_save_refuses_non_finite_and_contradicting_meta(tmp_path):
    m = _trained_like()
    with pytest.raises(InputError, match="contradicts"):
        save_weights(tmp_path / "w.safetensors", m, meta={"n": 4})
    save_weights(tmp_path / "ok.safetensors", m, meta={"n": 3, "channels": 1})  # agreeing is ok
    with torch.no_grad():
        m.head.bias[0] = float("nan")
    with pytest.raises(WeightsError, match="NaN"):
        save_weights(tmp_path / "w.safetensors", m, meta={})
    assert not (tmp_path / "w.safetensors").exists()


# --------------------------------------------------------------------------------------------
# errors on loading


def test_missing_file(tmp_path):
    with pytest.raises(WeightsError, match="not found"):
        load_weights(tmp_path / "nope.safetensors")


def test_no_shipped_weights_message(no_shipped_weights):
    with pytest.raises(WeightsError, match="no shipped .*`weights`"):
        load_weights(None)


def test_truncated_file(saved, tmp_path):
    _, p = saved
    data = p.read_bytes()
    bad = tmp_path / "trunc.safetensors"
    bad.write_bytes(data[: len(data) - 100])
    with pytest.raises(WeightsError, match="truncated or corrupt"):
        load_weights(bad)


def test_random_bytes(tmp_path):
    bad = tmp_path / "rand.safetensors"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(WeightsError, match="safetensors"):
        load_weights(bad)
    empty = tmp_path / "empty.safetensors"
    empty.write_bytes(b"")
    with pytest.raises(WeightsError):
        load_weights(empty)


def test_pickle_and_torch_checkpoints_rejected_unopened(tmp_path):
    # a pickle that would create a file if unpickled: loading must refuse before that
    marker = tmp_path / "unpickled"

    class Boom:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    pkl = tmp_path / "w.pkl"
    pkl.write_bytes(pickle.dumps(Boom()))
    with pytest.raises(WeightsError, match="pickle"):
        load_weights(pkl)
    pt = tmp_path / "w.pth"
    torch.save(create_model("test_trmd").state_dict(), pt)
    with pytest.raises(WeightsError, match="PyTorch checkpoint"):
        load_weights(pt)
    assert not marker.exists()


def test_safetensors_without_metadata(tmp_path):
    from safetensors.torch import save_file

    p = tmp_path / "plain.safetensors"
    save_file(create_model("test_trmd").state_dict(), str(p))
    with pytest.raises(WeightsError, match="without trmd metadata"):
        load_weights(p)


def _rewrite(p: Path, out: Path, *, drop: str | None = None, meta_update: dict | None = None):
    """Copy a safetensors file, dropping one tensor or editing metadata, byte by byte."""
    raw = p.read_bytes()
    (size,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + size])
    body = raw[8 + size:]
    if meta_update:
        header["__metadata__"].update(meta_update)
    if drop:
        del header[drop]
        # rebuild the byte buffer without the dropped tensor's bytes
        items = sorted(((k, v) for k, v in header.items() if k != "__metadata__"),
                       key=lambda kv: kv[1]["data_offsets"][0])
        new_body, pos = b"", 0
        for _, v in items:
            a, b = v["data_offsets"]
            new_body += body[a:b]
            v["data_offsets"] = [pos, pos + b - a]
            pos += b - a
        body = new_body
    hb = json.dumps(header).encode()
    hb += b" " * (-len(hb) % 8)
    out.write_bytes(struct.pack("<Q", len(hb)) + hb + body)
    return out


def test_keys_do_not_match_architecture(saved, tmp_path):
    _, p = saved
    bad = _rewrite(p, tmp_path / "drop.safetensors", drop="head.bias")
    with pytest.raises(WeightsError, match="missing.*head.bias"):
        load_weights(bad)
    # metadata claiming another width: shapes no longer fit
    args = dict(read_metadata(p)["args"], widths=[4, 8, 8, 16])
    bad2 = _rewrite(p, tmp_path / "wide.safetensors", meta_update={"args": json.dumps(args)})
    with pytest.raises(WeightsError, match="shape"):
        load_weights(bad2)


def test_wrong_n_or_channels(saved):
    _, p = saved
    load_weights(p, expect_n=3, expect_channels=1)
    with pytest.raises(WeightsError, match="N = 3, not N = 2"):
        load_weights(p, expect_n=2)
    with pytest.raises(WeightsError, match="1-channel .*not 3-channel"):
        load_weights(p, expect_channels=3)
    with pytest.raises(WeightsError, match="N = 3"):
        TrmdEstimator.load(p, device="cpu", expect_n=4)


def test_error_messages_are_one_line(saved, tmp_path):
    _, p = saved
    bad = tmp_path / "rand.safetensors"
    bad.write_bytes(os.urandom(64))
    for call in (lambda: load_weights(tmp_path / "x.safetensors"), lambda: load_weights(bad),
                 lambda: load_weights(p, expect_n=5)):
        with pytest.raises(WeightsError) as e:
            call()
        assert "\n" not in str(e.value) and e.value.hint


# --------------------------------------------------------------------------------------------
# the estimator


@pytest.fixture
def estimator(saved):
    _, p = saved
    return TrmdEstimator.load(p, device="auto", threads=None)


def test_estimator_gray(estimator, saved):
    m, p = saved
    rng = np.random.default_rng(0)
    blurry = rng.random((21, 30)).astype(np.float32)
    vox = rng.normal(size=(6, 21, 30)).astype(np.float32)
    out = estimator(blurry, vox)
    assert out.shape == (7, 21, 30) and out.dtype == np.float32
    np.testing.assert_allclose(out.mean(0), blurry, atol=1e-5)
    # same numbers as model + reconstruct by hand
    with torch.no_grad():
        tb, tv = torch.from_numpy(blurry)[None, None], torch.from_numpy(vox)[None]
        ref = reconstruct(tb, m(RENetInputs(tb, tv)))[0, :, 0].numpy()
    np.testing.assert_allclose(out, ref, atol=1e-6)
    assert estimator.n == 3 and estimator.channels == 1
    assert estimator.weights_hash == weights_hash(p)
    assert estimator.meta["recipe"] == RECIPE


def test_estimator_rgb_frame_gray_model_runs_per_channel(estimator):
    rng = np.random.default_rng(1)
    rgb = rng.random((17, 13, 3)).astype(np.float32)
    vox = rng.normal(size=(6, 17, 13)).astype(np.float32)
    out = estimator(rgb, vox)
    assert out.shape == (7, 17, 13, 3)
    for c in range(3):
        np.testing.assert_allclose(out[..., c], estimator(rgb[..., c], vox), atol=1e-5)
    np.testing.assert_allclose(out.mean(0), rgb, atol=1e-5)


def test_estimator_rgb_model(tmp_path):
    p = save_weights(tmp_path / "rgb.safetensors", _trained_like(n=1, channels=3), meta={})
    est = TrmdEstimator.load(p, device="cpu")
    rng = np.random.default_rng(2)
    rgb = rng.random((9, 11, 3)).astype(np.float32)
    vox = rng.normal(size=(2, 9, 11)).astype(np.float32)
    out = est(rgb, vox)
    assert out.shape == (3, 9, 11, 3)
    np.testing.assert_allclose(out.mean(0), rgb, atol=1e-5)
    gray = rgb[..., 0]
    out_g = est(gray, vox)  # replicated to RGB, outputs averaged
    assert out_g.shape == (3, 9, 11)
    np.testing.assert_allclose(out_g.mean(0), gray, atol=1e-5)


def test_estimator_input_errors(estimator):
    b = np.zeros((10, 12), np.float32)
    with pytest.raises(InputError, match="N = 3"):
        estimator(b, np.zeros((4, 10, 12), np.float32))
    with pytest.raises(ShapeError):
        estimator(b, np.zeros((6, 10, 13), np.float32))
    with pytest.raises(ShapeError):
        estimator(np.zeros((10, 12, 4), np.float32), np.zeros((6, 10, 12), np.float32))
    bad = b.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        estimator(bad, np.zeros((6, 10, 12), np.float32))


def test_estimator_load_errors(tmp_path):
    with pytest.raises(WeightsError, match="not found"):
        TrmdEstimator.load(tmp_path / "missing.safetensors")
    with pytest.raises(InputError):
        TrmdEstimator.load(tmp_path / "missing.safetensors", threads=0)
