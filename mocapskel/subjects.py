"""Several subjects in one take: which markers belong to which, found from the data alone.

Run between merge-ids and segment (see :func:`mocapskel.pipeline.fit`). The
markers of one articulated subject are linked by near neighbours: every marker
stays close to some other marker of its subject (on its segment or the next)
in every frame. Markers of two subjects never move together: the nearest pair
across them is far apart compared with those links.

Method: the largest distance over a sample of frames of every pair of markers
(``d_max``, mm; pairs never seen together are not linked), single-linkage
clustering on it, and the tree cut at a gap: between two consecutive merge
heights of which the higher is :data:`GAP_RATIO` times the lower — a gap
between groups, not a long bone, and free of the subjects' scale — provided
every group carries :data:`MIN_MARKERS` markers and every two groups move
relative to each other (their cross distances vary by more than
:data:`MOVE_MM`: a rigid object in two marker clusters stays one). Of several
such cuts, the one at the largest ratio. A group whose own markers all keep their distances
is a rigid object (a box, a prop), not a subject: it goes with the subject nearest to it. Frames
are sampled and the pairwise distances computed in blocks, so memory stays
small for hundreds of labels.
"""
from __future__ import annotations

import numpy as np

from .artifacts import Markers
from .model.measures import visible

__all__ = ["GAP_RATIO", "MIN_MARKERS", "MOVE_MM", "split_subjects", "subset"]

#: A merge this many times higher than every merge inside the groups it joins separates two subjects.
GAP_RATIO = 3.0
#: Markers a group needs to be a subject of its own (a skeleton needs at least two segments).
MIN_MARKERS = 4
#: Cross distances of two subjects vary by more than this (std, mm).
MOVE_MM = 10.0
#: Frames looked at (spread over the take).
SAMPLE_FRAMES = 400
#: Subjects one take may hold.
MAX_SUBJECTS = 20
_BLOCK = 4_000_000  # distances per block (frames x pairs)


