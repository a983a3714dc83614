"""Kirk's joint cost Q (with its gradient), the fit result shared by the joint solvers, and the
distance penalty's weights."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["JointFit", "joint_cost", "joint_cost_grad"]

#: Floor for distances when normalising directions (a joint exactly on a marker).
_TINY = 1e-300


@dataclass(frozen=True, eq=False)
class JointFit:
    """Result of a joint fit. Falsy when the fit failed (see ``reason``).

    centre : (F, 3) ndarray
        Joint-centre trajectory; NaN in frames that cannot be solved.
    cost : float
        Kirk's joint cost Q at ``centre`` (same ``alpha`` as the fit; units of
        length squared, plus ``alpha`` times length). ``inf`` when nothing was fitted.
    n_iter : int
        Optimiser iterations used.
    ok : bool
        Whether the joint is determined by the data.
    reason : str
        Why not, when ``ok`` is False ("" otherwise).
    params : (3,) ndarray or None
        MTB only: the affine coefficients lambda of the basis (Hang (6)).
    radii : (M,) ndarray or None
        Mean joint-to-point distance ``dbar`` of every point that entered the cost
        (markers of group a, then of group b).
    """

    centre: np.ndarray
    cost: float
    n_iter: int
    ok: bool
    reason: str = ""
    params: np.ndarray | None = None
    radii: np.ndarray | None = None

    def __bool__(self) -> bool:
        return bool(self.ok)


# --------------------------------------------------------------------------- the cost


def _as_points(x: ArrayLike, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(f"{name} must be (F, N, 3), got {a.shape}")
    return a


def _stack(markers_a: ArrayLike, markers_b: ArrayLike) -> np.ndarray:
    a = _as_points(markers_a, "markers_a")
    b = _as_points(markers_b, "markers_b")
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"markers_a has {a.shape[0]} frames, markers_b {b.shape[0]}")
    return np.concatenate([a, b], axis=1)


def _sqnorm(v: np.ndarray) -> np.ndarray:
    """Squared lengths of vectors (..., 3) (faster than einsum or sum(-1) over a length-3 axis)."""
    return v[..., 0] ** 2 + v[..., 1] ** 2 + v[..., 2] ** 2


def _seen(pts: np.ndarray) -> np.ndarray:
    """Where points (..., 3) have all three coordinates finite (faster than isfinite(...).all(-1))."""
    return np.isfinite(pts[..., 0] + pts[..., 1] + pts[..., 2])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products along the last axis (faster than np.cross for small arrays)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _cost_terms(c: np.ndarray, pts: np.ndarray, valid: np.ndarray, alpha: float):
    """Distances and Q. c (F,3), pts (F,M,3), valid (F,M) (c finite already folded in).

    Returns Q, d (F,M) (0 where invalid), diff (F,M,3), n (M,), dbar (M,), used (M,).
    """
    F, M = valid.shape
    if F and valid.all():  # every point seen in every frame: no masks
        diff = c[:, None, :] - pts
        d = np.sqrt(_sqnorm(diff))
        dbar = d.sum(0) / F
        dev = d - dbar
        q = float((np.einsum("fm,fm->", dev, dev) / F + np.sum(alpha * dbar)) / M)
        return q, d, diff, np.full(M, F), dbar, np.ones(M, dtype=bool)
    diff = c[:, None, :] - pts
    diff[~valid] = 0.0
    d = np.sqrt(_sqnorm(diff))
    n = valid.sum(0)
    used = n > 0
    nn = np.where(used, n, 1)
    dbar = d.sum(0) / nn
    var = (np.where(valid, (d - dbar) ** 2, 0.0)).sum(0) / nn
    k = int(used.sum())
    if k == 0:
        return np.inf, d, diff, n, dbar, used
    q = float((var[used] + (np.broadcast_to(alpha, used.shape) * dbar)[used]).sum() / k)
    return q, d, diff, n, dbar, used


def balanced_alpha(alpha: float, n_a: int, n_b: int) -> float | np.ndarray:
    """Kirk's distance penalty per point (``n_a`` of one segment, then ``n_b`` of the other), each
    segment's share half of the whole.

    Kirk's term is ``alpha`` times the mean distance over all points, so a segment of four
    markers pulls the joint twice as hard as one of two: along a direction the motion does not
    fix (a hip's flexion axis in a walk) the joint then sits in the middle of the bigger segment
    (the pelvis), not near both. Weighted per segment, the prior is "near each of its two
    segments". The total weight is Kirk's; equal groups keep his scalar.
    """
    alpha = float(alpha)
    if n_a == n_b or alpha == 0.0 or n_a == 0 or n_b == 0:
        return alpha
    n = n_a + n_b
    return np.concatenate([np.full(n_a, alpha * n / (2.0 * n_a)), np.full(n_b, alpha * n / (2.0 * n_b))])


def _alpha_const(alpha, used: np.ndarray | None = None) -> float:
    """The least value of Q (all distances constant): the mean of alpha^2 / 4 over the points used."""
    a = np.asarray(alpha, dtype=float)
    if a.ndim == 0:
        return float(a * a / 4.0)
    if used is not None and used.any():
        a = a[used]
    return float(np.mean(a * a) / 4.0)


def joint_cost(c: ArrayLike, markers: ArrayLike, alpha: float = 0.0) -> float:
    """Kirk's joint cost Q of a joint trajectory (Kirk 2005, §3.2).

    Parameters
    ----------
    c : (F, 3) ndarray
        Joint positions; NaN rows are frames without a joint (left out).
    markers : (F, N, 3) ndarray
        Marker trajectories of both segments; NaN where a marker is not seen.
    alpha : float
        Weight of the mean-distance penalty (length units).

    Returns
    -------
    float
        ``1/N' sum_m [var_f |c_f - m_f| + alpha mean_f |c_f - m_f|]`` where each
        marker averages over the frames it is seen in (and ``c`` is finite), and
        ``N'`` counts the markers seen at least once. ``inf`` when no marker is
        ever seen together with the joint.
    """
    c = np.asarray(c, dtype=float)
    pts = _as_points(markers, "markers")
    if c.shape != (pts.shape[0], 3):
        raise ValueError(f"c must be ({pts.shape[0]}, 3), got {c.shape}")
    valid = _seen(pts) & _seen(c)[:, None]
    return _cost_terms(c, pts, valid, np.asarray(alpha, dtype=float) if np.ndim(alpha) else float(alpha))[0]


def joint_cost_grad(c: ArrayLike, markers: ArrayLike, alpha: float = 0.0) -> tuple[float, np.ndarray]:
    """Kirk's Q and its analytic gradient with respect to every joint position.

    ``dQ/dc_f = 1/N' sum_m 1/|m| (2 (d_fm - dbar_m) + alpha) u_fm`` with
    ``d_fm = |c_f - m_f|`` and ``u_fm = (c_f - m_f) / d_fm`` (the derivative
    of ``dbar`` drops out of the variance term because deviations sum to zero).

    Parameters
    ----------
    c : (F, 3) ndarray
        Joint positions; NaN rows are left out.
    markers : (F, N, 3) ndarray
        Markers of both segments; NaN where not seen.
    alpha : float
        Mean-distance penalty.

    Returns
    -------
    q : float
        As :func:`joint_cost`.
    grad : (F, 3) ndarray
        dQ/dc; NaN rows where ``c`` is NaN.
    """
    c = np.asarray(c, dtype=float)
    pts = _as_points(markers, "markers")
    if c.shape != (pts.shape[0], 3):
        raise ValueError(f"c must be ({pts.shape[0]}, 3), got {c.shape}")
    cok = np.isfinite(c).all(-1)
    valid = np.isfinite(pts).all(-1) & cok[:, None]
    cc = np.where(cok[:, None], c, 0.0)
    q, d, diff, n, dbar, used = _cost_terms(cc, pts, valid, float(alpha))
    k = max(int(used.sum()), 1)
    w = np.where(used, 1.0 / (k * np.maximum(n, 1)), 0.0)
    coef = np.where(valid, w * (2.0 * (d - dbar) + alpha) / np.maximum(d, _TINY), 0.0)
    grad = (coef[..., None] * diff).sum(1)
    grad[~cok] = np.nan
    return q, grad


def distance_penalty(info: dict, k: float, fallback: float = 0.01) -> float:
    """Kirk's distance penalty alpha scaled to a take: ``k`` skin variances per median marker distance.

    info : the segment stage's info, with ``skin_level_mm`` (the take's own level of skin motion
    and noise, a distance std) and ``size_mm`` (the median distance between markers). A joint as
    far from its markers as markers are from each other then costs ``k`` times the variance that
    skin motion alone gives; where the motion fixes the joint, its cost outweighs that, and where
    it does not (a hinge's axis, a joint the take barely moves) the joint stays near its markers
    instead of running off along the free direction. ``fallback`` when the info has no level.
    """
    level, size = info.get("skin_level_mm"), info.get("size_mm")
    if not level or not size or not (level > 0 and size > 0):
        return fallback
    return float(k * level**2 / size)
