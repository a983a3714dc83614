"""Pairwise marker distances over a take: their spread, the affinity and the average-linkage rigid groups
they give, and the take's own level of skin motion and noise."""
from __future__ import annotations

import numpy as np

from .spectral import eigengap_k, normalized_affinity


def _pair_distances(points: np.ndarray) -> np.ndarray:
    """(K, P) distance of every marker pair ``i < j`` (``np.triu_indices`` order) in every frame.

    points : (K, M, 3) ndarray, NaN gaps. Bit for bit ``np.linalg.norm`` of the
    difference, NaN or inf where a marker is not seen; each pair once, without
    a (K, M, M, 3) array of differences.
    """
    i, j = np.triu_indices(points.shape[1], 1)
    sq = None
    with np.errstate(invalid="ignore"):  # inf - inf
        for c in range(3):
            x = points[:, :, c]
            d = np.take(x, i, axis=1) - np.take(x, j, axis=1)  # (K, P), C order like the sums below expect
            d *= d
            sq = d if sq is None else np.add(sq, d, out=sq)
    return np.sqrt(sq, out=sq)


def distance_std(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Std over frames of every pairwise marker distance.

    points : (K, M, 3) ndarray, NaN gaps.
    Returns (std (M, M) with NaN where never seen together, count (M, M) frames seen together).
    """
    return _distance_std(points, _pair_distances(points))


def _distance_std(points: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`distance_std` from the pair distances ``d`` (K, P) of ``points``."""
    M = points.shape[1]
    ok = np.isfinite(d)
    cnt_p = ok.sum(axis=0)
    d0 = np.where(ok, d, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = d0.sum(axis=0) / cnt_p
        var = (np.where(ok, d - mean, 0.0) ** 2).sum(axis=0) / cnt_p
    i, j = np.triu_indices(M, 1)
    std = np.zeros((M, M))
    std[i, j] = std[j, i] = np.sqrt(var)
    cnt = np.zeros((M, M), dtype=cnt_p.dtype)
    cnt[i, j] = cnt[j, i] = cnt_p
    # a marker with itself: distance 0 in every frame it is seen
    np.fill_diagonal(cnt, (np.isfinite(points[..., 0]) & np.isfinite(points[..., 1]) & np.isfinite(points[..., 2])).sum(axis=0))
    std[cnt < 2] = np.nan
    return std, cnt


def spread_cost(std: np.ndarray, labels: np.ndarray) -> float:
    """Kirk's criterion: sum over groups of within-group distance std, normalised by group size."""
    cost = 0.0
    for g in np.unique(labels[labels >= 0]):
        idx = np.flatnonzero(labels == g)
        if idx.size > 1:
            sub = std[np.ix_(idx, idx)]
            cost += np.nansum(np.triu(sub, 1)) / idx.size
    return float(cost)


def affinity(std: np.ndarray, sigma: float) -> np.ndarray:
    W = np.exp(-0.5 * (np.nan_to_num(std, nan=np.inf) / sigma) ** 2)
    np.fill_diagonal(W, 1.0)
    return W


#: A take whose sampled markers' smallest spread across a plane is below this fraction of their
#: largest is flat: no 3-D joint.
FLAT_FRAC = 1e-3


def _flat(X: np.ndarray) -> bool:
    """Whether the points ``X`` (n, 3) all lie in one plane (relative to their extent)."""
    s = np.linalg.svd(X - X.mean(0), compute_uv=False)
    return bool(s[2] < FLAT_FRAC * s[0])


#: A marker's second partner varying more than this many times its first is across a joint
#: (the marker sits on a two-marker segment): the first partner's std is its level.
ACROSS_RATIO = 4.0

SCALE_PERCENTILE = 25
SIGMA_FRACTIONS = (0.06, 0.12, 0.25, 0.5, 1.0)


def _median_distance(d: np.ndarray) -> float:
    """Median distance between markers, over frames and pairs, from the pair distances (K, P)."""
    v = d[np.isfinite(d)]
    return float(np.median(v)) if v.size else float("nan")


def by_first_marker(labels) -> np.ndarray:
    """Group labels renumbered 0.. in the order of each group's first marker."""
    first: dict[int, int] = {}
    return np.array([first.setdefault(int(g), len(first)) for g in labels], dtype=int)


def rigid_groups(std: np.ndarray, rigid_mm: float) -> np.ndarray:
    """(M,) labels 0.. of the average-linkage groups of ``std`` (M, M) cut at ``rigid_mm``.

    Each group's markers vary in distance by at most ``rigid_mm`` on average;
    groups are numbered by their first marker.
    """
    M = std.shape[0]
    D = np.nan_to_num(std, nan=np.nanmax(std) if np.isfinite(std).any() else 1.0)
    D = 0.5 * (D + D.T)
    _, root = _average_linkage(D, rigid_mm)
    _, lab = np.unique(root, return_inverse=True)
    return by_first_marker(lab.reshape(-1)) if M else lab


def average_linkage_heights(D: np.ndarray) -> np.ndarray:
    """Merge heights (M - 1,) of average-linkage (UPGMA) clustering of a symmetric distance matrix (M, M).

    The same heights as ``scipy.cluster.hierarchy.linkage(..., method="average")``
    (the tests compare them), without importing scipy's clustering (a third
    of a second per run). O(M^3): a few milliseconds for a hundred markers.
    """
    return _average_linkage(D, np.inf)[0]


def _average_linkage(D: np.ndarray, stop: float, size: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """UPGMA merges while they are at most ``stop`` high: (their heights, each point's cluster (a member index)).

    ``size`` : how many points each row already stands for (its distances the mean over them); default 1.
    """
    D = np.array(D, dtype=float)
    M = D.shape[0]
    np.fill_diagonal(D, np.inf)
    size = np.ones(M) if size is None else np.array(size, dtype=float)
    root = np.arange(M)
    heights = []
    for _ in range(M - 1):
        i, j = divmod(int(np.argmin(D)), M)
        if not D[i, j] <= stop:
            break
        heights.append(D[i, j])
        row = (size[i] * D[i] + size[j] * D[j]) / (size[i] + size[j])  # the merged cluster's mean distances
        D[i], D[:, i] = row, row
        D[i, i] = np.inf
        D[j], D[:, j] = np.inf, np.inf
        size[i] += size[j]
        root[root == j] = i
    return np.array(heights), root


def merge_still_groups(std: np.ndarray, labels: np.ndarray, stop: float) -> np.ndarray:
    """Go on with average linkage from the groups ``labels`` (M,) while groups vary against each other
    by at most ``stop`` on average; returns the labels numbered by first marker."""
    G = int(labels.max()) + 1
    S = np.nan_to_num(std, nan=np.nanmax(std) if np.isfinite(std).any() else 1.0)
    S = 0.5 * (S + S.T)
    onehot = np.zeros((labels.size, G))
    onehot[np.arange(labels.size), labels] = 1.0
    size = onehot.sum(0)
    D = (onehot.T @ S @ onehot) / np.outer(size, size)
    _, root = _average_linkage(D, stop, size)
    return by_first_marker(root[labels])


def skin_level(std: np.ndarray, floor: float = 0.0) -> float:
    """The take's own level of skin motion and noise, from the distance stds ``std`` (M, M).

    The median, over markers, of each marker's std to its second most rigid partner:
    a marker on a segment of three or more markers has two partners that vary only by
    skin motion and noise; on a two-marker segment the second is across a joint, so
    where the second varies more than ``ACROSS_RATIO`` times the first, the first counts. Markers whose second
    partner varies by less than ``floor`` are left out (points computed from a model,
    not measured: a take may carry them rigid to a hundredth of a millimetre). 0 when
    nothing varies.
    """
    M = std.shape[0]
    if M < 2:
        return 0.0
    D = np.where(np.eye(M, dtype=bool), np.inf, np.nan_to_num(std, nan=np.inf))
    D.sort(axis=1)
    second = D[:, min(1, M - 2)]
    second = np.where(second <= ACROSS_RATIO * D[:, 0], second, D[:, 0])
    second = second[np.isfinite(second)]
    if (second > floor).sum() * 2 > second.size:  # a few computed points among measured markers
        second = second[second > floor]
    return float(np.median(second)) if second.size else 0.0


def _extent(mean_d: np.ndarray, idx: np.ndarray) -> float:
    return float(np.nanmax(mean_d[np.ix_(idx, idx)])) if idx.size > 1 else 0.0


def choose_sigma(std: np.ndarray, sigma: float | None, k: int | None) -> tuple[float, int, np.ndarray]:
    """Affinity width, number of groups (from the eigen-gap) and the eigenvalues.

    std : (M, M) pooled distance std. When ``sigma`` is None, try a few
    fractions of the upper spread of the off-diagonal stds and keep the width
    whose eigen-gap (at ``k``, or at its own best k) is the widest.
    """
    M = std.shape[0]
    off = std[~np.eye(M, dtype=bool)]
    off = off[np.isfinite(off)]
    scale = float(np.percentile(off, SCALE_PERCENTILE)) if off.size else 1.0
    scale = scale if scale > 0 else 1.0
    cands = [sigma] if sigma is not None else [f * scale for f in SIGMA_FRACTIONS]
    best = None
    for sg in cands:
        eig = np.linalg.eigvalsh(normalized_affinity(affinity(std, sg)))[::-1]
        kk = k if k is not None else eigengap_k(eig, min(2, M - 1), max(1, M - 1))
        gap = float(eig[kk - 1] - eig[kk]) if kk < M else float(eig[kk - 1])
        if best is None or gap > best[0] + 1e-9:
            best = (gap, sg, kk, eig)
    return float(best[1]), int(best[2]), best[3]


#: Computed points are sought only where the take's measured markers vary, on their own bodies, by at
#: least this many times the floor of :func:`computed_points`: a take without noise (a generated chain, a
#: static trial read to hundredths of a millimetre) is rigid to that floor everywhere, and nothing in it
#: can be told apart as a model's output. Real moving takes: 17-56 times (HDM05's 1.2 mm, a CMU take's 3.7
#: mm against floors of 0.07 mm); static trials 1-2 times.
COMPUTED_LEVEL_RATIO = 10.0


def computed_points(std: np.ndarray, floor: float, min_measured: int = 3) -> np.ndarray:
    """Points a model computed from the markers (joint centres, a body model's segment points), (M,) bool.

    ``std`` (M, M): the distance stds; ``floor``: a distance std below which two points are rigid beyond
    what skin or camera noise allows (hundredths of a millimetre on a person). A point is computed when it
    is rigid to that floor with two points that themselves move against each other (their distance varies
    by more than the take's own level of skin and noise): it keeps its place on two bodies at once, as a
    model's joint centre does and no marker can, on skin or not. So is every point rigid to that floor with
    a computed one (the model's other points on that body). Points rigid only among themselves, on one body
    (markers a processing step made rigid, a cluster reconstructed as a whole), are kept: they ride on that
    body. Nothing is computed when fewer than ``min_measured`` points are left, or when those vary by less
    than ``COMPUTED_LEVEL_RATIO`` times the floor (a take without noise: a marker on a pure hinge's axis
    is as rigid with both bodies as a joint centre).
    """
    M = std.shape[0]
    out = np.zeros(M, dtype=bool)
    if M < 3 or not floor > 0:
        return out
    S = np.where(np.eye(M, dtype=bool), np.inf, np.nan_to_num(std, nan=np.inf))
    tight = S < floor
    cand = tight.sum(1) >= 2
    if (~cand).sum() < min_measured or not cand.any():
        return out
    level = skin_level(std[np.ix_(~cand, ~cand)])
    if not level > COMPUTED_LEVEL_RATIO * floor:
        return out
    for p in np.flatnonzero(cand):
        nb = np.flatnonzero(tight[p])
        sub = np.where(np.isfinite(S[np.ix_(nb, nb)]), S[np.ix_(nb, nb)], 0.0)
        out[p] = bool((sub > level).any())
    while out.any():
        more = tight[out].any(0) & ~out
        if not more.any():
            break
        out |= more
    if (~out).sum() < min_measured:
        return np.zeros(M, dtype=bool)
    return out
