"""Export: the BVH motion of a solved take (DESIGN: "BVH the way importers want it").

Axes: with ``up="z"`` BVH axes are the lab's; with ``up="y"`` lab (x, y, z)
maps to BVH (x, z, -y), so a Y-up importer such as Blender's puts the subject
back in its lab frame. Units: mm, cm or m. Rest pose (all channels zero) is the
subject's shape at the skeleton's rest frame (``rest="frame"``), or for a
person a T-pose or an A-pose (``rest="tpose"|"apose"``: every bone along a
standard direction, the motion re-expressed so that every joint's world
position is unchanged); the root's OFFSET is zero and its position channels
are absolute, which every BVH reader agrees on.

Names (:mod:`mocapskel.model.naming`): with ``names="auto"`` (the default) a
skeleton recognised as a person gets the humanoid names and is rooted at the
pelvis (``Hips``, between the hip joints, so that the bone to the spine is
visible); ``names="segments"`` keeps the segment names and the fitted root.
Re-rooting changes no joint's world position: every BVH joint is a joint of
the fitted tree (the root: a point fixed in the pelvis).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..artifacts import Motion
from ..errors import DataError
from ..solvers.bvh_pose import (BvhSkeleton, choose_rest_and_order, choose_rotation_order, global_to_local_rot,
                                bvh_rot_to_lab, lab_rot_to_bvh, lab_to_bvh, local_to_global_rot, rerest_local)
from ..model.tree import depth_first_order, tree_from
from ..model.kinematics import joint_points_rest
from ..model.naming import SCHEMES, Naming, name_skeleton
from ..solvers.rotations import ORDERS, rotation_between

VERSION = 6

UPS = ("y", "z")
UNITS = ("cm", "mm", "m")
RESTS = ("frame", "tpose", "apose")
NAMES = SCHEMES


@dataclass(frozen=True)
class Params:
    up: str = "y"
    units: str = "cm"
    order: str = "auto"
    """Rotation channel order of every joint; "auto": the order with the fewest Euler spikes
    (channel steps beyond the joint's turn plus 5 degrees), chosen with the rest frame (below), or
    for a given rest ZXY among equals unless some joint comes within 30 degrees of gimbal lock in
    it, then the order that keeps joints farthest from lock
    (:func:`~mocapskel.solvers.bvh_pose.choose_rotation_order`)."""
    names: str = "auto"
    rest: str = "frame"
    rest_frame: int | str = "auto"
    """With ``rest="frame"``, the frame whose pose is the rest pose: a frame number; "skeleton": the
    skeleton's own rest pose (``solve`` keeps one skeleton, and its OFFSETs, across takes); "auto":
    chosen with the order for the fewest Euler spikes
    (:func:`~mocapskel.solvers.bvh_pose.choose_rest_and_order`) among the frames where the whole
    subject is seen (:func:`rest_candidates`), the skeleton's rest frame preferred among equals."""


@dataclass(frozen=True, eq=False)
class BvhMotion:
    """Everything a BVH file holds, in BVH axes and units.

    root_pos : (F, 3); local_rot : (F, S, 3, 3) rotation of each joint relative to its parent.
    segment  : (S,) the skeleton segment of each BVH joint.
    naming   : how the joints were named (and why).
    rest     : the rest pose written ("frame", "tpose" or "apose").
    notes    : what the user should know (a rest pose asked for but not possible ...).
    rest_frame : the frame whose pose is the rest pose (None for a T-pose or A-pose rest; with
               ``Params.rest_frame="skeleton"`` the skeleton's, for ``solve`` a frame of the take it was fitted to).
    rest_rot : (S, 3, 3) lab axes: each joint's segment turned from the skeleton's rest pose to the
               BVH's (the identity where they are the same), e.g. a marker's offset in the BVH's rest
               is ``rest_rot @ Skeleton.marker_local``.
    """

    skeleton: BvhSkeleton
    root_pos: np.ndarray
    local_rot: np.ndarray
    frame_time: float
    segment: np.ndarray | None = None
    naming: Naming | None = None
    rest: str = "frame"
    notes: tuple[str, ...] = ()
    up: str = "y"
    units: str = "cm"
    rest_frame: int | None = None
    rest_rot: np.ndarray | None = None

    def report(self) -> dict:
        """The report's ``export`` entry."""
        out = {"names": self.naming.report() if self.naming else None, "rest": self.rest, "rest_frame": self.rest_frame,
               "root": self.skeleton.names[0], "notes": list(self.notes)}
        if self.naming is not None and self.segment is not None:
            out["joints"] = {self.skeleton.names[i]: int(s) for i, s in enumerate(self.segment.tolist())}
        return out


def _frame_of(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """Orthonormal columns (primary, secondary made perpendicular, their cross product)."""
    e1 = primary / np.linalg.norm(primary)
    e2 = secondary - np.dot(secondary, e1) * e1
    e2 /= np.linalg.norm(e2)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=1)


def rest_rotations(skel, new_parent: np.ndarray, r: np.ndarray, naming: Naming, rest: str) -> np.ndarray:
    """(S, 3, 3) rotation of each segment from the fitted rest pose to a T-pose or A-pose (lab axes, Z up).

    Every bone (a joint to the mean of its children's joints, a leaf to its
    End Site) is turned onto its standard direction by the smallest rotation:
    the trunk, neck and head up, the legs down, the feet and toes forward, the
    arms sideways (A-pose: 45 degrees down, the clavicles sideways). The pelvis
    is turned so that the line between the hips lies along lab +X (the
    subject's left) and its bone (to the spine) points up as far as it is
    perpendicular to that line, so that the subject faces lab -Y (BVH +Z with
    ``--up y``, the usual facing of a BVH character; Blender's front view
    with ``--up z``); the
    segment that carries the arms likewise with the line between the shoulders.
    """
    S = len(new_parent)
    names = naming.names
    up = np.array([0.0, 0.0, 1.0])
    hl, hr = (r[naming.hips_children[0]], r[naming.hips_children[1]])  # left hip, right hip
    left = np.array([1.0, 0.0, 0.0])  # the subject faces lab -Y: BVH +Z with --up y, Blender's front with --up z
    forward = np.cross(left, up)
    down45 = np.sqrt(0.5)
    kids: list[list[int]] = [[] for _ in range(S)]
    for s, q in enumerate(new_parent.tolist()):
        if q >= 0:
            kids[q].append(s)
    Q = np.empty((S, 3, 3))
    for s in range(S):
        if kids[s]:
            d = np.mean(r[kids[s]], axis=0) - r[s]
        else:
            d = np.asarray(skel.end_site[s], dtype=np.float64)
        n = names[s]
        side = 1.0 if n.startswith("Left") else -1.0 if n.startswith("Right") else 0.0
        base = n[4:] if n.startswith("Left") else n[5:] if n.startswith("Right") else n
        if n == "Hips":
            spine = [k for k in kids[s] if k not in naming.hips_children]
            d_up = (r[spine].mean(axis=0) if spine else r[s] + up) - r[s]
            Q[s] = _frame_of(left, up) @ _frame_of(hl - hr, d_up).T
            continue
        arms = [k for k in kids[s] if names[k].endswith(("Shoulder", "Arm")) and not names[k].endswith("ForeArm")]
        if side == 0.0 and len(arms) == 2 and np.linalg.norm(d) > 1e-9:
            # the segment carrying the arms: its bone up and the line between the shoulders sideways
            la, ra = sorted(arms, key=lambda k: not names[k].startswith("Left"))
            Q[s] = _frame_of(up, left) @ _frame_of(d, r[la] - r[ra]).T
            continue
        if base in ("UpLeg", "Leg"):
            t = -up
        elif base in ("Foot", "ToeBase"):
            t = forward
        elif base in ("Shoulder", "Arm", "ForeArm", "Hand"):
            t = side * left if (rest == "tpose" or base == "Shoulder") else side * down45 * left - down45 * up
        else:
            t = up
        Q[s] = rotation_between(d, t) if np.linalg.norm(d) > 1e-9 else np.eye(3)
    return Q


def rest_candidates(motion: Motion) -> np.ndarray:
    """Frames whose pose may be the rest pose: every segment seen (as many of its markers as the rigid
    stage asks of its rest frame: three, or all it has if fewer), or as many segments as any frame sees,
    and the frame's marker rms no outlier among those frames (within three robust standard deviations,
    1.4826 MAD, of their median: not a pose the fit got wrong, such as a limb flipped onto a marker
    that jumped). Empty when no marker residual is known."""
    res = np.asarray(motion.residual, dtype=np.float64)
    seg = np.asarray(motion.skeleton.marker_segment)
    S = len(motion.skeleton.parent)
    if res.ndim != 2 or res.shape[1] != seg.size or res.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    seen = np.isfinite(res)
    on = seg >= 0
    count = np.zeros((res.shape[0], S), dtype=np.int64)
    for s in range(S):
        count[:, s] = seen[:, on & (seg == s)].sum(1)
    need = np.minimum(3, np.bincount(seg[on], minlength=S))
    full = (count >= need).sum(1)
    ok = (full == full.max()) & seen.any(1)
    if not ok.any():
        return np.zeros(0, dtype=np.int64)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.nanmean(np.where(seen[ok], res[ok] ** 2, np.nan), axis=1))
    f = np.flatnonzero(ok)
    med = np.median(rms)
    return f[rms <= med + 3.0 * 1.4826 * np.median(np.abs(rms - med))]


