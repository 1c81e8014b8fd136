"""Training recipes: a TOML file → a frozen, validated :class:`Recipe`.

A recipe holds everything that decides the trained weights except the data itself: model and
its arguments, crops, batch, schedule, losses, seeds. The default ships in
``trmd_cli/recipes/default.toml``. Layout (every table and key optional; defaults below)::

    name = "default"
    seed = 0

    [model]            # trmd_cli.models.create_model(name, n=…, channels=…, **args)
    name = "trmd_paper"
    n = 3
    channels = 1
    [model.args]       # architecture overrides

    [data]
    crop = 128
    batch_size = 8
    length = 6000      # samples per epoch drawn from image folders (on-the-fly simulation)
    val_data = ""      # held-out set (path relative to the recipe file); "" = split the data
    [data.simulator]   # keyword arguments of SimulatedDataset (motion, noise, thresholds …)

    [optim]
    lr = 2e-4 …

    [train]
    steps = 20000 …

    [loss]             # a weight per registered loss (trmd_cli.train.losses.LOSSES) + options
    residual = 1.0
    middle = 1.0
    penalty = "mse"

A ``[loss]`` table that names any weight replaces the default weights as a whole (so a recipe
with ``event_consistency = 1.0`` alone trains without ground truth).

Errors name the file, the key (``optim.lr``), what was expected and, for unknown keys, the
closest known key.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from ..errors import InputError

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - 3.10
    import tomli as tomllib  # type: ignore[no-redef]

__all__ = [
    "Recipe", "ModelSpec", "DataSpec", "OptimSpec", "TrainSpec", "LossSpec",
    "load_recipe", "default_recipe_path", "recipe_from_dict", "apply_overrides",
    "recipe_diff", "RESUME_SAFE_KEYS", "RESUME_LENGTH_KEYS",
]


@dataclass(frozen=True)
class ModelSpec:
    """Which network: ``create_model(name, n=n, channels=channels, **args)``."""

    name: str = "trmd_paper"
    n: int = 3  # 2N+1 latent frames per exposure
    channels: int = 1  # 1 = gray, 3 = RGB
    args: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DataSpec:
    """Samples: crop size, batching, validation split, simulator settings."""

    crop: int = 128  # square training crop, pixels
    batch_size: int = 8  # per process
    num_workers: int = 0  # DataLoader workers per process
    length: int = 6000  # samples per epoch from image folders (simulated on the fly)
    val_data: str = ""  # held-out set; "" = hold out val_fraction of the training data
    val_fraction: float = 0.05
    val_samples: int = 64  # at most this many validation samples
    val_crop: int = 0  # centre crop of validation samples, 0 = whole frames
    simulator: dict[str, Any] = field(default_factory=dict)  # SimulatedDataset keywords
    augment: bool = True  # flips, transpose, time reversal of pre-generated training samples
    # networks that take the threshold c (prior "edi_c") get the sample's true c times
    # exp(N(0, σ)) in training, like the estimate they get in use; validation gets the true c
    contrast_jitter: float = 0.15


@dataclass(frozen=True)
class OptimSpec:
    """Optimiser and learning-rate schedule (linear warm-up, then cosine to ``min_lr``)."""

    name: str = "adamw"  # adam | adamw
    lr: float = 2e-4
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 0.0
    grad_clip: float = 1.0  # max global gradient norm; 0 = off
    schedule: str = "cosine"  # cosine | constant
    warmup_steps: int = 200
    min_lr: float = 1e-6
    # exponential moving average of the weights, per step (0 = off); validation, best and
    # final weights then use the average. 0.999 averages over about the last 1,000 steps.
    ema: float = 0.0


@dataclass(frozen=True)
class TrainSpec:
    """How long, how often to validate / log / checkpoint, and compute settings."""

    steps: int = 20000  # optimiser steps in total (all processes step together)
    epochs: int = 0  # > 0: steps = epochs × batches per epoch (overrides steps)
    time_budget_minutes: float = 0.0  # stop cleanly (validate, save) before this; 0 = none
    # mixed precision where the hardware computes it natively: float16 on CUDA, bfloat16 on
    # CPUs with AMX / AVX512-BF16 (about 2× faster there); float32 elsewhere or when false
    amp: bool = True
    val_every: int = 500  # steps
    log_every: int = 20  # steps between rows of log.csv
    checkpoint_every: int = 500  # steps
    checkpoint_minutes: float = 10.0  # also checkpoint after this much wall time; 0 = off
    threads: int = 0  # torch CPU threads per process; 0 = cores / processes
    channels_last: bool = False


@dataclass(frozen=True)
class LossSpec:
    """Weighted sum of registered losses, and the options they read."""

    weights: dict[str, float] = field(
        default_factory=lambda: {"residual": 1.0, "middle": 1.0})
    penalty: str = "mse"  # mse | l1 | charbonnier
    charbonnier_eps: float = 1e-3
    contrast: float = 0.2  # event contrast threshold when the batch carries none
    log_eps: float = 1e-3  # log(I + eps) in event_consistency


@dataclass(frozen=True)
class Recipe:
    """A complete, validated training recipe. Build with :func:`load_recipe`."""

    name: str = "default"
    seed: int = 0
    description: str = ""
    model: ModelSpec = field(default_factory=ModelSpec)
    data: DataSpec = field(default_factory=DataSpec)
    optim: OptimSpec = field(default_factory=OptimSpec)
    train: TrainSpec = field(default_factory=TrainSpec)
    loss: LossSpec = field(default_factory=LossSpec)
    #: folder that relative paths in the recipe (``data.val_data``) refer to
    base_dir: str = ""

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict in the TOML layout (JSON-able); ``base_dir`` left out."""
        out: dict[str, Any] = {"name": self.name, "seed": self.seed,
                               "description": self.description}
        for sec in _SECTIONS:
            d = {f.name: _plain(getattr(getattr(self, sec), f.name))
                 for f in dataclasses.fields(_SECTIONS[sec])}
            if sec == "loss":
                d.update(d.pop("weights"))
            out[sec] = d
        return out

    def resolve_path(self, text: str) -> Path:
        """A path from the recipe, relative to the recipe file's folder."""
        p = Path(text).expanduser()
        return p if p.is_absolute() or not self.base_dir else Path(self.base_dir) / p

    def with_(self, **sections: Any) -> Recipe:
        """Copy with whole sections or top-level fields replaced (no validation)."""
        return dataclasses.replace(self, **sections)


