"""C3D marker files out: write markers as a float C3D through ezc3d, atomically."""
from __future__ import annotations

import contextlib
import os

import numpy as np

from ..artifacts import Markers
from .atomic import atomic_path
from .c3d_layout import _SATURATED

__all__ = ["write_c3d", "write_ezc3d"]


def write_c3d(path: str | os.PathLike, markers: Markers) -> None:
    """Write markers as a float C3D file (mm) through ezc3d, atomically.

    Parameters
    ----------
    path : str or PathLike
        Output file; it is replaced only once the new file is complete.
    markers : Markers
        ``points`` (F, M, 3) in mm, NaN for gaps (written as residual -1 with
        zero coordinates); ``labels`` (LABELS, LABELS2 ... beyond 255 labels);
        ``rate``. Takes longer than 65535 frames also get ``POINT:LONG_FRAMES``
        and ``TRIAL:ACTUAL_START_FIELD``/``ACTUAL_END_FIELD``.
    """
    import ezc3d
    from ezc3d import ezc3d as _swig

    pts = np.asarray(markers.points, dtype=np.float64)
    F, M = pts.shape[:2]
    seen = np.isfinite(pts).all(axis=2)  # (F, M)
    data = np.zeros((4, M, F))
    data[:3] = np.where(seen[..., None], pts, 0.0).transpose(2, 1, 0)
    data[3] = 1.0
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(markers.rate)]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(markers.labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = np.where(seen.T, 0.0, -1.0)[None]
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, M, F), dtype=bool)
    if F > _SATURATED:
        c.add_parameter("POINT", "LONG_FRAMES", np.array([float(F)]), "number of frames (more than 65535)")
        params = c["parameters"]
        params.create_group_if_needed("TRIAL")
        for name, words in (("ACTUAL_START_FIELD", [1, 0]), ("ACTUAL_END_FIELD", [F & 0xFFFF, F >> 16])):
            params["TRIAL"][name] = {  # 16-bit integer words (low, high), as the C3D manual has them
                "type": _swig.INT, "value": np.array(words), "description": "frame number (low, high word)", "is_locked": False
            }
    write_ezc3d(c, path)


def write_ezc3d(c, path: str | os.PathLike) -> None:
    """Write the ezc3d object ``c`` to ``path`` atomically (temporary file, then rename)."""
    with atomic_path(path) as tmp:
        tmp_c3d = tmp + ".c3d"  # ezc3d's Python writer appends .c3d to any other name
        try:
            c.write(tmp_c3d)
            os.replace(tmp_c3d, tmp)
        finally:
            with contextlib.suppress(OSError):
                os.unlink(tmp_c3d)

