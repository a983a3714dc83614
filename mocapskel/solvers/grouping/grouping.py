"""Grouping rules for the rigid groups of markers: a place for markers left alone, pairs that are one
body's skin, groups split where they do not move as one body, markers moved to the frame that holds them."""
from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from .distances import by_first_marker
from .partition import best_split, frame_path, frame_scatters, rigid_rms, scatter_in_frame
from ..spheres.sphere import sphere_lls


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
