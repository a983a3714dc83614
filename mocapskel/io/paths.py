"""Checks on a file argument before anything opens it."""
from __future__ import annotations

import os
import stat
from pathlib import Path

from ..errors import InputError

__all__ = ["require_regular_file"]


def require_regular_file(path: str | os.PathLike, give: str) -> Path:
    """The path, when it names an existing regular file (symbolic links followed); else InputError.

    Only ``stat`` is called: a named pipe or a device is refused without being
    opened (opening a pipe with no writer, or reading ``/dev/zero``, would never end).

    Parameters
    ----------
    path : str or PathLike
        The file argument.
    give : str
        What the user should give instead, e.g. ``"a .skel file written by 'fit --skeleton-out'"``.
    """
    spath = str(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError("no such file — check the path", spath) from None
    except NotADirectoryError:
        raise InputError("no such file (a part of the path is a file, not a folder) — check the path", spath) from None
    except OSError as e:
        raise InputError(f"cannot read ({e.strerror or e}) — check the path and the file's permissions", spath) from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"is a folder, not a file — give {give}", spath)
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"not a regular file — give {give}", spath)
    return Path(path)
