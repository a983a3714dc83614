"""Marker-ID merging, the evidence: robust pairwise label distances over shared frames, and rigid partners.

A passive system gives a marker a new label whenever it loses it, and adds
ghost points. The merging kernels (this module, :mod:`~mocapskel.solvers.merging.jumps`,
:mod:`~mocapskel.solvers.merging.links` and :mod:`~mocapskel.solvers.merging.cluster`)
decide which labels are one physical marker.
Notation: ``F`` frames, ``L`` labels, ``T`` tracks (groups of labels that are
believed to be one marker; at first one per label).

The evidence is rigidity. Two labels on one rigid body keep their distance;
a label's *partners* are the labels whose distance to it varies by no more
than ``rigid_mm`` (std) over the frames they share.

- :func:`pair_sums` — robust sums of every pairwise distance over the frames
  two labels share (median/MAD, then trimmed means, so that jumping samples
  do not hide a rigid pair), vectorised over frames through a compact
  "visible labels of each frame" table (:func:`compact_visible`); tracks
  aggregate them exactly (:func:`track_sums`); :func:`partners_of`.

Kernels know no pipeline and do no I/O; the stage
:mod:`mocapskel.stages.merge_ids` puts them together.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "PairSums",
    "compact_visible",
    "pair_sums",
    "pair_stats",
    "track_sums",
    "partners_of",
]

#: Entries (frame, label pair) held at once when pairwise distances are gathered.
_CHUNK_ENTRIES = 4_000_000


# --------------------------------------------------------------------------- visible-label table


def compact_visible(vis: np.ndarray) -> np.ndarray:
    """The visible labels of every frame, as a compact table.

    Parameters
    ----------
    vis : (G, L) bool ndarray

    Returns
    -------
    idx : (G, K) int ndarray
        The indices of the labels visible in each frame, ascending, padded
        with -1; ``K`` is the most labels visible in one frame (at least 1).
    """
    vis = np.asarray(vis, dtype=bool)
    G, L = vis.shape
    K = max(1, int(vis.sum(1).max()) if G else 1)
    order = np.argsort(~vis, axis=1, kind="stable")[:, :K]
    ok = np.take_along_axis(vis, order, axis=1)
    return np.where(ok, order, -1)


def _pairwise(pos: np.ndarray, iu0: np.ndarray, iu1: np.ndarray) -> np.ndarray:
    """Distances (G, N) between points ``iu0`` and ``iu1`` of every frame of pos (G, K, 3) (float32)."""
    p = pos.astype(np.float32)
    d2 = np.zeros((p.shape[0], iu0.size), dtype=np.float32)
    for x in range(3):
        c = p[:, :, x]
        diff = c[:, iu0] - c[:, iu1]
        d2 += diff * diff
    return np.sqrt(d2)


def _frame_chunks(n: int, per_frame: int) -> list[slice]:
    step = max(1, _CHUNK_ENTRIES // max(per_frame, 1))
    return [slice(s, min(n, s + step)) for s in range(0, n, step)]


# --------------------------------------------------------------------------- pairwise distance statistics


@dataclass(frozen=True)
class PairSums:
    """Sums over shared frames of every pairwise distance (symmetric, zero diagonal).

    n  : (L, L) number of (sampled) frames in which both labels are seen and
         the distance was kept (not trimmed as an outlier).
    s1 : (L, L) sum of the kept distances (mm).
    s2 : (L, L) sum of their squares (mm^2).
    shared : (L, L) number of sampled frames both are seen (kept or not).
    stride : frame sampling interval used.
    """

    n: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    shared: np.ndarray
    stride: int

    def stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (L, L) of the distances; NaN where fewer than 2 frames are shared."""
        return pair_stats(self.n, self.s1, self.s2)


