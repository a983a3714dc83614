"""Segment: group markers into rigid bodies (Kirk et al. 2005, §3.1).

Markers on one rigid segment keep constant distances. For a jittered uniform
sampling of frames (every half second, plus or minus a few thirtieths), the
standard deviation of every pairwise distance is computed; these become
Gaussian affinities that Ng–Jordan–Weiss spectral clustering splits into
groups. Several samplings are clustered and the clustering with the smallest
within-group spread is kept (a RANSAC-like guard against sporadic jumps). The
number of groups is given or taken from the eigen-gap.

Without a given number, the groups are the rigid groups at the take's own tolerance
(average linkage), lone markers then given a place, pairs of markers that are one body's
skin joined to it (:func:`absorb_pairs`); a group that keeps its distances but does not
move as one body (its rigid-fit residual above the tolerance) is then split in two
(:func:`split_nonrigid`), and last a marker that another group's moving frame holds clearly
tighter than its own group's moves there (:func:`reassign_by_frame`).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import warnings

import numpy as np

from ..artifacts import Markers, Segments
from ..errors import DataError
from ..solvers.partition import best_split, frame_path, frame_scatters, rigid_rms, scatter_in_frame
from ..solvers.sphere import sphere_lls
from ..solvers.spectral import eigengap_k, normalized_affinity, spectral_clustering

VERSION = 12


@dataclass(frozen=True)
class Params:
    n_segments: int | None = None
    """Number of segments (spectral clustering into that many); None: the rigid groups at the
    take's own tolerance (average linkage), lone markers then given a place."""
    interval_s: float = 0.5
    """Sampling interval (Kirk: half a second)."""
    jitter_s: float = 0.1
    """Each sample is moved by up to this much (Kirk: a few thirtieths of a second)."""
    min_samples: int = 60
    """Fewer samples than this: the interval shrinks (short takes)."""
    max_samples: int = 600
    """More samples than this: the interval grows (long takes)."""
    n_samplings: int = 5
    sigma_mm: float | None = None
    """Width of the Gaussian that turns a distance std into an affinity; None:
    chosen from the data (the width, among a few fractions of the spread of the
    stds, that gives the clearest eigen-gap)."""
    rigid_k: float = 2.0
    """Automatic count: markers whose distances vary (std) by at most this many times the
    take's own skin-and-noise level on average are one rigid group. The level is
    measured on the take: the median, over markers, of the std to the second most
    rigid partner (a marker on a segment of three or more has two partners at the
    level of its skin motion)."""
    join_k: float = 2.0
    """A marker left alone by the rigid groups may join a group, or take a partner from
    one, within this many times the rigid tolerance (a marker on a joint axis stays
    nearly rigid with both neighbours, and the group it was put in may need it less)."""
    free_k: float = 2.5
    """A marker still alone that varies against its nearest group by less than this many
    times the rigid tolerance does not move on its own (skin motion): it joins that group."""
    reach: float = 1.5
    """A marker joins or pairs only with markers within this many times the median
    extent of the rigid groups (markers far apart that move in step — an arm swinging
    with the opposite leg — are not one body)."""
    motion_frac: float = 0.005
    """Distances that vary by less than this fraction of the median marker distance never tell
    two segments apart, however rigid the take's markers are to each other: a body part that moves
    its markers against another's by less than that (a trunk swaying while one knee is exercised,
    rigid marker plates on one bone) does not locate a joint between them."""
    min_seen: int = 8
    """A marker seen in fewer sampled frames than this is left out of the groups."""
    absorb_pairs: bool = True
    """Two groups of two markers that cross each other and move as one rigid body are joined, and a
    group of two that straddles a group of three or more and moves against it by too little to locate
    a joint joins it (see :func:`absorb_pairs`)."""
    split_nonrigid: bool = True
    """Split a group in two where its markers keep their distances but do not move as one body
    (see :func:`split_nonrigid`)."""
    reframe: bool = True
    """Move a marker to the group whose moving frame holds it clearly tighter than its own group's
    (see :func:`reassign_by_frame`)."""
    seed: int = 0


