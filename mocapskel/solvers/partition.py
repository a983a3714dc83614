"""Two rigid bodies in one marker group: how far a group is from rigid, and its best split in two.

Distances between markers tell segments apart only to second order where markers lie
nearly in line with the joint between them (a trunk bending over a still pelvis and leg
keeps the neck-to-heel distances almost constant), so a group can keep nearly constant
distances and still not move as one body. Its rigid-fit residual shows it: each marker's
scatter about its mean place in the group's own moving frame.

The best split in two is sought among the rigid motions of the group's marker triples:
every marker's scatter in the frame of every triple, the pair of triples whose frames
together leave the least scatter (each marker counted in the frame that explains it
better), then a few rounds of refitting each part and reassigning each marker. All is
vectorised over frames; the loops run over triples and rounds.
"""
from __future__ import annotations

from itertools import combinations

import numpy as np

from .rigid import kabsch, procrustes_shape

#: Triples tried for the split; more than this are sampled (evenly over the combinations' order).
MAX_TRIPLES = 400
#: Triples' frames are computed in chunks of this many (memory: chunk x frames x markers x 3).
CHUNK = 64


def scatter_in_frame(P: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Every marker's rms scatter (n,) about its mean place in the moving frame of the markers ``idx``.

    P : (K, n, 3) the group's markers on K frames, all seen. The frame is the rigid motion
    of ``idx`` (three or more markers, not in line) from their shape (generalised Procrustes)
    to each frame; for the markers ``idx`` themselves the scatter is their rigid-fit residual.
    """
    shape = procrustes_shape(P[:, idx], ref_frame=0)[0]
    R, t, _ = kabsch(shape, P[:, idx])
    Q = np.einsum("kni,kij->knj", P - t[:, None, :], R)  # R^T (x - t): each frame back into the body
    return np.sqrt(((Q - Q.mean(0)) ** 2).sum(-1).mean(0))


def rigid_rms(P: np.ndarray, idx: np.ndarray | None = None) -> float:
    """Rigid-fit rms residual of the markers ``idx`` (default all) of P (K, n, 3), all seen."""
    idx = np.arange(P.shape[1]) if idx is None else np.asarray(idx)
    s = scatter_in_frame(P[:, idx], np.arange(idx.size))
    return float(np.sqrt((s**2).mean()))


def _triples(n: int, rng: np.random.Generator) -> np.ndarray:
    tri = np.array(list(combinations(range(n), 3)), dtype=int)
    if len(tri) > MAX_TRIPLES:
        tri = tri[np.sort(rng.choice(len(tri), MAX_TRIPLES, replace=False))]
    return tri


def _triple_scatter(P: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(T, n) squared scatter of every marker in the frame of every triple."""
    K, n, _ = P.shape
    out = np.empty((len(tri), n))
    for a in range(0, len(tri), CHUNK):
        tt = tri[a:a + CHUNK]
        obs = P[:, tt].reshape(K * len(tt), 3, 3)
        ref = np.broadcast_to(P[0, tt], (K, len(tt), 3, 3)).reshape(K * len(tt), 3, 3)
        R, t, _ = kabsch(ref, obs)
        R = R.reshape(K, len(tt), 3, 3)
        t = t.reshape(K, len(tt), 3)
        Q = np.einsum("kmni,kmij->kmnj", P[:, None] - t[:, :, None, :], R)  # (K, T, n, 3)
        out[a:a + len(tt)] = ((Q - Q.mean(0)) ** 2).sum(-1).mean(0)
    return np.where(np.isfinite(out), out, np.inf)  # a triple in line has no frame


def best_split(P: np.ndarray, rng: np.random.Generator, rounds: int = 5) -> np.ndarray | None:
    """Labels (n,) 0/1 of the split of P (K, n, 3) into two rigid bodies that leaves the least scatter.

    None when no split of at least three markers a side is found.
    """
    K, n, _ = P.shape
    if n < 6:
        return None
    tri = _triples(n, rng)
    s2 = _triple_scatter(P, tri)
    best = None
    for a in range(len(tri) - 1):
        tot = np.minimum(s2[a], s2[a + 1:]).sum(1)
        b = int(np.argmin(tot))
        if np.isfinite(tot[b]) and (best is None or tot[b] < best[0]):
            best = (float(tot[b]), a, a + 1 + b)
    if best is None:
        return None
    lab = (s2[best[2]] < s2[best[1]]).astype(int)
    for _ in range(rounds):
        if np.bincount(lab, minlength=2).min() < 3:
            return None
        sc = np.stack([scatter_in_frame(P, np.flatnonzero(lab == k)) for k in (0, 1)])
        new = (sc[1] < sc[0]).astype(int)
        if np.array_equal(new, lab):
            break
        lab = new
    return lab if np.bincount(lab, minlength=2).min() >= 3 else None
