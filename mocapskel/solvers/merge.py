"""Marker-ID merging for passive optical data (Kirk et al. 2005, §4, and beyond).

A passive system gives a marker a new label whenever it loses it, and adds
ghost points. The kernels here decide which labels are one physical marker.
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
- :func:`common_partner_cost` — one marker seen as two tracks keeps the same
  mean distance to every common partner: where the ending track's partners
  predict it.
- :func:`link_tracks` — track ends joined to track starts soon after by that
  cost, in an assignment (Hungarian) pass, only where the best match is
  clear; :func:`triangle_links` proposes joins for rigid triangles relabelled
  all at once (matched by their side lengths).
- :func:`pose_distance` — Kirk's distance: the smallest distance between the
  two markers over pairs of frames after rigid alignment of the markers both
  frames share (sampled at an interval, then refined around the best pairs).
- :func:`repulsion_spectral` — spectral clustering with attraction and
  repulsion (Yu & Shi 2001): labels ever seen together repel.
- :func:`rigid_outliers`, :func:`rigid_steps` — samples that leave their
  partners: by distance, and by the abrupt change of the vectors to them
  (sporadic jumps in any direction, bad samples at gap edges).

Kernels know no pipeline and do no I/O; the stage
:mod:`mocapskel.stages.merge_ids` puts them together.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .rigid import kabsch

__all__ = [
    "PairSums",
    "compact_visible",
    "pair_sums",
    "pair_stats",
    "track_sums",
    "partners_of",
    "rigid_outliers",
    "rigid_steps",
    "norm3",
    "rigid_jumps",
    "judged_by_partners",
    "runs_of",
    "time_gaps",
    "link_tracks",
    "triangle_links",
    "common_partner_cost",
    "pose_distance",
    "repulsion_spectral",
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


# --------------------------------------------------------------------------- outliers


def norm3(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` for (..., 3) vectors, bit for bit, without the slow short-axis reduction."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.sqrt((x * x + y * y) + z * z)


def rigid_outliers(
    points: np.ndarray,
    vis: np.ndarray,
    mean: np.ndarray,
    std: np.ndarray,
    partner: np.ndarray,
    *,
    jump_mm: float = 20.0,
    k_sigma: float = 6.0,
    soft: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Samples that leave their rigid partners.

    A sample of label ``i`` at frame ``f`` is *hard* when at least two of the
    partners seen at ``f`` are, and more than half of them, farther than
    ``max(jump_mm, k_sigma * std)`` from their usual distance to ``i``; it is
    *soft* likewise with ``soft`` times that threshold. A label with fewer
    than two partners in view cannot be judged (nothing is flagged).

    Parameters
    ----------
    points : (F, L, 3) ndarray, NaN where unseen.
    vis : (F, L) bool ndarray.
    mean, std : (L, L) ndarray
        Robust mean and std of every pairwise distance (:func:`pair_sums`).
    partner : (L, L) bool ndarray
        Rigid partners (:func:`partners_of`).
    jump_mm, k_sigma, soft : float

    Returns
    -------
    hard, soft : (F, L) bool ndarrays
    """
    F, L = vis.shape
    pi, pj = np.nonzero(np.triu(partner, 1))
    if F == 0 or pi.size == 0:
        return np.zeros((F, L), dtype=bool), np.zeros((F, L), dtype=bool)
    mu = np.nan_to_num(mean[pi, pj], nan=0.0)
    thr = np.maximum(jump_mm, k_sigma * np.nan_to_num(std[pi, pj], nan=np.inf))
    # incidence of pairs to labels: counts per (frame, label) by a matrix product
    E = np.zeros((pi.size, L), dtype=np.float32)
    E[np.arange(pi.size), pi] = 1.0
    E[np.arange(pi.size), pj] = 1.0
    nv = np.zeros((F, L), dtype=np.float32)
    nh = np.zeros((F, L), dtype=np.float32)
    ns = np.zeros((F, L), dtype=np.float32)
    step = max(1, _CHUNK_ENTRIES // max(pi.size, 1))
    for s0 in range(0, F, step):
        sl = slice(s0, min(F, s0 + step))
        d = norm3(np.take(points[sl], pi, axis=1) - np.take(points[sl], pj, axis=1))  # (g, P), NaN if either unseen
        valid = np.isfinite(d)
        dev = np.abs(np.where(valid, d, 0.0) - mu)
        nv[sl] = valid.astype(np.float32) @ E
        nh[sl] = (valid & (dev > thr)).astype(np.float32) @ E
        ns[sl] = (valid & (dev > soft * thr)).astype(np.float32) @ E
    hard_m = vis & (nh >= 2) & (2 * nh > nv)
    soft_m = vis & (ns >= 2) & (2 * ns > nv)
    return hard_m, soft_m


def _neighbour_median(dr: np.ndarray) -> np.ndarray:
    """Per frame and coordinate, the median of the changes ``dr`` (F, P, 3) two and one frames before and
    after (the mean of the middle two of four; of three seen, the middle one; of two, their mean;
    NaN with fewer), unseen changes (NaN) left out: one or two jump edges among them do not move it.

    The four sorted by a network of compare-exchanges, unseen ones as +inf so that they sort last, as a
    sort puts NaN last: the values of ``np.sort`` along a new first axis, bit for bit, in a fraction
    of its time.
    """
    F = dr.shape[0]
    fin = np.full((F + 4,) + dr.shape[1:], np.inf, dtype=dr.dtype)  # two frames of padding each side
    seen = ~np.isnan(dr)
    np.copyto(fin[2:-2], dr, where=seen)
    n_seen = np.zeros((F + 4,) + dr.shape[1:2], dtype=np.int8)
    n_seen[2:-2] = seen[..., 0]
    cnt = n_seen[0:F] + n_seen[1:F + 1] + n_seen[3:F + 3] + n_seen[4:F + 4]  # (F, P): how many are seen
    nbs = [fin[0:F], fin[1:F + 1], fin[3:F + 3], fin[4:F + 4]]  # 2 and 1 frames before, 1 and 2 after
    for i, j in ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)):
        nbs[i], nbs[j] = np.minimum(nbs[i], nbs[j]), np.maximum(nbs[i], nbs[j])
    nb = nbs[1] + nbs[2]
    nb *= 0.5
    f, p = np.nonzero(cnt < 4)  # next to gaps and at the ends: a few of the entries
    if f.size:
        c = cnt[f, p][:, None]
        s0, s1 = nbs[0][f, p], nbs[1][f, p]
        with np.errstate(invalid="ignore"):  # inf - inf where fewer than two are seen
            nb[f, p] = np.where(c == 3, s1, np.where(c == 2, 0.5 * (s0 + s1), np.nan))
    return nb


