"""Readers: event files (and the frames some of them hold) → :class:`Recording`.

``open_events(path)`` sniffs the format and dispatches; each format lives in its own module and
is imported only when used, so optional dependencies (aedat, evt3, scipy …) stay optional.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from ..errors import TrmdError
from .base import Frame, MemoryRecording, ReadOptions, Recording
from .frames import read_image
from .sniff import FORMATS, detect_format

__all__ = ["open_events", "detect_format", "read_image", "Recording", "MemoryRecording",
           "Frame", "ReadOptions", "FORMATS", "READERS"]

#: format → "module:function" taking (path, ReadOptions) and returning a Recording
READERS = {
    "text": "text:read_text",
    "npz": "npz:read_npz",
    "npy": "npz:read_npy",
    "hdf5": "hdf5:read_hdf5",
    "aedat4": "aedat4:read_aedat4",
    "evt3": "prophesee:read_evt3",
    "evt2": "prophesee:read_evt2",
    "dat": "prophesee:read_dat",
    "mat": "mat:read_mat",
    "aedat2": "aedat:read_aedat2",
    "aedat3": "aedat:read_aedat3",
    "rosbag1": "rosbag:read_rosbag",
    "rosbag2": "rosbag:read_rosbag",
    "rpg": "rpg:read_rpg",
}

#: the options about stamped frames and bag topics, and the formats that use them (for the rest
#: they are said to be ignored)
_USED_BY = {
    "exposure_length_us": ("rosbag1", "rosbag2", "rpg"),
    "stamp": ("rosbag1", "rosbag2", "rpg"),
    "topics": ("rosbag1", "rosbag2"),
}


def open_events(path: str | Path, options: ReadOptions | None = None) -> Recording:
    """Open an event file of any supported format.

    Raises:
        InputError / FormatError: with the file named and a hint how to fix it.
    """
    path = Path(path)
    fmt = detect_format(path)
    module, func = READERS[fmt].split(":")
    reader = getattr(importlib.import_module(f"{__package__}.{module}"), func)
    options = options or ReadOptions()
    try:
        rec = reader(path, options)
    except TrmdError as e:
        if e.path is not None:
            raise
        # helpers shared by every reader (unit conversion, make_stream) do not know the file
        raise type(e)(e.detail, path=path, hint=e.hint) from None
    for name, formats in _USED_BY.items():
        if getattr(options, name) is not None and fmt not in formats:
            rec.warnings.append(f"`{name}` ignored: it applies to ROS bags"
                                + (" and the RPG layout" if name != "topics" else "")
                                + f", not to {FORMATS[fmt]} files")
    return rec


def require(module: str, extra: str = "formats", path: str | Path | None = None):
    """Import an optional dependency or raise a FormatError telling how to install it."""
    from ..errors import FormatError

    try:
        return importlib.import_module(module)
    except ImportError:
        raise FormatError(f"reading this format needs the '{module}' package", path=path,
                          hint=f"pip install 'trmd[{extra}]'") from None
