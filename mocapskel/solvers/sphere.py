"""Sphere fits: points moving on spheres around one fixed centre.

A marker of a child segment, expressed in its parent segment's frame, moves on
a sphere around the joint centre. These kernels find that centre (and the
radius) from the samples, following Knight & Semwal 2009 ("New closed form
solutions for skeletal extraction from motion capture", ``knight2009-…`` in
the shared papers; equation numbers below are theirs):

- :func:`gdke`    generalised Delogne–Kåsa estimator, eqs. (2)–(6);
- :func:`ugdk`    the asymptotically unbiased GDK, eqs. (15)–(21), with the
                  noise variance given or estimated from the data (below);
- :func:`mgdk`    several markers at different radii around one centre,
                  eqs. (22)–(23);
- :class:`IGDK`   incremental GDK with constant memory, eqs. (24)–(25);
- :func:`sphere_lls`  the algebraic linear least-squares (Kåsa) fit;
- :func:`sphere_mle`  geometric maximum likelihood by Levenberg–Marquardt,
                  the reference;
- :func:`sphere_crlb` the Cramér–Rao lower bound of the centre.

All are pure functions of arrays. Rows with a NaN are ignored. A fit that
cannot be made is a value, not an exception: a :class:`SphereFit` with
``ok=False``, a ``reason`` and NaN centre and radii. Wrong shapes (a
programming error) raise ``ValueError``.

The closed forms share one code path: every batch of samples is reduced to
per-marker power sums about the batch mean (count, mean, scatter matrix
``M2 = sum y y^T``, third moment ``T = sum y |y|^2`` and fourth moment
``Q = sum |y|^4``, with ``y = x - mean``), obtained from one BLAS Gram matrix
of ``[1, x - o, |x - o|^2]`` about a provisional origin ``o`` and then shifted
exactly to the mean. Batches are merged exactly (the parallel-moment formulas
of Chan et al.), which is what makes :class:`IGDK` equal to the batch fits.

Noise model and the UGDK noise estimate
---------------------------------------
Samples are ``x = mu + e`` with ``mu`` on the sphere and ``e ~ N(0, s I)``
(``s = sigma^2`` per axis). The paper's UGDK subtracts ``s`` from the sample
covariance (eq. 15), but its estimator of ``Tr(Sigma)`` (eq. 19) needs the true
centre and radius, so it is not usable in practice (plugging in the fitted
radius of eq. 21 makes eq. 19 an identity). We estimate ``s`` as the unique
noise level at which the noise-corrected algebraic problem becomes exactly
consistent (the approach of Kukush, Markovsky & Van Huffel's consistent
ellipsoid fit, or Kanatani's renormalisation, specialised to spheres):

With ``z = (|y|^2, y, 1)`` and ``theta = (1, -2d, -rho)`` the algebraic
residual is ``z . theta`` (``d`` = centre minus mean, ``rho = r^2 - |d|^2``).
For Gaussian noise, ``E[z z^T] = z0 z0^T + s H(mu) + s^2 G``, which gives an
unbiased estimate ``M(s)`` of the noise-free moment matrix; its minimum over
``theta`` must be 0 at the true ``s``. Profiling out ``rho`` and the centre
leaves one scalar equation (summed over markers ``p``, ``w_p = n_p - 1``)::

    F(s) = sum_p [ V_p - 4 s Tr M2_p + 6 w_p s^2
                   - 4 d_p.T_p + 4 d_p^T (M2_p - w_p s I) d_p ] = 0,
    d_p  = c(s) - mean_p,   c(s) = the MGDK/UGDK centre for this s,
    V_p  = Q_p - (Tr M2_p)^2 / n_p.

``F(0) >= 0`` is the Kåsa residual sum of squares, ``F`` is strictly
decreasing on ``[0, lambda_min(sum M2_p) / sum w_p)`` (its derivative is
``sum_p [12 w_p s - 4 Tr M2_p - 4 w_p |d_p|^2] < 0`` there) and tends to
``-inf`` at the right end, so the root is unique; it is found by Brent's
method in well under a millisecond. The estimate is consistent (error
``O(1/sqrt(N))``), which keeps UGDK's centre bias at ``O(1/N)``. It assumes
isotropic Gaussian noise; only the trace of the noise covariance is
identifiable from sphere samples (as the paper also notes).

The paper's Leontief condition ``rho(Sigma C^-1) < 1`` is checked: a noise
variance that makes ``C - Sigma`` indefinite gives ``ok=False``.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "SphereFit",
    "sphere_lls",
    "gdke",
    "ugdk",
    "mgdk",
    "IGDK",
    "sphere_mle",
    "sphere_crlb",
]

#: Smallest accepted ratio of the smallest to the largest eigenvalue of the
#: (noise-corrected) scatter matrix; below it the samples are treated as
#: coplanar (a circle: the centre is undetermined along the plane's normal).
MIN_COND = 1e-12


@dataclass(frozen=True, eq=False)
class SphereFit:
    """Result of a sphere fit. Falsy when the fit failed.

    Attributes
    ----------
    centre : (3,) ndarray
        Centre estimate; NaN when the fit failed.
    radii : (K,) ndarray
        Radius of every marker's sphere (K = 1 for single-sphere fits); NaN
        where not determinable.
    sigma : float
        Per-axis noise standard deviation that the estimator subtracted
        (given or estimated for ``ugdk``/``mgdk``/``IGDK.result``; 0 for
        estimators without a noise correction: ``gdke``, ``sphere_lls``,
        ``sphere_mle``).
    rms : float
        Root-mean-square radial residual ``|x - c| - r``. Exact for
        ``sphere_mle``; for the closed forms it is the algebraic residual
        ``(|x - c|^2 - r^2) / (2 r)`` (equal to first order, and computable
        from the moments, so ``IGDK`` reports the same value as the batch fit).
    cond : float
        Conditioning: smallest over largest eigenvalue of the matrix that was
        inverted for the centre (closed forms), or of the centre's Fisher
        information (``sphere_mle``). Small means the centre is poorly
        determined along one direction (small cap, nearly coplanar samples).
    n : int
        Number of samples used (rows without NaN, over all markers).
    method : str
        ``"lls"``, ``"gdke"``, ``"ugdk"``, ``"mgdk"``, ``"igdk"`` or ``"mle"``.
    ok : bool
        Whether the fit succeeded.
    reason : str
        Why it failed ("" on success).
    iterations : int
        Function evaluations of the iterative fit (0 for closed forms).
    """

    centre: np.ndarray
    radii: np.ndarray
    sigma: float
    rms: float
    cond: float
    n: int
    method: str
    ok: bool
    reason: str = ""
    iterations: int = 0

    @property
    def radius(self) -> float:
        """The radius of a single-sphere fit (NaN when there are several markers)."""
        return float(self.radii[0]) if self.radii.shape[0] == 1 else float("nan")

    def __bool__(self) -> bool:
        return bool(self.ok)


def _failed(method: str, k: int, n: int, reason: str, sigma: float = float("nan")) -> SphereFit:
    return SphereFit(
        centre=np.full(3, np.nan),
        radii=np.full(k, np.nan),
        sigma=float(sigma),
        rms=float("nan"),
        cond=float("nan"),
        n=int(n),
        method=method,
        ok=False,
        reason=reason,
    )


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


# --------------------------------------------------------------------------
# the closed-form solve


def _centre_for(m: _Moments, s: float, ref: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and matrix A(s) for noise variance s (eq. 22 with Sigma = s I)."""
    B = m.M2 - (w * s)[:, None, None] * np.eye(3)
    A = B.sum(0)
    rhs = np.einsum("kij,kj->i", B, m.mean - ref) + 0.5 * m.T.sum(0)
    return ref + np.linalg.solve(A, rhs), A


