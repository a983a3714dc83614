"""Marker-ID merging, Kirk's clustering: pose distance between tracks, spectral clustering with repulsion.

Notation as in :mod:`mocapskel.solvers.merging.pairs` (``F`` frames, ``T`` tracks).

- :func:`pose_distance` — Kirk's distance: the smallest distance between the
  two markers over pairs of frames after rigid alignment of the markers both
  frames share (sampled at an interval, then refined around the best pairs).
- :func:`repulsion_spectral` — spectral clustering with attraction and
  repulsion (Yu & Shi 2001): labels ever seen together repel.

Kernels know no pipeline and do no I/O; the stage
:mod:`mocapskel.stages.merge_ids` puts them together.
"""
from __future__ import annotations

import numpy as np

from ..rigid import kabsch

__all__ = [
    "time_gaps",
    "pose_distance",
    "repulsion_spectral",
]


# --------------------------------------------------------------------------- distances between tracks


def time_gaps(vis: np.ndarray) -> np.ndarray:
    """Frames between two tracks: the smallest ``|f - g|`` with one seen at ``f``, the other at ``g``.

    Parameters
    ----------
    vis : (F, T) bool ndarray

    Returns
    -------
    (T, T) int ndarray; 0 where two tracks are seen in one frame, ``F`` for a track never seen.
    """
    F, T = vis.shape
    ar = np.arange(F)[:, None]
    before = np.where(vis, ar, -(2 * F))
    np.maximum.accumulate(before, axis=0, out=before)
    after = np.where(vis, ar, 3 * F)
    after = np.minimum.accumulate(after[::-1], axis=0)[::-1]
    dist = np.minimum(ar - before, after - ar)  # (F, T): frames to the nearest sample of each track
    out = np.full((T, T), F, dtype=np.int64)
    for j in range(T):
        if vis[:, j].any():
            out[j] = dist[vis[:, j]].min(axis=0)
    return np.minimum(out, out.T)


