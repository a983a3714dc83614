"""Geometric (maximum-likelihood) sphere fit, and the Cramér–Rao lower bound of the centre.

- :func:`sphere_mle`  geometric maximum likelihood by Levenberg–Marquardt,
                  the reference;
- :func:`sphere_crlb` the Cramér–Rao lower bound of the centre.

All are pure functions of arrays. Rows with a NaN are ignored. A fit that
cannot be made is a value, not an exception: a :class:`SphereFit` with
``ok=False``, a ``reason`` and NaN centre and radii. Wrong shapes (a
programming error) raise ``ValueError``.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .moments import _as_markers, _finite_rows, _moments
from .solve import MIN_COND, SphereFit, _failed, _solve

__all__ = [
    "sphere_mle",
    "sphere_crlb",
]


# --------------------------------------------------------------------------
# maximum likelihood and the Cramér–Rao bound


def sphere_mle(
    X: np.ndarray | Sequence[np.ndarray],
    init: SphereFit | np.ndarray | None = None,
    *,
    max_nfev: int = 200,
) -> SphereFit:
    """Geometric (maximum-likelihood) sphere fit by Levenberg–Marquardt.

    Minimises ``sum_p sum_i (|x_pi - c| - r_p)^2`` over the centre and one
    radius per marker with ``scipy.optimize.least_squares(method="lm")`` and
    an analytic Jacobian. The reference estimator: efficient at small noise,
    but iterative and much slower than the closed forms.

    Parameters
    ----------
    X : (N, 3) or (N, K, 3) ndarray, or sequence of K (N_p, 3) ndarrays
        Samples; NaN rows are ignored.
    init : SphereFit or (3,) ndarray, optional
        Starting centre (radii start at the mean distance to it). Default:
        the :func:`~mocapskel.solvers.spheres.sphere.mgdk` fit with ``sigma=0`` (i.e. :func:`~mocapskel.solvers.spheres.sphere.gdke` for one
        marker), or the data mean shifted off the data when that fails.
    max_nfev : int, optional
        Function-evaluation budget.

    Returns
    -------
    SphereFit
        ``method="mle"``, ``sigma=0``, exact geometric ``rms``,
        ``iterations`` = function evaluations.
    """
    xs = [_finite_rows(x) for x in _as_markers(X)]
    k = len(xs)
    n_total = int(sum(x.shape[0] for x in xs))
    if n_total < 4:
        return _failed("mle", k, n_total, f"too few samples: {n_total} (a sphere needs at least 4)")
    pts = np.concatenate(xs)
    idx = np.repeat(np.arange(k), [x.shape[0] for x in xs])
    o = pts.mean(0)
    y = pts - o  # centred for conditioning
    if init is None:
        f0 = _solve(_moments(xs), 0.0, "mgdk")
        c0 = f0.centre if f0.ok else None
        if c0 is None:
            sd = np.sqrt(np.linalg.eigvalsh(np.cov(y.T))[-1])
            c0 = o + np.array([0.0, 0.0, sd])
    else:
        c0 = np.asarray(init.centre if isinstance(init, SphereFit) else init, dtype=float)
        if c0.shape != (3,):
            raise ValueError(f"init centre must be (3,), got {c0.shape}")
    c0 = c0 - o
    dist0 = np.linalg.norm(y - c0, axis=1)
    cnt = np.bincount(idx, minlength=k)
    r0 = np.bincount(idx, weights=dist0, minlength=k) / np.maximum(cnt, 1)

    def fun(p):
        return np.linalg.norm(y - p[:3], axis=1) - p[3:][idx]

    def jac(p):
        v = y - p[:3]
        dist = np.linalg.norm(v, axis=1)
        J = np.zeros((y.shape[0], 3 + k))
        J[:, :3] = -v / np.maximum(dist, np.finfo(float).tiny)[:, None]
        J[np.arange(y.shape[0]), 3 + idx] = -1.0
        return J

    if n_total < 3 + k:
        return _failed("mle", k, n_total, "fewer samples than unknowns")
    from scipy.optimize import least_squares

    res = least_squares(fun, np.concatenate([c0, r0]), jac=jac, method="lm", max_nfev=max_nfev, x_scale="jac")
    p = res.x
    c = p[:3] + o
    radii = np.where(cnt > 0, p[3:], np.nan)
    rms = float(np.sqrt(np.mean(res.fun**2)))
    info = _centre_information(pts - c, idx, k)
    lam = np.linalg.eigvalsh(info)
    cond = float(lam[0] / lam[2]) if lam[2] > 0 else 0.0
    ok = bool(res.status > 0 and np.all(np.isfinite(p)) and np.all(radii[cnt > 0] > 0) and cond > MIN_COND)
    reason = "" if ok else f"Levenberg–Marquardt did not converge: {res.message}"
    return SphereFit(c, radii, 0.0, rms, cond, n_total, "mle", ok, reason, int(res.nfev))


def _centre_information(v: np.ndarray, idx: np.ndarray, k: int) -> np.ndarray:
    """sum_p sum_i (u_pi - mean_p u)(u_pi - mean_p u)^T with unit directions u (none for a sample on the
    centre itself)."""
    n = np.linalg.norm(v, axis=1)
    u = v / np.where(n > 0, n, 1.0)[:, None]
    cnt = np.bincount(idx, minlength=k).astype(float)
    mu = np.stack([np.bincount(idx, weights=u[:, j], minlength=k) for j in range(3)], 1)
    mu = mu / np.maximum(cnt, 1)[:, None]
    uc = u - mu[idx]
    return uc.T @ uc


def sphere_crlb(directions: np.ndarray | Sequence[np.ndarray], sigma: float) -> np.ndarray:
    """Cramér–Rao lower bound on the covariance of any unbiased centre estimate.

    Knight & Semwal compare against the CRLB but do not print it; this is the
    standard derivation (Chan & Thomas 1995 for circles, extended to spheres
    and several radii). With samples ``x_pi = c + r_p u_pi + e``,
    ``e ~ N(0, sigma^2 I)``, unknown centre, radii and directions, the
    tangential noise only informs the nuisance directions; eliminating them
    and the radii (Schur complement) leaves the centre's Fisher information
    ``sigma^-2 sum_p sum_i (u_pi - mean_p u)(u_pi - mean_p u)^T``. The radii
    do not appear: the bound depends on sigma and the directions only.

    Parameters
    ----------
    directions : (N, 3) or (N, K, 3) ndarray, or sequence of (N_p, 3)
        True sample directions from the centre (any length; normalised
        here), per marker; NaN rows are ignored.
    sigma : float
        Per-axis noise standard deviation.

    Returns
    -------
    (3, 3) ndarray
        Covariance bound of the centre; ``sqrt(trace)`` bounds the RMS
        centre error. All entries infinite when the directions do not
        determine the centre (e.g. all on one great or small circle).
    """
    xs = [_finite_rows(x) for x in _as_markers(directions)]
    k = len(xs)
    pts = np.concatenate(xs)
    idx = np.repeat(np.arange(k), [x.shape[0] for x in xs])
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive number, got {sigma!r}")
    if pts.shape[0] == 0:
        return np.full((3, 3), np.inf)
    info = _centre_information(pts, idx, k)
    lam = np.linalg.eigvalsh(info)
    if not (lam[2] > 0 and lam[0] > MIN_COND * lam[2]):
        return np.full((3, 3), np.inf)
    return float(sigma) ** 2 * np.linalg.inv(info)