def _secular(s: float, m: _Moments, ref: np.ndarray, w: np.ndarray, V: np.ndarray, tr: np.ndarray) -> float:
    """F(s) of the module docstring: 0 at the consistent noise variance."""
    c, _ = _centre_for(m, s, ref, w)
    d = c - m.mean
    Bd = np.einsum("kij,kj->ki", m.M2, d) - (w * s)[:, None] * d
    val = V - 4 * s * tr + 6 * w * s**2 - 4 * np.einsum("ki,ki->k", d, m.T) + 4 * np.einsum("ki,ki->k", d, Bd)
    return float(val.sum())


def _estimate_s(m: _Moments, ref: np.ndarray, w: np.ndarray, s_hi: float) -> float | None:
    """Consistent noise variance (root of F); None when there is none below s_hi."""
    n = np.where(m.n > 0, m.n, 1.0)
    tr = np.einsum("kii->k", m.M2)
    V = np.where(m.n > 0, m.Q - tr**2 / n, 0.0)
    f0 = _secular(0.0, m, ref, w, V, tr)
    if not f0 > 0:  # noise-free (to rounding) or exactly consistent
        return 0.0
    hi = s_hi * (1 - 1e-12)
    fhi = _secular(hi, m, ref, w, V, tr)
    if not fhi < 0:
        return None
    return brentq(lambda s: _secular(s, m, ref, w, V, tr), 0.0, hi, xtol=1e-15 * hi, rtol=1e-15, maxiter=200)


