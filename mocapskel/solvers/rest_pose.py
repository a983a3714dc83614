"""A fitted skeleton's rest pose: where its markers sit and how far apart, and its bone lines."""
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