def _pair_stats(points: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, M) largest distance and (M, M) distance std over ``frames`` (NaN where never seen together).

    Distances from the Gram matrix of every frame (one batched product), in blocks of frames.
    """
    M = points.shape[1]
    dmax = np.full((M, M), -np.inf)
    s1 = np.zeros((M, M))
    s2 = np.zeros((M, M))
    n = np.zeros((M, M))
    step = max(1, _BLOCK // max(M * M, 1))
    for lo in range(0, frames.size, step):
        P = points[frames[lo:lo + step]]  # (f, M, 3), NaN where unseen
        sq = (P**2).sum(axis=-1)  # (f, M)
        d2 = sq[:, :, None] + sq[:, None, :] - 2.0 * (P @ P.transpose(0, 2, 1))
        d = np.sqrt(np.maximum(d2, 0.0))  # NaN stays NaN: a pair with an unseen marker
        ok = np.isfinite(d)
        dz = np.where(ok, d, 0.0)
        dmax = np.maximum(dmax, np.where(ok, d, -np.inf).max(axis=0))
        s1 += dz.sum(axis=0)
        s2 += (dz**2).sum(axis=0)
        n += ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / n
        std = np.sqrt(np.maximum(s2 / n - mean**2, 0.0))
    dmax[n == 0] = np.nan
    std[n == 0] = np.nan
    np.fill_diagonal(dmax, 0.0)
    np.fill_diagonal(std, 0.0)
    return dmax, std


def split_subjects(markers: Markers) -> list[np.ndarray] | None:
    """The markers of each subject (index arrays, in marker order, ordered by their first marker), or None for one.

    Parameters
    ----------
    markers : Markers
        The take after merge-ids: points (F, M, 3) mm, NaN for gaps.
    """
    pts = markers.points
    F, M = pts.shape[:2]
    if M < 2 * MIN_MARKERS or F < 2:
        return None
    seen = visible(pts)
    frames = np.flatnonzero(seen.any(axis=1))
    if frames.size > SAMPLE_FRAMES:
        frames = frames[np.unique(np.linspace(0, frames.size - 1, SAMPLE_FRAMES).round().astype(int))]
    dmax, dstd = _pair_stats(pts, frames)
    # markers never seen are left with the first subject (the stages after leave them out)
    used = np.flatnonzero(np.isfinite(dmax).sum(axis=1) > 1)
    if used.size < 2 * MIN_MARKERS:
        return None
    D = dmax[np.ix_(used, used)]
    big = np.nanmax(D) * 10.0 + 1.0
    D = np.where(np.isfinite(D), D, big)  # never seen together: not linked
    edges = single_linkage(D)
    h = edges[:, 2]  # merge heights, ascending
    best = None
    # a cut between two consecutive merge heights leaves len(h) - k + 1 groups; try the cuts at a gap
    for k in range(len(h) - 1, max(0, len(h) - MAX_SUBJECTS), -1):
        if not (h[k] < big and h[k] > GAP_RATIO * max(h[k - 1], 1e-9)):
            continue
        lab = _components(used.size, edges[:k])
        parts = [np.flatnonzero(lab == c) for c in np.unique(lab)]
        if min(p.size for p in parts) < MIN_MARKERS:
            continue
        moving = all(
            np.isfinite(c := dstd[np.ix_(used[parts[i]], used[parts[j]])]).any() and np.nanmedian(c) > MOVE_MM
            for i in range(len(parts)) for j in range(i + 1, len(parts))
        )
        if moving and (best is None or h[k] / h[k - 1] > best[0]):
            best = (h[k] / h[k - 1], parts)
    if best is None:
        return None
    parts = best[1]
    # a group whose markers all keep their distances is one rigid object (a box, a prop), not a subject:
    # it goes with the subject nearest to it (the stages after leave it out if nothing ties it to that one)
    art = [_articulated(dstd[np.ix_(used[p], used[p])]) for p in parts]
    moving = [p for p, a in zip(parts, art) if a]
    if len(moving) < 2:
        return None
    joined = [[p] for p in moving]
    for p, a in zip(parts, art):
        if not a:
            near = [np.nanmin(d) if np.isfinite(d := dmax[np.ix_(used[p], used[q])]).any() else np.inf for q in moving]
            joined[int(np.argmin(near))].append(p)
    parts = [np.concatenate(j) for j in joined]
    groups = [np.sort(used[p]) for p in parts]
    groups.sort(key=lambda g: int(g[0]))
    rest = np.setdiff1d(np.arange(M), used)
    if rest.size:
        groups[0] = np.sort(np.concatenate([groups[0], rest]))
    return groups


def _articulated(std: np.ndarray) -> bool:
    """Whether a group's markers move against each other (a subject) rather than as one rigid object: some of
    their distances (the top 5 %) vary by more than :data:`MOVE_MM` (std)."""
    v = std[~np.eye(std.shape[0], dtype=bool)]
    v = v[np.isfinite(v)]
    return bool(v.size) and float(np.percentile(v, 95)) > MOVE_MM


def single_linkage(D: np.ndarray) -> np.ndarray:
    """The merges of single-linkage clustering of a symmetric distance matrix (M, M): the edges of its
    minimum spanning tree as rows (i, j, height), ascending by height.

    The same heights as ``scipy.cluster.hierarchy.linkage(..., method="single")`` (the tests compare
    them), from the topology's Kruskal tree, without importing scipy's clustering (a fifth of a
    second per run, more than the clustering of a hundred markers takes).
    """
    from .stages.topology import minimum_spanning_tree

    D = np.asarray(D, dtype=float)
    tree = minimum_spanning_tree(D.shape[0], D) if D.shape[0] > 1 else None
    if tree is None:
        return np.zeros((0, 3))
    return np.column_stack([tree, D[tree[:, 0], tree[:, 1]]])  # Kruskal takes them by increasing height


def _components(M: int, edges: np.ndarray) -> np.ndarray:
    """Cluster labels (M,) of the points joined by ``edges`` (rows (i, j, ...))."""
    lab = np.arange(M)
    for i, j in edges[:, :2].astype(int):
        a, b = lab[i], lab[j]
        if a != b:
            lab[lab == b] = a
    return lab


def subset(markers: Markers, idx: np.ndarray, index: int, of: int) -> Markers:
    """The take restricted to one subject's markers; ``info["subject"]`` says which."""
    from dataclasses import replace

    info = dict(markers.info)
    info["subject"] = {"index": index, "of": of, "markers": [markers.labels[i] for i in idx]}
    return replace(markers, points=markers.points[:, idx], labels=tuple(markers.labels[i] for i in idx), info=info)
