"""Functional joints between two segments with known poses: SCoRE and SARA.

Given the pose ``(R_f, t_f)`` of two segments in every frame ``f`` (a point
``p`` fixed in a segment is at ``R_f p + t_f`` in the lab):

- :func:`score` — Symmetrical Centre of Rotation Estimation (Ehrig et al.
  2006): the joint centre is a point fixed in both segments, ``c1`` in
  segment 1 and ``c2`` in segment 2, found by linear least squares::

      min_{c1, c2}  sum_f w_f |(R1_f c1 + t1_f) - (R2_f c2 + t2_f)|^2

  The 6x6 normal equations are accumulated over frames with BLAS
  contractions and solved by an eigen-decomposition, whose eigenvalues give
  the conditioning.
- :func:`sara` — Symmetrical Axis of Rotation Approach (Ehrig et al. 2007):
  for a hinge the solutions of the system above form a line; its direction
  ``(a1, a2)`` with ``R1_f a1 = R2_f a2`` (the axis fixed in both segments)
  is the null vector of the same system.
- :func:`score_hinge` — the hinge centre: the point on the SARA axis closest
  to the centroid of the markers of both segments.
- :func:`score_from_markers` — per-frame poses from two marker groups by a
  batched rigid fit (:func:`~.rigid_shape.shape_poses`), then :func:`score`.

Conditioning. Divided by the total weight, the normal matrix is
``[[I, -M], [-M^T, I]]`` with ``M = mean_f R1_f^T R2_f``; its eigenvalues are
``1 +- s_k(M)``. The singular values of the (weight-normalised) stacked
system, ``sqrt`` of those, are reported in ``singular_values`` (largest
first). For a small relative rotation of RMS angle ``theta`` about some axis
the matching singular value is about ``theta / 2``:

- ``cond = s_min / s_max``: overall conditioning (0 with no motion);
- ``axis_ratio = s_min / s_second_smallest``: near 0 when the motion is a
  rotation about one axis only (a hinge: the centre is undetermined along
  the axis). :func:`score` switches to the hinge solution when
  ``axis_ratio < hinge_threshold`` and marker positions are given.

Frames with a NaN anywhere in either pose, or zero weight, are skipped; their
per-frame outputs are NaN. Failures are values (``ok=False`` and a
``reason``), never exceptions; wrong shapes raise ``ValueError``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rigid_shape import _SMALL_GEMV, _SMALL_PRODUCT, _rotate, _solvable_frames, shape_poses

__all__ = ["ScoreFit", "SaraFit", "score", "score_hinge", "sara", "score_from_markers"]

#: Default ``hinge_threshold``: below this ``axis_ratio`` the relative motion
#: is treated as a rotation about one axis (the RMS rotation about the weakest
#: axis is under about a tenth of that about the next one).
HINGE_THRESHOLD = 0.1

#: Below ``MIN_SV * s_max`` a singular value counts as zero: with two such
#: directions the relative rotation does not determine even an axis.
MIN_SV = 1e-6

#: Marker groups whose second principal spread (standard deviation) is below
#: this fraction of the first are collinear: their rotation is undetermined.
COLLINEAR_TOL = 1e-6


@dataclass(frozen=True, eq=False)
class ScoreFit:
    """Result of :func:`score`, :func:`score_hinge` or :func:`score_from_markers`. Falsy when failed.

    Attributes
    ----------
    c1 : (3,) ndarray
        Joint centre in segment 1's local frame (NaN when failed).
    c2 : (3,) ndarray
        Joint centre in segment 2's local frame.
    centre : (F, 3) ndarray
        Lab joint centre per frame, the mean of ``R1 c1 + t1`` and
        ``R2 c2 + t2``; NaN for skipped frames.
    residual : (F,) ndarray
        ``|(R1 c1 + t1) - (R2 c2 + t2)|`` per frame; NaN for skipped frames.
    rms : float
        Weighted RMS of ``residual`` over the frames used.
    cond : float
        ``s_min / s_max`` of the stacked system (see the module docstring).
    axis_ratio : float
        ``s_min / s_second_smallest``; small for hinge-like motion.
    singular_values : (6,) ndarray
        Singular values of the weight-normalised stacked system, largest first.
    hinge : bool
        True when the centre was placed on the hinge axis (fixed along it by
        the markers' centroid), or when hinge-like motion was detected but no
        markers were given (then ``ok`` is False).
    axis1 : (3,) ndarray
        Unit hinge axis in segment 1 (NaN unless ``hinge``).
    axis2 : (3,) ndarray
        Unit hinge axis in segment 2, with ``R1 axis1 = R2 axis2``.
    n_frames : int
        Number of frames used.
    ok : bool
        Whether the fit succeeded.
    reason : str
        Why it failed ("" on success).
    markers1 : (K1, 3) ndarray or None
        Local marker coordinates of segment 1 that were used to place a hinge
        centre (and, from :func:`score_from_markers`, the reference shape
        that defines segment 1's local frame).
    markers2 : (K2, 3) ndarray or None
        The same for segment 2.
    """

    c1: np.ndarray
    c2: np.ndarray
    centre: np.ndarray
    residual: np.ndarray
    rms: float
    cond: float
    axis_ratio: float
    singular_values: np.ndarray
    hinge: bool
    axis1: np.ndarray
    axis2: np.ndarray
    n_frames: int
    ok: bool
    reason: str = ""
    markers1: np.ndarray | None = None
    markers2: np.ndarray | None = None

    def __bool__(self) -> bool:
        return bool(self.ok)


@dataclass(frozen=True, eq=False)
class SaraFit:
    """Result of :func:`sara`. Falsy when failed.

    Attributes
    ----------
    axis1 : (3,) ndarray
        Unit axis direction in segment 1's frame (sign: its largest
        component is positive).
    axis2 : (3,) ndarray
        Unit axis direction in segment 2's frame, ``R1 axis1 = R2 axis2``.
    point1 : (3,) ndarray
        A point on the axis in segment 1's frame: the minimum-norm solution
        of the least-squares system restricted to the well-determined
        directions (an arbitrary but reproducible choice: it depends on the
        segment frames' origins; see :func:`score_hinge` for a point chosen
        by the markers).
    point2 : (3,) ndarray
        The same point in segment 2's frame.
    axis : (F, 3) ndarray
        Lab axis direction per frame, the normalised mean of ``R1 axis1`` and
        ``R2 axis2``; NaN for skipped frames.
    point : (F, 3) ndarray
        Lab position of the axis point per frame; NaN for skipped frames.
    residual : (F,) ndarray
        ``|(R1 point1 + t1) - (R2 point2 + t2)|`` per frame.
    angle : (F,) ndarray
        Angle (rad) between ``R1 axis1`` and ``R2 axis2`` per frame: how far
        the motion is from a perfect hinge.
    rms : float
        Weighted RMS of ``residual``.
    cond : float
        ``s_min / s_max`` of the stacked system.
    axis_ratio : float
        ``s_min / s_second_smallest``: small for a well-defined hinge; near 1
        when the motion does not single out one axis (a ball joint), and the
        axis is then meaningless.
    singular_values : (6,) ndarray
        Singular values of the weight-normalised stacked system, largest first.
    n_frames : int
        Number of frames used.
    ok : bool
        Whether the fit succeeded.
    reason : str
        Why it failed ("" on success).
    """

    axis1: np.ndarray
    axis2: np.ndarray
    point1: np.ndarray
    point2: np.ndarray
    axis: np.ndarray
    point: np.ndarray
    residual: np.ndarray
    angle: np.ndarray
    rms: float
    cond: float
    axis_ratio: float
    singular_values: np.ndarray
    n_frames: int
    ok: bool
    reason: str = ""

    def __bool__(self) -> bool:
        return bool(self.ok)


# --------------------------------------------------------------------------
# the shared linear system


@dataclass(frozen=True, eq=False)
class _System:
    R1: np.ndarray  # (F, 3, 3) as given (NaN possible where invalid)
    t1: np.ndarray
    R2: np.ndarray
    t2: np.ndarray
    w: np.ndarray  # (F,) normalised weights, 0 where invalid
    valid: np.ndarray  # (F,) bool
    lam: np.ndarray  # (6,) eigenvalues of the normalised normal matrix, ascending
    vec: np.ndarray  # (6, 6) eigenvectors (columns)
    rhs: np.ndarray  # (6,)
    sv: np.ndarray  # (6,) singular values, descending
    M: np.ndarray  # (3, 3) sum_f w R1^T R2
    n: int  # number of valid frames

    @property
    def cond(self) -> float:
        return float(self.sv[5] / self.sv[0]) if self.sv[0] > 0 else 0.0

    @property
    def axis_ratio(self) -> float:
        return float(self.sv[5] / self.sv[4]) if self.sv[4] > 0 else 1.0


def _check_poses(R1, t1, R2, t2, weights):
    R1, t1, R2, t2 = (np.asarray(a, dtype=float) for a in (R1, t1, R2, t2))
    F = R1.shape[0] if R1.ndim == 3 else -1
    for name, a, shape in (("R1", R1, (F, 3, 3)), ("t1", t1, (F, 3)), ("R2", R2, (F, 3, 3)), ("t2", t2, (F, 3))):
        if a.shape != shape:
            raise ValueError(f"{name} must have shape {shape} (F, ...), got {a.shape}")
    if weights is None:
        w = np.ones(F)
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (F,):
            raise ValueError(f"weights must have shape ({F},), got {w.shape}")
        if np.any(w < 0):
            raise ValueError("weights must be non-negative")
    return R1, t1, R2, t2, w


def _system(R1, t1, R2, t2, weights) -> _System:
    R1, t1, R2, t2, w = _check_poses(R1, t1, R2, t2, weights)
    F = R1.shape[0]
    # fast path: a finite grand total says every entry is finite
    if np.isfinite(R1.sum() + t1.sum() + R2.sum() + t2.sum() + w.sum()):
        valid = np.ones(F, dtype=bool) if weights is None else w > 0
    else:  # the frames with finite translations and weight, then the rotations among them
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(np.einsum("fi->f", t1) + np.einsum("fi->f", t2) + w) & (w > 0)
    for _ in range(2):
        n = int(np.count_nonzero(valid))
        if n == F:
            R1v, t1v, R2v, t2v, wv = R1, t1, R2, t2, w
        else:
            idx = np.flatnonzero(valid)
            R1v, t1v, R2v, t2v, wv = (np.take(a, idx, axis=0) for a in (R1, t1, R2, t2, w))
        if np.isfinite(R1v.sum() + R2v.sum()):
            break
        with np.errstate(invalid="ignore"):
            valid &= np.isfinite(np.einsum("fi->f", R1.reshape(F, 9)) + np.einsum("fi->f", R2.reshape(F, 9)))
    if n == 0:
        z = np.zeros(6)
        return _System(R1, t1, R2, t2, np.zeros(F), valid, z, np.eye(6), z, z, np.zeros((3, 3)), 0)
    d = (t2v - t1v).reshape(3 * n)
    A1 = R1v.reshape(3 * n, 3)
    B2 = R2v.reshape(3 * n, 3)
    if weights is None:  # unit weights: plain sums, divided by n
        M, g1, g2 = _tdot(A1, B2) / n, _tdot(A1, d) / n, _tdot(B2, d) / n
        wn = valid / n
    else:
        wv = wv / wv.sum()
        wd = np.repeat(wv, 3)
        M = _tdot(A1 * wd[:, None], B2)  # sum_f w R1^T R2
        g1 = _tdot(A1, wd * d)  # sum_f w R1^T (t2 - t1)
        g2 = _tdot(B2, wd * d)  # sum_f w R2^T (t2 - t1)
        wn = np.zeros(F)
        wn[valid] = wv
    N = np.eye(6)
    N[:3, 3:] = -M
    N[3:, :3] = -M.T
    rhs = np.concatenate([g1, -g2])
    lam, vec = np.linalg.eigh(N)
    sv = np.sqrt(np.clip(lam, 0.0, None))[::-1]
    return _System(R1, t1, R2, t2, wn, valid, lam, vec, rhs, sv, M, n)


def _tdot(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A.T @ B for tall A (k, m) and B (k,) or (k, n), summed over pieces of rows (see rigid_shape._SMALL_PRODUCT)."""
    rows = _SMALL_GEMV // A.shape[1] if B.ndim == 1 else _SMALL_PRODUCT // (A.shape[1] * B.shape[1])
    if A.shape[0] <= rows:
        return A.T @ B
    out = A[:rows].T @ B[:rows]
    for lo in range(rows, A.shape[0], rows):
        out += A[lo : lo + rows].T @ B[lo : lo + rows]
    return out


def _truncated(sy: _System, drop: int) -> np.ndarray:
    """Minimum-norm solution ignoring the ``drop`` smallest eigen-directions."""
    lam, vec = sy.lam[drop:], sy.vec[:, drop:]
    return vec @ ((vec.T @ sy.rhs) / lam)


def _images(sy: _System, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lab positions of local points p1 (segment 1) and p2 (segment 2), NaN where invalid."""
    q1 = _rotate(sy.R1, p1) + sy.t1
    q2 = _rotate(sy.R2, p2) + sy.t2
    if sy.n < sy.valid.size:
        q1[~sy.valid] = np.nan
        q2[~sy.valid] = np.nan
    return q1, q2


def _nan_score(F: int, reason: str, sv=None, n: int = 0, hinge: bool = False, markers1=None, markers2=None) -> ScoreFit:
    nan3 = np.full(3, np.nan)
    sv = np.full(6, np.nan) if sv is None else sv
    return ScoreFit(
        c1=nan3, c2=nan3.copy(), centre=np.full((F, 3), np.nan), residual=np.full(F, np.nan),
        rms=float("nan"), cond=float("nan"), axis_ratio=float("nan"), singular_values=sv,
        hinge=hinge, axis1=nan3.copy(), axis2=nan3.copy(), n_frames=n, ok=False, reason=reason,
        markers1=markers1, markers2=markers2,
    )


def _degenerate(sy: _System) -> str:
    if sy.n == 0:
        return "no frame where both segment poses are known"
    if not sy.sv[4] > MIN_SV * sy.sv[0]:
        return (
            f"too little relative rotation between the segments over {sy.n} frames "
            "(the joint is undetermined): use frames where the joint moves"
        )
    return ""


def _local_markers(m, name: str) -> np.ndarray:
    m = np.asarray(m, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"{name} must be (K, 3), got shape {m.shape}")
    return m


def _finish(
    sy: _System, x: np.ndarray, hinge: bool, axis: np.ndarray | None, ok: bool, reason: str,
    markers1=None, markers2=None,
) -> ScoreFit:
    c1, c2 = x[:3].copy(), x[3:].copy()
    q1, q2 = _images(sy, c1, c2)
    diff = q1 - q2
    r2 = np.einsum("fi,fi->f", diff, diff)
    rms = float(np.sqrt(np.dot(sy.w, np.where(sy.valid, r2, 0.0) if sy.n < sy.valid.size else r2)))
    if axis is None:
        a1 = a2 = np.full(3, np.nan)
    else:
        a1 = axis[:3] / np.linalg.norm(axis[:3])
        a2 = axis[3:] / np.linalg.norm(axis[3:])
    return ScoreFit(
        c1=c1, c2=c2, centre=0.5 * (q1 + q2), residual=np.sqrt(r2), rms=rms, cond=sy.cond,
        axis_ratio=sy.axis_ratio, singular_values=sy.sv, hinge=hinge, axis1=a1, axis2=a2,
        n_frames=sy.n, ok=ok, reason=reason, markers1=markers1, markers2=markers2,
    )


def _hinge_solution(sy: _System, markers1: np.ndarray, markers2: np.ndarray) -> tuple[np.ndarray, np.ndarray] | str:
    """Point on the hinge axis closest (least squares over frames) to the markers' centroid."""
    x0 = _truncated(sy, 1)
    v = sy.vec[:, 0].copy()
    if v[np.argmax(np.abs(v[:3]))] < 0:  # sign as in sara(): axis1's largest component > 0
        v = -v
    ok1 = np.isfinite(markers1).all(1)
    ok2 = np.isfinite(markers2).all(1)
    k1, k2 = int(ok1.sum()), int(ok2.sum())
    if k1 + k2 == 0:
        return "no finite marker position to place the centre on the hinge axis"
    m1 = markers1[ok1].mean(0) if k1 else np.zeros(3)
    m2 = markers2[ok2].mean(0) if k2 else np.zeros(3)
    # alpha = sum_f w u.(g - p0) / sum_f w |u|^2 with u = (R1 v1 + R2 v2) / 2 the lab axis, g the lab
    # centroid of all markers and p0 the lab image of x0; all linear in the poses, so the sums over
    # frames come from the system's: sum w R^T R = I, M = sum w R1^T R2, g1, g2 = sum w R^T (t2 - t1)
    v1, v2 = v[:3], v[3:]
    b2 = k2 / (k1 + k2) - 0.5  # weight of t2 (and minus that of t1) in g - p0
    a1 = k1 / (k1 + k2) * m1 - 0.5 * x0[:3]
    a2 = k2 / (k1 + k2) * m2 - 0.5 * x0[3:]
    M, g1, g2 = sy.M, sy.rhs[:3], -sy.rhs[3:]
    num = 0.5 * (v1 @ a1 + v1 @ M @ a2 + v2 @ M.T @ a1 + v2 @ a2 + b2 * (v1 @ g1 + v2 @ g2))
    den = 0.25 * (v1 @ v1 + v2 @ v2 + 2.0 * v1 @ M @ v2)
    alpha = num / den
    return x0 + alpha * v, v


# --------------------------------------------------------------------------
# public


def _hinge_fit(sy: _System, m1: np.ndarray, m2: np.ndarray) -> ScoreFit:
    """The hinge result: the centre on the axis, placed by the markers (or the failure)."""
    sol = _hinge_solution(sy, m1, m2)
    if isinstance(sol, str):
        return _finish(sy, _truncated(sy, 1), True, sy.vec[:, 0], False, sol, m1, m2)
    x, v = sol
    return _finish(sy, x, True, v, True, "", m1, m2)


def score(
    R1: np.ndarray,
    t1: np.ndarray,
    R2: np.ndarray,
    t2: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    markers1: np.ndarray | None = None,
    markers2: np.ndarray | None = None,
    hinge_threshold: float = HINGE_THRESHOLD,
) -> ScoreFit:
    """Joint centre fixed in two segments (SCoRE, Ehrig et al. 2006).

    Minimises ``sum_f w_f |(R1_f c1 + t1_f) - (R2_f c2 + t2_f)|^2`` over the
    local centres ``c1``, ``c2``. When the motion is hinge-like
    (``axis_ratio < hinge_threshold``) the centre is undetermined along the
    axis: with ``markers1`` and ``markers2`` it is then placed as in
    :func:`score_hinge` (``hinge=True``); without them the fit fails
    (``ok=False``, ``hinge=True``, ``c1``/``c2`` an arbitrary point on the
    axis, the minimum-norm one).

    Parameters
    ----------
    R1 : (F, 3, 3) ndarray
        Rotations of segment 1 (local to lab); NaN for unknown frames.
    t1 : (F, 3) ndarray
        Translations of segment 1.
    R2 : (F, 3, 3) ndarray
        Rotations of segment 2.
    t2 : (F, 3) ndarray
        Translations of segment 2.
    weights : (F,) ndarray, optional
        Non-negative frame weights (default 1); frames with weight 0 are skipped.
    markers1 : (K1, 3) ndarray, optional
        Marker positions in segment 1's local frame (for the hinge fallback).
    markers2 : (K2, 3) ndarray, optional
        Marker positions in segment 2's local frame.
    hinge_threshold : float, optional
        ``axis_ratio`` below which the motion is treated as a hinge.

    Returns
    -------
    ScoreFit
    """
    sy = _system(R1, t1, R2, t2, weights)
    F = sy.valid.shape[0]
    m1 = None if markers1 is None else _local_markers(markers1, "markers1")
    m2 = None if markers2 is None else _local_markers(markers2, "markers2")
    why = _degenerate(sy)
    if why:
        return _nan_score(F, why, sy.sv, sy.n, markers1=m1, markers2=m2)
    if sy.axis_ratio >= hinge_threshold:
        return _finish(sy, _truncated(sy, 0), False, None, True, "", m1, m2)
    if m1 is None or m2 is None:
        v = sy.vec[:, 0]
        return _finish(
            sy, _truncated(sy, 1), True, v, False,
            f"hinge-like motion (axis_ratio {sy.axis_ratio:.3g} < {hinge_threshold:g}): the centre is "
            "undetermined along the axis; pass markers1 and markers2 to place it",
            m1, m2,
        )
    return _hinge_fit(sy, m1, m2)


def score_hinge(
    R1: np.ndarray,
    t1: np.ndarray,
    R2: np.ndarray,
    t2: np.ndarray,
    markers_local1: np.ndarray,
    markers_local2: np.ndarray,
    weights: np.ndarray | None = None,
) -> ScoreFit:
    """Hinge joint centre: the point on the SARA axis closest to the markers.

    The least-squares solutions of :func:`score` along the weakest direction
    (the hinge axis, fixed in both segments) fit equally well. This takes the
    minimum-norm solution with that direction removed and shifts it along the
    axis to the point whose lab position is closest, in least squares over
    the frames, to the lab centroid of all markers of both segments. Used
    whatever the motion (for a ball joint it drops the weakest direction).

    Parameters
    ----------
    R1, t1, R2, t2 : ndarrays
        Segment poses as in :func:`score`.
    markers_local1 : (K1, 3) ndarray
        Marker positions in segment 1's local frame (NaN rows ignored).
    markers_local2 : (K2, 3) ndarray
        Marker positions in segment 2's local frame.
    weights : (F,) ndarray, optional
        Frame weights.

    Returns
    -------
    ScoreFit
        With ``hinge=True`` and the axis in ``axis1``/``axis2``.
    """
    sy = _system(R1, t1, R2, t2, weights)
    F = sy.valid.shape[0]
    m1 = _local_markers(markers_local1, "markers_local1")
    m2 = _local_markers(markers_local2, "markers_local2")
    why = _degenerate(sy)
    if why:
        return _nan_score(F, why, sy.sv, sy.n, hinge=True, markers1=m1, markers2=m2)
    return _hinge_fit(sy, m1, m2)


def sara(
    R1: np.ndarray,
    t1: np.ndarray,
    R2: np.ndarray,
    t2: np.ndarray,
    weights: np.ndarray | None = None,
) -> SaraFit:
    """Axis of rotation fixed in two segments (SARA, Ehrig et al. 2007).

    The direction ``(a1, a2)`` with ``R1_f a1 = R2_f a2`` for all frames is
    the eigenvector of the SCoRE normal matrix with the smallest eigenvalue
    (the null space of the stacked system ``[R1_f, -R2_f]``); a point on the
    axis is the least-squares solution restricted to the other directions.

    Parameters
    ----------
    R1, t1, R2, t2 : ndarrays
        Segment poses as in :func:`score`.
    weights : (F,) ndarray, optional
        Frame weights.

    Returns
    -------
    SaraFit
        ``ok=False`` when the relative rotation is too small to define an
        axis. Check ``axis_ratio``: near 1 the motion is not hinge-like and
        the axis is arbitrary.
    """
    sy = _system(R1, t1, R2, t2, weights)
    F = sy.valid.shape[0]
    why = _degenerate(sy)
    nan3 = np.full(3, np.nan)
    if why:
        return SaraFit(
            nan3, nan3.copy(), nan3.copy(), nan3.copy(), np.full((F, 3), np.nan), np.full((F, 3), np.nan),
            np.full(F, np.nan), np.full(F, np.nan), float("nan"), sy.cond if sy.n else float("nan"),
            sy.axis_ratio if sy.n else float("nan"), sy.sv, sy.n, False, why,
        )
    v = sy.vec[:, 0]
    a1 = v[:3] / np.linalg.norm(v[:3])
    a2 = v[3:] / np.linalg.norm(v[3:])
    if a1[np.argmax(np.abs(a1))] < 0:
        a1, a2 = -a1, -a2
    x = _truncated(sy, 1)
    q1, q2 = _images(sy, x[:3], x[3:])
    diff = q1 - q2
    residual = np.sqrt(np.einsum("fi,fi->f", diff, diff))
    rms = float(np.sqrt(np.sum(sy.w[sy.valid] * residual[sy.valid] ** 2)))
    e1 = _rotate(sy.R1, a1)
    e2 = _rotate(sy.R2, a2)
    s = e1 + e2
    axis = s / np.linalg.norm(s, axis=1, keepdims=True).clip(1e-300)
    angle = 2 * np.arctan2(np.linalg.norm(e1 - e2, axis=1), np.linalg.norm(s, axis=1))
    axis[~sy.valid] = np.nan
    angle[~sy.valid] = np.nan
    return SaraFit(
        axis1=a1, axis2=a2, point1=x[:3].copy(), point2=x[3:].copy(), axis=axis, point=0.5 * (q1 + q2),
        residual=residual, angle=angle, rms=rms, cond=sy.cond, axis_ratio=sy.axis_ratio,
        singular_values=sy.sv, n_frames=sy.n, ok=True, reason="",
    )


# --------------------------------------------------------------------------
# poses from markers


def group_pose(P: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """Per-frame pose of a marker group against its first complete frame whose markers are not in one line
    (two labels on one point, a body seen edge-on, are no reference); a reason on failure."""
    F, K, _ = P.shape
    if K < 3:
        return f"group {name} has {K} marker(s): at least 3 non-collinear markers are needed for its rotation"
    first, seen = -1, False
    for lo in range(0, F, 1024):  # the first complete frame out of line, usually among the first few
        B = P[lo : lo + 1024]
        vis = np.isfinite(B).all(-1)
        complete = vis.all(1)
        seen = seen or bool(complete.any())
        good = complete & _solvable_frames(B, vis, COLLINEAR_TOL)
        if good.any():
            first = lo + int(np.argmax(good))
            break
    if not seen:
        return f"group {name}: no frame where all its {K} markers are seen (needed for the reference shape)"
    if first < 0:
        return f"group {name}: its markers are collinear, so its rotation about their line is undetermined"
    ref = P[first] - P[first].mean(0)
    R, t = shape_poses(ref, P)
    return R, t, ref


def score_from_markers(
    A: np.ndarray,
    B: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    hinge_threshold: float = HINGE_THRESHOLD,
) -> ScoreFit:
    """SCoRE joint centre between two rigid marker groups.

    Each group's pose per frame comes from a batched rigid fit (Horn's
    quaternion method, vectorised) of its reference shape: the first frame
    where all its markers are seen (its noise only shifts the local frame by
    a constant rigid offset, which SCoRE absorbs). A segment's local frame is that
    shape's: origin at the markers' centroid, axes parallel to the lab axes
    at the first complete frame; the shapes are returned in ``markers1`` and
    ``markers2``. Frames where a group has fewer than 3 (non-collinear)
    visible markers are skipped. Hinge-like motion is handled as in
    :func:`score`, with the groups' markers.

    Parameters
    ----------
    A : (F, Na, 3) ndarray
        Markers of segment 1, NaN where not seen.
    B : (F, Nb, 3) ndarray
        Markers of segment 2.
    weights : (F,) ndarray, optional
        Frame weights.
    hinge_threshold : float, optional
        As in :func:`score`.

    Returns
    -------
    ScoreFit
        ``ok=False`` with the reason when a group has fewer than 3 markers,
        collinear markers, or no complete frame.
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if A.ndim != 3 or B.ndim != 3 or A.shape[2] != 3 or B.shape[2] != 3 or A.shape[0] != B.shape[0]:
        raise ValueError(f"A and B must be (F, N, 3) with the same F, got {A.shape} and {B.shape}")
    F = A.shape[0]
    pa = group_pose(A, "A")
    if isinstance(pa, str):
        return _nan_score(F, pa)
    pb = group_pose(B, "B")
    if isinstance(pb, str):
        return _nan_score(F, pb)
    R1, t1, ref1 = pa
    R2, t2, ref2 = pb
    return score(R1, t1, R2, t2, weights, markers1=ref1, markers2=ref2, hinge_threshold=hinge_threshold)
