"""Hinges between two limbs with a marker over their axis (a knee) moved along it to one limb
half-width inside that marker."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...artifacts import Skeleton
from ..joints.hinges import _hinge_direction, _relative_rotations
from ..joint_moves import _move_joint, _with_moves
from ..rest_pose import _bone_line, _rest_markers
from ..rotations import segments_seen


def _limb_radius(skel: Skeleton, s: int, pos: np.ndarray, skip: set) -> float | None:
    """Median distance of segment ``s``'s markers (but ``skip``) from its bone line (its joint to the
    mean of its child joints), over markers along its middle 70 %; None for a root or a leaf."""
    line = _bone_line(skel, s)
    if line is None:
        return None
    a, u, n = line
    r = []
    for m in np.flatnonzero(skel.marker_segment == s):
        if m in skip or not np.isfinite(pos[m]).all():
            continue
        v = pos[m] - a
        t = float(v @ u)
        if 0.15 * n < t < 0.85 * n:
            r.append(float(np.linalg.norm(v - t * u)))
    return float(np.median(r)) if r else None


#: A limb's half-width is at most this fraction of its length (adult thigh, shank, upper arm and
#: forearm: 0.10-0.15).
LIMB_WIDTH = 0.2


def _half_width(skel: Skeleton, origin: np.ndarray, c: int, point: np.ndarray, pos: np.ndarray,
                skip: set) -> tuple[float, float] | None:
    """(half-width, length) of the limbs on either side of segment ``c``'s joint put at ``point``
    (``origin`` the skeleton's rest origins otherwise): the mean of :func:`_limb_radius` of the parent
    and of ``c`` (markers ``skip`` left out), and the shorter of their bone lengths. None when one of
    them gives none, or the half-width is more than ``LIMB_WIDTH`` of the length (no limb has it). Each
    limb's may rest on one marker, and the two may differ by more than a factor of 2 (a thigh marker on
    the muscle, a shin marker on the bone); their mean is the joint's."""
    lv = origin.copy()
    lv[c] = point
    at = replace(skel, origin=lv)
    p = int(skel.parent[c])
    radii = [r for s_ in (p, c) if (r := _limb_radius(at, s_, pos, skip)) is not None]
    if len(radii) < 2:
        return None
    r = float(np.mean(radii))
    length = min(line[2] for s_ in (p, c) if (line := _bone_line(at, s_)) is not None)
    return None if r > LIMB_WIDTH * length else (r, length)


def _inward(skel: Skeleton, p: int, m: int, ax: np.ndarray, at_rest: float) -> float:
    """+1 or -1: the way along the hinge axis ``ax`` (in segment ``p``'s frame, the lab's at rest) from marker
    ``m`` towards the subject's middle (the mean of the markers seen), as most of the refinement's frames
    have it (``at_rest``, that projection at rest, where there are none): one pose, such as a leg lifted and
    turned out in a range of motion's rest frame, can put the body's middle on the marker's side."""
    v = np.array([at_rest])
    if skel.pose_frames is not None and skel.pose_rot is not None:
        pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
        seen = np.isfinite(pts).all(-1)
        n = seen.sum(1)
        mid = np.where(seen[..., None], pts, 0.0).sum(1) / np.maximum(n, 1)[:, None]
        a = skel.pose_rot[:, p] @ ax  # the axis in the lab, frame by frame
        ok = seen[:, m] & (n > 1) & np.isfinite(a).all(1)
        if ok.any():
            v = np.einsum("fi,fi->f", mid[ok] - pts[ok, m], a[ok])
    return float(np.sign(np.median(v))) or 1.0


def deepen_joints(skel: Skeleton, hinge_ratio: float, like: list[tuple[int, int]] | None = None) -> Skeleton:
    """Hinges between two limbs with a marker over their axis get their centre one limb half-width
    inside that marker.

    A knee marker sits on the skin over the flexion axis; the joint centre lies on that axis, about
    half the joint's width deeper. Along the axis the markers hardly fix the centre (the fit leaves it
    near the marker, or slides it past). For a joint whose relative rotations (the refinement's poses)
    turn about one axis (spread about the second axis at most ``hinge_ratio`` of the first, their part
    about the child's bone line left out: a limb segment of one or two markers hardly fixes its own
    twist) and a marker of its two segments within one limb half-width of that axis and, along it,
    within a quarter of the shorter limb's length (or one and a half half-widths, if more) of the
    centre, the centre is moved along the axis, away from the marker towards the subject's middle (as
    most of the refinement's frames have it: :func:`_inward`), to one limb half-width from it. The
    half-width is the mean of the median distances of the two limbs' other markers from their bone
    lines, drawn through the axis at the level of that marker; both limbs must give one (a leaf, such
    as a foot or a forearm that carries the hand's markers, has no bone line: ankles deepened by the shank's half-width alone came out
    from 25 mm nearer to 51 mm farther from the truth on generated kicks and walks). A second marker
    on the axis (both nearer it than a quarter of their distance apart), one to three half-widths
    along it from the first (a medial and a lateral knee marker), puts it between the two, wherever
    the fit left it. Each segment keeps its markers where they were; the move is along the axis the
    joint turns about, so the poses still fit. With ``like`` (pairs of like limbs'
    segments, :func:`~mocapskel.solvers.model.joint_map.like_bone_pairs`), two like joints that both measure a
    half-width use the mean of the two (:func:`like_half_widths`).
    """
    return _deepen(skel, hinge_ratio, like_half_widths(skel, hinge_ratio, like) if like else {})[0]