def sample_frames(n_frames: int, rate: float, params: Params, rng: np.random.Generator) -> np.ndarray:
    """A jittered uniform sampling of frame indices (sorted, unique)."""
    step = params.interval_s * rate
    n = n_frames / max(step, 1e-9)
    if n < params.min_samples:
        step = n_frames / params.min_samples
    elif n > params.max_samples:
        step = n_frames / params.max_samples
    base = np.arange(step / 2, n_frames, max(step, 1.0))
    jit = min(params.jitter_s * rate, step / 2)
    idx = np.rint(base + rng.uniform(-jit, jit, size=base.size)).astype(int)
    return np.unique(np.clip(idx, 0, n_frames - 1))


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
#: A skin-and-noise level above this fraction of the median distance std means no two markers are
#: rigid together (each marker's most rigid partner is across a joint). Measured: one marker per
#: segment gives 0.7-1.9 (generated chains of 3-6 links); real takes with markers sharing bodies
#: 0.004-0.28, the highest where the bodies barely move against each other (an OptiTrack walk's
#: shank and foot bodies, 0.28; a 3-segment arm, 0.23).
NO_PAIR_FRAC = 0.5
#: Distances that vary by more than this fraction of the median marker distance are not those of
#: one rigid body, however alike they vary.
RIGID_FRAC = 0.02

#: A marker whose distances to its partners vary by less than this fraction of the median
#: marker distance is a point computed from a model, not a measured marker.
COMPUTED_FRAC = 1e-4
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


#: A lone marker takes a partner from a group only if their distance varies by at most this many
#: times the partner's mean std to its own group: a marker on a joint axis keeps its distances to both
#: sides about equally (a knee or an elbow marker: 0.6-1.9 times on real takes), while one that
#: belongs to its group varies three times as much or more against the lone marker (a pelvis marker
#: taken by a thigh marker on CMU and HDM05 takes: 2.9-260 times; a spine marker taken by an
#: acromion marker: 3.2 times).
PARTNER_RATIO = 2.5


def pair_lone_markers(
    std: np.ndarray, mean_d: np.ndarray, labels: np.ndarray, tau_join: float, tau_free: float, reach: float,
    depth: int = 4, keep: Callable[[int, np.ndarray], bool] | None = None,
) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """Give each marker left alone by the rigid groups a segment, where the data allow.

    A marker on a joint axis keeps a nearly constant distance to the markers of both
    neighbouring segments, so the rigid groups may put it with the segment that
    needs it less and leave the other side's marker alone. A lone marker ``m`` may
    join a group (mean std to it at most ``tau_join``) or take a partner ``j``
    (std at most ``tau_join``, and at most ``PARTNER_RATIO`` times ``j``'s mean std to
    the rest of its group: a marker on the axis) from its group; if that leaves ``j``'s group with one
    marker, that marker must in turn find a partner the same way (a chain of at most
    ``depth`` moves). The cheapest chain (sum of the new stds) that leaves nobody
    newly alone wins. A marker still alone that varies against its nearest group by
    less than ``tau_free`` does not move on its own: it joins that group. Markers
    join or pair only within ``reach`` (mean distance) of each other. A lone marker does
    not join a group (it may take a partner from it) for which ``keep(marker, the group's
    markers)`` holds (it turns on its own against it, see :func:`turns_about_a_point`).

    std, mean_d : (M, M) distance std and mean distance; labels : (M,) groups.
    Returns the new labels (numbered by first marker) and the moves made
    (marker index, "paired" | "joined" | "absorbed").
    """
    lab = np.array(labels, dtype=int)
    M = lab.size
    S = np.where(np.eye(M, dtype=bool), np.inf, np.nan_to_num(std, nan=np.inf))
    near = np.nan_to_num(mean_d, nan=np.inf) <= reach
    moves: list[tuple[int, str]] = []

    def group_cost(m: int, L: np.ndarray, g: int) -> float:
        mem = np.flatnonzero(L == g)
        mem = mem[mem != m]
        if not mem.size or not near[m, mem].all():
            return np.inf
        return float(S[m, mem].mean())

    def search(m: int, L: np.ndarray, moved: frozenset, d: int):
        best = None
        for g in np.unique(L):
            if g != L[m]:
                c = group_cost(m, L, g)
                if c <= tau_join and (best is None or c < best[0]) and not (
                        keep is not None and keep(m, np.flatnonzero(L == g))):
                    best = (c, [(m, int(g), "joined")])
        if d == 0:
            return best
        for j in np.flatnonzero((S[m] <= tau_join) & near[m]):
            if j in moved or L[j] == L[m]:
                continue
            mem = np.flatnonzero(L == L[j])
            if mem.size < 2:
                continue
            c = float(S[m, j])
            if c > PARTNER_RATIO * float(S[j, mem[mem != j]].mean()):
                continue  # j is far more rigid with its own group: not a marker on the axis between the two
            if best is not None and c >= best[0]:
                continue
            L2 = L.copy()
            L2[j] = L[m]
            if mem.size == 2:  # j's old partner is left alone: it must find a place too
                r = int(mem[mem != j][0])
                sub = search(r, L2, moved | {m, int(j)}, d - 1)
                if sub is None:
                    continue
                if best is None or c + sub[0] < best[0]:
                    best = (c + sub[0], [(int(j), int(L[m]), "paired")] + sub[1])
            elif best is None or c < best[0]:
                best = (c, [(int(j), int(L[m]), "paired")])
        return best

    for _ in range(M):
        sizes = np.bincount(lab)
        lone = [i for i in range(M) if sizes[lab[i]] == 1]
        for m in sorted(lone, key=lambda i: (S[i].min(), i)):
            res = search(m, lab, frozenset({m}), depth)
            if res is not None:
                for i, g, how in res[1]:
                    lab[i] = g
                    moves.append((i, how))
                break
        else:
            break
    # still alone: a marker that hardly moves against its nearest group is skin on it
    lab, more = absorb_lone_markers(std, mean_d, lab, tau_free, reach, keep=keep)
    return lab, moves + more


