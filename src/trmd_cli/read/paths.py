"""What an input path must be before anything is opened: an existing, readable file (or folder).

A pipe (a FIFO, or ``<(cat events.txt)``) is refused rather than read: trmd reads an input more
than once — its first bytes to recognise the format, then the whole, and windows again later —
and a pipe gives its bytes only once (opening a FIFO nobody writes to would also wait forever).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ..errors import InputError

__all__ = ["check_input_path"]

_SPECIAL = ((stat.S_ISFIFO, "a pipe"), (stat.S_ISSOCK, "a socket"),
            (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def check_input_path(path: str | Path) -> Path:
    """Refuse, with one line, an input that is missing, not a regular file or folder, or not
    readable. Returns ``path`` as a :class:`~pathlib.Path`; opens nothing.

    Raises:
        InputError: missing; a pipe, socket or device; no permission to read it.
    """
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError("file not found", path=path, hint="check the path") from None
    except PermissionError:
        raise InputError("cannot be reached (permission denied on a folder above it)",
                         path=path, hint="check the folders' permissions") from None
    except OSError as e:
        raise InputError(f"cannot be opened ({e.strerror})", path=path,
                         hint="check the path") from None
    for test, kind in _SPECIAL:
        if test(st.st_mode):
            raise InputError(f"is {kind}, not a file: trmd reads an input more than once "
                             "(its format, then its events), which a pipe does not allow",
                             path=path, hint="save it to a file first (e.g. cat … > "
                             "events.txt) and give that file")
    if not os.access(path, os.R_OK | (os.X_OK if stat.S_ISDIR(st.st_mode) else 0)):
        what = "folder" if stat.S_ISDIR(st.st_mode) else "file"
        raise InputError(f"cannot be read (permission denied: the {what} is not readable by "
                         "this user)", path=path,
                         hint=f"check its permissions (chmod u+r{'x' if what == 'folder' else ''}"
                              f" {path.name})")
    return path
