"""Like limbs' parent's plane of symmetry: where the model's mirror factor puts the mean of their first joints."""
from __future__ import annotations

import numpy as np

from ...model.tree import like_subtrees
from ..rest_pose import _rest_groups


#: A segment's markers are symmetric about a plane when each, reflected in it, lies within this
#: fraction of the distance between the two limbs' joints from one of them.
MIRROR_MATCH = 0.25


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


def mirror_planes(skel, match: float = MIRROR_MATCH, loose: set | None = None
                  ) -> list[tuple[tuple[int, ...], np.ndarray, np.ndarray, float]]:
    """[(children, centre, unit normal, miss)]: the first joints of like limbs (two children), or a child on the middle
    line (one), whose mean lies in their parent's plane of symmetry, the plane through ``centre`` (the parent's
    marker centroid at rest) normal to ``normal``, its markers reflected in it landing up to ``miss`` (mm) from one of
    them.

    A body is mirror-symmetric: two legs hang from the pelvis, two arms from the thorax, at mirror places about its
    middle plane. When both legs move alike (a two-footed jump, a squat) or about one axis (a walk), the markers fix
    neither hip along the line between them (a real jump's free fit put its hips 90-100 mm to one side). For two
    children of one segment with subtrees of the same shape, segment for segment as many markers, each of two
    segments or more (two legs of thigh, shank and foot; not a head and an arm, nor the two ends of a chain held by
    its middle), a plane is found when the parent's markers are symmetric about a plane through their centroid
    (each, reflected in it, within ``match`` times the joints' distance of another: :func:`_symmetry_normal`) that
    lies across the line between the two joints (at most 60 degrees from its normal) with one limb's markers on
    either side. Another child of that parent whose own markers mirror onto themselves in that plane (a trunk's
    midline markers on a pelvis) lies in it too. A parent whose markers are not symmetric (a thorax with a marker on
    one shoulder blade) says nothing; the limbs' own markers are not compared (marker sets place them asymmetrically
    on purpose). ``loose``: only children of it (None: any).

    skel : anything with ``origin``, ``marker_local``, ``marker_segment`` and ``parent`` (rest pose).
    """
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
