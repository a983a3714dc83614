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

One marker in another body's frame (:func:`frame_scatters`): how far every marker moves in a group's
moving frame, and in the frame of the rest of its own group, as measured and beyond what the frame's
own fitting error explains at the marker's distance from the frame's markers (:func:`beyond_fit`).
"""
from __future__ import annotations

import warnings
from itertools import combinations

import numpy as np

from ..rigid import kabsch
from ..rigid_shape import procrustes_shape, shape_poses

#: Triples tried for the split; more than this are sampled (evenly over the combinations' order).
MAX_TRIPLES = 400
#: Triples' frames are computed in chunks of this many (memory: chunk x frames x markers x 3).
CHUNK = 64


def frame_path(P: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Every marker of P (K, n, 3), all seen, brought into the moving frame of the markers ``idx``
    (three or more, not in line; their shape by generalised Procrustes): (K, n, 3)."""
    shape = procrustes_shape(P[:, idx], ref_frame=0)[0]
    R, t, _ = kabsch(shape, P[:, idx])
    return _into_body(P, R, t)


def scatter_in_frame(P: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Every marker's rms scatter (n,) about its mean place in the moving frame of the markers ``idx``.

    P : (K, n, 3) the group's markers on K frames, all seen. The frame is the rigid motion
    of ``idx`` (three or more markers, not in line) from their shape (generalised Procrustes)
    to each frame; for the markers ``idx`` themselves the scatter is their rigid-fit residual.
    """
    Q = frame_path(P, idx)
    return np.sqrt(((Q - Q.mean(0)) ** 2).sum(-1).mean(0))


def _into_body(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points X (..., K, n, 3) brought back into the moving frames (R, t) (..., K, 3, 3), (..., K, 3):
    R^T (x - t)."""
    return np.einsum("...kni,...kij->...knj", X - t[..., None, :], R)


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


# --------------------------------------------------------------------------- one marker in another body's frame

#: A frame is fitted only to markers whose shape is not nearly in one line (second principal spread
#: at least this fraction of the first).
LINE_FRAC = 0.1


def _in_line(shape: np.ndarray) -> bool:
    """Whether the points ``shape`` (n, 3) lie nearly in one line (see ``LINE_FRAC``); also when the shape
    could not be fitted (NaN: no frame sees three of its points out of line)."""
    if not np.isfinite(shape).all():
        return True
    sv = np.linalg.svd(shape - shape.mean(0), compute_uv=False)
    return not sv[1] >= LINE_FRAC * sv[0]


def scatter_in_frames(X: np.ndarray, R: np.ndarray, t: np.ndarray, min_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's rms scatter about its mean place in the moving frames (R, t), and that mean place:
    X (..., K, n, 3) NaN where unseen, R (..., K, 3, 3), t (..., K, 3); NaN where seen on fewer than
    ``min_frames`` frames (:func:`scatter_in_frame` for points with gaps, and for many frames at once)."""
    Q = _into_body(X, R, t)
    seen = np.isfinite(Q).all(-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(Q, axis=-3)
        d2 = ((Q - mean[..., None, :, :]) ** 2).sum(-1)
        s = np.sqrt(np.nanmean(np.where(seen, d2, np.nan), axis=-2))
    return np.where(seen.sum(-2) >= min_frames, s, np.nan), mean


def beyond_fit(s: np.ndarray, place: np.ndarray, shape: np.ndarray, own: np.ndarray) -> np.ndarray:
    """How far markers move in a frame beyond what the frame's own fitting error explains.

    s : (m,) the markers' rms scatter in the frame; place : (m, 3) their mean places in it; shape : (n, 3)
    the frame's markers, own : (n,) their scatters. A frame fitted to n markers of noise sigma (per
    coordinate; their residual sum of squares has 3n - 6 degrees of freedom) carries a point at p from
    their centroid with error variance 3 sigma^2 / n + sigma^2 tr([p]x J^-1 [p]x^T), J the markers'
    inertia about the centroid: far from a small group's markers the frame's own turn moves a point
    that rides on it (a heel in the frame of three forefoot markers). Returns sqrt(max(s^2 - that, 0)).
    """
    n = shape.shape[0]
    sig2 = float(np.nansum(own**2)) / (3 * n - 6) if n > 2 else np.nan
    r = shape - shape.mean(0)
    J = (r**2).sum() * np.eye(3) - r.T @ r
    p = place - shape.mean(0)
    # tr([p]x Ji [p]x^T) = |p|^2 tr(Ji) - p^T Ji p
    Ji = np.linalg.pinv(J)
    lever = (p**2).sum(-1) * np.trace(Ji) - np.einsum("mi,ij,mj->m", p, Ji, p)
    return np.sqrt(np.maximum(s**2 - sig2 * (3.0 / n + lever), 0.0))


def frame_scatters(points: np.ndarray, idx: np.ndarray, frames: int, min_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """How far markers move in the moving frame of the markers ``idx`` (three or more) of ``points``
    (K, M, 3), NaN where unseen: their rms scatter about their mean place in it, and that beyond the
    frame's own fitting error (:func:`beyond_fit`).

    Returns both (2, M) for every marker in that frame, and both (2, len(idx)) for each member in the
    frame of the other members (NaN for a group of three: two markers leave the frame's turn about their
    line free). The frames are fitted on the frames that see all of ``idx`` (at most ``frames`` of them,
    evenly spread) to the group's shape (generalised Procrustes); NaN for a marker seen on fewer than
    ``min_frames`` of them and for frames of markers nearly in one line.
    """
    M, n = points.shape[1], idx.size
    whole, loo = np.full((2, M), np.nan), np.full((2, n), np.nan)
    f = np.flatnonzero(np.isfinite(points[:, idx]).all(-1).all(-1))
    if f.size < min_frames:
        return whole, loo
    X = points[f[np.unique(np.linspace(0, f.size - 1, min(frames, f.size)).round().astype(int))]]
    K = X.shape[0]
    shape = procrustes_shape(X[:, idx], ref_frame=0)[0]
    if _in_line(shape):
        return whole, loo
    R, t = shape_poses(shape, X[:, idx])
    s, place = scatter_in_frames(X, R, t, min_frames)
    whole = np.stack([s, beyond_fit(s, place, shape, s[idx])])
    if n >= 4:
        obs = np.repeat(X[None][:, :, idx], n, axis=0)  # (n, K, n, 3): copy i without member i
        obs[np.arange(n), :, np.arange(n)] = np.nan
        R, t = shape_poses(shape, obs.reshape(n * K, n, 3))
        s, place = scatter_in_frames(X[:, idx], R.reshape(n, K, 3, 3), t.reshape(n, K, 3), min_frames)
        for i in range(n):
            rest = np.delete(np.arange(n), i)
            if not _in_line(shape[rest]):
                loo[:, i] = s[i, i], beyond_fit(s[i, i:i + 1], place[i, i:i + 1], shape[rest], s[i, rest])[0]
    return whole, loo
