"""Topology: which segments are joined (Kirk et al. 2005, §3.2).

The joint cost of every pair of segments is computed on a drastic subsample of
frames (with Kirk's small distance penalty α so that wrong joints cannot hide
at infinity); the skeleton's tree is the minimum spanning tree of those costs
(networkx). The root is the tree's centre, like a pelvis.
"""
from __future__ import annotations

from dataclasses import dataclass

import networkx as nx
import numpy as np

from ..artifacts import Segments, Topology
from ..errors import DataError
from ..solvers.jmv import pair_cost

VERSION = 2


@dataclass(frozen=True)
class Params:
    n_frames: int = 100
    """Frames (evenly spread over the take, best-visible first) used for the pair costs."""
    alpha: float = 0.01
    """Kirk's distance penalty (mm^2 of cost per mm of mean distance)."""


def subsample(points: np.ndarray, n: int) -> np.ndarray:
    """Indices of ``n`` frames spread evenly over the take, each the best-visible in its slice."""
    F = points.shape[0]
    if F <= n:
        return np.arange(F)
    vis = np.isfinite(points).all(-1).sum(1)
    edges = np.linspace(0, F, n + 1).astype(int)
    return np.array([a + int(np.argmax(vis[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a])


def pair_frames(seen_a: np.ndarray, seen_b: np.ndarray, frames: np.ndarray, n: int) -> np.ndarray:
    """Frames for one pair's cost: the common subsample where both are seen, or,
    when that leaves too few, up to ``n`` frames spread over all frames where both are."""
    both = (seen_a > 0) & (seen_b > 0)
    fr = frames[both[frames]]
    if fr.size >= min(20, n):
        return fr
    allf = np.flatnonzero(both)
    if allf.size <= n:
        return allf
    return allf[np.linspace(0, allf.size - 1, n).round().astype(int)]


def tree_centre(tree: nx.Graph, size: dict[int, int]) -> int:
    """The centre of a tree (least eccentricity); ties go to the node with the least total distance, then most markers."""
    ecc = nx.eccentricity(tree)
    best = min(ecc.values())
    cands = [n for n, e in ecc.items() if e == best]
    dist = {n: sum(nx.single_source_shortest_path_length(tree, n).values()) for n in cands}
    return min(cands, key=lambda n: (dist[n], -size.get(n, 0), n))


def run(segments: Segments, params: Params = Params()) -> Topology:
    """Find the tree of segments and direct it away from the root."""
    pts = segments.markers.points
    S = segments.n_segments
    if S < 2:
        raise DataError("fewer than two segments — nothing to connect", segments.markers.source or None)
    frames = subsample(pts, params.n_frames)
    seen = np.stack([np.isfinite(pts[:, segments.members(s)]).all(-1).sum(1) for s in range(S)], axis=1)  # (F, S)
    C = np.full((S, S), np.inf)
    for a in range(S):
        for b in range(a + 1, S):
            fr = pair_frames(seen[:, a], seen[:, b], frames, params.n_frames)
            if fr.size:
                sub = pts[fr]
                C[a, b] = C[b, a] = pair_cost(sub[:, segments.members(a)], sub[:, segments.members(b)], alpha=params.alpha)
    G = nx.Graph()
    G.add_nodes_from(range(S))
    for a in range(S):
        for b in range(a + 1, S):
            if np.isfinite(C[a, b]):
                G.add_edge(a, b, weight=float(C[a, b]))
    if not nx.is_connected(G):
        raise DataError("some segments are never seen together with the others — cannot connect them", segments.markers.source or None)
    T = nx.minimum_spanning_tree(G, weight="weight", algorithm="kruskal")
    root = tree_centre(T, {s: int((segments.group == s).sum()) for s in range(S)})
    edges = np.array([(a, b) for a, b in nx.bfs_edges(T, root)], dtype=int).reshape(-1, 2)
    cost = np.array([C[a, b] for a, b in edges])
    info = {"version": VERSION, "frames_used": int(frames.size), "alpha": params.alpha}
    return Topology(segments=segments, edges=edges, cost=cost, pair_cost=C, root=int(root), info=info)