def rigid_steps(
    points: np.ndarray,
    vis: np.ndarray,
    partner: np.ndarray,
    *,
    step_mm: float = 20.0,
    max_len: int = 36,
) -> np.ndarray:
    """Short stretches a label spends displaced from its partners, found by their abrupt edges.

    The vector from a label to a rigid partner only turns with the body, so
    its change from one frame to the next varies smoothly; a jump changes it
    at once. A frame is an *edge* of label ``i`` when at least two of its
    partners, and more than half of those that can judge, see the change of
    their vector to ``i`` depart from the median of the changes one and two
    frames before and after, and from the cubic and parabolas through them, by more than ``step_mm`` and
    more than 8 times that pair's median departure (fast turns and low frame
    rates raise the bar). A stretch of a visible
    run between two edges, at most ``max_len`` frames long and shorter than
    the rest of its run, is a jump. Unlike distances, vectors catch a jump in any
    direction, even with only two partners. A stretch with an edge at one end
    only (a bad sample at a gap's edge) is a jump too, unless that edge
    belongs to a jump next to it.

    Parameters
    ----------
    points : (F, L, 3) ndarray, NaN where unseen.
    vis : (F, L) bool ndarray.
    partner : (L, L) bool ndarray, reliable rigid partners.
    step_mm : float
    max_len : int, frames.

    Returns
    -------
    (F, L) bool ndarray, True for samples in a jump.
    """
    F, L = vis.shape
    out = np.zeros((F, L), dtype=bool)
    pi, pj = np.nonzero(np.triu(partner, 1))
    if F < 2 or pi.size == 0:
        return out
    E = np.zeros((pi.size, L), dtype=np.float32)
    E[np.arange(pi.size), pi] = 1.0
    E[np.arange(pi.size), pj] = 1.0
    # per pair: the change of the vector between frames, against the mean change
    # two frames before and after (what turning with the body predicts)
    r = (np.take(points, pi, axis=1) - np.take(points, pj, axis=1)).astype(np.float32)  # (F, P, 3)
    dr = np.full_like(r, np.nan)
    dr[1:] = r[1:] - r[:-1]  # dr[f]: from f - 1 to f
    nb = _neighbour_median(dr)
    dev = norm3(dr - nb)  # (F, P), NaN where it cannot be judged
    # The median predicts a steady turn; a fast turn that speeds up (a far link of a long chain
    # swinging at metres per second) departs from it by its acceleration. The cubic through the
    # changes 2 and 1 frames before and after, and the parabolas through the 3 changes before
    # and the 3 after (at the take's ends and next to gaps), follow such a turn, but a jump edge
    # among their changes moves them: a frame is judged by the smallest of these departures
    # (an edge departs from all of them, none of which reads its own change; a smooth fast turn
    # only from the median; a frame next to an edge not from the predictions that skip it).
    pred = np.full_like(dr, np.nan)
    with np.errstate(invalid="ignore"):
        pred[2:-2] = (4.0 * (dr[1:-3] + dr[3:-1]) - (dr[:-4] + dr[4:])) / 6.0
        dev = np.fmin(dev, norm3(dr - pred))
        pred[:] = np.nan
        pred[:-3] = 3.0 * (dr[1:-2] - dr[2:-1]) + dr[3:]
        dev = np.fmin(dev, norm3(dr - pred))
        pred[:] = np.nan
        pred[3:] = 3.0 * (dr[2:-1] - dr[1:-2]) + dr[:-3]
        dev = np.fmin(dev, norm3(dr - pred))
    del pred
    ok = np.isfinite(dev)
    scale = np.zeros(pi.size)
    judged = ok.any(axis=0)
    if judged.any():
        scale[judged] = np.nanmedian(np.where(ok[:, judged], dev[:, judged], np.nan), axis=0)
    thr = np.maximum(step_mm, 8.0 * scale)
    nv = ok.astype(np.float32) @ E
    ns = (ok & (np.where(ok, dev, 0.0) > thr)).astype(np.float32) @ E
    edge = vis & (ns >= 2) & (2 * ns > nv)  # edge[f]: between f - 1 and f
    if not edge.any():
        return out
    prev_vis = np.zeros_like(vis)
    prev_vis[1:] = vis[:-1]
    start = vis & (~prev_vis | edge)
    # stretch ids, column by column (time runs down each column)
    sid = np.cumsum(start.T.ravel()).reshape(L, F).T
    sid = np.where(vis, sid, 0)
    n_s = int(sid.max())
    length = np.bincount(sid.ravel(), minlength=n_s + 1)
    e_start = np.zeros(n_s + 1, dtype=bool)
    e_start[sid[edge]] = True
    nxt = np.zeros_like(edge)
    nxt[:-1] = edge[1:]
    e_end = np.zeros(n_s + 1, dtype=bool)
    e_end[sid[vis & nxt]] = True
    # the displaced stretch is the shorter part of its run
    rid = np.cumsum((vis & ~prev_vis).T.ravel()).reshape(L, F).T
    rid = np.where(vis, rid, 0)
    run_len = np.bincount(rid.ravel(), minlength=int(rid.max()) + 1)
    run_of_stretch = np.zeros(n_s + 1, dtype=np.int64)
    run_of_stretch[sid[vis]] = run_len[rid[vis]]
    short = (length <= max_len) & (2 * length < run_of_stretch)
    short[0] = False
    # a jump: edges at both ends; a bad gap edge: an edge at one end only,
    # unless that edge is a jump's (stretch ids run on along each label's time)
    both = short & e_start & e_end
    nxt_both = np.r_[both[1:], False]
    prv_both = np.r_[False, both[:-1]]
    one = short & ((e_end & ~e_start & ~nxt_both) | (e_start & ~e_end & ~prv_both))
    return vis & (both | one)[sid]