def brentq(f, a: float, b: float, *, xtol: float, rtol: float, maxiter: int) -> float:
    """A root of ``f`` in [a, b] (``f(a)`` and ``f(b)`` of opposite signs) by Brent's method.

    The algorithm of ``scipy.optimize.brentq`` (Brent 1973, in the form of SciPy's C code: inverse
    quadratic extrapolation or secant steps while they shrink the bracket fast enough, bisection
    otherwise), step for step, so that the root is the same to the last bit; here because importing
    ``scipy.optimize`` costs more than half a second of every fit. Stops when the bracket is narrower
    than ``xtol + rtol |x|`` or ``f`` is exactly 0; raises RuntimeError after ``maxiter`` steps and
    ValueError when the signs at the ends agree or ``f`` gives NaN.
    """
    def call(x: float) -> float:
        v = float(f(x))
        if v != v:
            raise ValueError(f"the function is NaN at {x!r}")
        return v

    xpre, xcur = float(a), float(b)
    fpre, fcur = call(xpre), call(xcur)
    if fpre == 0:
        return xpre
    if fcur == 0:
        return xcur
    if math.copysign(1.0, fpre) == math.copysign(1.0, fcur):
        raise ValueError("f(a) and f(b) must have different signs")
    xblk = fblk = spre = scur = 0.0
    for _ in range(maxiter):
        if fpre != 0 and fcur != 0 and math.copysign(1.0, fpre) != math.copysign(1.0, fcur):
            xblk, fblk = xpre, fpre
            spre = scur = xcur - xpre
        if abs(fblk) < abs(fcur):
            xpre, xcur, xblk = xcur, xblk, xcur
            fpre, fcur, fblk = fcur, fblk, fcur
        delta = (xtol + rtol * abs(xcur)) / 2
        sbis = (xblk - xcur) / 2
        if fcur == 0 or abs(sbis) < delta:
            return xcur
        if abs(spre) > delta and abs(fcur) < abs(fpre):
            if xpre == xblk:  # interpolate
                stry = -fcur * (xcur - xpre) / (fcur - fpre)
            else:  # extrapolate
                dpre = (fpre - fcur) / (xpre - xcur)
                dblk = (fblk - fcur) / (xblk - xcur)
                stry = -fcur * (fblk * dblk - fpre * dpre) / (dblk * dpre * (fblk - fpre))
            if 2 * abs(stry) < min(abs(spre), 3 * abs(sbis) - delta):  # a good short step
                spre, scur = scur, stry
            else:  # bisect
                spre = scur = sbis
        else:  # bisect
            spre = scur = sbis
        xpre, fpre = xcur, fcur
        xcur += scur if abs(scur) > delta else (delta if sbis > 0 else -delta)
        fcur = call(xcur)
    raise RuntimeError(f"no convergence after {maxiter} iterations")


