"""Tests of a fitted skeleton's joints: off the body, on too long a bone, slid from where they were,
like limbs' joints slid together or their bones unlike (what the refinement keeps and holds by)."""
from __future__ import annotations

import numpy as np

from ...artifacts import Skeleton
from ...model.tree import like_limb_pairs, like_subtrees, unlike_bones
from ..rest_pose import _extent, _rest_groups, _rest_markers
from ..hull import beyond_hull


def far_joints(skel: Skeleton, far: float) -> list[int]:
    """Segments whose joint to their parent sits implausibly far from its markers, in the rest pose.

    Far: farther than ``far`` times the subject's marker extent (the largest distance between two
    markers at rest) from the nearest marker of the parent or of the child segment.
    """
    pos = _rest_markers(skel)
    ok = np.isfinite(pos).all(1)
    if ok.sum() < 2:
        return []
    lim = far * _extent(pos)
    out = []
    for c in np.flatnonzero(skel.parent >= 0):
        for s_ in (int(skel.parent[c]), int(c)):
            m = pos[ok & (skel.marker_segment == s_)]
            if len(m) and float(np.linalg.norm(m - skel.origin[c], axis=1).min()) > lim:
                out.append(int(c))
                break
    return out


def outside_joints(skel: Skeleton, frac: float) -> list[int]:
    """Segments whose joint to their parent sits outside the convex hull of all markers at rest by more
    than ``frac`` times the marker extent (the largest distance between two markers at rest)."""
    pos = _rest_markers(skel)
    kids = np.flatnonzero(skel.parent >= 0)
    out = beyond_hull(pos, skel.origin[kids])
    lim = frac * _extent(pos)
    return [int(c) for c, d in zip(kids, out) if d > lim]


def off_the_body(skel: Skeleton, far: float, outside: float) -> list[int]:
    """Segments whose joint to their parent is off the body: :func:`far_joints` or :func:`outside_joints`."""
    return sorted(set(far_joints(skel, far)) | set(outside_joints(skel, outside)))


#: Like limbs' first joints nearer each other than this fraction of the distance between the two limbs'
#: first segments' marker centroids at rest have slid together. Measured: fitted hips sit at 0.44-0.53 of
#: it (a real jump, a real walk, a generated range-of-motion subject), shoulders at 0.66; a real jump's
#: hips slid together, 0.04, and one of its starts, 0.24.
COLLAPSED = 0.3


def collapsed_pairs(skel: Skeleton, frac: float = COLLAPSED) -> list[int]:
    """Like limbs (two children of one segment whose subtrees have the same shape, segment for segment
    as many markers, each of two segments or more: two legs, two arms) whose joints sit nearer each
    other than ``frac`` times the distance between the two limbs' first segments' marker centroids at
    rest. Legs that move alike (a two-footed jump) do not fix their hips along the line between them,
    and a fit can slide both to the middle of the pelvis: no body has two hips at one point."""
    pos, seg, count = _rest_groups(skel)
    out: set[int] = set()
    for _, a, b in like_subtrees(skel.parent, count):
        if count[a] == 0:
            continue
        ca, cb = pos[seg == a].mean(0), pos[seg == b].mean(0)
        if float(np.linalg.norm(skel.origin[a] - skel.origin[b])) < frac * float(np.linalg.norm(ca - cb)):
            out |= {a, b}
    return sorted(out)


def unlike_limb_bones(skel: Skeleton, tol: float = 0.2) -> int:
    """How many bones of like limbs (two children of one segment that are chains of as many segments, two or
    more: two legs, two arms) differ by more than ``tol`` of the shorter, compared segment for segment down the
    chains (the ``limb_asymmetry`` check's rule, on the tree's shape alone)."""
    return len(unlike_bones(skel, [(a, b) for a, b, _ in like_limb_pairs(np.asarray(skel.parent))], tol))


def implausible_joints(skel: Skeleton, far: float, outside: float) -> list[int]:
    """Segments whose joint to their parent no body has: :func:`off_the_body`, or a bone (the joint's
    distance from the parent's joint) longer than the subject's marker extent at rest (the
    ``bone_length`` check's rule)."""
    lim = _extent(_rest_markers(skel))
    long = [int(c) for c in np.flatnonzero(skel.parent >= 0)
            if float(np.linalg.norm(skel.origin[c] - skel.origin[skel.parent[c]])) > lim]
    return sorted(set(off_the_body(skel, far, outside)) | set(long))


def slid_joints(before: Skeleton, after: Skeleton, slide: float) -> list[int]:
    """Segments whose joint to their parent moved, relative to the markers of the parent or of the child,
    by more than ``slide`` times the subject's marker extent between two fits (rest-pose axes)."""
    lim = slide * _extent(_rest_markers(before))
    out = []
    for c in np.flatnonzero(before.parent >= 0):
        p = int(before.parent[c])
        for s_, own in ((p, False), (int(c), True)):
            m = (before.marker_segment == s_) & np.isfinite(before.marker_local).all(1) & np.isfinite(after.marker_local).all(1)
            if not m.any():
                continue
            # the joint relative to the segment's marker centroid: -mean(l) in the child, d_c - mean(l) in the parent
            rel = [(sk.origin[c] - sk.origin[p] if not own else 0.0) - sk.marker_local[m].mean(0) for sk in (before, after)]
            if float(np.linalg.norm(rel[1] - rel[0])) > lim:
                out.append(int(c))
                break
    return out
