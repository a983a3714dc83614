"""Cheap joint cost of two marker groups (MTB where a group has a basis, else JMV on a subsample),
for choosing the topology."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ..joints.jmv import jmv_joint
from ..joints.cost import _as_points, joint_cost
from ..joints.mtb import mtb_basis, mtb_joint

__all__ = ["pair_cost"]


def pair_cost(
    markers_a: ArrayLike,
    markers_b: ArrayLike,
    *,
    alpha: float,
    frames: int | ArrayLike = 40,
    bases: tuple = (None, None),
    return_centre: bool = False,
) -> float | tuple[float, np.ndarray]:
    """Cheap joint cost of two marker groups, for choosing the topology.

    The cost is Kirk's Q of the best joint on a few frames only (Kirk 2005,
    §3.2: topology "drastically subsamples the number of frames"). When a group
    has three non-collinear markers the joint is an MTB affine combination of
    that group's basis (3 unknowns; both sides are tried and the lower cost
    kept); otherwise it is the full JMV fit on the subsample.

    Parameters
    ----------
    markers_a, markers_b : (F, Na, 3), (F, Nb, 3) ndarray
        The two groups; NaN where not seen.
    alpha : float
        Mean-distance penalty (length units); keeps wrong joints from hiding
        at infinity. Use a small positive value.
    frames : int or (K,) int array
        Number of evenly spaced frames to use, or the frame indices.
    bases : (Basis or None, Basis or None)
        The groups' :func:`~mocapskel.solvers.joints.mtb.mtb_basis` on those frames, when the
        caller has them (a topology scores every pair, each group's basis is made once).
    return_centre : bool
        Also return the joint's trajectory on the frames used (K, 3).

    Returns
    -------
    float
        Q (length squared), ``inf`` when the pair cannot be fitted (a group is
        empty, or fewer than 3 markers are seen together).
    """
    a = _as_points(markers_a, "markers_a")
    b = _as_points(markers_b, "markers_b")
    F = a.shape[0]
    if isinstance(frames, (int, np.integer)):
        k = int(min(max(frames, 1), F))
        idx = np.unique(np.linspace(0, F - 1, k).round().astype(int)) if F else np.zeros(0, int)
    else:
        idx = np.asarray(frames, dtype=int)
    a, b = a[idx], b[idx]
    def out(q: float, c: np.ndarray):
        return (q, c) if return_centre else q

    if a.shape[1] == 0 or b.shape[1] == 0 or a.shape[0] == 0:
        return out(float("inf"), np.full((a.shape[0], 3), np.nan))
    best, centre = np.inf, None
    tried = False
    for side, name, given in ((a, "a", bases[0]), (b, "b", bases[1])):
        if side.shape[1] >= 3:
            basis = mtb_basis(side) if given is None else given
            if basis:
                tried = True
                # a ranking needs Q to a few digits, not to rounding
                fit = mtb_joint(basis.points, a, b, alpha=alpha, basis_side=name, tol=1e-6)
                if np.isfinite(fit.cost) and fit.cost < best:
                    best, centre = float(fit.cost), fit.centre
    if tried and np.isfinite(best):
        return out(best, centre)
    fit = jmv_joint(a, b, alpha=alpha, max_iter=50, tol=1e-6)
    if not np.isfinite(fit.cost):
        return out(float(fit.cost), fit.centre)
    # the joint is free in every frame (3 unknowns a frame): of n markers' distances only n - 3
    # are checked, so the mean variance is scaled to what n - 3 redundant distances leave, as an
    # unbiased variance is — otherwise two groups of one or two markers join anything cheaply
    n = a.shape[1] + b.shape[1]
    var = joint_cost(fit.centre, np.concatenate([a, b], axis=1), alpha=0.0)
    return out(float(var * n / max(n - 3, 0.5) + (fit.cost - var)), fit.centre)