def _alg_rms(m: _Moments, c: np.ndarray, r2: np.ndarray) -> float:
    """RMS of (|x - c|^2 - r_p^2) / (2 r_p) over all samples, from the moments."""
    d = c - m.mean
    tr = np.einsum("kii->k", m.M2)
    rho = r2 - np.einsum("ki,ki->k", d, d)
    ss = (
        m.Q
        - 2 * rho * tr
        + m.n * rho**2
        - 4 * np.einsum("ki,ki->k", m.T, d)
        + 4 * np.einsum("ki,kij,kj->k", d, m.M2, d)
    )
    good = (m.n > 0) & (r2 > 0)
    if not good.any():
        return float("nan")
    return float(np.sqrt((np.maximum(ss[good], 0.0) / (4 * r2[good])).sum() / m.n[good].sum()))


def _solve(m: _Moments, sigma: float | None, method: str) -> SphereFit:
    """Centre and radii from per-marker central sums (eqs. 2-3, 17-18, 20-25)."""
    k = m.k
    n_total = int(m.n.sum())
    if sigma is not None and not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be a finite non-negative number or None, got {sigma!r}")
    w = np.maximum(m.n - 1, 0.0)
    if n_total < 4 or w.sum() < 3:
        return _failed(
            method, k, n_total,
            f"too few samples: {n_total} (a sphere needs at least 4, and 3 beyond one per marker)",
        )
    S2 = m.M2.sum(0)
    lam = np.linalg.eigvalsh(S2)
    if not (lam[2] > 0 and lam[0] > MIN_COND * lam[2]):
        return _failed(
            method, k, n_total,
            "samples are (nearly) coplanar: the centre is undetermined along the plane's normal",
        )
    used = m.n > 0
    ref = (m.n[:, None] * m.mean).sum(0) / m.n.sum()  # a point near the data, for precision
    s_hi = lam[0] / w.sum()  # largest s keeping sum (M2_p - w_p s I) positive definite
    if sigma is None:
        s = _estimate_s(m, ref, w, s_hi)
        if s is None:
            return _failed(method, k, n_total, "could not estimate the noise level: no consistent solution")
    else:
        s = float(sigma) ** 2
        if s >= s_hi:
            return _failed(
                method, k, n_total,
                f"noise variance {s:.3g} reaches the samples' smallest spread {s_hi:.3g} "
                "(Leontief condition violated): spread the samples wider or lower sigma",
                sigma=float(sigma),
            )
    c, A = _centre_for(m, s, ref, w)
    lamA = np.linalg.eigvalsh(A)
    cond = float(lamA[0] / lamA[2])
    if not (np.all(np.isfinite(c)) and cond > MIN_COND):
        return _failed(method, k, n_total, "the corrected scatter matrix is singular", sigma=np.sqrt(s))
    nsafe = np.where(used, m.n, 1.0)
    d = c - m.mean
    tr = np.einsum("kii->k", m.M2)
    r2 = (tr - 3 * w * s) / nsafe + np.einsum("ki,ki->k", d, d)  # eqs. (18), (23)
    radii = np.where(used & (r2 > 0), np.sqrt(np.where(r2 > 0, r2, 0.0)), np.nan)
    rms = _alg_rms(m, c, r2)
    if not np.isfinite(radii[used]).all():
        return SphereFit(c, radii, float(np.sqrt(s)), rms, cond, n_total, method, False,
                         "a squared radius came out non-positive: noise too large for the spread")
    return SphereFit(c, radii, float(np.sqrt(s)), rms, cond, n_total, method, True, "")


# --------------------------------------------------------------------------
# public closed forms


def gdke(X: np.ndarray) -> SphereFit:
    """Generalised Delogne–Kåsa estimator of a sphere (Knight & Semwal eqs. 2–6).

    ``c = mean + C^-1 S / 2`` with the sample covariance ``C`` and third
    central moment ``S``; ``r^2`` is the mean squared distance to ``c``. Fast
    and exact on noise-free data, but biased by ``O(sigma^2)`` under noise,
    a bias that does not shrink with more samples and grows as the samples
    cover a smaller cap. Prefer :func:`ugdk` on noisy data.

    Parameters
    ----------
    X : (N, 3) ndarray
        Samples; rows with a NaN are ignored.

    Returns
    -------
    SphereFit
        ``method="gdke"``, ``sigma=0``.
    """
    return _solve(_moments(_single(X)), 0.0, "gdke")