#: Frames of the search for a group's split (the checks use every sampled frame).
SPLIT_FRAMES = 150
#: Fewer sampled frames than this with a group's markers all seen: its rigidity is not tested.
SPLIT_MIN_FRAMES = 20


def split_nonrigid(points: np.ndarray, std: np.ndarray, labels: np.ndarray, tau: float, reveal: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, list[tuple[list[np.ndarray], float]]]:
    """Split each group that keeps its distances but does not move as one rigid body into two that do.

    Average linkage groups markers by their distance stds, and distances tell segments apart
    only to second order where markers lie nearly in line with the joint between them (a trunk
    bending over a still pelvis and leg). A group of six or more markers whose rigid-fit
    residual exceeds the rigid tolerance ``tau`` is split in two (:func:`best_split`) when
    - each part has at least three markers and a rigid-fit residual within ``tau``;
    - the distance stds agree: each part's markers vary less among themselves, on average,
      than against the other part's;
    - the parts move against each other by more than ``reveal`` (rms, one part's markers in
      the other's frame): the same bar as for a lone marker, below which the joint between
      them could not be located (skin and breathing move parts of one body by less).
    Parts are tested again. points : (K, M, 3) the sampled frames; std : (M, M) distance stds;
    labels : (M,) groups. Returns the new labels (numbered by first marker) and each split
    (its two parts' marker indices, the group's rigid-fit rms).
    """
    lab = np.array(labels, dtype=int)
    splits: list[tuple[list[np.ndarray], float]] = []
    queue = [np.flatnonzero(lab == g) for g in range(lab.max() + 1)]
    while queue:
        idx = queue.pop(0)
        if idx.size < 6:
            continue
        P = _seen_together(points, idx)
        if P is None:
            continue
        r = rigid_rms(P)
        if not r > tau:
            continue
        Ps = P[np.unique(np.linspace(0, len(P) - 1, min(SPLIT_FRAMES, len(P))).round().astype(int))]
        part = best_split(Ps, rng)
        if part is None:
            continue
        parts = [np.flatnonzero(part == k) for k in (0, 1)]
        # every marker's scatter in each part's frame: a part's own markers give its rigid-fit residual,
        # the other part's how far the two move against each other
        sc = [scatter_in_frame(P, p) for p in parts]
        if max(float(np.sqrt((sc[k][parts[k]] ** 2).mean())) for k in (0, 1)) > tau:
            continue
        S = std[np.ix_(idx, idx)]
        within = [np.nanmean(S[np.ix_(p, p)][~np.eye(p.size, dtype=bool)]) for p in parts]
        if not np.nanmean(S[np.ix_(parts[0], parts[1])]) > max(within):
            continue
        moved = max(float(np.sqrt((sc[k][parts[1 - k]] ** 2).mean())) for k in (0, 1))
        if not moved > reveal:
            continue
        lab[idx[parts[1]]] = lab.max() + 1
        splits.append(([idx[p] for p in parts], r))
        queue += [idx[p] for p in parts]
    return by_first_marker(lab), splits