def pair_stats(n: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std from count, sum and sum of squares (NaN where ``n < 2``)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / n
        var = np.maximum(s2 / n - mean**2, 0.0) * n / np.maximum(n - 1, 1)
    ok = n >= 2
    return np.where(ok, mean, np.nan), np.where(ok, np.sqrt(var), np.nan)


def pair_sums(
    points: np.ndarray,
    vis: np.ndarray,
    *,
    max_entries: int = 3_000_000,
    passes: int = 3,
    k_sigma: float = 3.0,
    band_mm: float = 6.0,
) -> PairSums:
    """Robust sums of every pairwise label distance over the frames both are seen.

    Frames are sampled at a constant stride so that at most ``max_entries``
    (frame, pair) distances are held. The first pass keeps, for every pair,
    the distances within ``max(k_sigma * s, band_mm)`` of their median
    (``s`` = 1.4826 MAD); each later pass those within
    ``max(k_sigma * std, band_mm)`` of the previous pass's mean, so that
    jumping samples — even a third of a short overlap — do not make a rigid
    pair look loose.

    Parameters
    ----------
    points : (F, L, 3) ndarray, mm, NaN where unseen.
    vis : (F, L) bool ndarray, True where seen.
    max_entries : int
    passes : int
    k_sigma, band_mm : float
        Trimming band (see above).

    Returns
    -------
    PairSums
    """
    F, L = vis.shape
    if F == 0 or L == 0:
        z = np.zeros((L, L))
        return PairSums(z, z.copy(), z.copy(), z.copy(), 1)
    K = max(1, int(vis.sum(1).max()))
    per = K * (K - 1) // 2
    stride = max(1, int(np.ceil(F * per / max(max_entries, 1))))
    frames = np.arange(0, F, stride)
    idx = compact_visible(vis[frames])
    iu0, iu1 = np.triu_indices(idx.shape[1], 1)
    ds, keys = [], []
    for sl in _frame_chunks(frames.size, idx.shape[1] ** 2):
        fr = frames[sl]
        ix = idx[sl]
        a, b = ix[:, iu0], ix[:, iu1]
        ok = (a >= 0) & (b >= 0)
        d = _pairwise(points[fr[:, None], np.maximum(ix, 0)], iu0, iu1)
        ds.append(d[ok])
        keys.append((a[ok].astype(np.int64) * L + b[ok]))
    d = np.concatenate(ds) if ds else np.zeros(0, np.float32)
    key = np.concatenate(keys) if keys else np.zeros(0, np.int64)
    d64 = d.astype(np.float64)
    shared = np.bincount(key, minlength=L * L).astype(float)
    # first centre and spread: median and MAD of every pair (a third of
    # jumping samples does not move them), then trimmed means
    centre, spread = _median_mad(key, d64, L * L)
    keep = np.abs(d64 - centre[key]) <= np.maximum(k_sigma * spread, band_mm)[key]
    for p in range(max(1, passes - 1)):
        kk, dd = key[keep], d64[keep]
        n = np.bincount(kk, minlength=L * L).astype(float)
        s1 = np.bincount(kk, weights=dd, minlength=L * L)
        s2 = np.bincount(kk, weights=dd * dd, minlength=L * L)
        if p == passes - 2:
            break
        mean, std = pair_stats(n, s1, s2)
        band = np.maximum(k_sigma * np.nan_to_num(std, nan=np.inf), band_mm)
        keep = np.abs(d64 - np.nan_to_num(mean, nan=0.0)[key]) <= band[key]

    def sym(x: np.ndarray) -> np.ndarray:
        x = x.reshape(L, L)
        return x + x.T

    return PairSums(sym(n), sym(s1), sym(s2), sym(shared), stride)


def _median_mad(key: np.ndarray, d: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray]:
    """Median and MAD-based std (n_keys,) of the values ``d`` of every ``key`` (0 where none)."""
    if key.size == 0:
        return np.zeros(n_keys), np.zeros(n_keys)
    cnt = np.bincount(key, minlength=n_keys)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    has = cnt > 0
    c, s0 = cnt[has], start[has]

    def group_median(x: np.ndarray) -> np.ndarray:
        q = np.rint(np.clip(x, 0.0, 1e7) * 100.0).astype(np.int64)  # sorted in 0.01 mm steps
        xs = x[np.argsort(key * np.int64(2 * 10**9 + 11) + q, kind="stable")]
        out = np.zeros(n_keys)
        out[has] = 0.5 * (xs[s0 + (c - 1) // 2] + xs[s0 + c // 2])
        return out

    med = group_median(d)
    mad = group_median(np.abs(d - med[key]))
    return med, 1.4826 * mad


def track_sums(sums: PairSums, track: np.ndarray, n_tracks: int) -> PairSums:
    """Pair sums of tracks (groups of labels never seen together) from those of their labels.

    Parameters
    ----------
    sums : PairSums over L labels.
    track : (L,) int, the track of every label (-1: left out).
    n_tracks : T.

    Returns
    -------
    PairSums over T tracks (sums are additive: the labels of a track share no frame).
    """
    ok = np.flatnonzero(track >= 0)
    t = track[ok]
    key = (t[:, None] * n_tracks + t[None, :]).ravel()
    T2 = n_tracks * n_tracks

    def agg(x: np.ndarray) -> np.ndarray:
        y = np.bincount(key, weights=x[np.ix_(ok, ok)].ravel(), minlength=T2).reshape(n_tracks, n_tracks)
        np.fill_diagonal(y, 0.0)
        return y

    return PairSums(agg(sums.n), agg(sums.s1), agg(sums.s2), agg(sums.shared), sums.stride)


def partners_of(
    mean: np.ndarray,
    std: np.ndarray,
    n: np.ndarray,
    rigid_mm: float,
    min_shared: int,
    shared: np.ndarray | None = None,
    max_trimmed: float = 1.0,
) -> np.ndarray:
    """Rigid partners: pairs seen together long enough whose distance hardly varies.

    Parameters
    ----------
    mean, std : (T, T) ndarray, robust distance statistics (:meth:`PairSums.stats`).
    n : (T, T) ndarray, distances kept by the trimming.
    rigid_mm : float, largest std.
    min_shared : int, fewest kept distances.
    shared : (T, T) ndarray, optional
        Distances before trimming; with ``max_trimmed``, pairs that needed
        more than that fraction trimmed (a joint that moved for a while, not
        a few sporadic jumps) are not partners.
    max_trimmed : float

    Returns
    -------
    (T, T) bool ndarray, symmetric, False on the diagonal.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (n >= min_shared) & (std <= rigid_mm) & np.isfinite(mean)
        if shared is not None:
            r &= n >= (1.0 - max_trimmed) * shared
    np.fill_diagonal(r, False)
    return r


def _auto_rigid(std: np.ndarray, n: np.ndarray, min_shared: int) -> float:
    """Twice the median, over labels, of the std of each label's most rigid partner (2–15 mm)."""
    s = np.where((n >= min_shared) & np.isfinite(std), std, np.inf)
    np.fill_diagonal(s, np.inf)
    best = s.min(axis=1) if s.size else np.zeros(0)
    best = best[np.isfinite(best)]
    if best.size == 0:
        return 4.0
    return float(np.clip(2.0 * np.median(best), 2.0, 15.0))
