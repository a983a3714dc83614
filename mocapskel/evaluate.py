"""Compare a fit with the ground truth of a generated take (for tests and benchmarks)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .artifacts import Joints, Markers, Motion, Segments, Skeleton, Topology
from .synth.truth import Truth


@dataclass
class Score:
    """How a fit compares with the truth.

    segments_ok  : the marker groups equal the true segments (labels of ghosts aside).
    topology_ok  : the tree's edges equal the true joints.
    joint_rms_mm : rms over frames and joints of the joint-centre error (matched joints).
    joint_rms_each : per true joint child segment name -> rms error (mm).
    bone_err     : per true segment name -> relative bone-length error.
    """

    segments_ok: bool
    topology_ok: bool
    joint_rms_mm: float = float("nan")
    joint_rms_each: dict = field(default_factory=dict)
    bone_err: dict = field(default_factory=dict)
    rse: float = float("nan")

    @property
    def bone_err_max(self) -> float:
        v = [abs(x) for x in self.bone_err.values() if np.isfinite(x)]
        return max(v) if v else float("nan")


def segment_map(group: np.ndarray, truth: Truth) -> dict[int, int]:
    """Found segment -> true segment, by majority of its markers."""
    out = {}
    for g in np.unique(group[group >= 0]):
        t = truth.marker_segment[group == g]
        t = t[t >= 0]
        if t.size:
            out[int(g)] = int(np.bincount(t).argmax())
    return out


def score_joints(joints: Joints, truth: Truth, frames: slice | None = None) -> Score:
    topo = joints.topology
    group = topo.segments.group
    smap = segment_map(group, truth)
    seg_ok = len(set(smap.values())) == len(smap) == len(truth.segment_names)
    # labels (physical markers) must not mix segments
    for g in smap:
        t = truth.marker_segment[group == g]
        if np.any((t >= 0) & (t != smap[g])):
            seg_ok = False
    true_edges = {frozenset((int(truth.parent[c]), int(c))): e for e, c in enumerate(truth.joint_child)}
    found = [frozenset((smap.get(int(a), -1), smap.get(int(b), -2))) for a, b in topo.edges]
    topo_ok = set(found) == set(true_edges)
    errs, each = [], {}
    for e, key in enumerate(found):
        if key in true_edges:
            te = true_edges[key]
            d = joints.centres[:, e] - truth.joints[:, te]
            if frames is not None:
                d = d[frames]
            n = np.linalg.norm(d, axis=1)
            n = n[np.isfinite(n)]
            if n.size:
                each[truth.segment_names[truth.joint_child[te]]] = float(np.sqrt(np.mean(n**2)))
                errs.append(n)
    allerr = np.concatenate(errs) if errs else np.array([np.nan])
    rms = float(np.sqrt(np.mean(allerr**2)))
    # Hang's RSE: sqrt(sum r^2) / (M F)
    rse = float(np.sqrt(np.sum(allerr**2)) / max(1, allerr.size)) if errs else float("nan")
    return Score(seg_ok, topo_ok, rms, each, {}, rse)


def score_skeleton(skel: Skeleton, truth: Truth) -> Score:
    """Joint errors (from the joints artifact) and bone lengths of the rigid skeleton."""
    sc = score_joints(skel.joints, truth)
    smap = segment_map(skel.marker_segment, truth)
    for s, t in smap.items():
        n_joints = int((skel.parent == s).sum()) + int(skel.parent[s] >= 0)
        true_len = _true_segment_length(truth, t)
        # a bone length is defined for a segment between exactly two joints
        if n_joints == 2 and np.isfinite(true_len) and np.isfinite(skel.bone_length[s]):
            sc.bone_err[truth.segment_names[t]] = float(skel.bone_length[s] / true_len - 1.0)
    return sc


def score_motion(motion: Motion, truth: Truth, truth_labels: tuple[str, ...] | None = None) -> Score:
    """Like score_skeleton, with joint centres taken from the IK solution (the skeleton's joints).

    ``truth_labels``: the labels of the take the truth belongs to, when the
    skeleton was fitted on another take (``solve``); segments are then matched
    to the truth by label.
    """
    skel = motion.skeleton
    if truth_labels is None:
        sc = score_skeleton(skel, truth)
        smap = segment_map(skel.marker_segment, truth)
    else:
        where = {l: i for i, l in enumerate(truth_labels)}
        group = np.array([truth.marker_segment[where[l]] if l in where else -1 for l in skel.labels])
        smap = {}
        for s in range(len(skel.names)):
            t = group[skel.marker_segment == s]
            t = t[t >= 0]
            if t.size:
                smap[s] = int(np.bincount(t).argmax())
        sc = Score(len(set(smap.values())) == len(smap) == len(truth.segment_names), True)
    pos = joint_positions(motion)  # (F, S, 3) segment origins
    errs, each = [], {}
    for s, t in smap.items():
        if skel.parent[s] < 0:
            continue
        tp = smap.get(int(skel.parent[s]))
        # the origin of s is the joint between s and its parent
        for e, c in enumerate(truth.joint_child):
            if {int(c), int(truth.parent[c])} == {t, tp}:
                n = np.linalg.norm(pos[:, s] - truth.joints[:, e], axis=1)
                each[truth.segment_names[c]] = float(np.sqrt(np.mean(n**2)))
                errs.append(n)
    if errs:
        allerr = np.concatenate(errs)
        sc.joint_rms_mm = float(np.sqrt(np.mean(allerr**2)))
        sc.joint_rms_each = each
    return sc


def joint_positions(motion: Motion) -> np.ndarray:
    """(F, S, 3) world position of every segment origin (joint) from the IK solution."""
    from .model.kinematics import segment_origins

    return segment_origins(motion)


def _true_segment_length(truth: Truth, t: int) -> float:
    """Mean distance between the two joints of true segment t (NaN unless it has exactly two)."""
    js = [e for e, c in enumerate(truth.joint_child) if c == t or truth.parent[c] == t]
    if len(js) != 2:
        return float("nan")
    return float(np.nanmean(np.linalg.norm(truth.joints[:, js[0]] - truth.joints[:, js[1]], axis=1)))


def true_topology(truth: Truth, markers: Markers) -> Topology:
    """The true groups and tree of a generated take as a topology artifact, for the stages after it
    (the joints, rigid and IK stages measured with the grouping and the tree handed in). It carries the
    take's scales the segment stage would have measured (:func:`~mocapskel.stages.segment.take_levels`):
    without them the joints stage's distance penalty is zero and a joint the motion leaves free along a
    line runs off along it."""
    from .stages.segment import take_levels

    S = len(truth.segment_names)
    seg = Segments(markers=markers, group=np.asarray(truth.marker_segment), dist_std=np.zeros((0, 0)),
                   eigvals=np.zeros(0), info=take_levels(markers))
    edges = np.stack([truth.parent[truth.joint_child], truth.joint_child], axis=1)
    return Topology(segments=seg, edges=edges, cost=np.zeros(len(edges)), pair_cost=np.full((S, S), np.inf), root=0)
