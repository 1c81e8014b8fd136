"""RE-Net weights as safetensors files that describe themselves; never pickle.

A weights file holds the model's tensors (fp16 parameters by default, fp32 BatchNorm statistics)
and string metadata saying what they are:

==================  =====================================================================
``format``          ``"trmd-weights"``; ``format_version`` ``"1"``
``architecture``    registered variant name (``trmd_small`` …), informative; old names are
                    read through :data:`~trmd_cli.models.renet.ALIASES`
``model_class``     ``"RENet"``
``args``            JSON of every constructor argument: the model is rebuilt from these
``n``, ``channels`` N and colour channels, repeated for quick checks
``recipe``          JSON: how it was trained (recipe file contents, data, seed …)
``figures``         JSON: training / validation figures (PSNR, loss, steps …)
``dtype``           ``float16`` or ``float32``; ``trmd_version``
==================  =====================================================================

Further keys given in ``meta`` are stored JSON-encoded. The shipped default lives in the package
at ``trmd_cli/weights/trmd_default.safetensors`` and is found through importlib.resources.

Reading metadata (:func:`read_metadata`, :func:`describe_weights`) needs no torch; torch is
imported only when weights are really saved or loaded.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
from importlib import resources
from math import prod
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import InputError, WeightsError
from ..write import write_bytes

if TYPE_CHECKING:  # torch stays unimported until weights are really saved or loaded
    from .renet import RENet

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "DEFAULT_WEIGHTS",
    "save_weights",
    "load_weights",
    "read_metadata",
    "describe_weights",
    "weights_hash",
    "default_weights_path",
    "resolve_device",
]

FORMAT = "trmd-weights"
FORMAT_VERSION = "1"
#: file name of the shipped weights inside the package folder ``trmd_cli/weights/``
DEFAULT_WEIGHTS = "trmd_default.safetensors"

_PLAIN = ("format", "format_version", "architecture", "model_class", "dtype", "trmd_version")
_INTS = ("n", "channels")
_RESERVED = (*_PLAIN, *_INTS, "args")
_NO_WEIGHTS_HINT = "pass `weights` (a .safetensors file written by `trmd train`)"


def default_weights_path() -> Path:
    """Where the shipped default weights are (the file may not exist yet)."""
    return Path(str(resources.files("trmd_cli") / "weights" / DEFAULT_WEIGHTS))


def weights_hash(path: str | Path) -> str:
    """First 12 hex digits of the file's SHA-256: names the weights in logs and outputs."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except OSError as e:
        raise WeightsError(f"cannot read weights file ({e.strerror})", path=path) from None
    return h.hexdigest()[:12]


