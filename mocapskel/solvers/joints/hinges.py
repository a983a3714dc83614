"""Hinge axes of a fitted skeleton's joints, from the relative rotations of their two segments."""
from __future__ import annotations

import numpy as np

from ...artifacts import Skeleton
from ..rotations import matrix_to_rotvec, project_to_so3


def _relative_rotations(rot: np.ndarray, p: int, c: int, seen: np.ndarray | None = None,
                        least: int = 10) -> np.ndarray | None:
    """``R_p^T R_c`` of poses ``rot`` (F, S, 3, 3) on the frames where both are known, or None when they
    are fewer than ``least`` (too few to tell how a joint turns).

    seen : (F, S) whether each segment has a marker seen in each frame
    (:func:`~mocapskel.solvers.rotations.segments_seen`): frames where either has none are left out (IK
    filled its pose there: a guess, not a measurement).
    """
    rel = np.swapaxes(rot[:, p], 1, 2) @ rot[:, c]
    ok = np.isfinite(rel).all((1, 2))
    if seen is not None:
        ok &= seen[:, p] & seen[:, c]
    rel = rel[ok]
    return rel if len(rel) >= least else None


def _relative_rotvecs(rel: np.ndarray) -> np.ndarray:
    """(F, 3) rotation vectors of the rotations ``rel`` (F, 3, 3) about their chordal mean."""
    return matrix_to_rotvec(np.swapaxes(project_to_so3(rel.sum(0)), 0, 1)[None] @ rel)


def _hinge_direction(rel: np.ndarray, hinge_ratio: float, twist: np.ndarray | None = None,
                     rv: np.ndarray | None = None) -> np.ndarray | None:
    """The axis the relative rotations ``rel`` (F, 3, 3) turn about when they turn about one (their
    spread about the second axis at most ``hinge_ratio`` of the first: a hinge); None otherwise.

    twist : the child's long axis (its rest-pose bone direction), or None: the rotations' part about
    it is left out (a limb segment of one or two markers along its bone hardly fixes its own twist,
    and a hinge turns across its bone, not about it).
    rv : ``_relative_rotvecs(rel)`` when the caller has them.
    """
    rv = _relative_rotvecs(rel) if rv is None else rv
    if twist is not None:
        rv = rv - np.outer(rv @ twist, twist)
    _, sv, Vt = np.linalg.svd(rv, full_matrices=False)
    if not sv[0] > 0 or sv[1] > hinge_ratio * sv[0]:
        return None
    return Vt[0]


def _hinge_axes(skel: Skeleton, rot: np.ndarray, hinge_ratio: float, seen: np.ndarray | None = None
                ) -> dict[int, np.ndarray]:
    """{child segment: hinge axis (rest-pose axes)} of the joints whose centre the markers hardly fix
    along one axis: those the joints stage placed as hinges, and those SCoRE fixed in full whose
    relative rotations ``R_parent^T R_child`` of ``rot`` (F, S, 3, 3) turn about one axis (spread
    about the second axis at most ``hinge_ratio`` of the first: :func:`_hinge_direction`): a walk's
    ankle, which SCoRE solves by least squares along an axis its motion barely fixes.

    The axis is the direction the relative rotations leave most nearly fixed: the eigenvector of
    SCoRE's ``[[I, -M], [-M^T, I]]`` (``M`` their mean) of the smallest eigenvalue. ``seen``: as
    :func:`_relative_rotations` takes it.
    """
    joints = skel.joints
    per = joints.info.get("per_joint") or []
    out = {}
    for e, (a, b) in enumerate(joints.topology.edges):
        placed = e < len(per) and per[e].get("hinge")
        if not placed and joints.method[e] != "score":
            continue  # a joint of a one- or two-marker segment: its start is too rough to hold
        c = int(b) if skel.parent[int(b)] == int(a) else int(a)
        p = int(skel.parent[c])
        rel = _relative_rotations(rot, p, c, seen)
        if rel is None:
            continue
        if not placed and _hinge_direction(rel, hinge_ratio) is None:
            continue
        M = rel.mean(0)
        N = np.eye(6)
        N[:3, 3:] = -M
        N[3:, :3] = -M.T
        v = np.linalg.eigh(N)[1][:, 0]
        axis = v[:3] + v[3:]
        if np.linalg.norm(axis) > 0:
            out[c] = axis / np.linalg.norm(axis)
    return out
