"""Training data: ``data`` paths → datasets, the held-out split, and a resumable sampler.

Every dataset yields dicts of float32 tensors::

    blurry   (C, H, W)          the blurry frame, [0, 1]
    voxels   (2N, H, W)         SCER voxels of its exposure
    sharp    (2N+1, C, H, W)    ground-truth latent frames (absent for unlabelled data)
    contrast ()                 true mean contrast threshold, NaN when unknown

What each ``data`` path becomes:

- an image file, or a folder of images (searched recursively) → ``SimulatedDataset`` (sharp
  sequences, events and blur simulated on the fly);
- an ``.h5`` in the trmd layout (root attribute ``format="trmd"``, written by
  ``trmd simulate``) → ``H5SampleDataset``;
- an ``.h5`` in the layout of the TRMD paper's GOPRO release (``blur_images``,
  ``sharp_images``, ``voxel``) → :class:`GoproH5Dataset` (best effort);
- a folder holding ``.h5`` files → each of them, as above.

Randomness (crops, sample order) is a pure function of (seed, epoch, index), so a run resumed
from a checkpoint sees exactly the batches an uninterrupted run would have seen.
"""

from __future__ import annotations

import hashlib
import inspect
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset, Sampler, Subset

from ..errors import FormatError, InputError
from ..read.frames import IMAGE_EXTENSIONS

__all__ = [
    "GoproH5Dataset", "CropDataset", "EpochSampler", "DataPlan", "build_data",
    "detect_kind", "gather", "set_epoch", "peek_item", "GOPRO_LUMA",
]

H5_EXTENSIONS = (".h5", ".hdf5")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm")
#: skimage.color.rgb2gray (Rec. 709) — what the paper's GOPRO loader used for gray training
GOPRO_LUMA = (0.2125, 0.7154, 0.0721)


# --------------------------------------------------------------------------------------------
# Which reader for which path


def detect_kind(path: Path) -> str:
    """``"images"``, ``"trmd_h5"`` or ``"gopro_h5"`` for one file; FormatError otherwise."""
    suffix = path.suffix.lower()
    if suffix in IMAGE_EXTENSIONS:
        return "images"
    if suffix in VIDEO_EXTENSIONS:
        raise InputError("video files are not read directly for training", path=path,
                         hint="extract its frames into a folder (ffmpeg -i VIDEO dir/%05d.png) "
                         "and pass the folder")
    if suffix not in H5_EXTENSIONS:
        raise InputError("not training data (expected images, a folder, or .h5)", path=path,
                         hint="pass an image folder or an HDF5 set from `trmd simulate`")
    import h5py

    from ..read.hdf5_strings import read_attr

    try:
        with h5py.File(path, "r") as f:
            if read_attr(f, "format") == "trmd":
                if "frames" not in f or "blurry" not in f["frames"]:
                    raise FormatError("trmd HDF5 without frames/blurry: events only, no samples",
                                      path=path, hint="write a training set with `trmd simulate`")
                return "trmd_h5"
            if {"blur_images", "sharp_images", "voxel"} <= set(f.keys()):
                return "gopro_h5"
            keys = ", ".join(sorted(f.keys())[:8])
    except OSError as e:
        raise FormatError(f"not a readable HDF5 file ({e})", path=path) from None
    raise FormatError(f"HDF5 layout not recognised (keys: {keys})", path=path,
                      hint="expected a `trmd simulate` set (format=\"trmd\") or the GOPRO layout "
                      "blur_images / sharp_images / voxel")


