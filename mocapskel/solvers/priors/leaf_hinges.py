"""Hinges at the end of a limb (an ankle) moved along their axis to the mean position of the end
segment's markers."""
from __future__ import annotations

import numpy as np

from ...artifacts import Skeleton
from ..joints.hinges import _hinge_axes, _hinge_direction, _relative_rotations, _relative_rotvecs
from ..joint_moves import _move_joint, _pose_ms, _with_moves
from ..rest_pose import _bone_line, _rest_markers
from ..rotations import segments_seen


#: The end of a limb is a short segment: its markers' centroid at most this fraction of its parent's
#: bone length from the joint (a foot's heel, toe and metatarsal markers: 0.15-0.3 of the shank; a
#: forearm carrying its markers at the wrist, a head band on a neck: 0.5 and more).
LEAF_SHORT = 0.5
#: ...and its markers lie across the hinge axis from the joint: their centroid's step along the axis at
#: most this fraction of its distance (45 degrees; feet whose centre sat at the ankle marker: 0.3-0.6;
#: two-marker toe and heel-toe groups that turn about an axis along them: 0.8-1.0).
LEAF_ACROSS = 0.7
#: ...and its motion is not exercised in every direction: the spread of its relative rotations about
#: the third axis at most this fraction of that about the second (walks', runs' and kicks' ankles,
#: generated and real, turn mostly about the flexion axis and one other: 0.30-0.79; a generated
#: range-of-motion take's ankles, turned alike every way across the flexion axis, 0.91-0.96: there
#: the motion fixes the centre (the takes' joints 3-6 mm rms from the truth), and the foot's markers
#: sit anywhere on it).
LEAF_PLANAR = 0.85


def centre_leaf_hinges(skel: Skeleton, hinge_ratio: float, seen: float | None = None) -> Skeleton:
    """Hinges at the end of a limb get their centre, along the axis, at the mean position of the child's
    markers.

    Along a hinge's axis the markers hardly fix its centre. The joints stage puts it at the point of
    the axis nearest the centroid of both segments' markers, and a limb's end is where that goes wrong:
    an axis tilted by a few degrees carries the parent's markers far up the limb tens of millimetres
    along it (a real walk's ankle, under a shank cluster, came out 46 mm medial), and markers on one
    side (a malleolus and a lateral shank marker) pull it outward (generated kicks' and walks' ankles
    sat at the ankle marker, 30-44 mm lateral). The child's markers, when they lie nearer the joint
    than the parent's (a foot's heel, toe and metatarsal markers around the ankle; not a forearm whose
    markers are at the wrist), surround the end segment's middle, which lies under the joint centre.
    For a leaf segment with two or more markers whose parent is not the root, whose relative rotations
    turn about one axis (a hinge the refinement held, or a spread about the second axis at most
    ``hinge_ratio`` of the first) and not exercised in every direction (``LEAF_PLANAR``), short beside its parent (``LEAF_SHORT``) and with its markers across
    the axis from the joint (``LEAF_ACROSS``), the centre is moved along that axis to the mean axial
    position of the child's markers, unless a marker of the parent over the axis (nearer it than half the child's
    markers' distance from the centre) shows the centre already lies farther from that skin marker
    than from the child's middle (inside the limb, where the fit put it), and unless the markers see
    the move: it is made only when it raises the mean squared marker residual on the refinement's
    frames (poses solved again) by at most ``seen`` (mm^2; None: the square of the take's own level of
    skin motion and noise, measured by the segment stage). Moved so, the ankles of generated walks,
    runs and kicks raised it by 0.004-0.1 of that, a real walk's 0.9; the left wrist of a generated
    range-of-motion take, whose markers sit anywhere on the hand and whose motion fixes it better,
    would have moved 105 mm (12 times it). Each segment keeps its markers where they
    were; the move is along the axis the joint turns about, so the poses still fit.
    """
    if skel.pose_rot is None or skel.pose_frames is None:
        return skel
    if seen is None:
        level = skel.joints.topology.segments.info.get("skin_level_mm")
        if not level or not np.isfinite(level):
            return skel
        seen = float(level) ** 2
    R = skel.pose_rot
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    vis = segments_seen(skel.marker_segment, len(skel.names), pts)
    base = None
    pos = _rest_markers(skel)
    ok_m = np.isfinite(pos).all(1)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    held = None
    moved = {}
    for c in np.flatnonzero(skel.parent >= 0):
        p = int(skel.parent[c])
        if skel.parent[p] < 0 or (skel.parent == c).any():
            continue  # on the root (not the end of a limb), or not a leaf
        mk = np.flatnonzero(ok_m & (skel.marker_segment == c))
        mp = np.flatnonzero(ok_m & (skel.marker_segment == p))
        if mk.size < 2 or mp.size == 0:
            continue
        J = origin[c]
        dc = float(np.linalg.norm(pos[mk].mean(0) - J))
        if not dc < float(np.linalg.norm(pos[mp].mean(0) - J)):
            continue  # the child's markers are no nearer the joint than the parent's
        rel = _relative_rotations(R, p, int(c), vis)
        if rel is None:
            continue
        if held is None:
            held = _hinge_axes(skel, R, hinge_ratio, vis)
        rv = _relative_rotvecs(rel)
        ax = held.get(int(c))
        if ax is None:
            ax = _hinge_direction(rel, hinge_ratio, rv=rv)
        if ax is None:
            continue
        sv = np.linalg.svd(rv, compute_uv=False)
        if not sv[1] > 0 or sv[2] > LEAF_PLANAR * sv[1]:
            continue  # it turns alike about every axis across the main one: exercised in every direction
        shift = float(np.mean((pos[mk] - J) @ ax))
        line = _bone_line(skel, p)
        if line is None or dc > LEAF_SHORT * line[2] or abs(shift) > LEAF_ACROSS * dc:
            continue  # not a short end segment whose markers lie across the axis from the joint
        t = (pos[mp] - J) @ ax
        off = np.linalg.norm(pos[mp] - J - t[:, None] * ax, axis=1)
        over = np.flatnonzero(off <= 0.5 * dc)
        if over.size and abs(float(t[over[np.argmin(off[over])]])) >= abs(shift):
            continue  # already inside the limb: farther from its skin marker than from the child's middle
        o2, l2 = _move_joint(origin, local, skel.marker_segment, c, shift * ax)
        if base is None:
            base = _pose_ms(skel, origin, local, pts)
        ms = _pose_ms(skel, o2, l2, pts)
        if ms - base > seen:
            continue  # the markers see the move: they fix the centre along the axis
        base = ms
        origin, local = o2, l2
        moved[skel.names[c]] = round(abs(shift), 1)
    if not moved:
        return skel
    # ends of limbs: none is a child of the root, whose origin stays
    return _with_moves(skel, origin, local, set(), "leaf_centred", moved)