def resolve_device(device: str = "auto"):
    """``"auto"`` → cuda when available, else cpu; checks that a named device exists."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise InputError(f"unknown device {device!r}", hint="use auto, cpu or cuda") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("CUDA is not available on this machine", hint="use `device='cpu'`")
    return dev


# --------------------------------------------------------------------------------------------
# Saving


def save_weights(path: str | Path, model: RENet, *, meta: dict[str, Any] | None = None,
                 half: bool = True) -> Path:
    """Write ``model``'s tensors and self-describing metadata to a safetensors file, atomically.

    Args:
        path: output file (``.safetensors``); its folder must exist. Overwrite policy is the
            caller's (:func:`trmd_cli.write.check_output`).
        model: a :class:`~trmd_cli.models.RENet`.
        meta: ``recipe``, ``figures`` and any other JSON-serialisable entries. Entries named like
            the model's own keys (``n``, ``channels``, ``args`` …) must agree with the model.
        half: store parameters as float16 (half the size; BatchNorm statistics stay float32).
    Returns:
        ``path``.
    Raises:
        WeightsError: non-finite values (or values beyond float16 range when ``half``).
        InputError: ``meta`` contradicts the model, is not JSON-serialisable, or the folder
            does not exist.
    """
    import torch
    from safetensors.torch import save

    from .. import __version__

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("the weights file's folder does not exist", path=path.parent,
                         hint="create it first")
    params = {name for name, _ in model.named_parameters()}
    tensors: dict[str, torch.Tensor] = {}
    for name, t in model.state_dict().items():
        t = t.detach().to("cpu")
        if t.is_floating_point():
            if not torch.isfinite(t).all():
                raise WeightsError(f"tensor {name} has NaN or infinite values; not saving",
                                   hint="the training diverged: lower the learning rate")
            t = t.to(torch.float16 if half and name in params else torch.float32)
            if not torch.isfinite(t).all():
                raise WeightsError(f"tensor {name} overflows float16", hint="save with half=False")
        tensors[name] = t.contiguous()

    own = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "architecture": getattr(model, "variant", None) or "custom",
        "model_class": type(model).__name__,
        "args": _dumps(model.args),
        "n": str(model.n),
        "channels": str(model.channels),
        "dtype": "float16" if half else "float32",
        "trmd_version": __version__,
    }
    metadata = dict(own)
    ours = {"n": model.n, "channels": model.channels, "args": model.args}
    for key, value in (meta or {}).items():
        if key == "architecture":
            metadata[key] = str(value)  # e.g. a name for a variant built with overrides
            continue
        if key in _RESERVED:
            if key not in ours or _dumps(value) != _dumps(ours[key]):
                raise InputError(f"meta[{key!r}] = {value!r} contradicts the model, which "
                                 "sets it", hint=f"leave {key!r} out of meta")
            continue
        metadata[key] = _dumps(value, key)
    for key in ("recipe", "figures"):
        metadata.setdefault(key, "null")

    data = _canonical(save(tensors, metadata=metadata))
    write_bytes(path, data)
    return path


def _canonical(data: bytes) -> bytes:
    """Rewrite the safetensors header with sorted metadata keys.

    safetensors writes metadata in hash-map order, which varies from run to run; sorting makes
    the same model + metadata give the same bytes, hence the same :func:`weights_hash`.
    """
    (size,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + size])
    meta = header.pop("__metadata__", None)
    ordered = {"__metadata__": dict(sorted(meta.items()))} if meta else {}
    ordered.update(sorted(header.items()))  # offsets are absolute in the body: order is free
    raw = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode()
    raw += b" " * (-len(raw) % 8)  # the format pads the header with spaces to 8 bytes
    return struct.pack("<Q", len(raw)) + raw + data[8 + size:]


def _dumps(value: Any, key: str = "") -> str:
    try:
        return json.dumps(value, sort_keys=True, default=_json_default)
    except (TypeError, ValueError) as e:
        raise InputError(f"meta[{key!r}] is not JSON-serialisable: {e}") from None


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON-serialisable")


# --------------------------------------------------------------------------------------------
# Loading


def _existing(path: str | Path | None) -> Path:
    if path is None:
        p = default_weights_path()
        if not p.is_file():
            raise WeightsError("no shipped TRMD weights are installed", hint=_NO_WEIGHTS_HINT)
        return p
    p = Path(path)
    if not p.exists():
        raise WeightsError("weights file not found", path=p,
                           hint="check the path, or leave out `weights` to use the shipped "
                           "weights")
    if not p.is_file():
        raise WeightsError("weights path is not a file", path=p, hint=_NO_WEIGHTS_HINT)
    if not os.access(p, os.R_OK):
        raise WeightsError("weights file cannot be read (permission denied)", path=p,
                           hint="check its permissions (chmod u+r)")
    return p


def _sniff(path: Path) -> None:
    """Name pickles and torch checkpoints explicitly: they are refused, never opened."""
    with open(path, "rb") as fh:
        head = fh.read(8)
    if head.startswith(b"PK\x03\x04"):
        raise WeightsError("this is a PyTorch checkpoint (zip of pickles), not safetensors",
                           path=path,
                           hint="trmd never unpickles files; convert it where you trust it with "
                           "safetensors.torch.save_file, or use weights from `trmd train`")
    if len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5:
        raise WeightsError("this is a Python pickle, not safetensors", path=path,
                           hint="trmd never unpickles files; use a .safetensors weights file")


def _stored_shapes(path: Path) -> dict[str, tuple[tuple[int, ...], str]]:
    """Name → (shape, safetensors dtype such as ``F16``) of every tensor in a safetensors
    file, from its header (no tensor read)."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="numpy") as fh:
            return {name: (tuple(fh.get_slice(name).get_shape()),
                           str(fh.get_slice(name).get_dtype()))
                    for name in fh.keys()}
    except (SafetensorError, OSError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise WeightsError(f"not a readable safetensors file ({reason})", path=path,
                           hint="the file is truncated or corrupt: copy it again") from None


#: limits on what a weights file's header may hold (its metadata comes from strangers too)
MAX_HEADER_BYTES = 100 << 20  # safetensors' own limit
MAX_METADATA_BYTES = 1 << 20  # all metadata values together; trmd writes a few kB
MAX_METADATA_DEPTH = 32  # nesting of a JSON metadata value


def _no_duplicates(path: Path, what: str):
    def hook(pairs):
        seen: dict[str, Any] = {}
        for key, value in pairs:
            if key in seen:
                raise WeightsError(f"the header names {what} {key!r} twice", path=path,
                                   hint="the file was edited or written by another tool: use "
                                   "weights written by `trmd train`")
            seen[key] = value
        return seen
    return hook


def _check_header(path: Path) -> dict[str, Any]:
    """The safetensors header as JSON, refusing what the safetensors library takes silently:
    a tensor (or metadata entry) named twice — the last one would win — and metadata beyond
    :data:`MAX_METADATA_BYTES`."""
    with open(path, "rb") as fh:
        head = fh.read(8)
        size = struct.unpack("<Q", head)[0] if len(head) == 8 else 0
        if not 0 < size <= MAX_HEADER_BYTES:
            raise WeightsError(f"not a readable safetensors file (header of {size} bytes)",
                               path=path, hint="the file is truncated or corrupt: copy it again")
        raw = fh.read(size)
    try:
        header = json.loads(raw, object_pairs_hook=_no_duplicates(path, "tensor"))
    except (ValueError, RecursionError):
        raise WeightsError("not a readable safetensors file (its header is not JSON)",
                           path=path, hint="the file is truncated or corrupt: copy it again"
                           ) from None
    meta = header.get("__metadata__") or {}
    total = sum(len(str(k)) + len(str(v)) for k, v in meta.items()) if isinstance(
        meta, dict) else 0
    if total > MAX_METADATA_BYTES:
        raise WeightsError(f"metadata of {total} bytes (trmd writes a few kB; at most "
                           f"{MAX_METADATA_BYTES} are read)", path=path,
                           hint="the file was edited or written by another tool")
    return header


def _depth(value: Any) -> int:
    """How deeply a decoded JSON value nests (iteratively: no recursion to exhaust)."""
    deepest, todo = 0, [(value, 1)]
    while todo:
        v, d = todo.pop()
        if isinstance(v, dict | list):
            deepest = max(deepest, d)
            todo.extend((c, d + 1) for c in (v.values() if isinstance(v, dict) else v))
    return deepest


def read_metadata(path: str | Path | None = None) -> dict[str, Any]:
    """The decoded metadata of a weights file (None = the shipped default), without torch.

    Returns:
        dict with ``architecture``, ``model_class``, ``args`` (dict), ``n``, ``channels``
        (ints), ``recipe``, ``figures`` and any extra entries, JSON-decoded.
    Raises:
        WeightsError: missing file, not safetensors, corrupt or truncated, or no trmd metadata.
    """
    from safetensors import SafetensorError, safe_open

    p = _existing(path)
    _sniff(p)
    try:
        with safe_open(str(p), framework="numpy") as fh:
            raw = fh.metadata() or {}
    except (SafetensorError, OSError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise WeightsError(f"not a readable safetensors file ({reason})", path=p,
                           hint="the file is truncated or corrupt: copy it again") from None
    _check_header(p)
    return _decode(raw, p)


def _trained_validation(figures) -> dict[str, Any] | None:
    """A run's own validation figures (``figures`` of ``trmd train``'s weights) in the layout
    of the shipped weights' ``validation``: the network's PSNR at the run's last validation,
    and on what."""
    if not isinstance(figures, dict) or figures.get("val_psnr_mid") is None:
        return None
    return {"trmd": {"psnr_mid": float(figures["val_psnr_mid"]),
                     "psnr_seq": float(figures.get("val_psnr_seq", float("nan")))},
            **({"set": figures["validation"]} if isinstance(figures.get("validation"), str)
               else {})}


def describe_weights(path: str | Path | None = None) -> dict[str, Any]:
    """What a weights file is, for people (``trmd info W.safetensors``), without torch.

    Returns:
        dict: ``file``, ``sha256`` (first 12 hex digits), ``size_mib``, ``architecture``,
        ``parameters`` (count, from the tensor shapes), ``dtype``, ``n``, ``channels``,
        ``inputs`` (what the network needs besides the blurry frame and the voxels),
        ``recipe`` (its name), ``training_data``, ``trmd_version`` and — when the file
        records them — ``validation``: {method: {figure: value}} on its validation set;
        ``finetune``: what ``trmd finetune`` adapted it on (inputs, windows, steps, held-out
        losses before and after), else None.
    Raises:
        WeightsError: as :func:`read_metadata`.
    """
    from safetensors import safe_open

    from .aliases import current_name

    p = _existing(path)
    meta = read_metadata(p)
    prefix = ""
    if meta.get("checkpoint"):  # its network's tensors only; the variant's full arguments
        meta, prefix = _resolve_checkpoint(meta, p)
    with safe_open(str(p), framework="numpy") as fh:
        params = 0
        for k in fh.keys():
            if not k.startswith(prefix):
                continue
            if k.endswith(("running_mean", "running_var", "num_batches_tracked")):
                continue  # BatchNorm statistics are buffers, not parameters
            shape = fh.get_slice(k).get_shape()
            params += int(prod(shape))
    args = meta.get("args") or {}
    inputs = []
    if args.get("prior") == "edi_c":
        inputs.append("the contrast threshold c (estimated per frame unless given)")
    if args.get("timing"):
        inputs.append("the events' sub-bin timing (voxel.scer_levels; raw events needed)")
    recipe = meta.get("recipe")
    val = meta.get("validation") if isinstance(meta.get("validation"), dict) else \
        _trained_validation(meta.get("figures"))
    return {
        "file": str(p),
        "sha256": weights_hash(p),
        "size_mib": round(p.stat().st_size / 2**20, 2),
        "architecture": current_name(str(meta.get("architecture"))),
        # the name the file records, when it is an old one that now stands for the above
        "recorded_as": meta.get("architecture")
        if current_name(str(meta.get("architecture"))) != meta.get("architecture") else None,
        "parameters": params,
        "dtype": meta.get("dtype"),
        "n": meta.get("n"),
        "channels": meta.get("channels"),
        "inputs": inputs,
        "recipe": recipe.get("name") if isinstance(recipe, dict) else recipe,
        "training_data": meta.get("training_data"),
        "trmd_version": meta.get("trmd_version"),
        "validation": val,
        "checkpoint": meta.get("checkpoint"),
        "finetune": meta.get("finetune") if isinstance(meta.get("finetune"), dict) else None,
    }


#: the metadata key of a training checkpoint (``trmd_cli.train.checkpoint``)
_CHECKPOINT_KEY = "trmd_checkpoint"


def _checkpoint_meta(raw: dict[str, str], path: Path) -> dict[str, Any]:
    """A training checkpoint described as weights: what ``trmd train`` leaves after
    ``--stop-after`` or an interruption is as usable as its final weights. The architecture
    comes from the run's recipe; ``args`` holds the recipe's own model arguments (the full set
    is the variant's with these applied: :func:`load_weights` resolves it)."""
    try:
        doc = json.loads(raw[_CHECKPOINT_KEY])
        recipe = doc.get("recipe") or {}
        model = recipe.get("model") or {}
        name = str(model["name"])
        n, channels = int(model.get("n", 3)), int(model.get("channels", 1))
        args = dict(model.get("args") or {})
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
        raise WeightsError("a training checkpoint without a readable recipe", path=path,
                           hint="the file is corrupt: resume the run or train again") from None
    return {"format": FORMAT, "architecture": name, "model_class": "RENet",
            "args": {**args, "n": n, "channels": channels}, "n": n, "channels": channels,
            "recipe": recipe,
            "training_data": [Path(str(d)).name for d in doc.get("data") or []],
            "figures": {"step": doc.get("step"), "total_steps": doc.get("total_steps"),
                        "last_val": doc.get("last_val")},
            "checkpoint": {"step": doc.get("step"), "variant_args": False}}


def _decode(raw: dict[str, str], path: Path) -> dict[str, Any]:
    if _CHECKPOINT_KEY in raw:
        return _checkpoint_meta(raw, path)
    if raw.get("format") != FORMAT or "args" not in raw:
        raise WeightsError("safetensors file without trmd metadata (architecture, args, N)",
                           path=path, hint="use weights written by `trmd train` "
                           "(trmd_cli.models.weights.save_weights)")
    if raw.get("format_version") != FORMAT_VERSION:
        raise WeightsError(f"weights format version {raw.get('format_version')!r} is not "
                           f"supported (this trmd reads version {FORMAT_VERSION})", path=path,
                           hint="upgrade trmd")
    meta: dict[str, Any] = {}
    try:
        for key, value in raw.items():
            if key in _PLAIN:
                meta[key] = value
            elif key in _INTS:
                meta[key] = int(value)
            else:
                meta[key] = json.loads(value)
                if _depth(meta[key]) > MAX_METADATA_DEPTH:
                    raise WeightsError(f"metadata entry {key!r} nests deeper than "
                                       f"{MAX_METADATA_DEPTH} levels", path=path,
                                       hint="the file was edited or written by another tool")
    except (ValueError, RecursionError):
        raise WeightsError(f"metadata entry {key!r} is malformed", path=path,
                           hint="the file is corrupt: copy it again") from None
    if not isinstance(meta["args"], dict):
        raise WeightsError("metadata 'args' is not a JSON object", path=path)
    for key in _INTS:  # repeated for quick checks: they must say what the architecture says
        if key in meta and key in meta["args"] and meta[key] != meta["args"][key]:
            raise WeightsError(f"metadata says {key} = {meta[key]} but the architecture it "
                               f"describes has {key} = {meta['args'][key]!r}", path=path,
                               hint="the metadata and tensors disagree: the file was edited "
                                    "or written by another tool")
    return meta


def _resolve_checkpoint(meta: dict[str, Any], path: Path) -> tuple[dict[str, Any], str]:
    """A checkpoint's full architecture arguments (the variant's, with the recipe's applied)
    and the prefix of the tensors to load: the weight average when the run kept one (what it
    validated and would have shipped), else the model's."""
    import torch
    from safetensors import safe_open

    from . import create_model  # (the package's: the variants register as it loads them)

    args = dict(meta["args"])
    try:
        with torch.device("meta"):
            net = create_model(meta["architecture"], **args)
    except (TypeError, ValueError, RuntimeError, InputError) as e:
        raise WeightsError(f"the checkpoint's recipe does not describe a network this version "
                           f"builds ({e})", path=path, hint="upgrade trmd") from None
    with safe_open(str(path), framework="numpy") as fh:
        prefix = "ema/" if any(k.startswith("ema/") for k in fh.keys()) else "model/"
    meta = {**meta, "args": dict(net.args),
            "checkpoint": {**meta["checkpoint"], "weights": prefix.rstrip("/"),
                           "variant_args": True}}
    return meta, prefix


def load_weights(path: str | Path | None = None, *, device: str = "cpu",
                 expect_n: int | None = None,
                 expect_channels: int | None = None) -> tuple[RENet, dict[str, Any]]:
    """Rebuild the model a weights file describes and load its tensors.

    Args:
        path: a ``.safetensors`` file; None = the shipped default weights.
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"`` or ``"auto"``.
        expect_n, expect_channels: refuse weights trained for another N / channel count.
    Returns:
        (model in eval mode on ``device``, decoded metadata as from :func:`read_metadata`).
    Raises:
        WeightsError: one line saying what is wrong with which file and what to do.

    Example::

        model, meta = load_weights("runs/small/best.safetensors", expect_n=3)
    """
    import torch
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from .registry import canonical_name
    from .renet import RENet

    p = _existing(path)
    meta = read_metadata(p)
    prefix = ""
    if meta.get("checkpoint"):
        meta, prefix = _resolve_checkpoint(meta, p)
    if meta.get("model_class") != "RENet":
        raise WeightsError(f"weights are for model class {meta.get('model_class')!r}, not RENet",
                           path=p, hint=_NO_WEIGHTS_HINT)
    n, channels = meta["args"].get("n"), meta["args"].get("channels")
    if expect_n is not None and n != expect_n:
        raise WeightsError(f"weights are for N = {n}, not N = {expect_n}", path=p,
                           hint=f"pass `n={n}`, or weights trained for N = {expect_n}")
    if expect_channels is not None and channels != expect_channels:
        kinds = {1: "gray", 3: "RGB"}
        raise WeightsError(f"weights are for {channels}-channel ({kinds.get(channels, '?')}) "
                           f"frames, not {expect_channels}-channel", path=p,
                           hint=f"use weights trained on {kinds.get(expect_channels, '?')} frames")
    # The metadata decides the architecture, so a stranger's file decides how much memory it
    # takes: build it on the meta device first (shapes only, nothing allocated) and check it
    # against the tensors the file really holds before building it for real.
    stored_full = {k[len(prefix):]: v for k, v in _stored_shapes(p).items()
                   if k.startswith(prefix)}
    stored = {k: v[0] for k, v in stored_full.items()}
    blocks = meta["args"].get("num_res_blocks")
    if isinstance(blocks, int) and blocks > len(stored):  # each block holds several tensors
        raise WeightsError(f"metadata asks for {blocks} residual blocks but the file holds "
                           f"{len(stored)} tensors", path=p, hint="the metadata and tensors "
                           "disagree: the file was edited or written by another tool")
    try:
        with torch.device("meta"):
            skeleton = RENet(**meta["args"])
    except (TypeError, ValueError, RuntimeError, InputError) as e:
        raise WeightsError(f"metadata args do not describe a RENet this version builds ({e})",
                           path=p, hint="upgrade trmd or retrain") from None
    expected = {name: tuple(t.shape) for name, t in skeleton.state_dict().items()}
    missing = sorted(set(expected) - set(stored))
    extra = sorted(set(stored) - set(expected))
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing (e.g. {', '.join(missing[:3])})")
        if extra:
            parts.append(f"{len(extra)} unexpected (e.g. {', '.join(extra[:3])})")
        raise WeightsError(f"tensors do not match the {meta.get('architecture')} architecture: "
                           + "; ".join(parts), path=p, hint="the metadata and tensors disagree: "
                           "the file was edited or written by another tool")
    kinds = {name: t.is_floating_point() for name, t in skeleton.state_dict().items()}
    for name, shape in stored.items():
        if shape != expected[name]:
            raise WeightsError(f"tensor {name} has shape {shape}, the architecture "
                               f"needs {expected[name]}", path=p,
                               hint="the metadata and tensors disagree")
        dtype = stored_full[name][1].upper()
        if dtype.startswith(("F", "BF")) != kinds[name]:
            need = "floating-point" if kinds[name] else "integer"
            raise WeightsError(f"tensor {name} is stored as {dtype}, the architecture needs "
                               f"{need} values", path=p,
                               hint="the file was edited (a relabelled tensor type) or "
                                    "written by another tool")
    model = RENet(**meta["args"])  # now no larger than the tensors in the file
    arch = meta.get("architecture")
    model.variant = canonical_name(arch) if isinstance(arch, str) else None

    try:
        state = load_file(str(p), device="cpu")
    except (SafetensorError, OSError) as e:
        raise WeightsError(f"cannot read tensors ({str(e).splitlines()[0]})", path=p,
                           hint="the file is truncated or corrupt: copy it again") from None
    if prefix:  # a checkpoint: its model's tensors only, not the optimiser's or the RNG's
        state = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    for name, t in state.items():
        if t.is_floating_point() and not torch.isfinite(t).all():
            raise WeightsError(f"tensor {name} holds NaN or infinite values", path=p,
                               hint="the weights are corrupt or from a diverged training")
    model.load_state_dict(state, strict=True)
    return model.to(resolve_device(device)).eval(), meta