def gather(paths: Sequence[str | Path]) -> list[tuple[str, list[Path]]]:
    """Group ``data`` paths by reader: ``[("images", [img, …]), ("trmd_h5", [file]), …]``.

    Images from all paths form one group; each HDF5 file is its own group.
    """
    if not paths:
        raise InputError("no training data given", hint="pass `data` (image folders or .h5 sets)")
    images: list[Path] = []
    groups: list[tuple[str, list[Path]]] = []
    for raw in paths:
        path = Path(raw).expanduser()
        if not path.exists():
            raise InputError("training data not found", path=path, hint="check the `data` path")
        if path.is_dir():
            h5s = sorted(p for p in path.rglob("*") if p.suffix.lower() in H5_EXTENSIONS
                         and p.is_file())
            imgs = sorted(p for p in path.rglob("*") if p.suffix.lower() in IMAGE_EXTENSIONS
                          and p.is_file() and not p.name.startswith("."))
            if not h5s and not imgs:
                raise InputError("folder holds no images and no .h5 files", path=path,
                                 hint="pass a folder of images or of HDF5 training sets")
            groups += [(detect_kind(p), [p]) for p in h5s]
            images += imgs
        else:
            kind = detect_kind(path)
            if kind == "images":
                images.append(path)
            else:
                groups.append((kind, [path]))
    if images:
        groups.insert(0, ("images", sorted(dict.fromkeys(images))))
    return groups


# --------------------------------------------------------------------------------------------
# The paper's GOPRO release


def _rng(*key: int) -> np.random.Generator:
    return np.random.default_rng([int(k) for k in key])


class GoproH5Dataset(Dataset):
    """Reader of the TRMD paper's GOPRO h5 files (best effort: written from its loader).

    Layout: ``blur_images`` uint8 (K, H, W, 3), ``sharp_images`` uint8 (K, 2N+1, H, W, 3),
    ``voxel`` (K, 2N, H, W) SCER voxels in the order used here (k = 0..N−1, N+1..2N). Gray
    training converts RGB with the Rec. 709 weights the paper's loader used.

    Args:
        path: the h5 file.
        n: expected N (the file must hold 2N+1 sharp frames).
        channels: 1 (gray) or 3 (RGB).
        crop: square crop side in pixels; 0 = whole frames.
        random_crop: crop position random per (seed, epoch, index), else centred.
        seed: base seed of the crop positions.
        levels: give every sample ``levels`` too (for networks with ``timing``): the file
            has no raw events, so they are the voxels themselves.
    """

    def __init__(self, path: str | Path, *, n: int = 3, channels: int = 1, crop: int = 0,
                 random_crop: bool = True, seed: int = 0, levels: bool = False) -> None:
        import h5py

        self.path = Path(path)
        self.n, self.channels, self.crop = n, channels, crop
        self.random_crop, self.seed, self.epoch = random_crop, seed, 0
        self.levels = levels
        with h5py.File(self.path, "r") as f:
            blur, sharp, vox = f["blur_images"], f["sharp_images"], f["voxel"]
            k, h, w = blur.shape[0], blur.shape[1], blur.shape[2]
            if blur.ndim != 4 or blur.shape[3] != 3:
                raise FormatError(f"blur_images has shape {blur.shape}, expected (K, H, W, 3)",
                                  path=path)
            if sharp.shape != (k, 2 * n + 1, h, w, 3):
                raise FormatError(f"sharp_images has shape {sharp.shape}, expected "
                                  f"{(k, 2 * n + 1, h, w, 3)} for N={n}", path=path,
                                  hint="set model.n to match the file (N=3 for the release)")
            if vox.shape != (k, 2 * n, h, w):
                raise FormatError(f"voxel has shape {vox.shape}, expected {(k, 2 * n, h, w)}",
                                  path=path)
        if crop and (crop > h or crop > w):
            raise InputError(f"crop {crop} is larger than the frames ({w}x{h})", path=path,
                             hint="lower data.crop")
        self.length, self.height, self.width = k, h, w
        self._file = None
        self._pid = -1

    def __len__(self) -> int:
        return self.length

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __getstate__(self) -> dict:
        # h5py handles cannot cross process boundaries: each worker opens its own
        return {**self.__dict__, "_file": None, "_pid": -1}

    def _window(self, index: int) -> tuple[slice, slice]:
        if not self.crop:
            return slice(None), slice(None)
        c = self.crop
        if self.random_crop:
            g = _rng(self.seed, self.epoch, index)
            y, x = int(g.integers(0, self.height - c + 1)), int(g.integers(0, self.width - c + 1))
        else:
            y, x = (self.height - c) // 2, (self.width - c) // 2
        return slice(y, y + c), slice(x, x + c)

    def _color(self, rgb: np.ndarray) -> np.ndarray:
        """(..., H, W, 3) uint8 → (..., C, H, W) float32 [0, 1]."""
        x = rgb.astype(np.float32) / 255.0
        if self.channels == 1:
            x = (x @ np.asarray(GOPRO_LUMA, np.float32))[..., None]
        return np.ascontiguousarray(np.moveaxis(x, -1, -3))

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        import h5py

        if not 0 <= index < self.length:
            raise IndexError(index)
        # one handle per process: DataLoader workers are forked with the parent's handle
        if self._file is None or self._pid != os.getpid():
            self._file = h5py.File(self.path, "r")
            self._pid = os.getpid()
        f = self._file
        ys, xs = self._window(index)
        blur = f["blur_images"][index, ys, xs]
        sharp = f["sharp_images"][index, :, ys, xs]
        vox = torch.from_numpy(np.ascontiguousarray(f["voxel"][index, :, ys, xs], np.float32))
        item = {"blurry": torch.from_numpy(self._color(blur)), "voxels": vox,
                "sharp": torch.from_numpy(self._color(sharp)),
                "contrast": torch.tensor(float("nan"))}
        if self.levels:
            item["levels"] = vox.clone()
        return item


