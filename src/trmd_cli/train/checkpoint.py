"""Resumable checkpoints: one safetensors file, written atomically, no pickle anywhere.

Tensors (model weights in full precision, optimiser moments, RNG state bytes) are safetensors
entries; everything else (step, epoch, sampler position, log history, recipe, optimiser
hyper-parameters, Python/NumPy RNG states, AMP scaler) is one JSON document stored in the
safetensors header metadata under ``"trmd_checkpoint"``. Keeping both in one file makes the
checkpoint atomic as a whole — a run killed while saving leaves the previous checkpoint intact,
never a tensor file from one step beside a sidecar from another — and loading never unpickles.

Entry names: ``model/<state-dict key>``, ``optim/<param index>/<state key>``, ``rng/torch``,
``rng/numpy``, ``rng/cuda/<device>``, and ``ema/<state-dict key>`` when the run averages its
weights (``optim.ema``).
"""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..errors import FormatError
from ..write import write_bytes
from .ema import WeightAverage

if TYPE_CHECKING:
    from ..models.grow import Grown

__all__ = ["save_checkpoint", "load_checkpoint", "read_checkpoint_state", "capture_rng",
           "restore_rng", "CHECKPOINT_FORMAT", "META_KEY"]

CHECKPOINT_FORMAT = 1
META_KEY = "trmd_checkpoint"


def capture_rng() -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Python, NumPy (global) and torch RNG states as (JSON-able dict, tensors)."""
    py = random.getstate()
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    js = {"python": [py[0], list(py[1]), py[2]],
          "numpy": [kind, int(pos), int(has_gauss), float(cached)]}
    tensors = {"rng/torch": torch.get_rng_state(),
               "rng/numpy": torch.from_numpy(np.asarray(keys, np.int64))}
    if torch.cuda.is_available():
        for i, s in enumerate(torch.cuda.get_rng_state_all()):
            tensors[f"rng/cuda/{i}"] = s
    return js, tensors


def restore_rng(js: dict[str, Any], tensors: dict[str, torch.Tensor]) -> None:
    """Inverse of :func:`capture_rng`."""
    version, state, gauss = js["python"]
    random.setstate((version, tuple(state), gauss))
    kind, pos, has_gauss, cached = js["numpy"]
    np.random.set_state((kind, tensors["rng/numpy"].numpy().astype(np.uint32), pos, has_gauss,
                         cached))
    torch.set_rng_state(tensors["rng/torch"])
    if torch.cuda.is_available():
        states = [tensors[k] for k in sorted(tensors) if k.startswith("rng/cuda/")]
        if len(states) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(states)


def _optimizer_split(optimizer: torch.optim.Optimizer
                     ) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    sd = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    plain: dict[str, dict[str, Any]] = {}
    for idx, st in sd["state"].items():
        plain[str(idx)] = {}
        for key, value in st.items():
            if torch.is_tensor(value):
                tensors[f"optim/{idx}/{key}"] = value
            else:
                plain[str(idx)][key] = value
    groups = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()}
              for g in sd["param_groups"]]
    return {"param_groups": groups, "state": plain}, tensors


def _optimizer_join(js: dict[str, Any], tensors: dict[str, torch.Tensor]) -> dict[str, Any]:
    state: dict[int, dict[str, Any]] = {int(i): dict(v) for i, v in js["state"].items()}
    for name, value in tensors.items():
        if name.startswith("optim/"):
            _, idx, key = name.split("/", 2)
            state.setdefault(int(idx), {})[key] = value
    groups = [{k: (tuple(v) if k == "betas" else v) for k, v in g.items()}
              for g in js["param_groups"]]
    return {"state": state, "param_groups": groups}


def save_checkpoint(path: str | Path, *, model: torch.nn.Module,
                    optimizer: torch.optim.Optimizer, state: dict[str, Any],
                    scaler: Any = None, ema: WeightAverage | None = None) -> Path:
    """Write model + optimiser + RNG + ``state`` (JSON-able) to ``path`` atomically.

    ``model`` is the bare module (not a DDP wrapper). Weights are saved in float32 whatever
    the training precision, so resuming is exact. ``ema``: the run's weight average, if any.
    """
    from safetensors.torch import save

    path = Path(path)
    tensors: dict[str, torch.Tensor] = {}
    for key, value in model.state_dict().items():
        tensors[f"model/{key}"] = value
    if ema is not None:
        for key, value in ema.state_dict().items():
            tensors[f"ema/{key}"] = value
        state = {**state, "ema_updates": ema.updates}
    optim_js, optim_t = _optimizer_split(optimizer)
    tensors.update(optim_t)
    rng_js, rng_t = capture_rng()
    tensors.update(rng_t)
    # safetensors refuses views and shared storage: give it plain CPU copies
    tensors = {k: v.detach().to("cpu", copy=True).contiguous() for k, v in tensors.items()}
    doc = {"format": CHECKPOINT_FORMAT, **state, "optimizer": optim_js, "rng": rng_js,
           "scaler": None if scaler is None else scaler.state_dict()}
    meta = {META_KEY: json.dumps(doc, default=_json_default)}
    # bytes, written by trmd's own atomic writer: safetensors' save_file writes a temporary
    # of its own (.tmpXXXXXX) beside the file, which a kill -9 would leave behind
    data = save(tensors, metadata=meta)
    write_bytes(path, data)
    return path


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if torch.is_tensor(o) and o.numel() == 1:
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable in a checkpoint: {type(o)}")


def read_checkpoint_state(path: str | Path) -> dict[str, Any]:
    """The JSON part of a checkpoint (step, recipe, history …) without loading tensors."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise FormatError("no checkpoint to resume from", path=path,
                          hint="start without `resume=True`, or point `run_dir` at the run folder")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except Exception as e:  # noqa: BLE001 - any parse failure means the same to the user
        raise FormatError(f"not a readable checkpoint ({type(e).__name__}: {e})",
                          path=path) from None
    if META_KEY not in meta:
        raise FormatError("safetensors file is not a trmd training checkpoint", path=path,
                          hint="`resume=True` needs a run folder with its checkpoint.safetensors")
    doc = json.loads(meta[META_KEY])
    if doc.get("format") != CHECKPOINT_FORMAT:
        raise FormatError(f"checkpoint format {doc.get('format')} is not supported "
                          f"(this version reads {CHECKPOINT_FORMAT})", path=path)
    return doc