def ugdk(X: np.ndarray, sigma: float | None = None) -> SphereFit:
    """Asymptotically unbiased GDK (Knight & Semwal eqs. 15–21).

    ``c = mean + (C - sigma^2 I)^-1 S / 2``: subtracting the noise covariance
    from the sample covariance removes GDKE's bias, leaving ``O(1/N)``.

    Parameters
    ----------
    X : (N, 3) ndarray
        Samples; rows with a NaN are ignored.
    sigma : float, optional
        Per-axis standard deviation of the (isotropic Gaussian) measurement
        noise, in the units of ``X``. When None it is estimated from the data
        as the noise level at which the noise-corrected algebraic fit becomes
        exactly consistent (see the module docstring); the estimate is
        returned in ``SphereFit.sigma``.

    Returns
    -------
    SphereFit
        ``method="ugdk"``; ``ok=False`` when ``sigma^2`` reaches the samples'
        smallest spread (Leontief condition) or no noise level is consistent.
    """
    return _solve(_moments(_single(X)), sigma, "ugdk")


def mgdk(X: np.ndarray | Sequence[np.ndarray], sigma: float | None = None) -> SphereFit:
    """Several markers on spheres of different radii around one centre (eqs. 22–23).

    Least squares over all markers with one radius per marker::

        c = [sum_p w_p (C_p - Sigma)]^-1 sum_p w_p [(C_p - Sigma) mean_p + S_p / 2]

    with ``w_p = N_p - 1`` (the paper's eq. 22 for equal counts; the weights
    make it the exact least-squares minimiser when markers have different
    numbers of valid samples), and ``r_p^2`` from eq. (23).

    Parameters
    ----------
    X : (N, K, 3) ndarray or sequence of (N_p, 3) ndarrays
        Samples of the K markers; NaN rows (per marker) are ignored. An
        (N, 3) array is one marker.
    sigma : float, optional
        Per-axis noise standard deviation, common to all markers; None (the
        default) estimates it as in :func:`ugdk`; ``0.0`` gives the plain
        (biased) multi-radius GDK.

    Returns
    -------
    SphereFit
        ``method="mgdk"``; ``radii`` has one entry per marker (NaN for a
        marker without samples).
    """
    return _solve(_moments(_as_markers(X)), sigma, "mgdk")


def sphere_lls(X: np.ndarray, *, solver: str = "normal") -> SphereFit:
    """Linear least-squares (algebraic, Kåsa) sphere fit.

    Solves ``|x - o|^2 = 2 d.(x - o) + rho`` in the least-squares sense for
    the 4 unknowns ``d = c - o`` and ``rho = r^2 - |d|^2``, with ``o`` the data
    mean. This is the same estimator as :func:`gdke` (GDKE is its closed-form
    solution with ``rho`` eliminated), so it shares GDKE's noise bias.
    Centring on the data avoids the numerical breakdown Knight & Semwal
    report for the raw design matrix at extreme scales.

    Parameters
    ----------
    X : (N, 3) ndarray
        Samples; rows with a NaN are ignored.
    solver : {"normal", "lstsq"}
        ``"normal"``: the 4x4 normal equations, assembled from the same
        moments as the GDK fits (fast). ``"lstsq"``: ``numpy.linalg.lstsq``
        on the full (N, 4) design matrix (several times slower; an
        independent reference).

    Returns
    -------
    SphereFit
        ``method="lls"``, ``sigma=0``.
    """
    if solver not in ("normal", "lstsq"):
        raise ValueError(f"solver must be 'normal' or 'lstsq', got {solver!r}")
    x = _finite_rows(_single(X)[0])
    m = _moments([x])
    n = x.shape[0]
    if n < 4:
        return _failed("lls", 1, n, f"too few samples: {n} (a sphere needs at least 4)")
    o = m.mean[0]
    if solver == "normal":
        N4 = np.zeros((4, 4))
        N4[:3, :3] = 4 * m.M2[0]
        N4[3, 3] = n
    else:
        y = x - o
        D = np.empty((n, 4))
        D[:, :3] = 2 * y
        D[:, 3] = 1.0
        N4 = D.T @ D
    lam = np.linalg.eigvalsh(N4)
    cond = float(lam[0] / lam[3]) if lam[3] > 0 else 0.0
    lam3 = np.linalg.eigvalsh(m.M2[0])
    if not (lam3[2] > 0 and lam3[0] > MIN_COND * lam3[2]):
        return _failed("lls", 1, n, "samples are (nearly) coplanar: the centre is undetermined along the plane's normal")
    if solver == "normal":
        theta = np.linalg.solve(N4, np.concatenate([2 * m.T[0], [np.trace(m.M2[0])]]))
    else:
        theta = np.linalg.lstsq(D, np.einsum("ij,ij->i", y, y), rcond=None)[0]
    d = theta[:3]
    r2 = np.array([theta[3] + d @ d])
    c = o + d
    if not r2[0] > 0:
        return _failed("lls", 1, n, "the squared radius came out non-positive")
    return SphereFit(c, np.sqrt(r2), 0.0, _alg_rms(m, c, r2), cond, n, "lls", True, "")


