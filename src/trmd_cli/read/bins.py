"""Binned events: per-pixel signed event counts in equal time bins, with no event times
(LEDVDI's ``EventBin3.mat`` and files like it).

The layout trmd reads (docs/formats.md, "Binned events"):

* one integer array of signed counts (ON events minus OFF events of a pixel in a bin) for all
  the frames, either flat ``(F·B, H, W)`` — bin j of frame i at row ``B·i + j`` — or
  ``(F, B, H, W)``. Floats are accepted when every value is a whole number (MATLAB stores
  doubles); NaN, infinite or fractional values are refused;
* in a ``.mat`` (MAT v5 or v7.3): the variable ``event_bins``; in a ``.npz``: the key
  ``event_bins``; a ``.npy``: the array itself (3-D or 4-D; an event list is (E, 4) or
  structured). No other key is read;
* the B bins of a frame are of equal duration, span its exposure and come in time order;
* the i-th frame in sorted order (see :func:`trmd_cli.read.folders.list_images`) pairs with the
  i-th block of B bins; for the flat layout B = rows / F.

There is no event clock: instants are fractions of the exposure (0 = start, 1 = end), never
µs. A ``.npy`` is memory-mapped (memory: one frame's bins); ``.mat`` and ``.npz`` are read
whole.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from tokenize import TokenError

import numpy as np

from ..errors import FormatError, InputError, TrmdError

__all__ = ["BINS_KEY", "BINNED_HINT", "BinnedEvents", "is_bins_file", "read_bins",
           "describe_bins"]

#: the key (``.mat`` variable, ``.npz`` entry) holding the bins
BINS_KEY = "event_bins"
#: where an event reader points a user who gave it a binned file
BINNED_HINT = ("give it after the folder of its frames (`trmd deblur IMAGES_DIR BINS_FILE`, "
               "`trmd hfr IMAGES_DIR BINS_FILE`), or as a dataset folder of blurry/ and the "
               "bins file (`trmd eval`)")


@dataclass(frozen=True, eq=False)
class BinnedEvents:
    """The bins of F frames.

    Attributes:
        path: the file.
        counts: (F, B, H, W) signed counts as stored (integers, or floats holding whole
            numbers); a read-only memory map for ``.npy``.
    """

    path: Path
    counts: np.ndarray

    @property
    def frames(self) -> int:
        """F, the number of frames."""
        return int(self.counts.shape[0])

    @property
    def bins_per_frame(self) -> int:
        """B, the equal bins spanning each exposure."""
        return int(self.counts.shape[1])

    @property
    def width(self) -> int:
        return int(self.counts.shape[3])

    @property
    def height(self) -> int:
        return int(self.counts.shape[2])

    def frame(self, i: int) -> np.ndarray:
        """(B, H, W) signed counts of frame ``i`` (0-based, sorted order), in time order."""
        return np.asarray(self.counts[i])


def _format(path: Path) -> str | None:
    from .sniff import detect_format

    try:
        fmt = detect_format(path)
    except TrmdError:
        return None  # not ours to report: the event readers say what is wrong with it
    return fmt if fmt in ("mat", "npz", "npy") else None


def is_bins_file(path: str | Path) -> bool:
    """True for a file holding binned events in the layout above: a ``.mat`` / ``.npz`` with
    ``event_bins``, or a ``.npy`` whose array is 3-D or 4-D. Reads names and headers only.

    A file that also holds the events the event readers look for first (eSL-Net's
    ``section_event_*``, an ``.npz``'s ``x, y, t, p``) stays an event file."""
    path = Path(path)
    if not path.is_file():
        return False
    fmt = _format(path)
    try:
        if fmt == "mat":
            from .mat import _ESL, mat_variable_names

            names = mat_variable_names(path)
            return BINS_KEY in names and not all(k in names for k in _ESL)
        if fmt == "npz":
            from .npz import _KEYSETS

            with zipfile.ZipFile(path) as z:
                keys = {n[:-4] for n in z.namelist() if n.endswith(".npy")}
            return BINS_KEY in keys and not any(set(ks) <= keys for ks in _KEYSETS)
        if fmt == "npy":
            shape, dtype = _npy_header(path)
            return dtype.names is None and len(shape) in (3, 4)
    except (TrmdError, OSError, zipfile.BadZipFile, ValueError, SyntaxError, TokenError):
        # (a damaged .npy header: not a bins file; the event readers name the damage)
        return False
    return False


def describe_bins(path: str | Path) -> dict:
    """What ``trmd info`` says of a bins file: its array's shape and type, the sensor, and the
    sum of |counts| (a lower bound on the events). How its rows split into frames follows
    from the number of frames given with it (:func:`read_bins`)."""
    path = Path(path)
    counts = _load(path)
    shape = tuple(int(d) for d in counts.shape)
    if len(shape) not in (3, 4):
        raise FormatError(f"binned events of shape {shape}, expected (F·B, H, W) or "
                          "(F, B, H, W)", path=path, hint=BINNED_HINT)
    whole = np.abs(np.asarray(counts, np.float64)).sum()
    fmt = _format(path)
    return {"format": "binned events (npy)" if fmt == "npy" else
            f"binned events ({fmt}, '{BINS_KEY}')",
            "shape": list(shape), "dtype": str(counts.dtype),
            "sensor": f"{shape[-1]}x{shape[-2]}",
            "abs_count": int(whole) if float(whole).is_integer() else float(whole),
            "abs_count_meaning": "sum of |per-pixel polarity sums| over every bin: a lower "
                                 "bound on the events",
            "frames": "F·B rows: the bins per frame follow from the number of frames given "
                      "with the file (trmd deblur IMAGES_DIR BINS_FILE)"
                      if len(shape) == 3 else shape[0]}


def _npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    from numpy.lib import format as npformat

    with open(path, "rb") as fh:
        version = npformat.read_magic(fh)
        read = {(1, 0): npformat.read_array_header_1_0,
                (2, 0): npformat.read_array_header_2_0}.get(version)
        if read is None:
            raise ValueError(f"npy version {version}")
        shape, _fortran, dtype = read(fh)
    return tuple(shape), dtype


def _load(path: Path) -> np.ndarray:
    fmt = _format(path)
    if fmt == "mat":
        from .mat import _load as load_mat

        data = load_mat(path, [BINS_KEY])
        if BINS_KEY not in data:
            raise FormatError(f"holds no '{BINS_KEY}' variable", path=path,
                              hint=f"store the bins as the variable '{BINS_KEY}'")
        return data[BINS_KEY]
    if fmt == "npz":
        from .npz import _get
        from .npz import _load as load_npz

        with load_npz(path) as npz:
            if BINS_KEY not in npz.files:
                raise FormatError(f"holds no '{BINS_KEY}' key (keys: "
                                  f"{', '.join(sorted(npz.files)) or 'none'})", path=path,
                                  hint=f"store the bins under the key '{BINS_KEY}'")
            return _get(npz, BINS_KEY, path)
    if fmt == "npy":
        try:
            return np.load(path, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise FormatError(f"cannot be read as a NumPy array ({str(e).splitlines()[0]})",
                              path=path, hint="the file may be incomplete or damaged") from None
    raise FormatError("not a bins file", path=path,
                      hint=f"binned events come as .mat / .npz (key '{BINS_KEY}') or .npy")


def read_bins(path: str | Path, frames: int, size: tuple[int, int] | None = None
              ) -> BinnedEvents:
    """Read and check the bins of ``frames`` frames.

    Args:
        path: a ``.mat`` / ``.npz`` (key ``event_bins``) or ``.npy``.
        frames: F, the number of frames the bins are for (the images beside them).
        size: (width, height) the bins must have (the frames' size), or None.
    Raises:
        FormatError: unreadable file, no ``event_bins``, not a 3-D / 4-D numeric array.
        InputError: rows that F does not divide, another frame count, NaN or fractional
            counts, another size than ``size``.
    """
    path = Path(path)
    a = _load(path)
    if a.dtype.names is not None or a.dtype.kind not in "iuf":
        raise FormatError(f"the bins have type {a.dtype}, expected integer counts", path=path,
                          hint="store signed per-pixel event counts as integers")
    if a.ndim == 3:
        rows = int(a.shape[0])
        if frames < 1 or rows % frames or rows == 0:
            raise InputError(f"the file holds {rows} bins, which {frames} frames do not divide "
                             "into equal parts", path=path,
                             hint="give one image per frame the bins are for (rows = frames × "
                                  "bins per frame), or store them as (F, B, H, W)")
        a = a.reshape(frames, rows // frames, *a.shape[1:])
    elif a.ndim == 4:
        if a.shape[0] != frames:
            raise InputError(f"the file holds the bins of {a.shape[0]} frames, the images "
                             f"number {frames}", path=path,
                             hint="give one image per frame, in the bins' order")
    else:
        raise FormatError(f"the bins have shape {a.shape}, expected (F·B, H, W) or "
                          "(F, B, H, W)", path=path,
                          hint="store per-pixel counts of B equal bins per frame")
    if a.shape[1] == 0:
        raise FormatError(f"the bins have shape {a.shape}: no bins", path=path)
    if size is not None and (a.shape[3], a.shape[2]) != tuple(size):
        raise InputError(f"the bins are {a.shape[3]}x{a.shape[2]} but the frames are "
                         f"{size[0]}x{size[1]}", path=path,
                         hint="give the bins recorded with these frames")
    if a.dtype.kind == "f":
        _check_whole(a, path)
    return BinnedEvents(path, a)


def _check_whole(a: np.ndarray, path: Path) -> None:
    """Float counts must be finite whole numbers (checked frame by frame: bounded memory)."""
    for i in range(a.shape[0]):
        f = np.asarray(a[i])
        finite = np.isfinite(f)
        if not finite.all():
            j = np.unravel_index(int(np.flatnonzero(~finite)[0]), f.shape)
            raise InputError(f"frame {i}, bin {j[0]} holds NaN or infinite counts", path=path,
                             hint="store whole-number event counts")
        frac = f != np.round(f)
        if frac.any():
            j = np.unravel_index(int(np.flatnonzero(frac)[0]), f.shape)
            raise InputError(f"frame {i}, bin {j[0]} holds a count that is not a whole number "
                             f"({f[j]:g})", path=path, hint="store whole-number event counts")
