"""The closed-form sphere solve the GDK fits share: centre and radii from the moments, the noise
estimate (Brent's root), and the fit's result.

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
from dataclasses import dataclass

import numpy as np

from .moments import _Moments

__all__ = ["SphereFit"]

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
# the closed-form solve


def _centre_for(m: _Moments, s: float, ref: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and matrix A(s) for noise variance s (eq. 22 with Sigma = s I)."""
    B = m.M2 - (w * s)[:, None, None] * np.eye(3)
    A = B.sum(0)
    rhs = np.einsum("kij,kj->i", B, m.mean - ref) + 0.5 * m.T.sum(0)
    try:
        x = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:  # singular to rounding (s at the edge of its range): no centre
        x = np.full(3, np.nan)
    return ref + x, A


def _secular(s: float, m: _Moments, ref: np.ndarray, w: np.ndarray, V: np.ndarray, tr: np.ndarray) -> float:
    """F(s) of the module docstring: 0 at the consistent noise variance."""
    c, _ = _centre_for(m, s, ref, w)
    d = c - m.mean
    Bd = np.einsum("kij,kj->ki", m.M2, d) - (w * s)[:, None] * d
    val = V - 4 * s * tr + 6 * w * s**2 - 4 * np.einsum("ki,ki->k", d, m.T) + 4 * np.einsum("ki,ki->k", d, Bd)
    return float(val.sum())


def _estimate_s(m: _Moments, ref: np.ndarray, w: np.ndarray, s_hi: float) -> float | None:
    """Consistent noise variance (root of F); None when there is none below s_hi, or F cannot be
    evaluated on the way (A(s) singular to rounding: samples barely out of a plane)."""
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
    try:
        return brentq(lambda s: _secular(s, m, ref, w, V, tr), 0.0, hi, xtol=1e-15 * hi, rtol=1e-15, maxiter=200)
    except (ValueError, RuntimeError):  # F NaN on the way, or no convergence
        return None


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