def _other_groups(lab: np.ndarray, m: int) -> list[tuple[int, np.ndarray]]:
    """The groups of two or more markers other than marker ``m``'s: [(group, its markers)]."""
    out = []
    for g in np.unique(lab):
        mem = np.flatnonzero(lab == g)
        if g != lab[m] and mem.size > 1:
            out.append((int(g), mem))
    return out


def absorb_lone_markers(std: np.ndarray, mean_d: np.ndarray, labels: np.ndarray, tau_free: float,
                        reach: float, nearest: bool = False,
                        keep: Callable[[int, np.ndarray], bool] | None = None,
                        ) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """Each marker alone in its group that varies against its nearest group of several markers (nearest
    in mean distance among those with all of them within ``reach``; with ``nearest``: the nearest of
    them within ``reach``) by at most ``tau_free`` (mean std; with ``nearest``: against every member)
    joins that group ("absorbed"), unless ``keep(marker, group's markers)`` says it turns on its own.
    Returns the labels numbered by first marker and the moves."""
    lab = np.array(labels, dtype=int)
    M = lab.size
    S = np.where(np.eye(M, dtype=bool), np.inf, np.nan_to_num(std, nan=np.inf))
    near = np.nan_to_num(mean_d, nan=np.inf) <= reach
    moves: list[tuple[int, str]] = []
    sizes = np.bincount(lab)
    for m in [i for i in range(M) if sizes[lab[i]] == 1]:
        got = _nearest_group(S, mean_d, lab, m, near, nearest)
        if got is not None:
            c, g = got
            if c <= tau_free and not (keep is not None and keep(m, np.flatnonzero(lab == g))):
                lab[m] = g
                moves.append((m, "absorbed"))
    return by_first_marker(lab), moves


def _nearest_group(S: np.ndarray, mean_d: np.ndarray, lab: np.ndarray, m: int, near: np.ndarray,
                   nearest: bool) -> tuple[float, int] | None:
    """(cost, group) of the group of two or more markers nearest to marker ``m`` in mean distance, among
    those with all members within reach (``near``; with ``nearest``: any member): its members' mean
    distance std to ``m`` (with ``nearest``: the largest). None when no group is within reach. Skin on
    a body is on it: the group nearest in space, not the one that varies least anywhere within reach
    (a real walk's lone thigh marker varied least against the same side's upper arm)."""
    costs = []
    for g, mem in _other_groups(lab, m):
        if near[m, mem].any() if nearest else near[m, mem].all():
            costs.append((float(S[m, mem].max() if nearest else S[m, mem].mean()), int(g),
                          float(np.nan_to_num(mean_d[m, mem], nan=np.inf).mean())))
    if not costs:
        return None
    c, g, _ = min(costs, key=lambda x: x[2])
    return c, g


#: A lone marker turns about a point of its group's frame only if that point is no farther from the group's
#: nearest marker than this many times the marker's own distance from it (see :func:`turns_about_a_point`).
#: Measured on the real takes of the shared folders and the generated ranges of motion: markers that turn
#: about a joint (a hand's about the wrist, a toe's about the foot, a shank's about the ankle, an upper arm's
#: about the trunk) 0.6-2.4; markers that keep still on their group but for skin wobble, whose paths fit a
#: sphere of 1-15 mm about a point beside them, 5-150.
TURN_REACH = 3.0


def turns_about_a_point(points: np.ndarray, m: int, group: np.ndarray, level: float) -> bool:
    """Whether marker ``m`` turns about a point fixed in the moving frame of the markers ``group``, one
    that its path locates and that could be their joint.

    The stds of distances hide a marker that swings about a joint near the group's markers (a hand's
    marker about the wrist: its distances to the wrist's markers hardly change however far it turns),
    so a lone marker that varies too little against its group to be kept by them is tested in the
    group's frame, on the sampled frames where all are seen. Its path there must

    - lie on a sphere to within the take's own skin-and-noise ``level`` (rms radial residual), which
      skin sliding over a body does not;
    - turn about a point that could join the two bodies: no farther from the group's nearest marker
      than ``TURN_REACH`` times the sphere's radius. A marker that keeps still on its body save for a
      millimetre or two of wobble also lies on a sphere, a small one about a point beside it, far
      from the group (and so does a short arc whose radius the path does not fix: the algebraic fit
      takes a small sphere for it).

    points : (K, M, 3) the sampled frames; group : three or more markers not in line.
    """
    if group.size < 3:
        return False
    P = _seen_together(points, np.r_[group, m])
    if P is None:
        return False
    Q = frame_path(P, np.arange(group.size))
    fit = sphere_lls(Q[:, -1])
    if not fit.ok:
        return False
    to_group = float(np.linalg.norm(Q[:, :-1].mean(0) - fit.centre, axis=-1).min())
    return bool(fit.rms <= level and to_group <= TURN_REACH * fit.radius)