_SECTIONS: dict[str, type] = {"model": ModelSpec, "data": DataSpec, "optim": OptimSpec,
                              "train": TrainSpec, "loss": LossSpec}
_TOP = {"name": str, "seed": int, "description": str}

#: keys that may differ between a checkpoint's recipe and the one given to ``--resume``: they
#: change speed or bookkeeping, never the numbers
RESUME_SAFE_KEYS = frozenset({
    "description", "data.num_workers", "train.time_budget_minutes", "train.log_every",
    "train.checkpoint_every", "train.checkpoint_minutes", "train.threads", "train.val_every",
})
#: keys that may change on ``--resume`` to lengthen or shorten a run (the schedule changes)
RESUME_LENGTH_KEYS = frozenset({"train.steps", "train.epochs"})


def default_recipe_path() -> Path:
    """The recipe shipped inside the package."""
    return Path(str(resources.files("trmd_cli") / "recipes" / "default.toml"))


def load_recipe(path: str | Path | None = None, overrides: list[str] | None = None) -> Recipe:
    """Read and validate a recipe TOML (the shipped default when ``path`` is None).

    Args:
        overrides: ``"section.key=value"`` strings applied after reading; the value is parsed
            as a TOML value (``optim.lr=1e-3``, ``model.name="test_trmd"``; bare words are
            taken as strings).
    Raises:
        InputError: missing file, TOML syntax error, unknown key, wrong type or value.
    """
    path = default_recipe_path() if path is None else Path(path)
    if not path.is_file():
        raise InputError("recipe not found", path=path,
                         hint="give a TOML file, or omit `recipe` for the default")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"not valid TOML: {e}", path=path,
                         hint="fix the line named, or start from `trmd_cli/recipes/default.toml`"
                         ) from None
    except UnicodeDecodeError:
        raise InputError("not a text file", path=path, hint="a recipe is a TOML file") from None
    recipe = recipe_from_dict(data, source=path, base_dir=path.parent)
    if not overrides:
        return recipe
    # the file was checked alone: what fails now is the overrides' to answer for (merged into
    # the file's own tables, whose rules — a [loss] table that names weights replaces the
    # default's — see them as written there)
    return _overridden(_merge_overrides(data, overrides, None), overrides, path.parent)