def rigid_jumps(
    points: np.ndarray,
    vis: np.ndarray,
    mean: np.ndarray,
    std: np.ndarray,
    partner: np.ndarray,
    *,
    jump_mm: float = 20.0,
    step_mm: float = 40.0,
    max_len: int = 36,
) -> tuple[np.ndarray, np.ndarray]:
    """Sporadic jumps: samples that leave their rigid partners for at most ``max_len`` frames.

    The samples :func:`rigid_outliers` calls hard, grown along time into the
    soft ones next to them, in runs of at most ``max_len`` frames (a marker
    away from its partners for longer is not a sporadic jump), plus the
    stretches :func:`rigid_steps` finds by their abrupt edges. Speed plays no
    part: a marker that moves fast with its partners keeps its samples.

    Returns
    -------
    jumps, soft : (F, L) bool ndarrays (``soft``: :func:`rigid_outliers`' soft samples).
    """
    hard, soft = rigid_outliers(points, vis, mean, std, partner, jump_mm=jump_mm)
    jumps = hard.copy()
    if hard.any():  # grow every hard sample along time through the soft samples next to it
        from scipy import ndimage  # (importing it costs a tenth of a second)

        vert = np.zeros((3, 3), dtype=bool)
        vert[:, 1] = True
        jumps = ndimage.binary_propagation(hard, structure=vert, mask=soft | hard)
        col, s0, s1 = runs_of(jumps)
        long = (s1 - s0) > max_len
        for c_, a_, b_ in zip(col[long], s0[long], s1[long]):
            jumps[a_:b_, c_] = False
    jumps |= rigid_steps(points, vis, partner, step_mm=step_mm, max_len=max_len)
    return jumps, soft