# --------------------------------------------------------------------------------------------
# Wrappers


class CropDataset(Dataset):
    """Crop every sample of ``base`` to ``crop``×``crop`` (random per seed/epoch/index or centred)
    and give it a ``contrast`` entry (NaN if missing). Samples already that small pass as is."""

    def __init__(self, base: Dataset, crop: int, *, random_crop: bool, seed: int,
                 augment: bool = False) -> None:
        self.base, self.crop, self.random_crop, self.seed, self.epoch = (
            base, crop, random_crop, seed, 0)
        self.augment = augment

    def __len__(self) -> int:
        return len(self.base)  # type: ignore[arg-type]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        set_epoch(self.base, epoch)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = dict(self.base[index])
        h, w = item["blurry"].shape[-2:]
        c = self.crop
        if c and (h < c or w < c):
            # (whole frames of another size would batch badly, or train on what the recipe
            # does not say)
            raise InputError(f"sample {index} is {w}x{h}, smaller than the crop {c}",
                             hint="lower data.crop")
        if c and (h > c or w > c):
            if self.random_crop:
                g = _rng(self.seed, self.epoch, index)
                y, x = int(g.integers(0, h - c + 1)), int(g.integers(0, w - c + 1))
            else:
                y, x = (h - c) // 2, (w - c) // 2
            for key in ("blurry", "voxels", "levels", "sharp"):
                if key in item:
                    item[key] = item[key][..., y:y + c, x:x + c].contiguous()
        if self.augment:
            item = augment_item(item, _rng(self.seed + 1, self.epoch, index))
        if "contrast" not in item:
            item["contrast"] = torch.tensor(float("nan"))
        else:
            item["contrast"] = torch.as_tensor(item["contrast"], dtype=torch.float32).reshape(())
        return item


def augment_item(item: dict[str, torch.Tensor], g: np.random.Generator) -> dict[str, torch.Tensor]:
    """Random flips, transpose (square crops) and time reversal of one sample.

    All keep the physics exact. Reversing time maps latent frame k to 2N−k and flips every
    event's polarity; with SCER's sign convention that is exactly V'(k) = V(2N−k), i.e. the
    voxel channels reversed (no negation) — so pre-generated sets count 16× over. Samples with
    timing levels (``levels``, :func:`~trmd_cli.voxel.scer_levels`) are flipped and transposed
    but never reversed: the levels follow the sensor, which is not symmetric in time.
    """
    item = dict(item)
    keys = [k for k in ("blurry", "voxels", "levels", "sharp") if k in item]
    hflip, vflip, transpose, reverse = (bool(b) for b in g.integers(0, 2, 4))
    # the timing levels of a reversed stream are not the reversed levels (voxel.scer_levels)
    reverse = reverse and "levels" not in item
    h, w = item["blurry"].shape[-2:]
    for k in keys:
        t = item[k]
        if hflip:
            t = t.flip(-1)
        if vflip:
            t = t.flip(-2)
        if transpose and h == w:
            t = t.transpose(-1, -2)
        if reverse and k in ("voxels", "levels", "sharp"):
            t = t.flip(0)
        item[k] = t.contiguous()
    return item


