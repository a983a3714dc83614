"""Convex hulls of marker sets: their facet planes, and how far points lie outside them."""
from __future__ import annotations

import numpy as np

__all__ = ["beyond_hull"]


def beyond_hull(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """How far each of ``queries`` (Q, 3) lies outside the convex hull of ``points`` (N, 3) (NaN rows
    left out): its distance beyond the hull's farthest facet plane, negative inside. A lower bound
    of the distance to the hull, exact where the nearest point of the hull lies on a facet. All
    -inf when fewer than 5 points or all in a plane (no inside to be outside of)."""
    P = points[np.isfinite(points).all(1)]
    q = np.asarray(queries, dtype=float).reshape(-1, 3)
    planes = hull_planes(P) if len(P) >= 5 else None
    if planes is None:
        return np.full(len(q), -np.inf)
    return (q @ planes[:, :3].T + planes[:, 3]).max(axis=1)


#: Points nearer a facet plane than this fraction of the points' size count as on it (the hull's
#: own rounding); a set whose thickness is below it is flat.
HULL_TOL = 1e-10


def hull_planes(points: np.ndarray) -> np.ndarray | None:
    """The facet planes (K, 4) of the convex hull of ``points`` (N, 3), rows ``(n, d)`` with ``n`` the
    outward unit normal and ``n . x + d <= 0`` inside; None for fewer than 4 points or points all in a
    plane or a line.

    Incremental (Clarkson-Shor / quickhull-like): a tetrahedron of extreme points, then every point
    outside the hull so far replaces the facets it sees by a fan from it to their horizon. The same
    planes as Qhull's (``scipy.spatial.ConvexHull(points).equations``, triangulated facets) to
    rounding; here because importing ``scipy.spatial`` costs a third of a second of every fit. A
    Python loop over the points (tens to hundreds of markers), never over frames.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 4:
        return None
    size = float(np.abs(P - P.mean(0)).max())
    if not size > 0:
        return None
    eps = HULL_TOL * size
    i0 = int(np.argmin(P[:, 0]))
    i1 = int(np.argmax(np.linalg.norm(P - P[i0], axis=1)))
    u = P[i1] - P[i0]
    if not np.linalg.norm(u) > eps:
        return None
    u = u / np.linalg.norm(u)
    off = (P - P[i0]) - np.outer((P - P[i0]) @ u, u)
    i2 = int(np.argmax(np.linalg.norm(off, axis=1)))
    if not np.linalg.norm(off[i2]) > eps:
        return None
    nrm = np.cross(P[i1] - P[i0], P[i2] - P[i0])
    nrm /= np.linalg.norm(nrm)
    h = (P - P[i0]) @ nrm
    i3 = int(np.argmax(np.abs(h)))
    if not abs(h[i3]) > eps:
        return None
    inner = P[[i0, i1, i2, i3]].mean(0)
    faces = []
    for a, b, c in ((i0, i1, i2), (i0, i1, i3), (i0, i2, i3), (i1, i2, i3)):
        n_ = np.cross(P[b] - P[a], P[c] - P[a])
        faces.append((a, b, c) if n_ @ (inner - P[a]) < 0 else (a, c, b))

    def planes_of(fs: list) -> np.ndarray:
        F = np.array(fs)
        n_ = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
        n_ /= np.linalg.norm(n_, axis=1, keepdims=True)
        return np.column_stack([n_, -np.einsum("ki,ki->k", n_, P[F[:, 0]])])

    pl = planes_of(faces)
    done = {i0, i1, i2, i3}
    for p in range(len(P)):
        if p in done:
            continue
        seen = P[p] @ pl[:, :3].T + pl[:, 3] > eps
        if not seen.any():
            continue  # inside (or on) the hull so far
        vis = [f for f, s_ in zip(faces, seen) if s_]
        edges = {(f[k], f[(k + 1) % 3]) for f in vis for k in range(3)}
        horizon = [(a, b) for a, b in edges if (b, a) not in edges]
        faces = [f for f, s_ in zip(faces, seen) if not s_] + [(a, b, p) for a, b in sorted(horizon)]
        pl = planes_of(faces)
    return pl
