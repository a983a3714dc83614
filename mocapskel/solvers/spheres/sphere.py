"""Closed-form sphere fits: points moving on spheres around one fixed centre.

A marker of a child segment, expressed in its parent segment's frame, moves on
a sphere around the joint centre. These kernels find that centre (and the
radius) from the samples, following Knight & Semwal 2009 ("New closed form
solutions for skeletal extraction from motion capture", ``knight2009-…`` in
the shared papers; equation numbers below are theirs):

- :func:`gdke`    generalised Delogne–Kåsa estimator, eqs. (2)–(6);
- :func:`ugdk`    the asymptotically unbiased GDK, eqs. (15)–(21), with the
                  noise variance given or estimated from the data
                  (:mod:`~mocapskel.solvers.spheres.solve`);
- :func:`mgdk`    several markers at different radii around one centre,
                  eqs. (22)–(23);
- :class:`IGDK`   incremental GDK with constant memory, eqs. (24)–(25);
- :func:`sphere_lls`  the algebraic linear least-squares (Kåsa) fit;

The geometric fit and the Cramér–Rao bound are in :mod:`~mocapskel.solvers.spheres.mle`;
the moments and the solve the closed forms share, in :mod:`~mocapskel.solvers.spheres.moments`
and :mod:`~mocapskel.solvers.spheres.solve`.

All are pure functions of arrays. Rows with a NaN are ignored. A fit that
cannot be made is a value, not an exception: a :class:`SphereFit` with
``ok=False``, a ``reason`` and NaN centre and radii. Wrong shapes (a
programming error) raise ``ValueError``.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .moments import _as_markers, _empty_moments, _finite_rows, _merge, _Moments, _moments, _single
from .solve import MIN_COND, SphereFit, _alg_rms, _failed, _solve

__all__ = [
    "sphere_lls",
    "gdke",
    "ugdk",
    "mgdk",
    "IGDK",
]


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
        exactly consistent (see :mod:`~mocapskel.solvers.spheres.solve`); the estimate is
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