def run(motion: Motion, params: Params = Params()) -> BvhMotion:
    if params.up not in UPS:
        raise ValueError(f"up must be one of {UPS}")
    if params.units not in UNITS:
        raise ValueError(f"units must be one of {UNITS}")
    if params.names not in NAMES:
        raise ValueError(f"names must be one of {NAMES}")
    if params.rest not in RESTS:
        raise ValueError(f"rest must be one of {RESTS}")
    if isinstance(params.rest_frame, str) and params.rest_frame not in ("auto", "skeleton"):
        raise ValueError("rest_frame must be a frame number, 'auto' or 'skeleton'")
    sk = motion.skeleton
    naming = name_skeleton(sk, motion, params.names)
    notes: list[str] = []
    if params.names == "humanoid" and not naming.humanoid:
        notes.append(f"--names humanoid: {naming.note}; generic names kept")
    rest = params.rest
    if rest != "frame" and not naming.humanoid:
        why = ("the humanoid names (not --names segments)" if params.names == "segments"
               else "a skeleton recognised as a person")
        notes.append(f"--rest {rest} needs {why}; the rest pose is the rest frame's")
        rest = "frame"
    old_parent = np.asarray(sk.parent)
    parent = tree_from(old_parent, naming.root) if naming.root != int(np.flatnonzero(old_parent < 0)[0]) else old_parent
    r = joint_points_rest(sk, parent, naming) if naming.humanoid else np.asarray(sk.origin, dtype=np.float64)
    rot = motion.rot
    root = naming.root
    # the root joint's world position: a point fixed in the root segment
    from ..model.kinematics import segment_origin

    if np.array_equal(parent, old_parent) and np.allclose(r[root], sk.origin[root]):
        root_world = motion.root_pos
    else:
        o = segment_origin(motion, root)
        root_world = o + np.einsum("fij,j->fi", rot[:, root], r[root] - sk.origin[root])
    offset_lab = r.copy()
    has = parent >= 0
    offset_lab[has] -= r[parent[has]]
    end_lab = np.asarray(sk.end_site, dtype=np.float64).copy()
    leaf = np.ones(len(parent), dtype=bool)
    leaf[parent[has]] = False
    was_leaf = np.ones(len(parent), dtype=bool)
    was_leaf[old_parent[old_parent >= 0]] = False
    end_lab[leaf & ~was_leaf] = 0.0  # a new leaf (re-rooting): the writer's default End Site
    if rest != "frame":
        Q = rest_rotations(sk, parent, r, naming, rest)
        offset_lab[has] = np.einsum("sij,sj->si", Q[parent[has]], offset_lab[has])
        end_lab = np.einsum("sij,sj->si", Q, end_lab)
        rot = np.einsum("fsij,skj->fsik", rot, Q)  # rot @ Q^T: the new rest is Q times the old
    perm = depth_first_order(parent)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    par = np.where(parent[perm] >= 0, inv[np.maximum(parent[perm], 0)], -1)
    offset = lab_to_bvh(offset_lab[perm], params.up, params.units)
    offset[par < 0] = 0.0
    end_site = lab_to_bvh(end_lab[perm], params.up, params.units)
    local = global_to_local_rot(par, lab_rot_to_bvh(rot, params.up, joints=perm))
    rest_rot = Q[perm] if rest != "frame" else np.broadcast_to(np.eye(3), (perm.size, 3, 3)).copy()
    order = params.order
    rest_frame = int(sk.rest_frame) if rest == "frame" else None
    if rest == "frame" and params.rest_frame != "skeleton":
        F = local.shape[0]
        if params.rest_frame == "auto":
            orders = ORDERS if order == "auto" else (order.upper(),)
            r, order = choose_rest_and_order(local, par, rest_candidates(motion), int(sk.rest_frame), orders)
        else:
            r = int(params.rest_frame)
            if not 0 <= r < F:
                raise DataError(f"rest frame {r} is outside the take's {F} frames — choose a frame from 0 to {F - 1}",
                                motion.source or None)
        if r != int(sk.rest_frame):
            # frame r's pose as the rest: every joint's rest turned by its global rotation at r
            Q = local_to_global_rot(par, local[r : r + 1])[0]
            local = rerest_local(par, local, Q)
            sub = par >= 0
            offset[sub] = np.einsum("sij,sj->si", Q[par[sub]], offset[sub])
            end_site = np.einsum("sij,sj->si", Q, end_site)
            rest_rot = bvh_rot_to_lab(Q, params.up)
        rest_frame = r
    bskel = BvhSkeleton(
        names=tuple(naming.names[i] for i in perm),
        parent=par,
        offset=offset,
        end_site=end_site,
        order=choose_rotation_order(local) if order == "auto" else order,
    )
    rate = motion.rate if motion.rate and motion.rate > 0 else 1.0
    return BvhMotion(bskel, lab_to_bvh(root_world, params.up, params.units), local, 1.0 / rate,
                     segment=perm, naming=naming, rest=rest, notes=tuple(notes),
                     up=params.up, units=params.units, rest_frame=rest_frame, rest_rot=rest_rot)


def joint_positions_lab(motion: Motion, bvh: BvhMotion) -> np.ndarray:
    """(F, S, 3) where each BVH joint of ``bvh`` should be (lab, mm), from ``motion`` alone.

    A joint is the fitted tree's joint between its segment and its parent's
    (:func:`mocapskel.model.kinematics.segment_origins` of the child of that edge);
    a humanoid root is the midpoint of the two hip joints. Independent of the
    BVH's offsets and rotations: what a reader of the file should find.
    """
    from ..model.kinematics import segment_origins

    O = segment_origins(motion)
    old = np.asarray(motion.skeleton.parent)
    seg = bvh.segment
    out = np.empty((O.shape[0], len(seg), 3))
    for i, s in enumerate(seg.tolist()):
        p = int(bvh.skeleton.parent[i])
        if p >= 0:
            q = int(seg[p])
            out[:, i] = O[:, s] if old[s] == q else O[:, q]
        elif bvh.naming is not None and bvh.naming.hips_children:
            hips = [O[:, c] if old[c] == s else O[:, s] for c in bvh.naming.hips_children]
            out[:, i] = 0.5 * (hips[0] + hips[1])
        else:
            out[:, i] = O[:, s]
    return out