def pose_distance(
    points: np.ndarray,
    vis: np.ndarray,
    pairs: np.ndarray,
    *,
    samples: int = 16,
    refine: int = 4,
    top: int = 3,
    radius_mm: float = 300.0,
    min_shared: int = 4,
) -> np.ndarray:
    """Kirk's distance between tracks in matching poses.

    For tracks ``i`` and ``j`` (never seen together), frames of each are
    sampled at a constant interval; for every pair of sampled frames
    ``(a, b)`` the markers seen in both frames are rigidly aligned from ``b``
    to ``a`` (Kabsch, weighted by a Gaussian of their distance from ``i`` at
    ``a`` with width ``radius_mm``, so that the alignment is local), and the
    score is ``sqrt(|m_i(a) - A m_j(b)|^2 + rms^2)`` — the marker distance
    and how well the poses match. The ``top`` best sample pairs are refined
    over every frame pair within ``refine`` sampling steps (at the sampling
    interval's finest division); the distance is the smallest score.

    Parameters
    ----------
    points : (F, T, 3) ndarray, NaN where unseen.
    vis : (F, T) bool ndarray.
    pairs : (N, 2) int, the track pairs.
    samples, refine, top, radius_mm, min_shared : see above.

    Returns
    -------
    (N,) ndarray, mm; inf where no frame pair shares ``min_shared`` markers.
    """
    F, T = vis.shape
    out = np.full(len(pairs), np.inf)
    for k, (i, j) in enumerate(np.asarray(pairs, dtype=int)):
        fi, fj = np.flatnonzero(vis[:, i]), np.flatnonzero(vis[:, j])
        if fi.size == 0 or fj.size == 0:
            continue
        si = fi[np.unique(np.linspace(0, fi.size - 1, min(samples, fi.size)).round().astype(int))]
        sj = fj[np.unique(np.linspace(0, fj.size - 1, min(samples, fj.size)).round().astype(int))]
        a, b = np.repeat(si, sj.size), np.tile(sj, si.size)
        sc = _pose_scores(points, vis, i, j, a, b, radius_mm, min_shared)
        if not np.isfinite(sc).any():
            continue
        best = np.argsort(sc)[:top]
        step_i = max(1, fi.size // max(si.size, 1))
        step_j = max(1, fj.size // max(sj.size, 1))
        fine_i = max(1, step_i // refine)
        fine_j = max(1, step_j // refine)
        ra, rb = [], []
        for q in best:
            if not np.isfinite(sc[q]):
                continue
            ca = a[q] + fine_i * np.arange(-refine, refine + 1)
            cb = b[q] + fine_j * np.arange(-refine, refine + 1)
            ca = ca[(ca >= 0) & (ca < F)]
            cb = cb[(cb >= 0) & (cb < F)]
            ca = ca[vis[ca, i]]
            cb = cb[vis[cb, j]]
            ra.append(np.repeat(ca, cb.size))
            rb.append(np.tile(cb, ca.size))
        if ra:
            sc2 = _pose_scores(points, vis, i, j, np.concatenate(ra), np.concatenate(rb), radius_mm, min_shared)
            out[k] = float(min(np.nanmin(np.where(np.isfinite(sc), sc, np.inf)), np.min(np.where(np.isfinite(sc2), sc2, np.inf))))
        else:
            out[k] = float(np.nanmin(sc))
    return out


def _pose_scores(
    points: np.ndarray, vis: np.ndarray, i: int, j: int, a: np.ndarray, b: np.ndarray, radius_mm: float, min_shared: int
) -> np.ndarray:
    """Scores of frame pairs (a, b) (see :func:`pose_distance`)."""
    both = vis[a] & vis[b]
    both[:, [i, j]] = False
    cols = np.flatnonzero(both.any(0))
    if cols.size < 3:
        return np.full(a.size, np.inf)
    A = np.where(both[:, cols, None], points[a][:, cols], np.nan)
    B = np.where(both[:, cols, None], points[b][:, cols], np.nan)
    pi = points[a, i]
    with np.errstate(invalid="ignore"):
        r2 = ((A - pi[:, None, :]) ** 2).sum(-1)
    w = np.where(both[:, cols], np.exp(-0.5 * np.nan_to_num(r2, nan=0.0) / radius_mm**2), 0.0)
    R, t, rms = kabsch(B, A, w)
    pj = np.einsum("nij,nj->ni", R, points[b, j]) + t
    d = np.linalg.norm(pj - pi, axis=1)
    sc = np.sqrt(d**2 + rms**2)
    n_sh = both[:, cols].sum(1)
    return np.where((n_sh >= min_shared) & np.isfinite(sc), sc, np.inf)


# --------------------------------------------------------------------------- clustering with repulsion


def repulsion_spectral(
    A: np.ndarray, R: np.ndarray, k: int, *, rng: np.random.Generator, n_init: int = 8
) -> np.ndarray:
    """Spectral clustering with attraction and repulsion (Yu & Shi 2001).

    Solves the generalised eigenproblem ``(A - R + D_R) v = λ (D_A + D_R) v``
    (``D_X`` the degree matrix of ``X``), takes the ``k`` leading
    eigenvectors, normalises the rows and groups them by k-means.

    Parameters
    ----------
    A : (N, N) ndarray, symmetric non-negative attraction (a positive diagonal
        lets an item stand alone).
    R : (N, N) ndarray, symmetric non-negative repulsion (zero diagonal).
    k : number of clusters.
    rng : random generator (k-means seeding).

    Returns
    -------
    (N,) int cluster of every item, 0..k-1 (numbered by first appearance).
    """
    N = A.shape[0]
    k = int(max(1, min(k, N)))
    if k == 1 or N <= 1:
        return np.zeros(N, dtype=int)
    dA, dR = A.sum(1), R.sum(1)
    W = A - R + np.diag(dR)
    D = np.diag(np.maximum(dA + dR, 1e-12))
    from scipy import linalg

    vals, vecs = linalg.eigh(W, D)
    X = vecs[:, np.argsort(vals)[::-1][:k]]
    X = X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)
    best, best_in = None, np.inf
    for _ in range(n_init):
        lab, inertia = _kmeans(X, k, rng)
        if inertia < best_in - 1e-12:
            best, best_in = lab, inertia
    _, first = np.unique(best, return_index=True)
    remap = np.full(best.max() + 1, -1)
    remap[best[np.sort(first)]] = np.arange(first.size)
    return remap[best]


def _kmeans(X: np.ndarray, k: int, rng: np.random.Generator, iters: int = 50) -> tuple[np.ndarray, float]:
    """k-means with k-means++ seeding on the rows of X (N, d). Returns (labels, inertia)."""
    N = X.shape[0]
    cent = np.empty((k, X.shape[1]))
    cent[0] = X[rng.integers(N)]
    d2 = ((X - cent[0]) ** 2).sum(1)
    for c in range(1, k):
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(N, 1.0 / N)
        cent[c] = X[rng.choice(N, p=p)]
        d2 = np.minimum(d2, ((X - cent[c]) ** 2).sum(1))
    lab = np.full(N, -1)
    for _ in range(iters):
        dist = ((X[:, None, :] - cent[None]) ** 2).sum(2)
        new = dist.argmin(1)
        if np.array_equal(new, lab):
            break
        lab = new
        for c in range(k):
            sel = lab == c
            if sel.any():
                cent[c] = X[sel].mean(0)
    inertia = float(((X - cent[lab]) ** 2).sum())
    return lab, inertia
