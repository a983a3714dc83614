"""Like limbs' first joints moved together into their parent segment's plane of symmetry, where the
markers hardly see the step."""
from __future__ import annotations

import numpy as np

from ...artifacts import Skeleton
from ..joint_moves import _move_joint, _pose_ms, _with_moves
from ...model.tree import like_subtrees
from ..rest_pose import _rest_groups


#: A segment's markers are symmetric about a plane when each, reflected in it, lies within this
#: fraction of the distance between the two limbs' joints from one of them.
MIRROR_MATCH = 0.25

#: A step is taken when it raises the mean squared marker residual (poses solved again) by at most
#: this fraction of its own square: the markers hardly see it. Measured: hips the markers fix,
#: 0.0044-0.0094 (generated range-of-motion subjects, three and two markers a segment); hips that
#: slid, 0.00013-0.00054 (a real jump, generated walks and a kick); the bar sits a factor 2-4 from each.
MIRROR_SEEN = 0.002


def _symmetry_normal(points: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, float]:
    """The normal of the plane through the centroid of ``points`` (n, 3) that best mirrors them onto
    themselves, among ``guess`` and the directions between two of them (a mirror pair's direction is
    the plane's normal); and how far the worst reflected point lands from the nearest point."""
    cen = points.mean(0)
    cand = [guess] + [points[j] - points[i] for i in range(len(points)) for j in range(i + 1, len(points))]
    best, miss = guess, np.inf
    for c in cand:
        norm = float(np.linalg.norm(c))
        if not norm > 0:
            continue
        m = _mirror_miss(points, cen, c / norm)
        if m < miss:
            best, miss = c / norm, m
    return best, miss


