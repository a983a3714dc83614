"""Marker-ID merging, the links: track ends joined to track starts where common rigid partners put them.

Notation as in :mod:`mocapskel.solvers.merging.pairs` (``F`` frames, ``T`` tracks).

- :func:`common_partner_cost` — one marker seen as two tracks keeps the same
  mean distance to every common partner: where the ending track's partners
  predict it.
- :func:`link_tracks` — track ends joined to track starts soon after by that
  cost, in an assignment (Hungarian) pass, only where the best match is
  clear; :func:`triangle_links` proposes joins for rigid triangles relabelled
  all at once (matched by their side lengths).

Kernels know no pipeline and do no I/O; the stage
:mod:`mocapskel.stages.merge_ids` puts them together.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "link_tracks",
    "triangle_links",
    "common_partner_cost",
]


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
