"""GOPRO-style HDF5 (the paper's release): blurry frames, sharp frames and SCER voxels, no raw
events and no exposure times.

Layout: ``blur_images`` (K, H, W[, 3]) uint8 / uint16 / float, ``sharp_images``
(K, 2N+1, H, W[, 3]) (optional: ground truth), ``voxel`` (K, 2N, H, W) SCER
(:mod:`trmd_cli.voxel`). Frames are read one at a time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..voxel import bins_from_scer

__all__ = ["GoproFile", "is_gopro_h5"]

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def is_gopro_h5(path: str | Path) -> bool:
    """True for an HDF5 file holding ``blur_images`` and ``voxel``."""
    with open(path, "rb") as fh:
        if fh.read(8) != _HDF5_MAGIC:
            return False
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "blur_images" in f and "voxel" in f
    except OSError:
        return False


def _unit(a: np.ndarray) -> np.ndarray:
    """Stored pixels → float32 [0, 1] intensity."""
    a = np.asarray(a)
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0
    if a.dtype == np.uint16:
        return a.astype(np.float32) / 65535.0
    return a.astype(np.float32)


class GoproFile:
    """An opened GOPRO-style file.

    Attributes:
        path; width, height (pixels); n (2N voxel channels); has_sharp (ground truth stored);
        sharp_count: sharp frames per blurry frame (2N+1 when they fit), 0 without them.
    """

    def __init__(self, path: str | Path, n: int | None = None) -> None:
        """Open and check the layout; ``n``: refuse voxels of another N.

        Raises:
            FormatError: not HDF5, datasets missing or of shapes that do not fit.
            InputError: the voxels have another N than ``n``.
        """
        import h5py

        self.path = Path(path)
        self._f = None
        try:
            self._f = h5py.File(self.path, "r")
        except OSError as e:
            raise FormatError(f"cannot be opened as HDF5 ({e})", path=self.path) from None
        f = self._f
        try:
            self._blur, self._vox = f["blur_images"], f["voxel"]
            self._sharp = f["sharp_images"] if "sharp_images" in f else None
        except KeyError as e:
            self.close()
            raise FormatError(f"GOPRO-style file lacks {e}", path=self.path,
                              hint="expected blur_images, sharp_images and voxel") from None
        k = self._blur.shape[0]
        if self._blur.ndim not in (3, 4) or self._vox.ndim != 4 or self._vox.shape[0] != k:
            self.close()
            raise FormatError(f"blur_images {self._blur.shape} and voxel {self._vox.shape} do "
                              "not fit (K, H, W[, 3]) and (K, 2N, H, W)", path=self.path)
        self.height, self.width = self._blur.shape[1:3]
        self.n = int(self._vox.shape[1]) // 2
        if n is not None and self._vox.shape[1] != 2 * n:
            self.close()
            raise InputError(f"voxels have {self._vox.shape[1]} channels, not 2N = {2 * n}",
                             path=self.path, hint=f"pass `n={self._vox.shape[1] // 2}`")
        if self._sharp is not None and (self._sharp.shape[0] != k
                                        or self._sharp.shape[2:] != self._blur.shape[1:]):
            self.close()
            raise FormatError(f"sharp_images {self._sharp.shape} do not fit blur_images "
                              f"{self._blur.shape}", path=self.path)
        self.has_sharp = self._sharp is not None
        self.sharp_count = 0 if self._sharp is None else int(self._sharp.shape[1])

    def __len__(self) -> int:
        return int(self._blur.shape[0])

    def blurry(self, i: int) -> np.ndarray:
        """(H, W[, 3]) float32 [0, 1], frame ``i``."""
        return _unit(self._blur[i])

    def sharp(self, i: int) -> np.ndarray | None:
        """(2N+1, H, W[, 3]) float32 [0, 1] ground truth of frame ``i``, or None."""
        return None if self._sharp is None else _unit(self._sharp[i])

    def bins(self, i: int) -> np.ndarray:
        """(2N, H, W) float64 signed event counts of the 2N equal bins of exposure ``i``."""
        return bins_from_scer(self._vox[i])

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self) -> GoproFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
