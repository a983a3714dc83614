"""Marker-ID merging, the outliers: samples that leave their rigid partners (sporadic jumps, bad gap edges).

Notation as in :mod:`mocapskel.solvers.merging.pairs` (``F`` frames, ``L`` labels).

- :func:`rigid_outliers`, :func:`rigid_steps` — samples that leave their
  partners: by distance, and by the abrupt change of the vectors to them
  (sporadic jumps in any direction, bad samples at gap edges).

Kernels know no pipeline and do no I/O; the stage
:mod:`mocapskel.stages.merge_ids` puts them together.
"""
from __future__ import annotations

import numpy as np

from .pairs import _CHUNK_ENTRIES

__all__ = [
    "rigid_outliers",
    "rigid_steps",
    "norm3",
    "rigid_jumps",
    "judged_by_partners",
    "runs_of",
]


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
        Robust mean and std of every pairwise distance (:func:`~mocapskel.solvers.merging.pairs.pair_sums`).
    partner : (L, L) bool ndarray
        Rigid partners (:func:`~mocapskel.solvers.merging.pairs.partners_of`).
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
        jumps = grow_runs(hard, soft | hard, max_len)
    jumps |= rigid_steps(points, vis, partner, step_mm=step_mm, max_len=max_len)
    return jumps, soft


def grow_runs(seed: np.ndarray, mask: np.ndarray, max_len: int | None = None) -> np.ndarray:
    """(F, L) bool: the runs of ``mask`` along time (per column) that hold a ``seed`` sample, those
    longer than ``max_len`` frames left out (``seed`` must lie in ``mask``).

    What ``scipy.ndimage.binary_propagation(seed, structure=<time only>, mask=mask)`` gives, from the
    runs' bounds and a running count of the seeds (importing ``scipy.ndimage`` costs a fifth of a
    second, more than the whole search on a long take)."""
    out = np.zeros(mask.shape, dtype=bool)
    col, s0, s1 = runs_of(mask)
    if not col.size:
        return out
    cs = np.zeros((mask.shape[0] + 1, mask.shape[1]), dtype=np.int64)
    np.cumsum(seed, axis=0, out=cs[1:])
    keep = cs[s1, col] > cs[s0, col]
    if max_len is not None:
        keep &= (s1 - s0) <= max_len
    edge = np.zeros(cs.shape, dtype=np.int8)  # +1 where a kept run starts, -1 after it ends
    np.add.at(edge, (s0[keep], col[keep]), 1)
    np.add.at(edge, (s1[keep], col[keep]), -1)
    out[:] = np.cumsum(edge[:-1], axis=0, dtype=np.int8) > 0
    return out


def judged_by_partners(vis: np.ndarray, partner: np.ndarray, least: int = 2) -> np.ndarray:
    """(F, L) bool: samples seen with at least ``least`` of their rigid partners (what the rigid tests can judge)."""
    if vis.size == 0:
        return np.zeros(vis.shape, dtype=bool)
    return vis & ((vis.astype(np.float32) @ partner.astype(np.float32)) >= least)


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