def recipe_from_dict(data: dict[str, Any], *, source: str | Path | None = None,
                     base_dir: str | Path | None = None) -> Recipe:
    """Validate a nested dict (TOML layout) into a :class:`Recipe`."""
    src = None if source is None else str(source)
    if not isinstance(data, dict):
        raise InputError("a recipe must be a table of keys", path=src)
    known = set(_TOP) | set(_SECTIONS)
    top: dict[str, Any] = {}
    sections: dict[str, Any] = {}
    for key, value in data.items():
        if key not in known:
            raise _unknown(key, known, src)
        if key in _TOP:
            top[key] = _convert(value, _TOP[key], key, src)
        else:
            if not isinstance(value, dict):
                raise InputError(f"'{key}' must be a table ([{key}])", path=src)
            sections[key] = _section(key, value, src)
    recipe = Recipe(**top, **sections, base_dir="" if base_dir is None else str(base_dir))
    _validate(recipe, src)
    return recipe


def apply_overrides(recipe: Recipe, overrides: list[str]) -> Recipe:
    """Recipe with ``"section.key=value"`` overrides applied, validated again (an error names
    the overrides, not the recipe's file)."""
    return _overridden(_merge_overrides(recipe.to_dict(), overrides, None), overrides,
                       recipe.base_dir or None)


def _overridden(data: dict[str, Any], overrides: list[str], base_dir) -> Recipe:
    """``data`` with ``overrides`` merged in, validated; an error names the overrides."""
    try:
        return recipe_from_dict(data, base_dir=base_dir)
    except InputError as e:
        raise InputError(f"{e.detail} (after the overrides {' '.join(overrides)})",
                         hint=e.hint) from None


def recipe_diff(a: Recipe, b: Recipe) -> list[str]:
    """Dotted keys whose values differ between two recipes."""
    fa, fb = _flatten(a.to_dict()), _flatten(b.to_dict())
    return sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k))


# --------------------------------------------------------------------------------------------


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict) and k not in ("args", "simulator"):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return list(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _merge_overrides(data: dict[str, Any], overrides: list[str], src) -> dict[str, Any]:
    import copy

    data = copy.deepcopy(data)
    for item in overrides:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise InputError(f"override {item!r} is not KEY=VALUE",
                             hint='write it like optim.lr=1e-3 or model.name="test_trmd"')
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()  # a bare word: take it as a string
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise InputError(f"override {item!r}: '{part}' is not a table", path=src)
        node[parts[-1]] = value
    return data


def _unknown(key: str, known, src) -> InputError:
    close = difflib.get_close_matches(key.split(".")[-1], [k.split(".")[-1] for k in known], 1)
    hint = f"did you mean '{close[0]}'?" if close else f"known keys: {', '.join(sorted(known))}"
    return InputError(f"unknown recipe key '{key}'", path=src, hint=hint)


def _section(name: str, table: dict[str, Any], src) -> Any:
    cls = _SECTIONS[name]
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    if name == "loss":
        from .losses import LOSSES  # the registry decides which weights exist

        weights: dict[str, float] = {}
        for key, value in table.items():
            if key in fields and key != "weights":
                kwargs[key] = _convert(value, hints[key], f"loss.{key}", src)
            elif key in LOSSES:
                weights[key] = _convert(value, float, f"loss.{key}", src)
            else:
                raise _unknown(f"loss.{key}", {f"loss.{k}" for k in (fields | set(LOSSES))
                                               if k != "weights"}, src)
        if weights:
            kwargs["weights"] = weights
        return cls(**kwargs)
    for key, value in table.items():
        if key not in fields:
            raise _unknown(f"{name}.{key}", {f"{name}.{f}" for f in fields}, src)
        kwargs[key] = _convert(value, hints[key], f"{name}.{key}", src)
    return cls(**kwargs)


def _type_name(tp: Any) -> str:
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}.get(
        tp, "a table" if typing.get_origin(tp) is dict else str(tp))


