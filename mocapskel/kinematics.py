"""Forward kinematics of a solved Motion, and the virtual joint markers."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .artifacts import Markers, Motion
from .io.bvh import depth_first_order


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


def joint_marker_names(motion: Motion) -> list[str]:
    """Names of the virtual joint markers: ``<child segment>_JC`` for every joint."""
    sk = motion.skeleton
    return [f"{sk.names[s]}_JC" for s in range(len(sk.names)) if sk.parent[s] >= 0]


def with_joint_markers(markers: Markers, motion: Motion) -> Markers:
    """The input markers plus one virtual marker per joint centre per frame (for biomechanics tools)."""
    sk = motion.skeleton
    pos = segment_origins(motion)
    kids = [s for s in range(len(sk.names)) if sk.parent[s] >= 0]
    names = joint_marker_names(motion)
    taken = set(markers.labels)
    names = [n if n not in taken else f"{n}_{i}" for i, n in enumerate(names)]
    pts = np.concatenate([markers.points, pos[:, kids]], axis=1)
    info = dict(markers.info)
    info["virtual_joint_markers"] = names
    return replace(markers, points=pts, labels=tuple(markers.labels) + tuple(names), info=info)
