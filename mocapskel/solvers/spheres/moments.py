"""Per-marker central power sums of sphere samples (merged exactly), and the samples split into markers.

The closed forms share one code path: every batch of samples is reduced to
per-marker power sums about the batch mean (count, mean, scatter matrix
``M2 = sum y y^T``, third moment ``T = sum y |y|^2`` and fourth moment
``Q = sum |y|^4``, with ``y = x - mean``), obtained from one BLAS Gram matrix
of ``[1, x - o, |x - o|^2]`` about a provisional origin ``o`` and then shifted
exactly to the mean. Batches are merged exactly (the parallel-moment formulas
of Chan et al.), which is what makes :class:`~mocapskel.solvers.spheres.sphere.IGDK` equal to the batch fits.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


# --------------------------------------------------------------------------
# moments


@dataclass(frozen=True, eq=False)
class _Moments:
    """Per-marker central power sums (K markers).

    n : (K,) counts; mean : (K, 3); M2 : (K, 3, 3) = sum y y^T;
    T : (K, 3) = sum y |y|^2; Q : (K,) = sum |y|^4; with y = x - mean.
    Markers without samples have n = 0 and zero sums.
    """

    n: np.ndarray
    mean: np.ndarray
    M2: np.ndarray
    T: np.ndarray
    Q: np.ndarray

    @property
    def k(self) -> int:
        return int(self.n.shape[0])


def _shift(n, s1, s2, s3, s4, delta):
    """Power sums about origin a -> about origin a + delta (exact algebra).

    Shapes: n (K,), s1 (K,3), s2 (K,3,3), s3 (K,3), s4 (K,), delta (K,3).
    """
    dd = np.einsum("ki,ki->k", delta, delta)
    s1d = np.einsum("ki,ki->k", s1, delta)
    s2d = np.einsum("kij,kj->ki", s2, delta)
    tr = np.einsum("kii->k", s2)
    outer_s1d = np.einsum("ki,kj->kij", s1, delta)
    s2n = s2 - outer_s1d - np.swapaxes(outer_s1d, 1, 2) + n[:, None, None] * np.einsum(
        "ki,kj->kij", delta, delta
    )
    s3n = (
        s3
        - 2 * s2d
        + dd[:, None] * s1
        - tr[:, None] * delta
        + 2 * s1d[:, None] * delta
        - (n * dd)[:, None] * delta
    )
    s4n = (
        s4
        + 4 * np.einsum("ki,ki->k", delta, s2d)
        + n * dd**2
        - 4 * np.einsum("ki,ki->k", s3, delta)
        + 2 * dd * tr
        - 4 * dd * s1d
    )
    s1n = s1 - n[:, None] * delta
    return s1n, s2n, s3n, s4n


def _empty_moments(k: int) -> _Moments:
    return _Moments(
        n=np.zeros(k),
        mean=np.zeros((k, 3)),
        M2=np.zeros((k, 3, 3)),
        T=np.zeros((k, 3)),
        Q=np.zeros(k),
    )


def _marker_sums(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, float]:
    """Central sums of one marker's finite samples x (n, 3)."""
    n = x.shape[0]
    if n == 0:
        return 0.0, np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0
    m = _sums(x[None])
    return float(n), m.mean[0], m.M2[0], m.T[0], float(m.Q[0])


def _sums(X: np.ndarray) -> _Moments:
    """Central sums of K markers with the same n >= 1 finite samples each, X (K, n, 3)."""
    K, n, _ = X.shape
    origin = X[:, : min(n, 1024)].mean(1)  # provisional; corrected exactly below
    z = np.empty((K, 5, n))  # rows: 1, y (3), |y|^2 -- row-major for fast BLAS
    z[:, 0] = 1.0
    y = z[:, 1:4]
    np.subtract(np.swapaxes(X, 1, 2), origin[:, :, None], out=y)
    np.einsum("kij,kij->kj", y, y, out=z[:, 4])
    g = z @ np.swapaxes(z, 1, 2)
    s1 = g[:, 0, 1:4]
    nn = np.full(K, float(n))
    delta = s1 / n
    _, M2, T, Q = _shift(nn, s1, g[:, 1:4, 1:4], g[:, 1:4, 4], g[:, 4, 4], delta)
    return _Moments(n=nn, mean=origin + delta, M2=M2, T=T, Q=Q)


def _moments(xs: Sequence[np.ndarray]) -> _Moments:
    """Central sums of every marker; xs are (n_p, 3) arrays, NaN rows dropped."""
    xs = [_finite_rows(x) for x in xs]
    k = len(xs)
    if k and xs[0].shape[0] and all(x.shape[0] == xs[0].shape[0] for x in xs):
        return _sums(np.stack(xs))  # the common case: every marker seen in the same number of samples
    n = np.zeros(k)
    mean = np.zeros((k, 3))
    M2 = np.zeros((k, 3, 3))
    T = np.zeros((k, 3))
    Q = np.zeros(k)
    for p, x in enumerate(xs):  # loop over markers (few), never over samples
        n[p], mean[p], M2[p], T[p], Q[p] = _marker_sums(x)
    return _Moments(n=n, mean=mean, M2=M2, T=T, Q=Q)


def _merge(a: _Moments, b: _Moments) -> _Moments:
    """Exact merge of the central sums of two disjoint sample sets."""
    if a.k != b.k:
        raise ValueError(f"cannot merge moments of {a.k} and {b.k} markers")
    n = a.n + b.n
    nsafe = np.where(n > 0, n, 1.0)
    mean = np.where(
        (n > 0)[:, None], (a.n[:, None] * a.mean + b.n[:, None] * b.mean) / nsafe[:, None], 0.0
    )
    zero = np.zeros((a.k, 3))
    # where a set is empty its mean is arbitrary (0) but all its sums are 0
    _, M2a, Ta, Qa = _shift(a.n, zero, a.M2, a.T, a.Q, np.where((a.n > 0)[:, None], mean - a.mean, 0.0))
    _, M2b, Tb, Qb = _shift(b.n, zero, b.M2, b.T, b.Q, np.where((b.n > 0)[:, None], mean - b.mean, 0.0))
    return _Moments(n=n, mean=mean, M2=M2a + M2b, T=Ta + Tb, Q=Qa + Qb)


def _finite_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"samples must be (N, 3), got shape {x.shape}")
    if x.shape[0] and np.isfinite(x.sum()):
        return x  # fast path: no NaN/inf anywhere
    return x[np.isfinite(x).all(1)]


def _as_markers(X: np.ndarray | Sequence[np.ndarray]) -> list[np.ndarray]:
    """(N, 3) -> [X]; (N, K, 3) -> K columns; sequence of (N_i, 3) -> list."""
    if isinstance(X, np.ndarray) or not isinstance(X, Sequence):
        X = np.asarray(X, dtype=float)
        if X.ndim == 2 and X.shape[1] == 3:
            return [X]
        if X.ndim == 3 and X.shape[2] == 3:
            return [X[:, p, :] for p in range(X.shape[1])]
        raise ValueError(f"samples must be (N, 3) or (N, K, 3), got shape {X.shape}")
    return [np.asarray(x, dtype=float) for x in X]


def _single(X: np.ndarray) -> list[np.ndarray]:
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"samples must be (N, 3), got shape {X.shape}")
    return [X]

