"""Export: the BVH motion of a solved take (DESIGN: "BVH the way importers want it").

Axes: with ``up="z"`` BVH axes are the lab's; with ``up="y"`` lab (x, y, z)
maps to BVH (x, z, -y), so a Y-up importer such as Blender's puts the subject
back in its lab frame. Units: mm, cm or m. Rest pose (all channels zero) is the
subject at the skeleton's rest frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..artifacts import Motion
from ..io.bvh import BvhSkeleton

VERSION = 1

UNIT_SCALE = {"mm": 1.0, "cm": 0.1, "m": 0.001}
AXES = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}


@dataclass(frozen=True)
class Params:
    up: str = "y"
    units: str = "cm"
    order: str = "ZXY"


@dataclass(frozen=True, eq=False)
class BvhMotion:
    """Everything a BVH file holds, in BVH axes and units.

    root_pos : (F, 3); local_rot : (F, S, 3, 3) rotation of each joint relative to its parent.
    """

    skeleton: BvhSkeleton
    root_pos: np.ndarray
    local_rot: np.ndarray
    frame_time: float


def run(motion: Motion, params: Params = Params()) -> BvhMotion:
    if params.up not in AXES:
        raise ValueError(f"up must be one of {sorted(AXES)}")
    if params.units not in UNIT_SCALE:
        raise ValueError(f"units must be one of {sorted(UNIT_SCALE)}")
    C = AXES[params.up]
    k = UNIT_SCALE[params.units]
    sk = motion.skeleton
    G = np.einsum("ij,fsjk,lk->fsil", C, motion.rot, C)  # C R C^T
    local = G.copy()
    has = sk.parent >= 0
    local[:, has] = np.einsum("fsji,fsjk->fsik", G[:, sk.parent[has]], G[:, has])
    perm = depth_first(sk.parent)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    par = np.where(sk.parent[perm] >= 0, inv[np.maximum(sk.parent[perm], 0)], -1)
    bskel = BvhSkeleton(
        names=tuple(sk.names[i] for i in perm),
        parent=par,
        offset=(sk.offset[perm] @ C.T) * k,
        end_site=(sk.end_site[perm] @ C.T) * k,
        order=params.order,
    )
    rate = motion.rate if motion.rate and motion.rate > 0 else 1.0
    return BvhMotion(bskel, (motion.root_pos @ C.T) * k, local[:, perm], 1.0 / rate)


def depth_first(parent: np.ndarray) -> np.ndarray:
    """Segment indices in depth-first order from the root (parents before children)."""
    parent = np.asarray(parent)
    order: list[int] = []
    stack = [int(r) for r in np.flatnonzero(parent < 0)[::-1]]
    while stack:
        s = stack.pop()
        order.append(s)
        stack.extend(int(c) for c in np.flatnonzero(parent == s)[::-1])
    return np.array(order, dtype=int)
