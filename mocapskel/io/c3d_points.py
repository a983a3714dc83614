"""Add points to a C3D file and keep everything else it holds.

:func:`add_points` reads a C3D with ezc3d, appends points (labels,
descriptions, coordinates) and writes the result: the analog channels, force
platforms, events, every parameter group (TRIAL, SUBJECTS, MANUFACTURER ...),
the labels as written (``Subject:`` namespaces included), the points already
there and their residuals and camera masks are carried over unchanged. Only
what must change does: ``POINT:USED``, ``POINT:LABELS``/``DESCRIPTIONS`` (the
new points appended) and ``POINT:DATA_START`` (and ``ROTATION:DATA_START`` where
there is one: the data blocks move).
"""
from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from .c3d_write import write_ezc3d
from .raw import unit_factor

__all__ = ["FrameCountMismatch", "add_points"]

#: Labels per ``POINT:LABELS``/``LABELS2`` ... parameter (C3D: at most 255 entries each).
_PER_PARAM = 255
#: Longest description written (a C3D string parameter's dimensions are single bytes).
_MAX_TEXT = 250


class FrameCountMismatch(InputError):
    """ezc3d reads another number of frames than the points to add have."""


def _series(group: dict, base: str) -> list[str]:
    names = [base] + [f"{base}{i}" for i in range(2, 100)]
    out: list[str] = []
    for n in names:
        if n not in group:
            break
        out.append(n)
    return out


def _append_strings(group: dict, base: str, values: list[str], n_before: int, description: str) -> None:
    """Append ``values`` to the series ``base``, ``base2`` ... (255 per parameter), padding it to ``n_before`` first."""
    keys = _series(group, base)
    have: list[str] = []
    for k in keys:
        have.extend(str(v) for v in group[k]["value"])
    have = have[:n_before] + [""] * max(0, n_before - len(have))
    full = have + list(values)
    chunks = [full[i : i + _PER_PARAM] for i in range(0, max(len(full), 1), _PER_PARAM)]
    for i, chunk in enumerate(chunks):
        k = base if i == 0 else f"{base}{i + 1}"
        if k in group:
            group[k]["value"] = chunk
        else:
            from ezc3d import ezc3d as _swig

            group[k] = {"type": _swig.CHAR, "value": chunk, "description": description, "is_locked": False}


def add_points(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    labels: Sequence[str],
    descriptions: Sequence[str],
    points_mm: np.ndarray,
) -> list[str]:
    """Write ``dst``: the C3D file ``src`` with points added.

    Parameters
    ----------
    src : str or PathLike
        The C3D file to copy (never modified).
    dst : str or PathLike
        Output file, written atomically.
    labels, descriptions : sequences of str, length K
        The new points' labels and descriptions. A label already in the file
        gets a ``_2`` (``_3`` ...) suffix.
    points_mm : (F, K, 3) array
        Lab coordinates in mm (converted to the file's ``POINT:UNITS``), NaN
        where a point is not known (written as a gap: residual -1).

    Returns
    -------
    list of str
        The labels as written.

    Raises
    ------
    InputError
        When ezc3d cannot read ``src``; FrameCountMismatch (an InputError)
        when it reads another frame count than ``F``.
    """
    import ezc3d

    try:
        c = ezc3d.c3d(str(src))
    except Exception as e:  # noqa: BLE001 - ezc3d raises plain RuntimeError/IOError
        raise InputError(f"cannot read it again to add the joint points ({e})", str(src)) from None
    pts = np.asarray(points_mm, dtype=np.float64)
    data = c["data"]["points"]
    F, P = data.shape[2], data.shape[1]
    if pts.ndim != 3 or pts.shape[2] != 3 or pts.shape[1] != len(labels) or len(descriptions) != len(labels):
        raise ValueError(f"points_mm {pts.shape} does not match {len(labels)} labels and {len(descriptions)} descriptions")
    if pts.shape[0] != F:
        raise FrameCountMismatch(f"ezc3d reads {F} frames, the joint points have {pts.shape[0]}", str(src))
    K = pts.shape[1]
    point = c["parameters"]["POINT"]
    old_labels: list[str] = []
    for k in _series(point, "LABELS"):
        old_labels.extend(str(v) for v in point[k]["value"])
    taken = {s.strip() for s in old_labels}
    out_labels = []
    for lab in labels:
        name, n = lab, 2
        while name in taken:
            name, n = f"{lab}_{n}", n + 1
        taken.add(name)
        out_labels.append(name)
    units = point["UNITS"]["value"] if "UNITS" in point else []
    units = [str(u) for u in units if str(u).strip()]
    factor = unit_factor(units[0])[1] if units else None
    factor = factor or 1.0
    seen = np.isfinite(pts).all(axis=2)  # (F, K)
    new = np.zeros((4, K, F))
    new[:3] = np.where(seen[..., None], pts / factor, 0.0).transpose(2, 1, 0)
    new[3] = 1.0
    c["data"]["points"] = np.concatenate([data, new], axis=1)
    meta = c["data"]["meta_points"]
    res = meta.get("residuals")
    if res is None or res.size == 0:
        res = np.zeros((1, P, F))
    meta["residuals"] = np.concatenate([res, np.where(seen.T, 0.0, -1.0)[None]], axis=1)
    masks = meta.get("camera_masks")
    if masks is None or masks.size == 0:
        masks = np.zeros((7, P, F), dtype=bool)
    meta["camera_masks"] = np.concatenate([masks, np.zeros((7, K, F), dtype=bool)], axis=1)
    _append_strings(point, "LABELS", out_labels, P, "Point labels")
    _append_strings(point, "DESCRIPTIONS", [str(d)[:_MAX_TEXT] for d in descriptions], P, "Point descriptions")
    write_ezc3d(c, dst)
    return out_labels
