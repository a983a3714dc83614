"""Forward kinematics of a solved Motion: where its joints are in the lab, at rest and per frame."""
from __future__ import annotations

import numpy as np

from ..artifacts import Motion
from .tree import depth_first_order


def segment_origin(motion: Motion, s: int) -> np.ndarray:
    """(F, 3) lab position (mm) of segment ``s``'s origin: :func:`segment_origins`' column ``s``, to the
    bit, from the segments on the path from the root to ``s`` alone."""
    sk = motion.skeleton
    path = [int(s)]
    while sk.parent[path[-1]] >= 0:
        path.append(int(sk.parent[path[-1]]))
    pos = np.array(motion.root_pos, dtype=np.float64)
    for p, c in zip(path[::-1], path[-2::-1]):  # parent, child: root first
        pos = pos + np.einsum("fij,j->fi", motion.rot[:, p], sk.offset[c])
    return pos


def segment_origins(motion: Motion) -> np.ndarray:
    """(F, S, 3) lab position (mm) of every segment origin; a child's origin is its joint with the parent."""
    sk = motion.skeleton
    F, S = motion.rot.shape[:2]
    pos = np.full((F, S, 3), np.nan)
    off = sk.offset
    for s in depth_first_order(sk.parent):  # parents before children
        p = sk.parent[s]
        if p < 0:
            pos[:, s] = motion.root_pos
        else:
            pos[:, s] = pos[:, p] + np.einsum("fij,j->fi", motion.rot[:, p], off[s])
    return pos


def joint_points_rest(skel, new_parent: np.ndarray, naming) -> np.ndarray:
    """(S, 3) rest position (lab, mm) of each segment's joint with its parent in the tree ``new_parent``
    (the tree the BVH and the OpenSim model are written on).

    A segment's joint with its new parent is the joint of the fitted tree
    between them; the root's is its origin, or for a person the midpoint of
    the two hip joints.
    """
    old = np.asarray(skel.parent)
    origin = np.asarray(skel.origin, dtype=np.float64)
    r = origin.copy()
    for s, q in enumerate(new_parent.tolist()):
        if q >= 0 and old[s] != q:  # the edge is reversed: the joint is the old child's origin
            r[s] = origin[q]
    root = int(np.flatnonzero(new_parent < 0)[0])
    if naming.hips_children:
        r[root] = np.mean([origin[c] if old[c] == root else origin[root] for c in naming.hips_children], axis=0)
    return r