def _convert(value: Any, tp: Any, key: str, src) -> Any:
    origin = typing.get_origin(tp)
    bad = InputError(f"{key} = {value!r}: expected {_type_name(tp)}", path=src)
    if tp is bool:
        if not isinstance(value, bool):
            raise bad
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        if not math.isfinite(value):
            raise InputError(f"{key} = {value!r}: must be finite", path=src)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise bad
        return value
    if origin is dict:
        if not isinstance(value, dict):
            raise bad
        return dict(value)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise InputError(f"{key} = {value!r}: expected a list of {len(args)} numbers",
                             path=src)
        return tuple(_convert(v, a, key, src) for v, a in zip(value, args, strict=True))
    raise TypeError(f"no converter for {tp}")  # a programming error, not user input


def _validate(r: Recipe, src) -> None:
    def need(ok: bool, key: str, what: str, hint: str | None = None) -> None:
        if not ok:
            value = _flatten(r.to_dict()).get(key)
            raise InputError(f"{key} = {value!r}: {what}", path=src, hint=hint)

    m, d, o, t, lo = r.model, r.data, r.optim, r.train, r.loss
    need(r.seed >= 0, "seed", "must be ≥ 0")
    need(bool(r.name) and "/" not in r.name and r.name not in (".", ".."), "name",
         "must be a plain non-empty name (it names the run folder)")
    need(bool(m.name), "model.name", "must name a registered model",
         hint="e.g. trmd_paper, trmd_small, test_trmd")
    need(1 <= m.n <= 16, "model.n", "must be in 1..16")
    need(m.channels in (1, 3), "model.channels", "must be 1 (gray) or 3 (RGB)")
    need(d.crop >= 8, "data.crop", "must be ≥ 8 pixels")
    need(d.batch_size >= 1, "data.batch_size", "must be ≥ 1")
    need(d.num_workers >= 0, "data.num_workers", "must be ≥ 0")
    need(d.length >= 1, "data.length", "must be ≥ 1")
    need(0.0 <= d.val_fraction < 1.0, "data.val_fraction", "must be in [0, 1)")
    need(d.val_samples >= 0, "data.val_samples", "must be ≥ 0")
    need(d.val_crop >= 0, "data.val_crop", "must be ≥ 0 (0 = whole frames)")
    need(o.name in ("adam", "adamw"), "optim.name", "must be adam or adamw")
    need(o.lr > 0, "optim.lr", "must be > 0")
    need(all(0.0 <= b < 1.0 for b in o.betas), "optim.betas", "must be two numbers in [0, 1)")
    need(o.weight_decay >= 0, "optim.weight_decay", "must be ≥ 0")
    need(o.grad_clip >= 0, "optim.grad_clip", "must be ≥ 0 (0 = off)")
    need(o.schedule in ("cosine", "constant"), "optim.schedule", "must be cosine or constant")
    need(o.warmup_steps >= 0, "optim.warmup_steps", "must be ≥ 0")
    need(0 <= o.min_lr <= o.lr, "optim.min_lr", "must be in [0, optim.lr]")
    need(d.contrast_jitter >= 0, "data.contrast_jitter", "must be ≥ 0 (0 = the true c)")
    need(0 <= o.ema < 1, "optim.ema", "must be in [0, 1) (0 = off)", "0.999 is typical")
    need(t.steps >= 1 or t.epochs >= 1, "train.steps", "must be ≥ 1 (or set train.epochs)")
    need(t.epochs >= 0, "train.epochs", "must be ≥ 0")
    need(t.time_budget_minutes >= 0, "train.time_budget_minutes", "must be ≥ 0 (0 = none)")
    for key in ("val_every", "log_every", "checkpoint_every"):
        need(getattr(t, key) >= 1, f"train.{key}", "must be ≥ 1 step")
    need(t.checkpoint_minutes >= 0, "train.checkpoint_minutes", "must be ≥ 0 (0 = off)")
    need(t.threads >= 0, "train.threads", "must be ≥ 0 (0 = automatic)")
    need(lo.penalty in ("mse", "l1", "charbonnier"), "loss.penalty",
         "must be mse, l1 or charbonnier")
    need(lo.charbonnier_eps > 0, "loss.charbonnier_eps", "must be > 0")
    need(lo.contrast > 0, "loss.contrast", "must be > 0")
    need(lo.log_eps > 0, "loss.log_eps", "must be > 0")
    for name, w in lo.weights.items():
        need(w >= 0, f"loss.{name}", "a loss weight must be ≥ 0")
    if not any(w > 0 for w in lo.weights.values()):
        raise InputError("no loss has a positive weight", path=src,
                         hint="set e.g. [loss] residual = 1.0, middle = 1.0")