def _model_weights(tensors: dict[str, torch.Tensor], prefix: str = "model/"
                   ) -> dict[str, torch.Tensor]:
    """A state dict from a checkpoint's tensors: the model's (``model/``) or its average's."""
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}


def is_checkpoint(path: str | Path) -> bool:
    """True when ``path`` is a safetensors file written by :func:`save_checkpoint`."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return META_KEY in (f.metadata() or {})
    except Exception:  # noqa: BLE001 - unreadable: not a checkpoint; the weights loader says why
        return False


def load_init_state(model: torch.nn.Module, state: dict[str, torch.Tensor]) -> Grown:
    """Load starting weights into ``model``: exactly, or — a RE-Net — grown from the weights of
    a smaller network of its family (:func:`~trmd_cli.models.grow.load_grown`), computing what
    they computed. Returns what was grown.

    Raises:
        RuntimeError: the weights do not fit (as ``load_state_dict``).
    """
    from ..models.grow import Grown, load_grown
    from ..models.renet import RENet

    if isinstance(model, RENet):
        return load_grown(model, state)
    model.load_state_dict(state, strict=True)
    return Grown()


def load_checkpoint_weights(path: str | Path, model: torch.nn.Module) -> dict[str, Any]:
    """Only the model's weights from a checkpoint (fine-tuning from a run); its JSON state.

    When the run kept a weight average (``optim.ema``) that is what is loaded: it is the
    version the run validated and would have shipped. A network that can grow may come from a
    smaller one's checkpoint (:func:`load_init_state`); what was grown is under ``"grown"`` (a
    :class:`~trmd_cli.models.grow.Grown`) in the returned state.

    Raises:
        FormatError: not a checkpoint, or its weights do not fit ``model``.
    """
    from safetensors import safe_open

    doc = read_checkpoint_state(path)
    with safe_open(str(path), framework="pt", device="cpu") as f:
        keys = list(f.keys())
        prefix = "ema/" if any(k.startswith("ema/") for k in keys) else "model/"
        weights = _model_weights({k: f.get_tensor(k) for k in keys if k.startswith(prefix)},
                                 prefix)
    try:
        doc["grown"] = load_init_state(model, weights)
    except RuntimeError as e:
        model_name = doc.get("recipe", {}).get("model", {}).get("name")
        raise FormatError(f"checkpoint weights do not fit this model "
                          f"({str(e).splitlines()[0]})", path=path,
                          hint=f"the run trained {model_name}: set model.name and model.args "
                          "to match") from None
    return doc


def load_checkpoint(path: str | Path, *, model: torch.nn.Module,
                    optimizer: torch.optim.Optimizer, scaler: Any = None,
                    ema: WeightAverage | None = None,
                    restore_random: bool = True) -> dict[str, Any]:
    """Restore model, optimiser, RNG, scaler and weight average in place; return the JSON state.

    Raises:
        FormatError: not a checkpoint, or its tensors do not fit ``model``.
    """
    from safetensors.torch import load_file

    doc = read_checkpoint_state(path)
    tensors = load_file(str(path), device="cpu")
    weights = _model_weights(tensors)
    try:
        model.load_state_dict(weights, strict=True)
        optimizer.load_state_dict(_optimizer_join(doc["optimizer"], tensors))
        if ema is not None:
            ema.load_state_dict(_model_weights(tensors, "ema/"), int(doc["ema_updates"]))
    except (RuntimeError, ValueError, KeyError) as e:
        raise FormatError(f"checkpoint does not fit this model/optimiser: "
                          f"{str(e).splitlines()[0]}", path=path,
                          hint="resume with the recipe the run was started with") from None
    if scaler is not None and doc.get("scaler"):
        scaler.load_state_dict(doc["scaler"])
    if restore_random:
        restore_rng(doc["rng"], tensors)
    return doc