def set_epoch(dataset: Any, epoch: int) -> None:
    """Tell a dataset (and any it wraps) which epoch it serves, where it listens."""
    if hasattr(dataset, "set_epoch"):
        dataset.set_epoch(epoch)
    elif isinstance(dataset, ConcatDataset):
        for d in dataset.datasets:
            set_epoch(d, epoch)
    elif isinstance(dataset, Subset):
        set_epoch(dataset.dataset, epoch)


def peek_item(dataset: Dataset) -> dict[str, torch.Tensor]:
    return dataset[0]


# --------------------------------------------------------------------------------------------
# Sampler


class EpochSampler(Sampler[int]):
    """Shuffled indices for one process, reproducible and resumable mid-epoch.

    The order of epoch e is a permutation drawn from (seed, e); with ``world`` processes the
    permutation is truncated to a multiple of ``world`` and process ``rank`` takes every
    ``world``-th entry (so processes never share a sample within an epoch). ``skip`` drops the
    first entries of this process's share — where a resumed run picks up.
    """

    def __init__(self, length: int, *, seed: int, rank: int = 0, world: int = 1,
                 shuffle: bool = True) -> None:
        if length < world:
            raise InputError(f"{length} sample(s) cannot be shared by {world} processes")
        self.length, self.seed, self.rank, self.world, self.shuffle = (
            length, seed, rank, world, shuffle)
        self.epoch, self.skip = 0, 0

    def set_position(self, epoch: int, skip: int = 0) -> None:
        self.epoch, self.skip = int(epoch), int(skip)

    def indices(self) -> np.ndarray:
        order = (_rng(self.seed, self.epoch).permutation(self.length) if self.shuffle
                 else np.arange(self.length))
        order = order[: self.length // self.world * self.world]
        return order[self.rank :: self.world][self.skip :]

    def __iter__(self) -> Iterator[int]:
        return iter(self.indices().tolist())

    def __len__(self) -> int:
        return max(self.length // self.world - self.skip, 0)


# --------------------------------------------------------------------------------------------
# Building the training and validation sets


@dataclass
class DataPlan:
    """Datasets for one run, and notes worth telling the user.

    ``val_source`` says where the validation set comes from, for people (a path on this
    machine); ``val_record`` is what metadata keeps of it (:func:`data_record` for a file or
    folder given as ``data.val_data``, else ``val_source``).
    """

    train: Dataset
    val: Dataset | None
    sources: list[str]
    val_source: str
    notes: list[str] = field(default_factory=list)
    val_record: str | dict[str, Any] = "none"


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, 64 hex digits."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def data_record(path: Path, files: Sequence[Path]) -> dict[str, Any]:
    """A data set as metadata records it: by name and content, not by its path on this machine.

    A file: ``{"file": name, "sha256": <64 hex>}``. A folder: ``{"folder": name, "files": k,
    "sha256": <64 hex>}``, the digest of the lines ``<path relative to the folder>\t<sha256>``
    of the ``files`` read from it, sorted.
    """
    if path.is_file():
        return {"file": path.name, "sha256": file_sha256(path)}
    lines = sorted(f"{f.relative_to(path).as_posix()}\t{file_sha256(f)}\n" for f in files)
    digest = hashlib.sha256("".join(lines).encode()).hexdigest()
    return {"folder": path.name, "files": len(lines), "sha256": digest}


def wants_levels(recipe) -> bool:
    """Whether the recipe's network takes sub-bin timing (``timing``): its samples then carry
    ``levels`` (:func:`~trmd_cli.voxel.scer_levels`)."""
    from ..models.renet import variant_args

    m = recipe.model
    try:
        base = variant_args(m.name)  # an old name reads through the aliases
    except KeyError:  # not a registered RE-Net variant: only its own args can ask for timing
        base = {}
    return bool(m.args.get("timing", base.get("timing", False)))


def _simulated(images: list[Path], recipe, *, length: int, seed: int, crop: int,
               train: bool) -> Dataset:
    from ..simulate.dataset import SimulatedDataset

    kwargs: dict[str, Any] = {"n": recipe.model.n, "crop": crop, "length": length, "seed": seed,
                              **recipe.data.simulator}
    params = inspect.signature(SimulatedDataset).parameters
    takes_any = any(p.kind is p.VAR_KEYWORD for p in params.values())
    for key, value in (("channels", recipe.model.channels), ("train", train)):
        if key in params or takes_any:
            kwargs.setdefault(key, value)
    unknown = [k for k in recipe.data.simulator if k not in params and not takes_any]
    if unknown:
        takes = ", ".join(p for p in params if p != "images")
        raise InputError(f"data.simulator has unknown key(s) {', '.join(unknown)}",
                         hint=f"SimulatedDataset takes: {takes}")
    if wants_levels(recipe):
        kwargs["levels"] = True
    try:
        return SimulatedDataset(images, **kwargs)
    except TypeError as e:
        raise InputError(f"data.simulator: {e}") from None


def _h5(kind: str, path: Path, recipe, *, crop: int, train: bool, seed: int) -> Dataset:
    if kind == "gopro_h5":
        return GoproH5Dataset(path, n=recipe.model.n, channels=recipe.model.channels,
                              crop=crop, random_crop=train, seed=seed,
                              levels=wants_levels(recipe))
    from ..simulate.dataset import H5SampleDataset

    return CropDataset(H5SampleDataset(path, n=recipe.model.n, levels=wants_levels(recipe)),
                       crop, random_crop=train,
                       seed=seed, augment=train and recipe.data.augment)


def _check_item(ds: Dataset, source: str, recipe, supervised: bool) -> None:
    """Shapes of the first sample against the recipe's N and channels."""
    if len(ds) == 0:  # type: ignore[arg-type]
        raise InputError("the data set is empty", path=source)
    item = peek_item(ds)
    n, c = recipe.model.n, recipe.model.channels
    blur, vox = item["blurry"], item["voxels"]
    if blur.ndim != 3 or blur.shape[0] != c:
        raise InputError(f"samples have blurry {tuple(blur.shape)} but the recipe wants "
                         f"{c} channel(s)", path=source, hint="set model.channels to match")
    if vox.shape[0] != 2 * n:
        raise InputError(f"samples have {vox.shape[0]} voxel channels, the recipe's N={n} needs "
                         f"{2 * n}", path=source, hint="set model.n to match the data")
    sharp = item.get("sharp")
    if sharp is not None and tuple(sharp.shape[:2]) != (2 * n + 1, c):
        raise InputError(f"samples have sharp {tuple(sharp.shape)}, expected "
                         f"({2 * n + 1}, {c}, H, W)", path=source)
    if supervised and sharp is None:
        raise InputError("this data has no ground-truth sharp frames but the recipe's losses "
                         "need them", path=source,
                         hint="use only blur_consistency / event_consistency in [loss]")


def _split_images(images: list[Path], fraction: float) -> tuple[list[Path], list[Path]]:
    """Every k-th image (sorted order) held out; at least one kept for training."""
    if fraction <= 0 or len(images) < 2:
        return images, []
    k = max(2, round(1 / fraction))
    val = images[k // 2 :: k] or images[-1:]
    train = [p for p in images if p not in set(val)]
    return train, val


def _evenly(ds: Dataset, limit: int) -> Dataset:
    size = len(ds)  # type: ignore[arg-type]
    if limit <= 0 or size <= limit:
        return ds
    return Subset(ds, np.linspace(0, size - 1, limit).round().astype(int).tolist())


def build_data(paths: Sequence[str | Path], recipe, *, supervised: bool = True) -> DataPlan:
    """Training and validation sets for ``paths`` under ``recipe``.

    Validation: ``recipe.data.val_data`` when set; otherwise ``data.val_fraction`` of the
    training data held out (every k-th image of the folders, the last samples of each HDF5
    set). At most ``data.val_samples`` samples, centre-cropped to ``data.val_crop`` (0 = whole).

    Raises:
        InputError / FormatError: missing or unreadable paths, shapes that do not fit the recipe.
    """
    d, seed = recipe.data, recipe.seed
    groups = gather(paths)
    train_parts: list[Dataset] = []
    val_parts: list[Dataset] = []
    sources: list[str] = []
    notes: list[str] = []
    hold_out = not d.val_data and d.val_fraction > 0
    for kind, files in groups:
        if kind == "images":
            train_imgs, val_imgs = _split_images(files, d.val_fraction if hold_out else 0.0)
            ds = _simulated(train_imgs, recipe, length=d.length, seed=seed, crop=d.crop,
                            train=True)
            sources.append(f"{len(train_imgs)} image(s), simulated on the fly")
            if val_imgs:
                val_parts.append(_simulated(
                    val_imgs, recipe, length=max(d.val_samples, 1), seed=seed + 7919,
                    crop=d.val_crop or d.crop, train=False))
            elif hold_out:
                notes.append("only one image: no validation images held out")
            train_parts.append(ds)
            _check_item(ds, str(files[0].parent), recipe, supervised)
            continue
        path = files[0]
        full = _h5(kind, path, recipe, crop=d.crop, train=True, seed=seed)
        _check_item(full, str(path), recipe, supervised)
        size = len(full)  # type: ignore[arg-type]
        n_val = min(math.ceil(size * d.val_fraction), size - 1) if hold_out else 0
        if n_val > 0:
            train_parts.append(Subset(full, range(size - n_val)))
            val_parts.append(Subset(_h5(kind, path, recipe, crop=d.val_crop, train=False,
                                        seed=seed), range(size - n_val, size)))
        else:
            train_parts.append(full)
        sources.append(f"{path.name}: {size - n_val} sample(s)"
                       + (" (GOPRO layout)" if kind == "gopro_h5" else ""))
    if len({"sharp" in peek_item(part) for part in train_parts}) > 1:
        raise InputError("some `data` sets have ground-truth sharp frames and some do not",
                         hint="train on one kind at a time (e.g. fine-tune with `init_weights`)")
    train = train_parts[0] if len(train_parts) == 1 else ConcatDataset(train_parts)

    val: Dataset | None = None
    val_source = "none"
    val_files: list[Path] = []
    if d.val_data:
        vpath = recipe.resolve_path(d.val_data)
        vgroups = gather([vpath])
        vparts = []
        for kind, files in vgroups:
            val_files += files
            if kind == "images":
                vparts.append(_simulated(files, recipe, length=max(d.val_samples, 1),
                                         seed=seed + 7919, crop=d.val_crop or d.crop,
                                         train=False))
            else:
                vparts.append(_h5(kind, files[0], recipe, crop=d.val_crop, train=False,
                                  seed=seed))
        val = vparts[0] if len(vparts) == 1 else ConcatDataset(vparts)
        val_source = str(vpath)
        _check_item(val, val_source, recipe, True)
    elif val_parts:
        val = val_parts[0] if len(val_parts) == 1 else ConcatDataset(val_parts)
        val_source = f"held out {d.val_fraction:.0%} of the training data"
    else:
        notes.append("no validation set: set data.val_data or data.val_fraction > 0")
    if val is not None:
        val = _evenly(val, d.val_samples)
        if len(val) == 0:  # type: ignore[arg-type]
            val = None
        elif "sharp" not in peek_item(val):
            notes.append(f"validation data ({val_source}) has no ground truth: no validation")
            val, val_source = None, "none (no ground truth)"
    record: str | dict[str, Any] = val_source
    if val is not None and d.val_data:
        record = data_record(recipe.resolve_path(d.val_data), val_files)
    return DataPlan(train=train, val=val, sources=sources, val_source=val_source, notes=notes,
                    val_record=record)