#: A marker alone whose distances to the markers of two groups vary at most this fraction as much as those two
#: groups' distances to each other sits on their joint (see :func:`join_markers_on_joints`). Measured on the real
#: takes of the shared folders: lateral epicondyles between an arm's and a forearm's clusters, 0.16-0.18 (right
#: arms of two wheelchair takes) and 0.43 (left); lone thigh markers between pelvis and shank 0.46-0.58; every
#: other lone marker 0.85 or more.
ON_JOINT_RATIO = 0.25


def join_markers_on_joints(std: np.ndarray, mean_d: np.ndarray,
                           labels: np.ndarray) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """Each marker alone that sits on the joint of two groups joins the one it varies less against ("on a joint").

    A marker on a joint's axis keeps its distances to the markers of both bodies the joint links, however
    much the joint turns: its distance stds to both groups are a small fraction (``ON_JOINT_RATIO``) of the
    stds between the two groups themselves. Left alone it would be a segment between them whose two joints
    both sit on it: a link of no length, which no data place (a wheelchair racer's epicondyle marker
    between the clusters of the arm and the forearm, made the hub of the arm). The groups: the two of two or
    more markers it varies least against; it must lie between them, nearer each (mean distance) than they
    are to each other (far from both, distances vary little for any marker). Returns the labels numbered by
    first marker and the moves.
    """
    lab = np.array(labels, dtype=int)
    M = lab.size
    S = np.nan_to_num(std, nan=np.inf)
    D = np.nan_to_num(mean_d, nan=np.inf)
    moves: list[tuple[int, str]] = []
    sizes = np.bincount(lab)
    for m in [i for i in range(M) if sizes[lab[i]] == 1]:
        rows = [(float(S[m, mem].mean()), g, mem) for g, mem in _other_groups(lab, m)]
        if len(rows) < 2:
            continue
        rows.sort(key=lambda r: r[0])
        (sa, ga, ma), (sb, _, mb) = rows[:2]
        between = float(S[np.ix_(ma, mb)].mean())
        apart = float(D[np.ix_(ma, mb)].mean())
        if (np.isfinite(between) and sb <= ON_JOINT_RATIO * between
                and D[m, ma].mean() < apart and D[m, mb].mean() < apart):
            lab[m] = ga
            moves.append((m, "on a joint"))
    return by_first_marker(lab), moves


#: A marker moves to another group when that group's moving frame holds it at least this many times
#: tighter than its own group's frame does (rms scatter about its mean place, its own group's frame
#: fitted without it), both as measured and beyond each frame's own fitting error. Distance stds hide
#: a body's motion from a marker that lies near the axis of that motion; the frame does not. The moves
#: made on the realistic generated takes and the real takes of the shared folders: held 2.2-3.9 times
#: tighter (a back-waist marker that a walk whose lumbar joint hardly moves had put with the thorax,
#: 2.2; an elbow marker put with the acromions, 3.9; malleolus and knee markers to the other segment
#: of their joint, 2.2-2.8). A heel held 2.1 times tighter by its shank's frame, in a hip trial whose
#: ankle hardly moves, stays: beyond the fitting error of its own frame (three forefoot markers, far
#: from it) only 1.6 times.
REFRAME_RATIO = 2.0


