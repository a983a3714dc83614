"""Forward kinematics of a solved Motion: where its joints are in the lab."""
from __future__ import annotations

import numpy as np

from ..artifacts import Motion
from .tree import depth_first_order


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


