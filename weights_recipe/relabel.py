"""Name the validation set in a weights file by its file name and SHA-256 instead of a path.

    python weights_recipe/relabel.py src/trmd_cli/weights/trmd_default.safetensors \
        --valset ../runs/valset_kodak24.h5

`trmd train` records the validation file as the path it had on the training machine, in the
``recipe`` metadata (``data.val_data``) and in the ``figures`` metadata (``validation``). This
rewrites them as::

    recipe.data.val_data = "valset_kodak24.h5"
    figures.validation   = {"file": "valset_kodak24.h5", "sha256": "<64 hex digits>"}

The recipe keeps only keys `trmd train` reads, so ``recipe_from_dict`` still loads it. Only the
header changes: the tensor bytes are copied as they are, and the header is written the way
``trmd_cli.models.weights`` writes it (metadata keys sorted, compact JSON, padded with spaces to
a multiple of 8 bytes), so the same input always gives the same bytes. ``ship.py`` applies the
same labels when it writes weights. ``--valset`` must be the file the weights were validated on
(``make_valset.py`` rebuilds it byte for byte).
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import tempfile
from pathlib import Path
from typing import Any


def label_valset(recipe: dict[str, Any] | None, figures: dict[str, Any] | None,
                 valset: Path) -> None:
    """Replace paths to the validation file in ``recipe`` and ``figures`` (in place) by its name
    and, in ``figures``, its SHA-256. Entries that name no file (a held-out share) stay."""
    from trmd_cli.train.data import file_sha256

    name, digest = valset.name, file_sha256(valset)

    def check(recorded: str, where: str) -> None:
        if Path(recorded).name != name:
            raise SystemExit(f"{where} names {recorded!r}, not {name}: pass --valset that file")

    data = (recipe or {}).get("data") or {}
    recorded = data.get("val_data")
    if recorded:
        check(recorded, "recipe data.val_data")
        data["val_data"] = name
    val = (figures or {}).get("validation")
    if isinstance(val, dict) and "file" in val:  # labelled before
        val = val["file"]
    elif not (isinstance(val, str) and (recorded or Path(val).name == name)):
        return  # "held out 5 % of the training data", "none": no file
    check(val, "figures validation")
    figures["validation"] = {"file": name, "sha256": digest}


def read_header(data: bytes) -> tuple[dict[str, Any], bytes]:
    (size,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8:8 + size]), data[8 + size:]


def write_header(header: dict[str, Any], body: bytes) -> bytes:
    """The file ``trmd_cli.models.weights.save_weights`` would write for this header and body."""
    header = dict(header)
    meta = header.pop("__metadata__", None)
    ordered: dict[str, Any] = {"__metadata__": dict(sorted(meta.items()))} if meta else {}
    ordered.update(sorted(header.items()))  # tensor offsets count from the body: order is free
    raw = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode()
    raw += b" " * (-len(raw) % 8)
    return struct.pack("<Q", len(raw)) + raw + body


def relabel(path: Path, valset: Path, out: Path | None = None) -> Path:
    from safetensors import safe_open

    with safe_open(str(path), framework="numpy") as f:
        meta = dict(f.metadata() or {})
    recipe = json.loads(meta["recipe"]) if meta.get("recipe") else None
    figures = json.loads(meta["figures"]) if meta.get("figures") else None
    label_valset(recipe, figures, valset)
    # JSON entries as trmd_cli.models.weights encodes them (sorted keys, default separators)
    if recipe is not None:
        meta["recipe"] = json.dumps(recipe, sort_keys=True)
    if figures is not None:
        meta["figures"] = json.dumps(figures, sort_keys=True)
    header, body = read_header(path.read_bytes())
    header["__metadata__"] = meta
    data = write_header(header, body)
    out = out or path
    fd, tmp = tempfile.mkstemp(dir=out.parent, suffix=".safetensors")
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(tmp, 0o644)
    os.replace(tmp, out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("weights", type=Path)
    ap.add_argument("--valset", type=Path, required=True,
                    help="the validation file the weights were measured on")
    ap.add_argument("-o", "--output", type=Path, help="write here (default: in place)")
    args = ap.parse_args()
    out = relabel(args.weights, args.valset, args.output)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
