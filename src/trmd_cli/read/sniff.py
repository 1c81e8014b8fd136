"""Identify a file's format: magic bytes first, extension second (like faery)."""

from __future__ import annotations

from pathlib import Path

from ..errors import FormatError, InputError

__all__ = ["detect_format", "FORMATS", "is_rpg_folder", "is_ros2_folder", "is_recording_folder"]

#: format name → one-line description (for messages and `trmd info`)
FORMATS = {
    "text": "text events, one per line (t x y p)",
    "npz": "NumPy .npz archive",
    "npy": "NumPy .npy array",
    "hdf5": "HDF5 (trmd layout, event_utils/e2vid, DSEC)",
    "aedat4": "iniVation AEDAT 4.0",
    "evt3": "Prophesee EVT 3.0 .raw",
    "evt2": "Prophesee EVT 2.0 .raw",
    "dat": "Prophesee .dat (CD events)",
    "mat": "MATLAB .mat (eSL-Net layout)",
    "aedat2": "jAER AEDAT 2.0",
    "aedat3": "cAER / DV AEDAT 3.1",
    "rosbag1": "ROS 1 bag",
    "rosbag2": "ROS 2 bag (folder, .db3 or .mcap)",
    "rpg": "RPG event-camera folder (events.txt, images.txt, images/)",
}

_EXT = {
    ".txt": "text", ".csv": "text", ".dat": "dat", ".npz": "npz", ".npy": "npy", ".h5": "hdf5",
    ".hdf5": "hdf5", ".hdf": "hdf5", ".aedat4": "aedat4", ".mat": "mat", ".raw": None,
    ".aedat": "aedat2", ".bag": "rosbag1", ".db3": "rosbag2", ".mcap": "rosbag2",
}

#: the first bytes of a ROS 2 bag's storage files: SQLite 3 and MCAP
_ROS2_MAGIC = (b"SQLite format 3\x00", b"\x89MCAP0\r\n")


def detect_format(path: str | Path) -> str:
    """Return a key of :data:`FORMATS`.

    Raises:
        InputError: the file does not exist or is a folder.
        FormatError: the format cannot be recognised (names the formats supported).
    """
    path = Path(path)
    if not path.exists():
        raise InputError("file not found", path=path, hint="check the path")
    if path.is_dir():
        return _folder_format(path)
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if not head:
        raise FormatError("file is empty", path=path,
                          hint="the copy may be incomplete: copy the recording again")
    if head.startswith(b"\x89HDF\r\n\x1a\n") or (head.startswith(b"MATLAB 7.3") and len(head) > 520
                                               and head[512:520] == b"\x89HDF\r\n\x1a\n"):
        return "mat" if head.startswith(b"MATLAB") else "hdf5"
    if head.startswith(b"MATLAB 5.0 MAT-file"):
        return "mat"
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        return "npz"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith(b"#!AER-DAT4"):
        return "aedat4"
    if head.startswith((b"#!AER-DAT2.0\r\n", b"#!AER-DAT2.0\n")):
        return "aedat2"
    if head.startswith((b"#!AER-DAT3.1\r\n", b"#!AER-DAT3.1\n")):
        return "aedat3"
    if head.startswith(b"#ROSBAG V2.0\n"):
        return "rosbag1"
    if head.startswith(b"#ROSBAG V"):
        raise FormatError(f"{head[:12].decode(errors='replace')} bags are not supported",
                          path=path, hint="migrate it to a V2.0 bag (`rosbag fix`), or convert "
                          "it to a ROS 2 bag")
    if path.suffix.lower() in (".db3", ".mcap") and head.startswith(_ROS2_MAGIC):
        return "rosbag2"
    if head.startswith(b"#!AER-DAT"):
        raise FormatError(f"{head[:12].decode(errors='replace')} files are not supported yet",
                          path=path, hint="convert to AEDAT4 with DV, or to .h5/.npz")
    if head.startswith(b"%"):
        fmt = _prophesee_format(path, head)
        if fmt is not None:
            return fmt
    ext = _EXT.get(path.suffix.lower())
    if ext and ext != "text":
        raise FormatError(f"has the extension {path.suffix} but not the content of a "
                          f"{FORMATS[ext]} file (truncated or corrupt?)", path=path,
                          hint="copy the file again, or check that it is an event file")
    if _looks_like_text(head):
        return "text"
    raise FormatError("unknown event file format", path=path,
                      hint="supported: " + ", ".join(sorted(FORMATS)))