def reassign_by_frame(points: np.ndarray, labels: np.ndarray,
                      ratio: float = REFRAME_RATIO) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """Move each marker to the group whose moving frame holds it clearly tighter than its own group's.

    For every marker of a group of four or more, how far it moves in the frame of the rest of its group
    is compared with how far it moves in the frame of every other group of three or more (both as
    measured and beyond the frames' own fitting error). Where another holds it ``ratio`` times tighter
    both ways, while its own group's other markers (their median) scatter in that frame at least
    ``ratio`` times as much as it does (the two groups do move apart: where they hardly do, a marker's
    place between them is arbitrary), the marker moves there ("reframed"). One move at a time, the
    clearest first, the two groups' frames then fitted again. points : (K, M, 3) sampled frames, NaN
    where unseen; labels : (M,). Returns the labels numbered by first marker and the moves.
    """
    lab = np.array(labels, dtype=int)
    M = lab.size
    moves: list[tuple[int, str]] = []
    cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
    for _ in range(M):
        groups = [np.flatnonzero(lab == g) for g in range(lab.max() + 1)]
        for idx in groups:
            if idx.size >= 3 and tuple(idx) not in cache:
                cache[tuple(idx)] = frame_scatters(points, idx, SPLIT_FRAMES, SPLIT_MIN_FRAMES)
        best = None
        for g, idx in enumerate(groups):
            if idx.size < 4:
                continue
            for k, m in enumerate(idx):
                own = cache[tuple(idx)][1][:, k]
                if not np.isfinite(own).all():
                    continue
                mates = idx[idx != m]
                for h, hidx in enumerate(groups):
                    if h == g or hidx.size < 3:
                        continue
                    sc = cache[tuple(hidx)][0]
                    if not (sc[:, m] * ratio < own).all() or (best is not None and own[0] / sc[0, m] <= best[0]):
                        continue
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        apart = np.nanmedian(sc[0, mates])
                    if apart >= ratio * sc[0, m]:
                        best = (own[0] / sc[0, m], int(m), h)
        if best is None:
            break
        lab[best[1]] = best[2]
        moves.append((best[1], "reframed"))
    return by_first_marker(lab), moves


def _seen_together(points: np.ndarray, idx: np.ndarray) -> np.ndarray | None:
    """The markers ``idx`` of ``points`` (K, M, 3) on the frames where all are seen, (K', n, 3); None when
    fewer than ``SPLIT_MIN_FRAMES`` are."""
    P = points[:, idx]
    P = P[np.isfinite(P).all(axis=(1, 2))]
    return P if len(P) >= SPLIT_MIN_FRAMES else None


