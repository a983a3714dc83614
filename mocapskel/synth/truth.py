"""Ground truth that comes with a generated take."""
from __future__ import annotations

import json
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
