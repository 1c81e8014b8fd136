"""Binned sets made from simulated samples (known ground truth): a folder of blurry frames and
one bins file in the layout of docs/formats.md, "Binned events"."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trmd_cli.voxel import event_bins
from trmd_cli.write import write_image


@dataclass(frozen=True, eq=False)
class BinnedFrame:
    """One exposure: blurry (H, W) [0, 1], bins (B, H, W) int16, sharp (2N+1, H, W)."""

    blurry: np.ndarray
    bins: np.ndarray
    sharp: np.ndarray


def binned_frames(sample, bins_per_frame: int) -> list[BinnedFrame]:
    """Two exposures from one simulated sample: the sample binned with
    :func:`trmd_cli.voxel.event_bins`, and its mirror image (x → W−1−x: the same physics,
    other content), so that a mix-up of the pairing shows."""
    b = event_bins(sample.events, sample.exposure, bins_per_frame)
    assert np.array_equal(b, np.round(b))  # whole counts
    b = b.astype(np.int16)
    return [BinnedFrame(sample.blurry, b, sample.sharp),
            BinnedFrame(sample.blurry[:, ::-1].copy(), b[..., ::-1].copy(),
                        sample.sharp[..., ::-1].copy())]


def write_binned_set(folder: Path, frames: list[BinnedFrame], fmt: str = "mat",
                     layout: str = "flat", first: int = 2, images: str = "blurry"
                     ) -> tuple[Path, Path]:
    """``folder/<images>/NNNN.png`` (16-bit, numbered from ``first``) and
    ``folder/event_bins.<fmt>`` holding the bins (``layout`` "flat": (F·B, H, W), "4d":
    (F, B, H, W)). Returns (images folder, bins file)."""
    folder.mkdir(parents=True, exist_ok=True)
    img_dir = folder / images
    img_dir.mkdir()
    for k, f in enumerate(frames):
        write_image(img_dir / f"{first + k:04d}.png", f.blurry, 16)
    counts = np.stack([f.bins for f in frames])
    if layout == "flat":
        counts = counts.reshape(-1, *counts.shape[2:])
    return img_dir, write_bins(folder / f"event_bins.{fmt}", counts)


def write_bins(path: Path, counts: np.ndarray) -> Path:
    """``counts`` as a bins file of the format ``path``'s suffix names."""
    fmt = path.suffix.lstrip(".")
    if fmt == "mat":
        import scipy.io as sio

        sio.savemat(path, {"event_bins": counts})
    elif fmt == "npz":
        np.savez(path, event_bins=counts)
    else:
        np.save(path, counts)
    return path
