"""Joints of a fitted skeleton moved with their segments' markers kept where they were, and the
markers' residual after a move (the refinement's frames posed again)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..artifacts import Skeleton
from .ik.solve import solve_ik


def _with_moves(skel: Skeleton, origin: np.ndarray, local: np.ndarray, kids_moved: set, key: str,
                moved: dict) -> Skeleton:
    """``skel`` with rest offsets ``origin``, ``local`` after the joints of ``kids_moved`` were moved
    (each with its segment's markers kept where they were), ``moved`` ({name: mm}) noted in its info
    under ``key`` and in the refinement's section as ``key``_mm. The root's origin stays the mean of
    its children's joints (the refinement's gauge)."""
    parent = np.asarray(skel.parent)
    root = int(np.flatnonzero(parent < 0)[0])
    kids = np.flatnonzero(parent == root)
    origin, local = origin.copy(), local.copy()
    pose_root = skel.pose_root
    if any(int(k) in kids_moved for k in kids):
        m = origin[kids].mean(0) - skel.origin[kids].mean(0)
        origin[root] = origin[root] + m
        local[skel.marker_segment == root] -= m
        pose_root = pose_root + skel.pose_rot[:, root] @ m
    info = dict(skel.info, **{key: moved})
    if "refined" in info:  # the report's refinement section names them
        info["refined"] = dict(info["refined"], **{f"{key}_mm": moved})
    return replace(skel, origin=origin, marker_local=local, info=info, pose_root=pose_root)


def _move_joint(origin: np.ndarray, local: np.ndarray, seg: np.ndarray, c: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Copies of rest offsets with segment ``c``'s joint moved by ``d``, its markers kept where they were."""
    o2, l2 = origin.copy(), local.copy()
    o2[c] = o2[c] + d
    l2[seg == c] -= d
    return o2, l2


def _repose(skel: Skeleton, origin: np.ndarray, local: np.ndarray, pts: np.ndarray):
    """IK of a skeleton with rest offsets ``origin``, ``local`` on ``pts`` (F, M, 3), the refinement's
    frames, from the refinement's poses, with no prior."""
    return solve_ik(skel.parent, origin, skel.marker_segment, local, pts, init_rot=skel.pose_rot,
                    init_root=skel.pose_root, prior_weight=0.0)


def _pose_ms(skel: Skeleton, origin: np.ndarray, local: np.ndarray, pts: np.ndarray) -> float:
    """Mean squared marker residual (mm^2) of a skeleton with rest offsets ``origin``, ``local`` on
    ``pts`` (F, M, 3), the refinement's frames: :func:`_repose`."""
    res = _repose(skel, origin, local, pts)
    r = res.residual[np.isfinite(res.residual)]
    return float(np.mean(r * r)) if r.size else np.inf