class IGDK:
    """Incremental GDK with constant memory (Knight & Semwal eqs. 24–25).

    Feed batches of samples with :meth:`update`; :meth:`result` gives the fit
    on everything seen so far. Memory is a few numbers per marker whatever
    the number of samples (count, mean, scatter, third and fourth moments,
    merged exactly), so the result equals :func:`gdke` (one marker) or
    :func:`mgdk` (several) on the concatenated data, to rounding.

    Parameters
    ----------
    n_markers : int, optional
        Number of markers K; inferred from the first batch when omitted.

    Examples
    --------
    >>> inc = IGDK()
    >>> for batch in batches:           # each (N_i, 3) or (N_i, K, 3)
    ...     inc.update(batch)
    >>> fit = inc.result()              # == gdke(np.concatenate(batches))
    """

    def __init__(self, n_markers: int | None = None) -> None:
        self._m: _Moments | None = _empty_moments(int(n_markers)) if n_markers is not None else None

    @property
    def n(self) -> int:
        """Number of samples accumulated (rows without NaN, over all markers)."""
        return 0 if self._m is None else int(self._m.n.sum())

    def update(self, X: np.ndarray | Sequence[np.ndarray]) -> IGDK:
        """Add a batch of samples.

        Parameters
        ----------
        X : (N, 3) or (N, K, 3) ndarray, or sequence of K (N_p, 3) ndarrays
            The batch; NaN rows are ignored. The number of markers must stay
            the same from batch to batch.

        Returns
        -------
        IGDK
            ``self``, for chaining.
        """
        b = _moments(_as_markers(X))
        self._m = b if self._m is None else _merge(self._m, b)
        return self

    def result(self, sigma: float | None = 0.0) -> SphereFit:
        """Fit on all samples so far.

        Parameters
        ----------
        sigma : float, optional
            Noise correction as in :func:`mgdk`: 0.0 (default) is the plain
            GDK of eq. (24) and equals :func:`gdke`/``mgdk(..., sigma=0)``;
            a value or None (estimate) gives the unbiased form, equal to
            :func:`ugdk`/:func:`mgdk` with the same ``sigma``.

        Returns
        -------
        SphereFit
            ``method="igdk"``.
        """
        if self._m is None:
            return _failed("igdk", 1, 0, "no samples yet")
        return _solve(self._m, sigma, "igdk")


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
        the :func:`mgdk` fit with ``sigma=0`` (i.e. :func:`gdke` for one
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
    """sum_p sum_i (u_pi - mean_p u)(u_pi - mean_p u)^T with unit directions u."""
    u = v / np.linalg.norm(v, axis=1)[:, None]
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
