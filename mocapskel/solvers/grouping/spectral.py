"""Spectral clustering (Ng, Jordan & Weiss 2002) and eigen-gap model selection."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Spectral:
    """Result of :func:`spectral_clustering`.

    labels  : (N,) int cluster of each item, 0..k-1.
    eigvals : (N,) eigenvalues of the normalised affinity, largest first.
    k       : number of clusters.
    """

    labels: np.ndarray
    eigvals: np.ndarray
    k: int


def normalized_affinity(W: np.ndarray) -> np.ndarray:
    """D^-1/2 W D^-1/2 of a symmetric affinity (N, N)."""
    d = W.sum(axis=1)
    inv = np.where(d > 0, 1.0 / np.sqrt(np.maximum(d, 1e-300)), 0.0)
    return W * inv[:, None] * inv[None, :]


def eigengap_k(eigvals: np.ndarray, k_min: int = 1, k_max: int | None = None) -> int:
    """Number of clusters from the largest gap between sorted eigenvalues (largest first)."""
    n = eigvals.size
    k_max = n - 1 if k_max is None else min(k_max, n - 1)
    if k_max < k_min:
        return max(1, min(k_min, n))
    gaps = eigvals[k_min - 1 : k_max] - eigvals[k_min : k_max + 1]
    return int(k_min + np.argmax(gaps))


def spectral_clustering(
    W: np.ndarray, k: int | None, *, rng: np.random.Generator, n_init: int = 10, k_max: int | None = None
) -> Spectral:
    """Cluster items given a symmetric affinity matrix.

    Parameters
    ----------
    W : (N, N) ndarray, symmetric, non-negative affinities. A diagonal of ones
        (self-affinity) lets an item unlike all others form its own cluster.
    k : number of clusters, or None to pick it from the eigen-gap.
    rng : random generator for k-means seeding.
    """
    W = np.asarray(W, dtype=float)
    N = W.shape[0]
    L = normalized_affinity(W)
    vals, vecs = np.linalg.eigh(L)
    order = np.argsort(vals)[::-1]
    vals, vecs = vals[order], vecs[:, order]
    if k is None:
        k = eigengap_k(vals, 1, k_max)
    k = int(max(1, min(k, N)))
    if k == 1:
        return Spectral(np.zeros(N, dtype=int), vals, 1)
    X = vecs[:, :k]
    X = X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)
    best, best_inertia = None, np.inf
    for _ in range(n_init):
        seed = int(rng.integers(2**31 - 1))
        cent, lab = _kmeans(X, k, np.random.default_rng(seed))
        inertia = ((X - cent[lab]) ** 2).sum()
        if inertia < best_inertia - 1e-12:
            best, best_inertia = lab, inertia
    # relabel clusters in order of first appearance for determinism
    _, first = np.unique(best, return_index=True)
    remap = np.empty(k, dtype=int)
    remap[best[np.sort(first)]] = np.arange(len(first))
    return Spectral(remap[best], vals, int(len(first)))


def _kmeans(X: np.ndarray, k: int, rng: np.random.Generator, iters: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """k-means with k-means++ seeding. X (N, d). Returns (centres (k, d), labels (N,))."""
    N = X.shape[0]
    cent = np.empty((k, X.shape[1]))
    cent[0] = X[rng.integers(N)]
    d2 = ((X - cent[0]) ** 2).sum(axis=1)
    for j in range(1, k):
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(N, 1.0 / N)
        cent[j] = X[rng.choice(N, p=p)]
        d2 = np.minimum(d2, ((X - cent[j]) ** 2).sum(axis=1))
    lab = np.zeros(N, dtype=int)
    for _ in range(iters):
        dist = ((X[:, None, :] - cent[None]) ** 2).sum(axis=2)
        new = dist.argmin(axis=1)
        if _ > 0 and np.array_equal(new, lab):
            break
        lab = new
        for j in range(k):
            sel = lab == j
            if sel.any():
                cent[j] = X[sel].mean(axis=0)
            else:  # empty cluster: take the farthest point
                far = dist.min(axis=1).argmax()
                cent[j] = X[far]
                lab[far] = j
    return cent, lab