def judged_by_partners(vis: np.ndarray, partner: np.ndarray, least: int = 2) -> np.ndarray:
    """(F, L) bool: samples seen with at least ``least`` of their rigid partners (what the rigid tests can judge)."""
    if vis.size == 0:
        return np.zeros(vis.shape, dtype=bool)
    return vis & ((vis.astype(np.float32) @ partner.astype(np.float32)) >= least)


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


def runs_of(vis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Visible runs of every column of a (F, L) bool array.

    Returns
    -------
    col, start, stop : (R,) int ndarrays (``stop`` exclusive), ordered by column then start.
    """
    F, L = vis.shape
    v = np.zeros((F + 2, L), dtype=np.int8)
    v[1:-1] = vis
    d = np.diff(v, axis=0).T  # (L, F + 1)
    col, start = np.nonzero(d == 1)
    _, stop = np.nonzero(d == -1)
    return col, start, stop


# --------------------------------------------------------------------------- linking run ends to run starts


@dataclass(frozen=True)
class Links:
    """Result of :func:`link_tracks`.

    pairs : (N, 2) int, (ending track, starting track) joined.
    cost  : (N,) cost (mm) of each accepted link (:func:`common_partner_cost` plus the gap term).
    candidates : number of (end, start) pairs examined.
    ambiguous : number of best matches refused for want of a clear margin.
    table : (C, 4) float, every candidate examined: ending track, starting
            track, cost (inf when not acceptable), number of common partners.
    """

    pairs: np.ndarray
    cost: np.ndarray
    candidates: int
    ambiguous: int
    table: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))


def common_partner_cost(
    mean: np.ndarray, partner: np.ndarray, ci: np.ndarray, cj: np.ndarray, *, single_penalty_mm: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """How well track ``j`` sits where track ``i``'s rigid partners put it.

    A partner ``n`` rigid to both tracks (over the frames each shares with
    it) predicts ``mean[i, n] == mean[j, n]`` when they are one marker. With
    three or more such partners this pins ``j`` to ``i``'s place on the rigid
    body (up to a mirror image); with two, to a circle; with one, to a sphere.

    Parameters
    ----------
    mean : (T, T) ndarray, mean pairwise distances.
    partner : (T, T) bool ndarray, rigid partners.
    ci, cj : (C,) int, the track pairs.
    single_penalty_mm : float
        Added to the residual of a pair with a single common partner (weaker evidence).

    Returns
    -------
    cost : (C,) ndarray, mm: the rms of ``mean[i, n] - mean[j, n]`` over the
        best-agreeing majority of the common partners (all of them when there
        are one or two; plus the penalty when there is one); inf with none.
    common : (C,) int, the number of common partners.
    """
    both = partner[ci] & partner[cj]
    both[np.arange(ci.size), ci] = False
    both[np.arange(ci.size), cj] = False
    with np.errstate(invalid="ignore"):
        r = np.where(both, np.abs(mean[ci] - mean[cj]), np.inf)
    k = both.sum(1)
    # a majority of the common partners (at least two, or the one) must agree:
    # a partner that only looked rigid while its joint was still may not
    m = np.where(k <= 2, k, k - (k - 1) // 2)
    r = np.sort(r, axis=1)
    use = np.arange(r.shape[1])[None, :] < m[:, None]
    sq = np.where(use, r, 0.0) ** 2
    cost = np.sqrt(sq.sum(1) / np.maximum(m, 1))
    cost = np.where(k == 1, cost + single_penalty_mm, cost)
    return np.where(k >= 1, cost, np.inf), k


def link_tracks(
    first: np.ndarray,
    last: np.ndarray,
    p_first: np.ndarray,
    p_last: np.ndarray,
    mean: np.ndarray,
    partner: np.ndarray,
    overlap: np.ndarray,
    *,
    n_frames: int,
    max_gap: int,
    link_mm: float = 4.0,
    margin_mm: float = 4.0,
    gap_mm_per_frame: float = 0.005,
    max_speed: float = 40.0,
    min_common: int = 2,
) -> Links:
    """Join track ends to track starts where the ending track's rigid partners predict it.

    For every track ``i`` that ends at frame ``a`` and track ``j`` that starts
    at ``b`` with ``0 < b - a <= max_gap``, the cost is
    :func:`common_partner_cost` (how far ``j`` is from where the partners
    that carried ``i`` put it), plus ``gap_mm_per_frame`` per frame of gap
    (so that the nearest of two compatible starts is taken first). A
    candidate needs a cost ≤ ``link_mm`` and a plausible speed across the
    gap (≤ ``max_speed`` mm per frame, plus ``link_mm``). An assignment
    (Hungarian) pairs ends with starts; a link is kept only when its cost
    beats by ``margin_mm`` every other candidate of its end that overlaps its
    start, and every other candidate of its start that overlaps its end
    (two candidates that could be one marker do not compete).

    Parameters
    ----------
    first, last : (T,) int ndarrays
        First and last frame in which each track is seen (``n_frames`` and
        -1 for a track never seen).
    p_first, p_last : (T, 3) ndarrays
        The track's positions at those frames.
    mean : (T, T) ndarray, robust mean pairwise distances.
    partner : (T, T) bool ndarray, rigid partners.
    overlap : (T, T) int, frames in which both tracks are seen (0: never together).
    n_frames : int, F.
    max_gap : int, frames.
    link_mm, margin_mm, gap_mm_per_frame, max_speed : float, see above.
    min_common : int
        Fewest common partners a link needs.

    Returns
    -------
    Links
    """
    F, T = int(n_frames), first.size
    empty = Links(np.zeros((0, 2), int), np.zeros(0), 0, 0)
    seen = last >= 0
    if T < 2 or not seen.any():
        return empty
    ends = np.flatnonzero(seen & (last < F - 1))
    starts = np.flatnonzero(seen & (first > 0))
    if ends.size == 0 or starts.size == 0:
        return empty
    gap = first[starts][None, :] - last[ends][:, None]
    ci, cj = np.nonzero((gap > 0) & (gap <= max_gap))
    ci, cj = ends[ci], starts[cj]
    if ci.size == 0:
        return empty
    cost, k = common_partner_cost(mean, partner, ci, cj)
    g = first[cj] - last[ci]
    cost = cost + gap_mm_per_frame * g
    pa = p_last[ci]
    pb = p_first[cj]
    fast = np.linalg.norm(pb - pa, axis=1) > max_speed * g + link_mm
    cost = np.where(fast | (k < min_common), np.inf, cost)
    table = np.stack([ci, cj, cost, k], axis=1).astype(float)
    good = cost <= link_mm
    if not good.any():
        return Links(np.zeros((0, 2), int), np.zeros(0), int(ci.size), 0, table)
    gi, gj, gc = ci[good], cj[good], cost[good]
    ue, ie = np.unique(gi, return_inverse=True)
    us, js = np.unique(gj, return_inverse=True)
    BIG = 1e6
    M = np.full((ue.size, us.size), BIG)
    M[ie, js] = gc
    from scipy.optimize import linear_sum_assignment  # here: a costly import, for passive takes only

    r, c = linear_sum_assignment(M)
    keep = M[r, c] < BIG
    r, c = r[keep], c[keep]
    # rivals: the other candidates of the same end that overlap the chosen
    # start in time, and of the same start that overlap the chosen end
    out, costs, amb = [], [], 0
    for a, b in zip(r, c):
        cst = M[a, b]
        row_rivals = (M[a] < BIG) & (overlap[us, us[b]] > 0)
        col_rivals = (M[:, b] < BIG) & (overlap[ue, ue[a]] > 0)
        row_rivals[b] = False
        col_rivals[a] = False
        other = min(M[a][row_rivals].min(initial=BIG), M[:, b][col_rivals].min(initial=BIG))
        if other < cst + margin_mm:
            amb += 1
            continue
        out.append((ue[a], us[b]))
        costs.append(cst)
    return Links(np.array(out, dtype=int).reshape(-1, 2), np.array(costs), int(ci.size), amb, table)


def triangle_links(
    first: np.ndarray,
    last: np.ndarray,
    mean: np.ndarray,
    partner: np.ndarray,
    *,
    n_frames: int,
    max_gap: int,
    link_mm: float = 4.0,
    margin_mm: float = 4.0,
) -> np.ndarray:
    """Links for rigid triangles whose three markers were all relabelled at about the same time.

    When every marker of a three-marker body is lost and relabelled, no
    partner carries over the gap. Three mutually rigid tracks that end and
    three mutually rigid tracks that start soon after (each within
    ``max_gap`` of its match) are matched vertex to vertex by their side
    lengths: the permutation whose rms side difference is ≤ ``link_mm`` and
    beats every other candidate triangle and permutation for those ends by
    ``margin_mm`` (a nearly isosceles triangle is left alone). The links are
    proposals, to be checked (each must then find two common partners).

    Parameters
    ----------
    first, last : (T,) int, first and last frame of every track (``n_frames`` / -1: never seen).
    mean : (T, T) ndarray, mean pairwise distances.
    partner : (T, T) bool ndarray, rigid partners.
    n_frames, max_gap : int
    link_mm, margin_mm : float

    Returns
    -------
    (N, 2) int, (ending track, starting track) proposals.
    """
    from itertools import combinations, permutations

    F = int(n_frames)
    seen = last >= 0
    ends = np.flatnonzero(seen & (last < F - 1))
    starts = np.flatnonzero(seen & (first > 0))
    if ends.size < 3 or starts.size < 3:
        return np.zeros((0, 2), dtype=int)
    gap = first[None, :] - last[:, None]
    ok = (gap > 0) & (gap <= max_gap)

    def triangles(nodes: np.ndarray) -> list[tuple[int, int, int]]:
        out = []
        for a in nodes:
            nb = [b for b in nodes if b > a and partner[a, b]]
            for b, c in combinations(nb, 2):
                if partner[b, c]:
                    out.append((int(a), int(b), int(c)))
        return out

    e_nodes = ends[ok[ends].any(1)]
    s_nodes = starts[ok[:, starts].any(0)]
    tri_e, tri_s = triangles(e_nodes), triangles(s_nodes)
    if not tri_e or not tri_s:
        return np.zeros((0, 2), dtype=int)
    proposals: list[tuple[int, int]] = []
    for te in tri_e:
        side_e = np.array([mean[te[0], te[1]], mean[te[0], te[2]], mean[te[1], te[2]]])
        scored = []
        for ts in tri_s:
            for perm in permutations(ts):
                if not all(ok[a, x] for a, x in zip(te, perm)):
                    continue
                side_s = np.array([mean[perm[0], perm[1]], mean[perm[0], perm[2]], mean[perm[1], perm[2]]])
                scored.append((float(np.sqrt(np.mean((side_e - side_s) ** 2))), perm))
        if not scored:
            continue
        scored.sort(key=lambda x: x[0])
        best, perm = scored[0]
        rival = scored[1][0] if len(scored) > 1 else np.inf
        if best <= link_mm and rival >= best + margin_mm:
            proposals.extend(zip(te, perm))
    if not proposals:
        return np.zeros((0, 2), dtype=int)
    P = np.unique(np.array(proposals, dtype=int), axis=0)
    # an end or a start claimed twice, differently: drop it
    _, ce = np.unique(P[:, 0], return_counts=True)
    _, cs = np.unique(P[:, 1], return_counts=True)
    bad_e = np.unique(P[:, 0])[ce > 1]
    bad_s = np.unique(P[:, 1])[cs > 1]
    return P[~np.isin(P[:, 0], bad_e) & ~np.isin(P[:, 1], bad_s)]


# --------------------------------------------------------------------------- distances between tracks


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