def like_half_widths(skel: Skeleton, hinge_ratio: float, like: list[tuple[int, int]]) -> dict[int, float]:
    """{joint (its child segment): the mean of its own and its like joint's half-widths}, for the pairs ``like``
    of like segments whose joints both measure one in :func:`deepen_joints` (as it measures them without this
    pooling). A person's left and right knees are as wide as each other, while one limb's measure can rest on a
    single marker, whose distance from a bone line the start's joints slant: two measures of one width."""
    width = _deepen(skel, hinge_ratio, {})[1]
    out = {}
    for x, y in like:
        if x in width and y in width:
            out[x] = out[y] = 0.5 * (width[x] + width[y])
    return out


def _deepen(skel: Skeleton, hinge_ratio: float, widths: dict[int, float]) -> tuple[Skeleton, dict[int, float]]:
    """:func:`deepen_joints`, a joint of ``widths`` at that half-width instead of its own; also {joint: its own
    half-width} where it measured one."""
    R = skel.pose_rot
    vis = None if skel.pose_frames is None else segments_seen(
        skel.marker_segment, len(skel.names), skel.joints.topology.segments.markers.points[skel.pose_frames])
    pos = _rest_markers(skel)
    ok_m = np.isfinite(pos).all(1)
    if ok_m.sum() < 3:
        return skel, {}
    centre = pos[ok_m].mean(0)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    moved, measured = {}, {}
    for c in np.flatnonzero(skel.parent >= 0):
        p = int(skel.parent[c])
        if skel.parent[p] < 0 or not (skel.parent == c).any():
            continue  # the root or a leaf on one side: one limb to measure a half-width on
        rel = _relative_rotations(R, p, int(c), vis)
        if rel is None:
            continue
        J = origin[c]
        near = [int(m) for m in np.flatnonzero(ok_m & np.isin(skel.marker_segment, [p, c]))]
        if not near:
            continue
        # the axis, and the bone lines the half-widths are measured from, through the axis at the level
        # of the marker nearest it: a centre the fit slid along the axis, past that marker, would tilt
        # them. Twice: the child's twist is left out about its bone line through that level.
        level = origin.copy()
        for _ in range(2):
            at = replace(skel, origin=level)
            line = _bone_line(at, int(c))
            ax = _hinge_direction(rel, hinge_ratio, None if line is None else line[1])
            if ax is None:
                break
            t = {m: float((pos[m] - J) @ ax) for m in near}
            off = {m: float(np.linalg.norm(pos[m] - J - t[m] * ax)) for m in near}
            over = sorted(near, key=lambda m: off[m])
            level = origin.copy()
            level[c] = J + t[over[0]] * ax
        if ax is None:
            continue

        # a second marker on the axis (nearer it than a quarter of their distance apart) a joint's width
        # from the first (one to three half-widths, measured at either marker's level): a medial and
        # a lateral knee marker. The centre goes between them, wherever the fit left it along the axis
        m0, pair = over[0], None
        for m1 in over[1:]:
            gap = abs(t[m1] - t[m0])
            if max(off[m0], off[m1]) > 0.25 * gap:
                continue
            got = (_half_width(skel, origin, c, J + t[m0] * ax, pos, {m0, m1})
                   or _half_width(skel, origin, c, J + t[m1] * ax, pos, {m0, m1}))
            if got is not None and got[0] <= gap <= 3.0 * got[0]:
                pair = m1
                break
        if pair is not None:
            shift = 0.5 * (t[m0] + t[pair])
        else:
            got = _half_width(skel, origin, c, J + t[m0] * ax, pos, {m0})
            if got is None:
                continue
            r, length = got
            measured[int(c)] = r
            r = widths.get(int(c), r)
            # over the joint: on the axis, and along it within a limb's reach (where along it the fit
            # put the centre, the markers hardly said)
            on = [m for m in over if off[m] <= r and abs(t[m]) <= max(1.5 * r, 0.25 * length)]
            if not on:
                continue
            m = on[0]
            inward = _inward(skel, p, m, ax, float((centre - pos[m]) @ ax))
            shift = t[m] + inward * r
        origin, local = _move_joint(origin, local, skel.marker_segment, c, shift * ax)
        moved[skel.names[c]] = round(float(abs(shift)), 1)
    if not moved:
        return skel, measured
    # hinges between two limbs: none is a child of the root, whose origin stays
    return _with_moves(skel, origin, local, set(), "deepened", moved), measured
