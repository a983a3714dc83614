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

from dataclasses import dataclass

import warnings

import numpy as np

from ..artifacts import Markers, Segments
from ..errors import DataError
from ..solvers.grouping.distances import (
    _distance_std, _extent, _flat, _pair_distances, affinity, choose_sigma, computed_points, merge_still_groups,
    rigid_groups, skin_level, spread_cost,
)
from ..solvers.grouping.grouping import (
    absorb_lone_markers, absorb_pairs, join_markers_on_joints, pair_lone_markers, reassign_by_frame, split_nonrigid,
    turns_about_a_point,
)
from ..solvers.grouping.spectral import spectral_clustering

VERSION = 13


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


def take_levels(markers: Markers, params: Params = Params()) -> dict:
    """The take's own scales that the later stages read from the segment stage's info: ``skin_level_mm``
    (the skin-and-noise level, a distance std), ``size_mm`` (the median marker distance) and
    ``rigid_tolerance_mm``, measured as :func:`run` measures them (on one sampling of frames instead of
    the median of several), for a grouping made elsewhere (:func:`~mocapskel.evaluate.true_topology`):
    without them the joints stage's distance penalty is zero and a joint that the motion leaves free
    along a line runs off along it."""
    rng = np.random.default_rng(params.seed)
    pts = markers.points[sample_frames(markers.points.shape[0], markers.rate, params, rng)]
    d = _pair_distances(pts)
    std, cnt = _distance_std(pts, d)
    with warnings.catch_warnings():  # markers never seen (together): NaN, left out
        warnings.simplefilter("ignore", RuntimeWarning)
        md = np.nanmean(d, axis=0)
        size = float(np.nanmedian(md)) if np.isfinite(md).any() else 0.0
    seen = np.diag(cnt) >= params.min_seen
    level = skin_level(std[np.ix_(seen, seen)], COMPUTED_FRAC * size)
    tau = max(params.rigid_k * level, COMPUTED_FRAC * size)
    return {"skin_level_mm": level, "size_mm": size, "rigid_tolerance_mm": tau}


def _computed(markers: Markers, iu: np.ndarray, pooled: np.ndarray, floor: float) -> tuple[np.ndarray, list, list]:
    """The points among ``iu`` that a model computed (see :func:`computed_points`): their mask over ``iu``,
    ``[label, why]`` for each, and the warning that says so."""
    computed = computed_points(pooled, floor)
    if not computed.any():
        return computed, [], []
    S = np.where(np.eye(iu.size, dtype=bool), np.inf, np.nan_to_num(pooled, nan=np.inf))
    tight = np.sort(S[computed], axis=1)[:, 1]
    measured = skin_level(pooled[np.ix_(~computed, ~computed)])
    labels = [markers.labels[i] for i in iu[computed]]
    why = (f"computed by a model: rigid with its neighbours to {float(np.max(tight)):.3g} mm or better, and with"
           " points on two bodies that move against each other")
    info = [[lab, why] for lab in labels]
    shown = ", ".join(labels[:12]) + (" …" if len(labels) > 12 else "")
    said = [f"{len(labels)} points left out of the fit as computed by a model (joint centres, a body model's"
            f" points), however they are labelled: {shown} — each keeps its distances to within"
            f" {float(np.max(tight)):.3g} mm, far below the take's own {measured:.2g} mm, and sits rigidly on two"
            " bodies that move against each other, as no marker can"]
    return computed, info, said


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
        md = np.nanmean(first, axis=0)  # mean distance of every marker pair
    size = float(np.nanmedian(md)) if np.isfinite(md).any() else 0.0
    computed, computed_info, said = _computed(markers, iu, pooled, COMPUTED_FRAC * size)
    if computed.any():
        # the points a model computed are left out as markers seen too rarely are, and the take measured without them
        use[iu[computed]] = False
        iu, pooled = iu[~computed], pooled[np.ix_(~computed, ~computed)]
        ti, tj = np.triu_indices(M, 1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            size = float(np.nanmedian(md[use[ti] & use[tj]]))
    k = params.n_segments
    if k is not None and k > iu.size:  # before the eigen-gap, which indexes k eigenvalues
        raise DataError(
            f"asked for {k} segments but only {iu.size} markers are seen often enough — ask for fewer segments",
            markers.source or None,
        )
    off = pooled[~np.eye(pooled.shape[0], dtype=bool)]
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
        "computed": computed_info,
        "warnings": said,
        "groups": [[markers.labels[i] for i in np.flatnonzero(group == g)] for g in range(n)],
        "moved": split,
        "split_nonrigid": split_info,
        "skin_level_mm": level,
        "size_mm": size,
        "rigid_tolerance_mm": tau,
    }
    return Segments(markers=markers, group=group, dist_std=stds[si], eigvals=eig, info=info)

