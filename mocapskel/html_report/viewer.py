"""The data of the HTML report's 3-D view: markers, joints and end sites per frame, decimated and rounded,
as JSON that is safe inside a script element."""
from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np

from ..artifacts import Motion
from ..evaluate import joint_positions
from .colours import colour
from .data import _chain

__all__ = ["MAX_VIEWER_FRAMES", "viewer_data"]

#: At most this many frames of the take go into the 3-D view (longer takes are decimated).
MAX_VIEWER_FRAMES = 2000
#: Positions in the 3-D view's data are integers in this unit (mm): 0.1 mm.
VIEWER_QUANTUM_MM = 0.1


def _quantise(a: np.ndarray, origin: np.ndarray) -> list[list[int | None]]:
    """(n, K, 3) mm -> n flat lists of integers in units of 0.1 mm relative to ``origin``; None for NaN."""
    n = a.shape[0]
    q = np.round((a - origin) / VIEWER_QUANTUM_MM).reshape(n, -1)
    bad = ~np.isfinite(q)
    rows = np.where(bad, 0, q).astype(np.int64).tolist()
    for f, k in zip(*np.nonzero(bad)):
        rows[f][k] = None
    return rows


def viewer_data(motion: Motion, max_frames: int = MAX_VIEWER_FRAMES) -> dict[str, Any]:
    """The 3-D view's data: markers, joints and end sites per frame, decimated and rounded.

    Parameters
    ----------
    motion : Motion
        The IK artifact.
    max_frames : int
        At most this many frames are kept: every ``ceil(F / max_frames)``-th.

    Returns
    -------
    dict
        JSON-able: ``rate``, ``step`` (frames of the take per kept frame),
        ``frames`` (frames in the take), ``n`` (frames kept), ``quantum_mm``,
        ``origin`` (mm, subtracted from every position), ``up`` ("z": the lab
        frame's up axis), ``labels``, ``marker_segment``, ``names``, ``parent``,
        ``colours``, ``leaves`` (segments with an end site), and per kept frame
        the flat lists ``markers`` (3 M), ``joints`` (3 S) and ``ends``
        (3 per leaf) of integers in ``quantum_mm`` (None where not seen).
    """
    if max_frames < 1:
        raise ValueError(f"max_frames must be at least 1, got {max_frames}")
    sk = motion.skeleton
    F, S = motion.rot.shape[:2]
    step = max(1, math.ceil(F / max_frames))
    idx = np.arange(0, F, step)
    sub = dataclasses.replace(motion, root_pos=motion.root_pos[idx], rot=motion.rot[idx], residual=motion.residual[idx])
    jp = joint_positions(sub)  # (n, S, 3)
    leaves = [s for s in range(S) if np.linalg.norm(sk.end_site[s]) > 0]
    ends = (
        jp[:, leaves] + np.einsum("fsij,sj->fsi", sub.rot[:, leaves], sk.end_site[leaves])
        if leaves else np.zeros((idx.size, 0, 3))
    )
    mk, _, _ = _chain(motion)
    if mk is not None and mk.points.shape[0] == F and mk.n_markers == sk.marker_segment.size:
        pts = mk.points[idx]
        labels = list(mk.labels)
    else:  # a motion that carries no markers: show the skeleton alone
        pts = np.zeros((idx.size, 0, 3))
        labels = []
    allp = np.concatenate([jp.reshape(-1, 3), pts.reshape(-1, 3), ends.reshape(-1, 3)])
    allp = allp[np.isfinite(allp).all(axis=1)]
    origin = np.round(allp.mean(axis=0)) if allp.size else np.zeros(3)
    return {
        "rate": float(motion.rate) if motion.rate else 0.0,
        "step": int(step),
        "frames": int(F),
        "n": int(idx.size),
        "quantum_mm": VIEWER_QUANTUM_MM,
        "origin": [float(v) for v in origin],
        "up": "z",
        "labels": labels,
        "marker_segment": [int(s) for s in sk.marker_segment.tolist()][: len(labels)],
        "names": list(sk.names),
        "parent": [int(p) for p in sk.parent.tolist()],
        "colours": [colour(s) for s in range(S)],
        "leaves": leaves,
        "markers": _quantise(pts, origin),
        "joints": _quantise(jp, origin),
        "ends": _quantise(ends, origin),
        "unc": _uncertainty_axes(sk, sub.rot),
    }


def _uncertainty_axes(sk, rot: np.ndarray) -> dict[str, Any]:
    """Each joint's principal axes of uncertainty, two standard deviations long, turned with its child
    segment in every kept frame (``rot`` (n, S, 3, 3)): ``joints`` (segments whose joint has an axis of at
    least half a millimetre), ``prior`` (set by the prior) and per frame the flat list ``axes`` (9 per
    joint, in ``quantum_mm``). Empty lists when the skeleton carries no uncertainty."""
    unc = (sk.info.get("uncertainty") or {}).get("joints") or {}
    names = list(sk.names)
    joints, prior, rest = [], [], []
    for name, u in unc.items():
        if name not in names or 2.0 * max(u["sd_mm"]) < 0.5:
            continue
        joints.append(names.index(name))
        prior.append(bool(u["set_by_prior"]))
        rest.append(2.0 * np.asarray(u["sd_mm"])[:, None] * np.asarray(u["directions"]))  # (3 axes, 3)
    if not joints:
        return {"joints": [], "prior": [], "axes": []}
    A = np.einsum("fjik,jak->fjai", rot[:, joints], np.array(rest))  # (n, J, 3 axes, 3)
    return {"joints": joints, "prior": prior, "axes": _quantise(A.reshape(A.shape[0], -1, 3), np.zeros(3))}


def _json_for_script(obj: Any) -> str:
    """JSON text that is safe inside ``<script type="application/json">`` ("<", ">", "&" escaped)."""
    text = json.dumps(obj, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
