"""Weights whose header says what the tensors are not: the header is checked against the
tensors, and its metadata has limits of size and depth (``trmd info`` and loading alike)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
from typer.testing import CliRunner

from trmd_cli.cli.app import app
from trmd_cli.errors import WeightsError
from trmd_cli.models.weights import describe_weights, load_weights, save_weights

runner = CliRunner()


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> Path:
    from trmd_cli.models import create_model

    path = tmp_path_factory.mktemp("w") / "w3.safetensors"
    save_weights(path, create_model("test_trmd", n=3), meta={})
    return path


def split(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    (size,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8:8 + size]), data[8 + size:]


def join(path: Path, header_text: str, body: bytes) -> Path:
    raw = header_text.encode()
    raw += b" " * (-len(raw) % 8)
    path.write_bytes(struct.pack("<Q", len(raw)) + raw + body)
    return path


def edited(weights: Path, out: Path, edit) -> Path:
    header, body = split(weights)
    edit(header)
    return join(out, json.dumps(header), body)


def refused(path: Path, match: str) -> None:
    """Refused by loading, by describing (`trmd info`), and by `trmd info` as one line."""
    with pytest.raises(WeightsError, match=match):
        load_weights(path)
    r = runner.invoke(app, ["info", str(path)])
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "unexpected" not in lines[0], r.stderr


def test_deeply_nested_metadata_is_refused_not_a_recursion_error(weights, tmp_path):
    def deep(h):
        h["__metadata__"]["figures"] = "[" * 100_000 + "]" * 100_000

    refused(edited(weights, tmp_path / "deep.safetensors", deep), "figures")

    def nested(h):  # deep, but within what json parses: the depth limit says it
        h["__metadata__"]["figures"] = "[" * 500 + "]" * 500

    refused(edited(weights, tmp_path / "nested.safetensors", nested), "nests deeper than 32")


def test_oversized_metadata_is_refused(weights, tmp_path):
    def big(h):
        h["__metadata__"]["notes"] = json.dumps("x" * (2 << 20))

    refused(edited(weights, tmp_path / "big.safetensors", big), "metadata of .* bytes")


def test_a_float16_tensor_relabelled_int16_is_refused(weights, tmp_path):
    def relabel(h):
        name = next(k for k, v in h.items() if k != "__metadata__" and v["dtype"] == "F16")
        h[name]["dtype"] = "I16"  # the same bytes, read as integers

    path = edited(weights, tmp_path / "i16.safetensors", relabel)
    with pytest.raises(WeightsError, match="is stored as I16, the architecture needs "
                                           "floating-point"):
        load_weights(path)


def test_a_tensor_named_twice_is_refused(weights, tmp_path):
    header, body = split(weights)
    name = next(k for k in header if k != "__metadata__")
    text = json.dumps(header)
    entry = f'"{name}": {json.dumps(header[name])}'
    assert entry in text
    path = join(tmp_path / "dup.safetensors", text.replace(entry, f"{entry}, {entry}", 1), body)
    refused(path, f"names tensor '{name}' twice")


def test_metadata_n_that_the_architecture_contradicts_is_refused(weights, tmp_path):
    def huge_n(h):
        h["__metadata__"]["n"] = "1000000000"

    path = edited(weights, tmp_path / "n.safetensors", huge_n)
    refused(path, "metadata says n = 1000000000 but the architecture it describes has n = 3")
    with pytest.raises(WeightsError):
        describe_weights(path)  # `trmd info` reported N = 1000000000 while deblur ran N = 3


def test_the_weights_as_written_pass(weights):
    model, meta = load_weights(weights)
    assert meta["n"] == 3 and describe_weights(weights)["n"] == 3