def is_rpg_folder(path: Path) -> bool:
    """The RPG event-camera layout: ``events.txt`` and ``images.txt`` in the folder."""
    return (path / "events.txt").is_file() and (path / "images.txt").is_file()


def is_ros2_folder(path: Path) -> bool:
    """A ROS 2 bag: a folder holding ``metadata.yaml``."""
    return (path / "metadata.yaml").is_file()


def is_recording_folder(path: Path) -> bool:
    """A folder that is one recording, read like an event file: a ROS 2 bag or the RPG
    layout. A folder that also holds the frames-folder layout (``blurry/``, ``Exposure_*.txt``)
    is not: it keeps its old meaning."""
    path = Path(path)
    if not path.is_dir():
        return False
    if is_ros2_folder(path):
        return True
    if not is_rpg_folder(path):
        return False
    names = {p.name.lower() for p in path.iterdir()}
    return not names & {"blurry", "blur", "blurred", "exposure_start.txt", "exposure_end.txt"}


def _folder_format(path: Path) -> str:
    """A folder that is a recording (ROS 2 bag, RPG layout); anything else is bad input."""
    if is_ros2_folder(path):
        return "rosbag2"
    if is_recording_folder(path):
        return "rpg"
    stores = [p for p in path.iterdir() if p.suffix.lower() in (".db3", ".mcap")]
    if stores:
        raise InputError("looks like a ROS 2 bag folder but holds no metadata.yaml", path=path,
                         hint=f"give the storage file itself ({stores[0].name}), or copy the "
                              "bag again")
    rpg = [name for name in ("events.txt", "images.txt") if (path / name).is_file()]
    if len(rpg) == 1:
        missing = "images.txt" if rpg[0] == "events.txt" else "events.txt"
        raise InputError(f"holds {rpg[0]} but no {missing}: an RPG recording folder needs both",
                         path=path, hint=f"add {missing}, or give the event file itself")
    raise InputError("is a folder, expected an event file", path=path,
                     hint="give the event file inside it")


def _prophesee_format(path: Path, head: bytes) -> str | None:
    """evt2 / evt3 / dat from a Prophesee ``%`` header (only its lines are looked at: binary data
    after it may contain any bytes); None when the ``%`` lines are a text file's comments."""
    from .prophesee import parse_header

    header = parse_header(head)
    suffix = path.suffix.lower()
    encoding = header.encoding
    if encoding is None and suffix == ".raw" and header.sensor_hint == (640, 480):
        encoding = "evt2"  # Gen3 sensors only write EVT 2.0; old headers do not say so
    if encoding in ("evt2", "evt3"):
        return encoding
    if encoding is not None:
        raise FormatError(f"Prophesee {encoding.upper()} is not supported", path=path,
                          hint="record or convert to EVT 2.0 / EVT 3.0 (.raw) or .dat")
    body = head[header.data_offset:]
    if suffix == ".dat" and header.fields and (len(body) < 2 or body.startswith(b"%")):
        return "dat"  # a .dat cut inside or right after its '%' header, not a text table
    if suffix == ".dat":
        # a plain-text table with '%' comments that happens to end in .dat
        return "text" if body and _looks_like_text(body) else "dat"
    if suffix == ".raw":
        raise FormatError("Prophesee .raw whose header names no known event format "
                          "(cut short?)", path=path,
                          hint="only EVT 2.0 and EVT 3.0 are supported; a cut copy needs copying "
                               "again")
    if header.width and body and not _looks_like_text(body):
        return "dat"
    return None


#: bytes never found in a text event file (C0 controls other than tab, newline, return)
_BINARY = bytes(c for c in range(32) if c not in (9, 10, 13))


def _looks_like_text(head: bytes) -> bool:
    if len(head.translate(None, _BINARY)) != len(head):
        return False
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as e:  # a multi-byte char cut at the end of the sample is fine
        if e.start < len(head) - 4:
            return False
    return True
