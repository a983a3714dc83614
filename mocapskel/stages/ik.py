"""IK: per-frame segment rotations and root translation that best fit the markers.

Started from per-segment Horn/Kabsch fits of markers and joint centres
(gaps bridged by slerping the joints' rotations), then refined jointly for
the whole skeleton by a batched Gauss–Newton over all frames at once.
Segments with 1–2 markers are held by their joints; gaps are filled by the
skeleton. Where nothing of a limb is seen (no marker on it or below it), its
joints keep their angles, slerped across the stretch or held at the take's
ends (:func:`~mocapskel.solvers.rotations.hold_unobserved`): the limb moves
with the body instead of staying fixed in the lab.

When some segment carries fewer than 3 markers, its rotation about the line
of its markers is fixed only through its joints, and a start from the joints
stage's centres (tens of mm off for such segments) leads IK to the wrong
twist in many frames. Such a skeleton's refined poses (the rigid stage's
``pose_frames``) are then the start instead: IK is solved coarse to fine in
time from them (:func:`~mocapskel.solvers.ik.track.track`), each frame
started and held by the slerp of the joints' rotations of the frames already
solved around it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..artifacts import Motion, Skeleton, markers_of
from ..solvers.ik.motion import MAX_STEP_DEG, TOL, _centres_by_edges, solve

VERSION = 8


@dataclass(frozen=True)
class Params:
    iterations: int = 10
    use_joint_centres: bool = True
    """Start from Kabsch fits that include the estimated joint centres."""
    tol: float = TOL
    """A frame stops iterating once its pose is estimated to be within this (mm) of the
    solution (``solve_ik``'s ``tol``): joints end within a few hundredths of a millimetre
    of the fully converged solution, in 2-3 iterations from the Kabsch start."""
    track_below: int = 3
    """Skeletons with a segment of fewer markers than this are solved from the
    rigid stage's refined poses, coarse to fine in time (when it has them); 0: never."""
    max_step_deg: float = MAX_STEP_DEG
    """Stretches of up to 0.5 s that a segment spends between two turns of more than this
    (deg) in one frame are solved again from its rotation slerped across them, and take
    the new poses where they fit as well (:func:`~mocapskel.solvers.ik.unflip.unflip`); 0: never."""


def run(skel: Skeleton, params: Params = Params()) -> Motion:
    """Solve every frame of the take the skeleton was fitted on."""
    mk = markers_of(skel)
    centres = skel.joints.centres if (params.use_joint_centres and skel.joints is not None) else None
    # joint centres are per tree edge in the joints artifact's edge order; map to child segments
    if centres is not None:
        centres = _centres_by_edges(skel, centres)
    key = None
    counts = np.bincount(skel.marker_segment[skel.marker_segment >= 0], minlength=len(skel.names))
    if skel.pose_frames is not None and (counts < params.track_below).any():
        key = (skel.pose_frames, skel.pose_rot, skel.pose_root)
    return solve(skel, mk.points, centres, iterations=params.iterations, rate=mk.rate, source=mk.source, tol=params.tol,
                 key_poses=key, max_step_deg=params.max_step_deg, version=VERSION)
