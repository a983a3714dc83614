"""Topology: which segments are joined (Kirk et al. 2005, §3.2).

The joint cost of every pair of segments is computed on a drastic subsample of
frames (with Kirk's small distance penalty α so that wrong joints cannot hide
at infinity); the costs are then made again with each one- or two-marker
segment given its cheapest joint as one more point (it fixes the segment's
turn about its marker axis, which a joint with it otherwise leaves free; the
point's variance counts, not its share of the mean cost); the skeleton's tree
is the minimum spanning tree of those costs, each less the part its markers'
own scatter in their segments gives by itself (:func:`own_floor`; Kruskal, equal
costs taken in pair order), a pair whose joint no body has (nearer a third segment's
markers than its own, or far from both) taken only when nothing else connects. The
root is the tree's centre, like a pelvis.

Only the subsample and the per-frame visibility of the segments depend on the
length of the take; both are one pass over the visibility of the markers.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..artifacts import Segments, Topology
from ..model.measures import marker_extent
from ..model.measures import visible as _seen
from ..errors import DataError
from ..solvers.parallel import n_threads, run_forked
from ..solvers.joints.cost import balanced_alpha, distance_penalty
from ..solvers.joints.mtb import mtb_basis
from ..solvers.grouping.pair_cost import pair_cost
from ..solvers.grouping.partition import rigid_rms

VERSION = 12


#: Frames of each pair's cost (``pair_cost``'s subsample of the common frames).
PAIR_FRAMES = 40
#: A segment's own floor (:func:`own_floor`) needs all its markers seen together on this many frames.
OWN_FLOOR_FRAMES = 5


@dataclass(frozen=True)
class Params:
    n_frames: int = 100
    """Frames (evenly spread over the take, best-visible first) used for the pair costs."""
    alpha: float | None = None
    """Kirk's distance penalty (mm^2 of cost per mm of mean distance); None: from the take,
    ``alpha_k`` times the skin-and-noise variance the segment stage measured per median
    marker distance, so that a joint as far from its markers as markers are from each
    other costs ``alpha_k`` skin variances (the prior that a joint sits near its
    segments' markers; Kirk notes it helps where the motion does not exercise every
    degree of freedom)."""
    alpha_k: float = 8.0
    nearer: float = 0.7
    """A pair's joint is implausible when some third segment's nearest marker is closer to it
    than this fraction of the nearer of its own two segments' nearest markers (the farther is no
    measure: a hip sits far from a thigh's markers at mid-thigh and knee, and a hanging arm's
    elbow is nearer)."""
    far: float = 0.5
    """...or lies farther than this fraction of the subject's marker extent from every marker of its two
    segments (the output check ``joint_far``'s bar)."""
    elsewhere_factor: float = 10.0
    """Cost factor of such a pair (kept finite: the tree may still need it)."""
    own_floor: bool = True
    """Choose the tree on each pair's cost less the part its markers' own scatter gives (see
    :func:`own_floor`); the reported costs are Kirk's."""
    augment: bool = True
    """Cost the pairs again with each one- or two-marker segment given its cheapest joint as a
    third point (see :func:`_augmented_costs`)."""


def subsample(points: np.ndarray, n: int, *, visible: np.ndarray | None = None) -> np.ndarray:
    """Indices of ``n`` frames spread evenly over the take, each the best-visible in its slice.

    ``visible`` : the (F, M) visibility of ``points``, when the caller has it.
    """
    F = points.shape[0]
    if F <= n:
        return np.arange(F)
    vis = (_seen(points) if visible is None else visible).sum(1)
    edges = np.linspace(0, F, n + 1).astype(int)
    return np.array([a + int(np.argmax(vis[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a])


def pair_frames(seen_a: np.ndarray, seen_b: np.ndarray, frames: np.ndarray, n: int) -> np.ndarray:
    """Frames for one pair's cost: the common subsample where both are seen, or,
    when that leaves too few, up to ``n`` frames spread over all frames where both are."""
    fr = frames[(seen_a[frames] > 0) & (seen_b[frames] > 0)]
    if fr.size >= min(20, n):
        return fr
    allf = np.flatnonzero((seen_a > 0) & (seen_b > 0))
    if allf.size <= n:
        return allf
    return allf[np.linspace(0, allf.size - 1, n).round().astype(int)]


def minimum_spanning_tree(n_nodes: int, cost: np.ndarray) -> np.ndarray | None:
    """Kruskal's minimum spanning tree of a symmetric cost matrix (inf: no edge).

    Edges are tried by increasing cost, equal costs in pair order ``(a, b)``,
    ``a < b``, as networkx's Kruskal does. Returns the (n_nodes - 1, 2) edges
    in the order they were taken, or None when the graph is not connected.
    """
    a, b = np.triu_indices(n_nodes, 1)
    w = cost[a, b]
    ok = np.isfinite(w)
    a, b, w = a[ok], b[ok], w[ok]
    root = list(range(n_nodes))

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    taken = []
    for k in np.argsort(w, kind="stable"):
        ra, rb = find(int(a[k])), find(int(b[k]))
        if ra != rb:
            root[rb] = ra
            taken.append((int(a[k]), int(b[k])))
    if len(taken) != n_nodes - 1:
        return None
    return np.array(taken, dtype=int).reshape(-1, 2)


def _neighbours(n_nodes: int, edges: np.ndarray) -> list[list[int]]:
    """Adjacency lists, each in the order the edges are listed."""
    nb: list[list[int]] = [[] for _ in range(n_nodes)]
    for a, b in edges.tolist():
        nb[a].append(b)
        nb[b].append(a)
    return nb


def _bfs(nb: list[list[int]], source: int) -> tuple[list[tuple[int, int]], list[int]]:
    """Breadth-first edges (parent, child) from ``source`` and the hop distance of every node."""
    dist = [-1] * len(nb)
    dist[source] = 0
    out = []
    queue = deque([source])
    while queue:
        p = queue.popleft()
        for c in nb[p]:
            if dist[c] < 0:
                dist[c] = dist[p] + 1
                out.append((p, c))
                queue.append(c)
    return out, dist


def tree_centre(n_nodes: int, edges: np.ndarray, size: dict[int, int]) -> int:
    """The centre of a tree (least eccentricity); ties go to the node with the least total distance, then most markers."""
    nb = _neighbours(n_nodes, edges)
    dist = [_bfs(nb, s)[1] for s in range(n_nodes)]
    ecc = [max(d) for d in dist]
    best = min(ecc)
    cands = [s for s in range(n_nodes) if ecc[s] == best]
    return min(cands, key=lambda s: (sum(dist[s]), -size.get(s, 0), s))


def _nearer_elsewhere(centre: np.ndarray, pts: np.ndarray, members: list, a: int, b: int, ratio: float,
                      far: float = np.inf) -> bool:
    """Whether the joint ``centre`` (K, 3) of segments ``a`` and ``b`` sits nearer to another segment, or
    farther than ``far`` from every marker of both: no joint of theirs lies there.

    Each segment's distance is the median over frames of its nearest marker's distance to the joint;
    the joint belongs elsewhere when another segment's is below ``ratio`` times the smaller of ``a``'s
    and ``b``'s. Far: the median over frames of the distance of the nearest marker of the two.
    pts : (K, M, 3) the markers on the same frames.
    """
    if centre is None or not np.isfinite(centre).any():
        return False
    with np.errstate(invalid="ignore"):
        d = np.linalg.norm(pts - centre[:, None, :], axis=2)  # (K, M)
    if np.isfinite(far):
        dm = d[:, np.concatenate([members[a], members[b]])]
        ok = np.isfinite(dm).any(axis=1)
        if ok.any() and float(np.median(np.nanmin(dm[ok], axis=1))) > far:
            return True
    near = []
    for mem in members:
        dm = d[:, mem]
        ok = np.isfinite(dm).any(axis=1)
        near.append(float(np.median(np.nanmin(dm[ok], axis=1))) if ok.any() else np.inf)
    own = min(near[a], near[b])
    others = [near[s] for s in range(len(members)) if s not in (a, b)]
    return bool(others) and bool(np.isfinite(own)) and min(others) < ratio * own


def run(segments: Segments, params: Params = Params()) -> Topology:
    """Find the tree of segments and direct it away from the root."""
    pts = segments.markers.points
    S = segments.n_segments
    if S < 2:
        raise DataError("fewer than two segments — nothing to connect", segments.markers.source or None)
    alpha = params.alpha if params.alpha is not None else distance_penalty(segments.info, params.alpha_k)
    vis = _seen(pts)
    frames = subsample(pts, params.n_frames, visible=vis)
    # markers of each segment seen in each frame: one product with the (M, S) membership
    member = np.zeros((pts.shape[1], S), dtype=np.float32)
    inseg = segments.group >= 0
    member[np.flatnonzero(inseg), segments.group[inseg]] = 1.0
    seen = (vis.astype(np.float32) @ member).astype(np.int64)  # (F, S), exact small counts
    C = np.full((S, S), np.inf)
    members = [segments.members(s) for s in range(S)]
    # pair_cost's own subsample of the common frames, and each group's basis on it, made once
    # for all the group's pairs that use those frames
    k = min(PAIR_FRAMES, frames.size)
    sub = pts[frames[np.unique(np.linspace(0, frames.size - 1, k).round().astype(int))]]
    bases = [mtb_basis(sub[:, members[s]]) if members[s].size >= 3 else None for s in range(S)]
    elsewhere = np.zeros((S, S), dtype=bool)
    far = params.far * marker_extent(pts, columns=inseg)
    on_sub: dict[tuple[int, int], np.ndarray] = {}  # (a, b), a < b: the joint on the common subsample
    def cost_pair(ab: tuple[int, int]):
        a, b = ab
        fr = pair_frames(seen[:, a], seen[:, b], frames, params.n_frames)
        if not fr.size:
            return None
        if fr.size == frames.size and np.array_equal(fr, frames):
            at = sub
            q, c = pair_cost(sub[:, members[a]], sub[:, members[b]], alpha=alpha,
                             frames=np.arange(sub.shape[0]), bases=(bases[a], bases[b]), return_centre=True)
        else:
            pf = pts[fr]
            at = pf[np.unique(np.linspace(0, fr.size - 1, min(PAIR_FRAMES, fr.size)).round().astype(int))]
            q, c = pair_cost(at[:, members[a]], at[:, members[b]], alpha=alpha, frames=np.arange(at.shape[0]),
                             return_centre=True)
        return q, (c if at is sub else None), _nearer_elsewhere(c, at, members, a, b, params.nearer, far)

    # the pairs are independent: shared out between processes (each pair's cost is the same either way)
    pairs = [(a, b) for a in range(S) for b in range(a + 1, S)]
    k = max(1, min(n_threads(), len(pairs) // 8))
    shares = run_forked(lambda j: [cost_pair(ab) for ab in pairs[j::k]], range(k))
    for j in range(k):
        for (a, b), got in zip(pairs[j::k], shares[j]):
            if got is None:
                continue
            q, c, far = got
            C[a, b] = C[b, a] = q
            elsewhere[a, b] = elsewhere[b, a] = far
            if c is not None:
                on_sub[a, b] = c
    # a joint that sits nearer to a third segment's markers than to its own two is not theirs (two
    # limbs that swing about one axis "join" on it, inside the trunk): taken only if nothing else connects
    C = np.where(elsewhere, C * params.elsewhere_factor, C)
    first = C
    if params.augment:
        C = _augmented_costs(C, sub, members, on_sub, alpha, params)
    # the tree is chosen on each pair's cost less what its markers' own scatter in their segments
    # gives by itself: a segment that is not quite rigid (a trunk whose lumbar joint the take
    # hardly moves) otherwise costs more with every partner, and two rigid limbs that swing about
    # one axis (the upper arms in a walk) "join" more cheaply than either joins it
    floor = own_floor(sub, members) if params.own_floor else np.zeros(S)
    n = np.array([m.size for m in members], dtype=float)
    E = (n[:, None] * floor[:, None] + n[None, :] * floor[None, :]) / np.maximum(n[:, None] + n[None, :], 1.0)
    tree = minimum_spanning_tree(S, C - E)
    if tree is None:
        raise DataError("some segments are never seen together with the others — cannot connect them", segments.markers.source or None)
    # the tree's edges in the order of the first costs (as Kruskal took them before the costs were made
    # again): where the second costs keep the tree, its edges and joints keep their order
    tree = tree[np.argsort([first[a, b] for a, b in tree.tolist()], kind="stable")]
    root = tree_centre(S, tree, {s: int((segments.group == s).sum()) for s in range(S)})
    edges = np.array(_bfs(_neighbours(S, tree), root)[0], dtype=int).reshape(-1, 2)
    cost = np.array([C[a, b] for a, b in edges])
    info = {"version": VERSION, "frames_used": int(frames.size), "alpha": alpha,
            "own_floor_mm2": [round(float(f), 3) for f in floor]}
    return Topology(segments=segments, edges=edges, cost=cost, pair_cost=C, root=int(root), info=info)


def own_floor(sub: np.ndarray, members: list) -> np.ndarray:
    """(S,) each segment's floor of Kirk's joint cost: what its markers' scatter about their places in
    the segment's own frame gives by itself, whatever the joint.

    A marker that scatters by ``s`` (rms, in 3-D, equally in every direction) about its place varies
    in distance to any point fixed in the segment by ``s^2 / 3`` (the radial part), so a segment's
    floor is a third of its squared rigid-fit residual (generalised Procrustes on the frames of
    ``sub`` (K, M, 3) where all its markers are seen). A segment of one or two markers has no frame
    to measure it in: it gets the least floor of the others (the take's cleanest rigid body). A
    pair's floor is the marker-weighted mean of its two segments' (Kirk's cost is a mean over the
    markers of both).
    """
    S = len(members)
    floor = np.full(S, np.nan)
    for s in range(S):
        if members[s].size < 3:
            continue
        P = sub[:, members[s]]
        P = P[np.isfinite(P).all(axis=(1, 2))]
        if len(P) >= OWN_FLOOR_FRAMES:
            floor[s] = rigid_rms(P) ** 2 / 3.0
    least = float(np.nanmin(floor)) if np.isfinite(floor).any() else 0.0
    return np.where(np.isfinite(floor), floor, least)


def _augmented_costs(C: np.ndarray, sub: np.ndarray, members: list, on_sub: dict, alpha: float,
                     params: Params) -> np.ndarray:
    """The pair costs again, each segment of one or two markers given its cheapest joint as one more point.

    A segment of two markers has no frame: its turn about its marker axis is free, so a joint
    with it need only keep two distances, and two such segments that move together (two thighs
    in a jump) "join" anywhere their two circles meet. Its cheapest joint (a knee for a thigh) is
    a point of the segment that fixes that turn; with it, a joint must be fixed in the segment's
    frame, as for a segment of three markers, and the costs of groups of 1, 2 and many markers
    compare. Only pairs costed on the common subsample ``sub`` are costed again: ``on_sub`` holds
    their joints there, by (a, b) with a < b.
    """
    S = len(members)
    M = sub.shape[1]
    extra: dict[int, np.ndarray] = {}
    partner: dict[int, int] = {}
    for s in range(S):
        if members[s].size >= 3 or not np.isfinite(C[s]).any():
            continue
        t = int(np.argmin(C[s]))
        c = on_sub.get((min(s, t), max(s, t)))
        if c is not None and np.isfinite(c).all():
            extra[s], partner[s] = c, t
    if not extra:
        return C
    order = sorted(extra)
    pts = np.concatenate([sub] + [extra[s][:, None] for s in order], axis=1)
    idx = list(members)
    for k, s in enumerate(order):
        idx[s] = np.append(members[s], M + k)
    out = C.copy()
    for a in range(S):
        for b in range(a + 1, S):
            # a segment's joint with the partner that gave it its point is costed without that point
            # (the point is that joint: the pair would join on it at no cost)
            ia = idx[a] if partner.get(a, -1) != b else members[a]
            ib = idx[b] if partner.get(b, -1) != a else members[b]
            if ia is members[a] and ib is members[b] or (a, b) not in on_sub:
                continue
            q, c = pair_cost(pts[:, ia], pts[:, ib], alpha=alpha, frames=np.arange(sub.shape[0]), return_centre=True)
            # Q is a mean over the points: the added point's term is counted, not its share of the mean (a
            # point the joint can sit on would otherwise lower the cost by dilution alone: a head moving with
            # the trunk "joined" the upper arm at the trunk's shoulder point, 7.1 against the trunk's 7.5)
            both = np.concatenate([ia, ib])
            added = np.flatnonzero(both >= M)
            if added.size:
                # summed over the real markers only, the added points' variances kept (what they say of
                # the joint) and their distance penalties (weight times mean distance) not: the prior is
                # about the markers
                weight = np.broadcast_to(balanced_alpha(alpha, ia.size, ib.size), both.shape)[added]
                with np.errstate(invalid="ignore"):
                    dist = np.nanmean(np.linalg.norm(pts[:, both[added]] - c[:, None, :], axis=2), axis=0)
                q = (q * both.size - float(weight @ dist)) / (members[a].size + members[b].size)
            use = list(idx)
            use[a], use[b] = ia, ib
            q *= params.elsewhere_factor if _nearer_elsewhere(c, pts, use, a, b, params.nearer) else 1.0
            out[a, b] = out[b, a] = q
    return out