def _median_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Median over frames of the distance between the point trajectories ``a`` and ``b`` (K, 3)."""
    return float(np.median(np.linalg.norm(a - b, axis=1)))


def absorb_pairs(points: np.ndarray, labels: np.ndarray, reveal: float, mean_d: np.ndarray,
                 reach: float, tau: float) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """Each group of two markers that moves against some group of three or more by too little for
    the joint between them to be located joins that group ("absorbed with its pair"); before, two
    pairs that cross each other and move as one rigid body (within ``tau``) are joined.

    The bar is the one a lone marker must pass (:func:`absorb_lone_markers` with ``reveal``): each
    of the two markers' rms scatter about its mean place in the other group's moving frame (that
    group's markers fitted as a rigid body on the frames where all are seen) at most ``reveal``.
    Two markers of one body that skin motion moves against the rest of it (a shoulder marker and a
    clavicle marker on a thorax, the two acromion markers of a subject holding a guard) otherwise
    make a segment whose joint no data locate, and the tree hangs the arms, or the head, on it.
    Groups of three or more are candidates only when one of their markers is within ``reach``
    (``mean_d``: mean marker distances) of one of the pair. The pair with the least scatter goes
    first, then the others again, until none passes. points : (K, M, 3) the sampled frames.
    Returns the labels numbered by first marker and the moves.
    """
    lab = np.array(labels, dtype=int)
    near = np.nan_to_num(mean_d, nan=np.inf) <= reach
    moves: list[tuple[int, str]] = []
    # two pairs that cross each other (the distance between their middles less than either's own
    # span) and move as one rigid body (rigid-fit residual within ``tau``) are one body the grouping
    # split, a pelvis's four markers paired diagonally: joined first (two thighs that move together
    # in a jump lie side by side, their middles farther apart than their spans)
    sizes = np.bincount(lab)
    pairs = [np.flatnonzero(lab == g) for g in np.flatnonzero(sizes == 2)]
    joined: set[int] = set()
    for i in range(len(pairs)):
        for j in range(i + 1, len(pairs)):
            if i in joined or j in joined:
                continue
            Q = _seen_together(points, np.concatenate([pairs[i], pairs[j]]))
            if Q is None:
                continue
            gap = _median_gap(Q[:, :2].mean(1), Q[:, 2:].mean(1))
            if gap < min(_median_gap(Q[:, 0], Q[:, 1]), _median_gap(Q[:, 2], Q[:, 3])) and rigid_rms(Q) <= tau:
                lab[pairs[j]] = lab[pairs[i][0]]
                moves += [(int(m), "joined a crossing pair") for m in pairs[j]]
                joined |= {i, j}
    _, lab = np.unique(lab, return_inverse=True)
    while True:
        sizes = np.bincount(lab)
        best = None
        for g in np.flatnonzero(sizes == 2):
            pair = np.flatnonzero(lab == g)
            for h in np.flatnonzero(sizes >= 3):
                mem = np.flatnonzero(lab == h)
                if not near[np.ix_(pair, mem)].any():
                    continue
                Q = _seen_together(points, np.concatenate([mem, pair]))
                if Q is None:
                    continue
                # the pair straddles the group (its middle nearer the group's centroid than its two
                # markers are apart): a part of that body, not a limb beside or below it
                if not _median_gap(Q[:, -2:].mean(1), Q[:, :-2].mean(1)) < _median_gap(Q[:, -1], Q[:, -2]):
                    continue
                worst = float(scatter_in_frame(Q, np.arange(mem.size))[mem.size:].max())
                if worst <= reveal and (best is None or worst < best[0]):
                    best = (worst, int(g), int(h), pair)
        if best is None:
            return by_first_marker(lab), moves
        _, g, h, pair = best
        lab[pair] = h
        moves += [(int(m), "absorbed with its pair") for m in pair]
        _, lab = np.unique(lab, return_inverse=True)


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


def run(markers: Markers, params: Params = Params()) -> Segments:
    """Group the markers of a take into rigid segments.

    Raises DataError when fewer than two segments can be told apart.
    """
    rng = np.random.default_rng(params.seed)
    F, M, _ = markers.points.shape
    if M < 2:
        raise DataError(f"only {M} marker — a skeleton needs markers on at least two segments", markers.source or None)
    samplings = [sample_frames(F, markers.rate, params, rng) for _ in range(params.n_samplings)]
    stds = []
    seen = np.zeros(M, dtype=int)
    for si, s in enumerate(samplings):
        pts = markers.points[s]
        d = _pair_distances(pts)
        std, cnt = _distance_std(pts, d)
        if si == 0:
            first = d  # the marker spread (below) is measured on the first sampling
        stds.append(std)
        seen = np.maximum(seen, np.diag(cnt))
    use = seen >= params.min_seen
    if use.sum() < 2:
        raise DataError("fewer than two markers are seen often enough to be grouped", markers.source or None)
    iu = np.flatnonzero(use)
    with warnings.catch_warnings():  # pairs never seen together stay NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        pooled = np.nanmedian(np.stack(stds), axis=0)[np.ix_(iu, iu)]
    k = params.n_segments
    if k is not None and k > iu.size:  # before the eigen-gap, which indexes k eigenvalues
        raise DataError(
            f"asked for {k} segments but only {iu.size} markers are seen often enough — ask for fewer segments",
            markers.source or None,
        )
    off = pooled[~np.eye(pooled.shape[0], dtype=bool)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        md = np.nanmean(first, axis=0)  # mean distance of every marker pair
    size = float(np.nanmedian(md)) if np.isfinite(md).any() else 0.0
    level = skin_level(pooled, COMPUTED_FRAC * size)
    tau = max(params.rigid_k * level, COMPUTED_FRAC * size)  # exact data: rigid to rounding
    p95 = float(np.nanpercentile(off, 95)) if np.isfinite(off).any() else 0.0
    still = max(tau, params.motion_frac * size)
    if k is None and not p95 > still and not p95 > RIGID_FRAC * size:
        raise DataError(
            f"all markers move as one rigid body (95 % of marker distances vary by less than {still:.3g} mm,"
            f" {params.rigid_k:g} times the take's own skin and noise level or {params.motion_frac:g} of the"
            " median marker distance)"
            " — nothing moves relative to anything, so there is no joint to find",
            markers.source or None,
        )
    if params.n_segments is None:
        X = markers.points[samplings[0]][np.isfinite(markers.points[samplings[0]]).all(-1)]
        if len(X) >= 3 and _flat(X):
            raise DataError("the take is flat: every marker lies in one plane — joints need 3-D data", markers.source or None)
        offd = pooled[~np.eye(iu.size, dtype=bool)]
        offd = offd[np.isfinite(offd)]
        if offd.size and level > NO_PAIR_FRAC * float(np.median(offd)):
            # the "level" is itself the std across joints: no two markers ride on one body
            raise DataError(
                f"every segment carries a single marker ({iu.size} segments) — a joint needs at least 3 markers"
                " on its two segments: put 2 or 3 markers on each segment",
                markers.source or None,
            )
    sigma, k_auto, eig = choose_sigma(pooled, params.sigma_mm, k)
    split = []
    split_info: list[dict] = []
    if k is None:
        # the rigid groups at the take's own tolerance, then markers left alone given a place
        lab = rigid_groups(pooled, tau)
        mean_d = np.full((M, M), np.nan)
        ti, tj = np.triu_indices(M, 1)
        mean_d[ti, tj] = mean_d[tj, ti] = md
        mean_d = mean_d[np.ix_(iu, iu)]
        np.fill_diagonal(mean_d, 0.0)
        ext = [_extent(mean_d, np.flatnonzero(lab == g)) for g in range(lab.max() + 1) if (lab == g).sum() > 1]
        reach = params.reach * float(np.median(ext)) if ext else np.inf
        sampled = markers.points[samplings[0]][:, iu]

        def turns(m: int, g: np.ndarray) -> bool:
            return turns_about_a_point(sampled, m, g, level)

        lab, moves = pair_lone_markers(pooled, mean_d, lab, params.join_k * tau, params.free_k * tau, reach,
                                       keep=turns)
        if params.motion_frac * size > tau:
            lab = merge_still_groups(pooled, lab, params.motion_frac * size)
        if ext:
            # a marker alone is a segment only if its joint can be found: moving by d against a group,
            # at a distance R (a segment's size) from its joint, it sweeps a cap of angle d / R, on which
            # a sphere fit's radius is known to about level / (d / R)^2 — no better than R itself unless
            # d > sqrt(level R)
            # (the largest segments, a pelvis or a trunk, are two or three times the median group's size)
            reveal = float(np.sqrt(level * np.median(ext)))
            lab, more = absorb_lone_markers(pooled, mean_d, lab, reveal, 2.0 * reach, nearest=True, keep=turns)
            moves += more
            lab, more = join_markers_on_joints(pooled, mean_d, lab)
            moves += more
            if params.absorb_pairs:
                lab, more = absorb_pairs(sampled, lab, reveal, mean_d, 2.0 * reach, tau)
                moves += more
            if params.split_nonrigid:
                lab, splits = split_nonrigid(sampled, pooled, lab, tau, reveal,
                                             np.random.default_rng(params.seed))
                split_info = [{"parts": [[markers.labels[iu[i]] for i in part] for part in parts],
                               "rigid_rms_mm": round(r, 3)} for parts, r in splits]
            if params.reframe:
                lab, more = reassign_by_frame(sampled, lab)
                moves += more
        split = [[markers.labels[iu[i]], how] for i, how in moves]
        si = 0
        cost = spread_cost(pooled, lab)
    else:
        if k > iu.size:
            raise DataError(f"asked for {k} segments but only {iu.size} usable markers", markers.source or None)
        best = None
        for si, std in enumerate(stds):
            sub = std[np.ix_(iu, iu)]
            res = spectral_clustering(affinity(sub, sigma), k, rng=rng)
            cost = spread_cost(sub, res.labels)
            if best is None or cost < best[0] - 1e-12:
                best = (cost, si, res.labels)
        cost, si, lab = best
    group = np.full(M, -1, dtype=int)
    group[iu] = lab
    # number groups by the first marker in each, for stable output
    order = {}
    for g in group:
        if g >= 0 and g not in order:
            order[g] = len(order)
    group = np.array([order.get(g, -1) for g in group], dtype=int)
    n = len(order)
    if n < 2:
        raise DataError(
            "all markers move as one rigid body — nothing moves relative to anything, so there is no joint to find",
            markers.source or None,
        )
    info = {
        "version": VERSION,
        "n_segments": n,
        "auto": params.n_segments is None,
        "sampling": int(si),
        "samples": int(samplings[si].size),
        "spread_cost": cost,
        "sigma_mm": sigma,
        "left_out": [markers.labels[i] for i in np.flatnonzero(~use)],
        "groups": [[markers.labels[i] for i in np.flatnonzero(group == g)] for g in range(n)],
        "moved": split,
        "split_nonrigid": split_info,
        "skin_level_mm": level,
        "size_mm": size,
        "rigid_tolerance_mm": tau,
    }
    return Segments(markers=markers, group=group, dist_std=stds[si], eigvals=eig, info=info)

