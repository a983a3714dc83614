"""Export: the BVH motion of a solved take (DESIGN: "BVH the way importers want it").

Axes: with ``up="z"`` BVH axes are the lab's; with ``up="y"`` lab (x, y, z)
maps to BVH (x, z, -y), so a Y-up importer such as Blender's puts the subject
back in its lab frame. Units: mm, cm or m. Rest pose (all channels zero) is the
subject's shape at the skeleton's rest frame; the root's OFFSET is zero and its
position channels are absolute, which every BVH reader agrees on.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..artifacts import Motion
from ..io.bvh import BvhSkeleton, choose_rotation_order, depth_first_order, global_to_local_rot, lab_rot_to_bvh, lab_to_bvh

VERSION = 3

UPS = ("y", "z")
UNITS = ("cm", "mm", "m")


@dataclass(frozen=True)
class Params:
    up: str = "y"
    units: str = "cm"
    order: str = "auto"
    """Rotation channel order of every joint; "auto": ZXY unless some joint comes within
    30 degrees of gimbal lock in it, then the order that keeps joints farthest from lock
    (:func:`~mocapskel.io.bvh.choose_rotation_order`)."""


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
    if params.up not in UPS:
        raise ValueError(f"up must be one of {UPS}")
    if params.units not in UNITS:
        raise ValueError(f"units must be one of {UNITS}")
    sk = motion.skeleton
    perm = depth_first_order(sk.parent)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    par = np.where(sk.parent[perm] >= 0, inv[np.maximum(sk.parent[perm], 0)], -1)
    offset = lab_to_bvh(sk.offset[perm], params.up, params.units)
    offset[par < 0] = 0.0
    local = global_to_local_rot(par, lab_rot_to_bvh(motion.rot, params.up, joints=perm))
    bskel = BvhSkeleton(
        names=tuple(sk.names[i] for i in perm),
        parent=par,
        offset=offset,
        end_site=lab_to_bvh(sk.end_site[perm], params.up, params.units),
        order=choose_rotation_order(local) if params.order == "auto" else params.order,
    )
    rate = motion.rate if motion.rate and motion.rate > 0 else 1.0
    return BvhMotion(bskel, lab_to_bvh(motion.root_pos, params.up, params.units), local, 1.0 / rate)

