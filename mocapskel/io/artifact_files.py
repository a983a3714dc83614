"""Artifact files: an artifact written to, and read back from, its ``.npz`` file (the bytes are the
artifacts module's; the files, their atomic writing and their checks are here)."""
from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from ..artifacts import from_arrays, to_bytes
from ..errors import InputError
from .atomic import atomic_write_bytes
from .paths import require_regular_file


def save(obj: Any, path: str | os.PathLike, refs: dict[int, str] | None = None) -> None:
    """Save an artifact to ``path`` atomically (temporary file, then rename)."""
    atomic_write_bytes(path, to_bytes(obj, refs))


def read_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file (no pickles). Raises InputError when it cannot be read as one."""
    try:  # open the file here: np.load leaks its own handle when the zip is damaged (ResourceWarning)
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            if not hasattr(z, "files"):
                raise ValueError("a single array, not an archive of arrays")
            return {k: z[k] for k in z.files}
    except OSError as e:
        raise InputError(f"not a readable mocapskel artifact ({e.strerror or e}) — re-run the stage that wrote it", str(path)) from None
    except Exception as e:  # a damaged or crafted archive makes np.load and zipfile raise all kinds of errors
        what = str(e).splitlines()[0][:120] if str(e) else type(e).__name__
        raise InputError(f"not a readable mocapskel artifact ({what}) — re-run the stage that wrote it", str(path)) from None


def load(path: str | os.PathLike, resolve: Callable[[str], Any] | None = None) -> Any:
    """Load an artifact saved by :func:`save`, checked. Raises InputError when it is not one.

    ``resolve`` turns a stored reference back into the artifact (see :func:`to_bytes`).
    """
    require_regular_file(path, "a .npz artifact written by mocapskel")
    return from_arrays(read_arrays(path), str(path), resolve)
