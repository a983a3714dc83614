"""A fitted skeleton's rest pose: where its markers sit and how far apart, its bone lines, and its
like limbs."""
from __future__ import annotations

import numpy as np

from ..artifacts import Skeleton


def _rest_markers(skel: Skeleton) -> np.ndarray:
    """(M, 3) every marker's rest-pose position (NaN for markers on no segment or without an offset)."""
    seg = skel.marker_segment
    ok = (seg >= 0) & np.isfinite(skel.marker_local).all(1)
    pos = np.full(skel.marker_local.shape, np.nan)
    pos[ok] = skel.origin[seg[ok]] + skel.marker_local[ok]
    return pos


def _extent(pos: np.ndarray) -> float:
    """The largest distance between two of the markers ``pos`` (M, 3) (NaN rows left out); 0 for fewer than 2."""
    P = pos[np.isfinite(pos).all(1)]
    return float(np.sqrt(((P[:, None] - P[None]) ** 2).sum(-1)).max()) if len(P) > 1 else 0.0


def _bone_line(skel: Skeleton, s: int) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Segment ``s``'s joint, the unit direction to the mean of its child joints and that length;
    None for a root, a leaf or a zero length."""
    kids = np.flatnonzero(skel.parent == s)
    if skel.parent[s] < 0 or kids.size == 0:
        return None
    a = skel.origin[s]
    v = skel.origin[kids].mean(0) - a
    n = float(np.linalg.norm(v))
    return (a, v / n, n) if n > 0 else None


def _rest_groups(skel: Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The markers at rest (M, 3), each one's segment (-1 where unplaced) and each segment's count."""
    pos = _rest_markers(skel)
    seg = np.where(np.isfinite(pos).all(1), skel.marker_segment, -1)
    return pos, seg, np.bincount(seg[seg >= 0], minlength=len(skel.parent))


def _like_limb_pairs(parent: np.ndarray, count: np.ndarray) -> list[tuple[int, int, int]]:
    """(parent, a, b) for every two children of one segment that are like limbs: subtrees of the same
    shape, segment for segment as many markers (``count``), each of two segments or more (two legs,
    two arms; not a head and an arm). By parent, then in child order."""
    parent = np.asarray(parent)
    out = []
    for p in range(len(parent)):
        kids = [int(k) for k in np.flatnonzero(parent == p)]
        shape = {c: _subtree_shape(parent, count, c) for c in kids}
        out += [(p, a, b) for i, a in enumerate(kids) for b in kids[i + 1:] if shape[a] == shape[b] and shape[a][1]]
    return out


def _subtree_shape(parent: np.ndarray, count: np.ndarray, s: int) -> tuple:
    """A canonical form of the subtree below segment ``s``: its marker count and its children's
    forms, sorted."""
    return (int(count[s]), tuple(sorted(_subtree_shape(parent, count, int(k)) for k in np.flatnonzero(parent == s))))
