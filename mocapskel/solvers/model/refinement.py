"""The frames the refinement of a fitted skeleton and its poses fits: the best seen of equal stretches of the
take, fewer for large skeletons and short takes."""
from __future__ import annotations

import numpy as np

from ...artifacts import Skeleton
from ...model.measures import visible


#: Segments up to which the refinement uses ``Params.refine_frames`` frames; beyond, fewer (see below).
REFINE_FULL_SEGMENTS = 15


#: A short take gives the refinement at most one frame in this many (its frames are close and
#: alike; a real take of a few seconds spent most of its fit here).
REFINE_STRIDE = 4


#: Markers up to which the refinement uses all its frames; beyond, fewer (see below).
REFINE_FULL_MARKERS = 48


def pick_frames(visible: np.ndarray, n: int, must: int | None = None) -> np.ndarray:
    """``n`` frames spread over the take, each the best-seen of its stretch.

    visible : (F, M) bool. The take is cut into ``n`` equal stretches and the
    frame seeing the most markers is taken from each (the first on ties);
    ``must`` is added if given. Sorted, unique.
    """
    F = visible.shape[0]
    n = max(1, min(n, F))
    edges = np.linspace(0, F, n + 1).round().astype(int)
    count = visible.sum(1)
    starts = edges[:-1]
    # argmax within each stretch: reduceat gives the maxima, then the first frame reaching it
    mx = np.maximum.reduceat(count, starts)
    stretch = np.repeat(np.arange(n), np.diff(edges))
    hit = count == mx[stretch]
    first = np.full(n, -1)
    idx = np.flatnonzero(hit)
    first[stretch[idx][::-1]] = idx[::-1]
    out = first[first >= 0]
    if must is not None:
        out = np.append(out, int(must))
    return np.unique(out)


def refine_frame_count(frames: int, n_segments: int, take_frames: int | None = None, n_markers: int | None = None,
                       stride: int = REFINE_STRIDE) -> int:
    """Frames for the refinement of a skeleton of ``n_segments``: ``frames`` up to 15 segments, then
    fewer as (15 / S)^2, at least 100 (or ``frames`` if that is less); likewise as (48 / M)^2 above
    48 markers; and at most a quarter of a take of ``take_frames`` (at least 100).

    An iteration costs about S^3 per frame (a segment's pose couples with every other's through
    the constant offsets), and M^2 (every marker's offset couples with every other's through the
    poses): this keeps a skeleton of 27 segments (a marker set with many markers on joints, split
    into rigid groups), or of 73 markers (clusters and anatomical markers), at the cost of one of
    15 segments and 48 markers. Each frame then holds more markers to fit.
    """
    if take_frames is not None:
        frames = min(frames, max(100, take_frames // stride))
    out = frames
    if n_segments > REFINE_FULL_SEGMENTS:
        out = min(out, max(100, int(frames * (REFINE_FULL_SEGMENTS / n_segments) ** 2)))
    if n_markers is not None and n_markers > REFINE_FULL_MARKERS:
        out = min(out, max(100, int(frames * (REFINE_FULL_MARKERS / n_markers) ** 2)))
    return min(out, frames)


def refinement_frames(skel: Skeleton, frames: int, stride: int = REFINE_STRIDE) -> np.ndarray:
    """The frames a refinement of ``skel`` fits (:func:`pick_frames`, as many as
    :func:`refine_frame_count` allows for ``frames`` and ``stride``), its rest frame among them."""
    pts = skel.joints.topology.segments.markers.points
    return pick_frames(visible(pts), refine_frame_count(frames, len(skel.names), pts.shape[0],
                                                        int((skel.marker_segment >= 0).sum()), stride), must=skel.rest_frame)