def _mirror_miss(points: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> float:
    """How far the worst of ``points`` (n, 3), reflected in the plane through ``centre`` normal to the
    unit ``normal``, lands from the nearest of them (0 for a set symmetric about that plane)."""
    refl = points - 2.0 * ((points - centre) @ normal)[:, None] * normal
    return float(np.linalg.norm(refl[:, None] - points[None], axis=2).min(1).max())


def centre_mirrored_pairs(skel: Skeleton, seen: float = MIRROR_SEEN, match: float = MIRROR_MATCH) -> Skeleton:
    """Like limbs on one segment: their first joints moved together into the segment's plane of
    symmetry (:func:`mirror_shifts`), where the markers hardly see the step. Each limb keeps its
    markers where they were, and the root's origin stays the mean of its children's joints.

    The steps under one segment are kept when they raise the mean squared marker residual on the
    refinement's frames (poses solved again from the refinement's) by at most ``seen`` times the
    square of the step: a slide along what the markers do not fix is put back; a joint they fix is
    not moved. (The rise itself does not tell: a free fit slides joints into skin motion, and putting
    them back raised the rms by 8 % on a real jump whose hips came 90 mm nearer the reference, 9-14 %
    on generated walks, 24 % where a generated range-of-motion subject's fixed hips would have
    moved 18 mm; per squared step the two differ tenfold.)"""
    if skel.pose_rot is None or skel.pose_frames is None:
        return skel
    shifts = mirror_shifts(skel, match, loose_joints(skel))
    if not shifts:
        return skel
    parent = np.asarray(skel.parent)
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    base = _pose_ms(skel, origin, local, pts)
    kept: dict[int, np.ndarray] = {}
    for p in sorted({int(parent[c]) for c in shifts}):
        group = {c: d for c, d in shifts.items() if parent[c] == p}
        o2, l2 = origin, local
        for c, d in group.items():
            o2, l2 = _move_joint(o2, l2, skel.marker_segment, c, d)
        step2 = max(float(d @ d) for d in group.values())
        if _pose_ms(skel, o2, l2, pts) - base <= seen * step2:
            origin, local = o2, l2
            kept.update(group)
    if not kept:
        return skel
    moved = {skel.names[c]: round(float(np.linalg.norm(d)), 1) for c, d in kept.items()}
    return _with_moves(skel, origin, local, set(kept), "mirrored", moved)


def loose_joints(skel: Skeleton) -> set[int]:
    """Child segments whose joint the markers may leave free along some direction: all but those SCoRE
    fixed in full (3+ markers on both segments, motion not hinge-like)."""
    edges = skel.joints.topology.edges
    return {int(b) for e, (_, b) in enumerate(edges) if skel.joints.method[e] != "score"}


def mirror_shifts(skel, match: float = MIRROR_MATCH, loose: set | None = None) -> dict[int, np.ndarray]:
    """{child segment: step (3,)} that puts the first joints of like limbs in their parent's plane of symmetry.

    A body is mirror-symmetric: two legs hang from the pelvis, two arms from the thorax, at mirror
    places about its middle plane. When both legs move alike (a two-footed jump, a squat) or about
    one axis (a walk), the markers fix neither hip along the line between them, and the fit can
    slide both together at almost no cost: a real jump's hips came out 90-100 mm to one side, one
    beside the other side of the pelvis. For two children of one segment with subtrees of the same
    shape, segment for segment as many markers, each of two segments or more (two legs of thigh,
    shank and foot; not a head and an arm, nor the two ends of a chain held by its middle), when the
    parent's markers are symmetric about a plane through their centroid (each, reflected in it,
    within ``match`` times the joints' distance of another: :func:`_symmetry_normal`) that lies
    across the line between the two joints (at most 60 degrees from its normal) with one limb's
    markers on either side, both joints get the same step along its normal, the one that puts
    their midpoint in the plane. The distance between them, which the markers fix, is kept. Another
    child of that parent whose own markers mirror onto themselves in that plane (a trunk's midline
    markers on a pelvis) has its joint moved along the normal into it. A parent whose markers are not
    symmetric (a thorax with a marker on one shoulder blade) says nothing. The limbs' own markers are
    not compared: marker sets place them asymmetrically on purpose (a thigh marker higher on one side).

    Only joints the markers may leave free are candidates: both of the pair in ``loose`` (child
    segments; None: any; see :func:`loose_joints`). Where the markers fix a joint (a range-of-motion
    take's hips) they know better than the symmetry of a body, whose markers are never placed exactly
    mirror-wise (a generated subject's hips, well fixed, were moved 18 mm off and its shoulders 43 mm);
    :func:`centre_mirrored_pairs` also asks the markers.

    skel : anything with ``origin``, ``marker_local``, ``marker_segment`` and ``parent`` (rest pose).
    """
    origin = skel.origin
    out: dict[int, np.ndarray] = {}
    for kids, cen, n, _ in mirror_planes(skel, match, loose):
        mid = origin[list(kids)].mean(0)
        d = float((cen - mid) @ n) * n
        for c in kids:
            out[c] = d.copy()
    return out


def mirror_planes(skel, match: float = MIRROR_MATCH, loose: set | None = None
                  ) -> list[tuple[tuple[int, ...], np.ndarray, np.ndarray, float]]:
    """[(children, centre, unit normal, miss)]: the first joints of like limbs (two children), or a child on the middle
    line (one), whose mean lies in their parent's plane of symmetry, the plane through ``centre`` (the parent's
    marker centroid at rest) normal to ``normal``, its markers reflected in it landing up to ``miss`` (mm) from one of
    them (see :func:`mirror_shifts` for when a plane is found)."""
    pos, seg, count = _rest_groups(skel)
    parent = np.asarray(skel.parent)
    origin = skel.origin
    out: list[tuple[tuple[int, ...], np.ndarray, np.ndarray, float]] = []
    done: set[int] = set()
    for p, a, b in like_subtrees(parent, count):
        mk = pos[seg == p]
        if len(mk) < 2 or a in done or b in done:
            continue
        if loose is not None and not {a, b} <= loose:
            continue  # the markers fix one of them
        v = origin[b] - origin[a]
        sep = float(np.linalg.norm(v))
        if not sep > 0 or count[a] == 0:  # (like shapes: as many markers on b)
            continue
        cen = mk.mean(0)
        n, miss = _symmetry_normal(mk, v / sep)
        if miss > match * sep or abs(float(n @ v)) < 0.5 * sep:
            continue  # no plane of symmetry, or not one across the line between the two joints
        sides = [float((pos[seg == c].mean(0) - cen) @ n) for c in (a, b)]
        if not sides[0] * sides[1] < 0:
            continue  # not one limb on either side
        out.append(((a, b), cen, n, miss))
        done |= {a, b}
        # a child on the middle line (a trunk on the pelvis: its markers mirror onto themselves
        # in the same plane) has its joint in the plane too
        for c in (int(k) for k in np.flatnonzero(parent == p)):
            own = pos[seg == c]
            if c in done or not len(own) or loose is not None and c not in loose:
                continue
            if _mirror_miss(own, cen, n) <= match * sep:
                out.append(((c,), cen, n, miss))
                done.add(c)
    return out
