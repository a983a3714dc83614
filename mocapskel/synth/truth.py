"""Ground truth that comes with a generated take."""
from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..artifacts import Markers


@dataclass(frozen=True, eq=False)
class Truth:
    """What a generated take really is.

    segment_names : S names.
    parent        : (S,) int, parent segment, -1 for the root segment.
    marker_segment: (M,) int, segment of each *label* of the take (-1: ghost).
    marker_id     : (M,) int, physical marker behind each label (-1: ghost);
                    equal to arange(M) when nothing was relabelled.
    joint_child   : (E,) int, child segment of each joint (its parent is parent[child]).
    joints        : (F, E, 3) true joint-centre trajectories, mm.
    bone_length   : (E,) for each joint's child segment, the distance from that
                    joint to the child's next joint (NaN for leaf segments).
    info          : free JSON-able notes (kind, seed, corruption settings).
    """

    segment_names: tuple[str, ...]
    parent: np.ndarray
    marker_segment: np.ndarray
    marker_id: np.ndarray
    joint_child: np.ndarray
    joints: np.ndarray
    bone_length: np.ndarray
    info: dict = field(default_factory=dict)

    def save(self, path) -> None:
        """Write as .npz (arrays) with the names and info as JSON strings."""
        np.savez(
            path,
            segment_names=np.array(self.segment_names, dtype=str),
            parent=self.parent,
            marker_segment=self.marker_segment,
            marker_id=self.marker_id,
            joint_child=self.joint_child,
            joints=self.joints,
            bone_length=self.bone_length,
            info=np.array(json.dumps(self.info)),
        )

    @classmethod
    def load(cls, path) -> "Truth":
        with np.load(path, allow_pickle=False) as z:
            return cls(
                segment_names=tuple(str(s) for s in z["segment_names"]),
                parent=z["parent"],
                marker_segment=z["marker_segment"],
                marker_id=z["marker_id"],
                joint_child=z["joint_child"],
                joints=z["joints"],
                bone_length=z["bone_length"],
                info=json.loads(str(z["info"])),
            )


@dataclass(frozen=True, eq=False)
class SynthTake:
    """A generated take (as mocapskel would read it from a file) and its truth."""

    markers: Markers
    truth: Truth


def restrict_truth(truth: Truth, keep: Sequence[int]) -> Truth:
    """The truth of a take whose markers sit on ``keep`` segments only (a subtree holding the root).

    Segments are renumbered in their old order; joints between kept segments
    stay, with their bone lengths recomputed over the kept tree."""
    keep = sorted(int(s) for s in keep)
    new = {s: i for i, s in enumerate(keep)}
    if truth.parent[keep[0]] != -1 or any(truth.parent[s] not in new for s in keep[1:]):
        raise ValueError("the kept segments must form a subtree holding the root")
    parent = np.array([-1 if truth.parent[s] < 0 else new[int(truth.parent[s])] for s in keep])
    cols = [e for e, c in enumerate(truth.joint_child) if int(c) in new]
    joint_child = np.array([new[int(truth.joint_child[e])] for e in cols], dtype=int)
    joints = truth.joints[:, cols]
    bone = np.full(len(cols), np.nan)
    for k, e in enumerate(cols):
        c = new[int(truth.joint_child[e])]
        kid_cols = [i for i, cc in enumerate(joint_child) if parent[cc] == c]
        if kid_cols:
            bone[k] = float(np.mean(np.linalg.norm(joints[:, kid_cols].mean(1) - joints[:, k], axis=-1)))
    ms = np.array([new[int(s)] if s >= 0 else -1 for s in truth.marker_segment])
    info = dict(truth.info)
    info["joint_names"] = [truth.info["joint_names"][e] for e in cols] if "joint_names" in truth.info else None
    if "rest_joints_mm" in info:
        info["rest_joints_mm"] = [truth.info["rest_joints_mm"][e] for e in cols]
    for key in ("hinges", "ball_joints"):
        if key in info:
            info[key] = [j for j in info[key] if j in info["joint_names"]]
    return Truth(segment_names=tuple(truth.segment_names[s] for s in keep), parent=parent, marker_segment=ms,
                 marker_id=truth.marker_id.copy(), joint_child=joint_child, joints=joints, bone_length=bone, info=info)
