"""Training data and models the tests share.

``make_gopro_h5`` writes a tiny, physically consistent set in the GOPRO layout (blur = mean of
the sharp frames, voxels = rounded log-intensity changes / c).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import torch

from trmd_cli.models import create_model
from trmd_cli.train.data import GOPRO_LUMA
from trmd_cli.train.recipe import Recipe, apply_overrides

N = 3


def make_gopro_h5(path: Path, k: int = 8, h: int = 40, w: int = 48, n: int = N,
                  seed: int = 0, c: float = 0.2) -> Path:
    """A tiny h5 in the layout of the TRMD paper's GOPRO release."""
    import h5py

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    sharp = np.zeros((k, 2 * n + 1, h, w, 3), np.uint8)
    tint = np.array([1.0, 0.9, 0.8], np.float32)
    for i in range(k):
        phase, fx, speed = rng.uniform(0, 6.28), rng.uniform(0.15, 0.4), rng.uniform(1, 3)
        for j in range(2 * n + 1):
            img = 0.5 + 0.4 * np.sin(fx * (xx + speed * j) + phase) * np.cos(0.2 * yy)
            sharp[i, j] = (np.clip(img, 0, 1)[..., None] * tint * 255).astype(np.uint8)
    blur = sharp.astype(np.float32).mean(1).round().astype(np.uint8)
    gray = (sharp.astype(np.float32) / 255) @ np.asarray(GOPRO_LUMA, np.float32)
    logl = np.log(gray + 1e-3)
    vox = np.zeros((k, 2 * n, h, w), np.float32)
    for j, kk in enumerate([x for x in range(2 * n + 1) if x != n]):
        vox[:, j] = np.round((logl[:, kk] - logl[:, n]) / c)
    with h5py.File(path, "w") as f:
        f["blur_images"] = blur
        f["sharp_images"] = sharp
        f["voxel"] = vox
    return path


def write_trmd_h5(path: Path, *, sharp: bool = True, n: int = N, k: int = 3, size: int = 24):
    from trmd_cli.events import EventStream, Exposure
    from trmd_cli.write import write_h5

    rng = np.random.default_rng(0)
    e = 200
    stream = EventStream(rng.integers(0, size, e).astype(np.uint16),
                         rng.integers(0, size, e).astype(np.uint16),
                         np.sort(rng.integers(0, 30_000, e)).astype(np.int64),
                         rng.choice(np.array([-1, 1], np.int8), e), size, size)
    blurry = rng.random((k, size, size)).astype(np.float32)
    gt = rng.random((k, 2 * n + 1, size, size)).astype(np.float32) if sharp else None
    exposures = [Exposure(10_000 * i, 10_000 * i + 6000) for i in range(k)]
    write_h5(path, stream, blurry=blurry, exposures=exposures, sharp=gt,
             contrast=np.full(k, 0.2) if sharp else None)
    return path


def make_image_folder(folder: Path, count: int) -> Path:
    """``count`` smooth random 70×60 PNGs in ``folder`` (created): stills to simulate from."""
    import cv2

    rng = np.random.default_rng(0)
    folder.mkdir()
    for i in range(count):
        img = (rng.random((60, 70)) * 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{i}.png"), cv2.GaussianBlur(img, (5, 5), 2))
    return folder


def recipe(*overrides: str) -> Recipe:
    base = ["model.name='test_trmd'", "data.crop=32", "data.batch_size=4", "train.threads=1",
            "data.val_fraction=0.25", "optim.lr=3e-3", "optim.warmup_steps=5",
            "train.log_every=5", "train.checkpoint_minutes=0"]
    return apply_overrides(Recipe(), base + list(overrides))


def read_log(path: Path) -> list[dict]:
    with open(path) as fh:
        return list(csv.DictReader(fh))


def net_inputs(seed: int = 5, b: int = 2, h: int = 21, w: int = 30):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(b, 1, h, w, generator=g),
            torch.randint(-4, 5, (b, 6, h, w), generator=g).float())


def trained_like(name: str = "test_trmd", **kw) -> torch.nn.Module:
    """A network whose weights are far from their initialisation (as after training)."""
    torch.manual_seed(1)
    net = create_model(name, **kw)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return net.eval()
