"""Marker-trajectory bases (MTB): a joint as a fixed affine combination of markers.

Hang, Lasenby & Li 2015, §II-A: if a rigid segment carries four non-coplanar
points ``r_1..r_4``, every point fixed on the segment (a joint in particular)
has the trajectory

    t_c = lambda_1 t_1 + lambda_2 t_2 + lambda_3 t_3 + (1 - sum lambda) t_4      (6)

with three constant ``lambda``; three non-collinear markers are completed by
the auxiliary marker ``r_+ = r_3 + (r_1 - r_3) x (r_2 - r_3)`` (9). The joint
between segments a and b is then found by minimising Kirk's cost Q over the
three ``lambda`` only.

This module builds the basis (:func:`mtb_basis`) and fits the joint
(:func:`mtb_joint`):

Basis
    All N >= 3 visible points of the group are used, not just four: the basis
    points are the centroid ``o`` and ``o + s a_k`` where ``a_1, a_2`` are the
    group's two in-plane principal directions written as *fixed linear
    combinations* of the markers (least-squares weights from a reference
    frame) and ``a_3 = a_1 x a_2`` is Hang's auxiliary cross-product marker (9),
    ``s`` the group's rms spread. For a rigid group ``[a_1 a_2 a_3]`` is exactly
    the group's rotation times a constant matrix, so (6) holds exactly; for
    N = 3 the affine family is the same as Hang's (9), for N = 4
    non-coplanar the same as the four markers', and for N > 4 the extra markers
    average the noise. The basis is well conditioned (orthonormal axes of the
    group's own size) even for nearly coplanar 4-marker groups. Frames where a
    marker is missing use the visible ones (at least 3 non-collinear), with
    weights per visibility pattern that reproduce the same basis points.
Joint
    A linear least-squares start that is exact for noise-free data: with
    ``c_f = o_f + E_f lambda`` and ``E_f^T E_f`` constant for a rigid basis,
    ``|c_f - m_f|^2 = const`` becomes ``2 (E_f^T (o_f - m_f)) . lambda - t_m =
    -|o_f - m_f|^2``, linear in ``lambda`` and one constant ``t_m`` per point
    (eliminated by centring over frames). Then Levenberg-Marquardt on Q
    itself with the analytic Jacobian (radii eliminated in closed form).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from .cost import JointFit, _alpha_const, _as_points, _cost_terms, _cross, _seen, _sqnorm, _stack, balanced_alpha

__all__ = ["Basis", "mtb_basis", "mtb_joint", "COLLINEAR_TOL"]

#: Default relative tolerance: a group whose second principal spread is below
#: this fraction of the first is collinear (a 'special' group).
COLLINEAR_TOL = 1e-2


@dataclass(frozen=True, eq=False)
class Basis:
    """A marker-trajectory basis of one group. Falsy when none exists.

    points : (F, 4, 3) ndarray
        Basis trajectories (origin, then three axis tips); NaN in frames with
        fewer than 3 non-collinear visible points. All NaN when not ``ok``.
    ok : bool
        Whether the group has 3 non-collinear points (seen together at least once).
    reason : str
        Why not ("" when ok).
    special : bool
        All points collinear (Hang's 'special group'; needs a solved joint).
    pair : (2,) int ndarray or None
        Special group: its two characteristic points (farthest apart).
    ratios : (2,) ndarray
        Median over frames of the group's principal spreads ``s2/s1, s3/s1``
        (NaN when undefined). ``s2/s1 < tol``: collinear; ``s3/s1 < tol``: coplanar.
    coplanar : bool
        All points in a plane (always so for three points): Hang's basis would
        need the auxiliary marker (9), which this basis uses for its third axis
        in any case.
    coverage : float
        Fraction of frames with a basis.
    """

    points: np.ndarray
    ok: bool
    reason: str = ""
    special: bool = False
    pair: np.ndarray | None = None
    ratios: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    coplanar: bool = False
    coverage: float = 0.0

    def __bool__(self) -> bool:
        return bool(self.ok)


def _frame_coeffs(Xref: np.ndarray, vmask: np.ndarray, axes: np.ndarray, s: float, tol: float, svd=None):
    """Weights rebuilding the full basis from the visible subset ``vmask`` of a reference shape.

    Returns (G (nv, 2), beta (4, 3)) so that, with o_V = mean of visible points,
    b_1, b_2 = sum_j (P_j - o_V) G_j and b_3 = b_1 x b_2, the basis points are
    o_V + [b1 b2 b3] beta[0] and that plus [b1 b2 b3] beta[k] (k = 1..3); or None
    when the visible subset is collinear. ``svd``: (singular values, Vt) of the
    centred subset when the caller has them.
    """
    XV = Xref if vmask.all() else Xref[vmask]
    cV = XV.sum(0) / XV.shape[0]
    Y0 = XV - cV
    sv, Wt = np.linalg.svd(Y0, full_matrices=False)[1:] if svd is None else svd
    if sv.size < 2 or sv[0] <= 0 or sv[1] < tol * sv[0]:
        return None
    W = _frame(Wt[0], Wt[1])
    # Y = Y0 W[:, :2] has orthogonal columns of norms sv[:2] (the SVD): the least-squares
    # weights Y (Y^T Y)^-1 are its columns over their squared norms
    G = (Y0 @ W[:, :2]) / (sv[:2] * sv[:2])  # (nv, 2)
    beta = np.empty((4, 3))
    beta[0] = -W.T @ cV  # full centroid sits at the reference origin
    beta[1:] = s * (W.T @ axes).T
    return G, beta


def _frame(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The 3x3 matrix with columns u, v, u x v (u, v (3,))."""
    W = np.empty((3, 3))
    W[:, 0] = u
    W[:, 1] = v
    W[:, 2] = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
    return W


def _basis_points(Bf: np.ndarray, oV: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """(f, 4, 3) points o_V + B coef[k] for frames' axes B (f, 3, 3) and origins o_V (f, 3),
    as products of the (3f, 3) stack in pieces small enough for BLAS to stay on one thread."""
    out = np.empty((oV.shape[0], 4, 3))
    for lo in range(0, oV.shape[0], 4096):
        Bk = Bf[lo : lo + 4096]
        out[lo : lo + 4096] = (Bk.reshape(-1, 3) @ coef.T).reshape(-1, 3, 4).transpose(0, 2, 1)
    out += oV[:, None, :]
    return out


def mtb_basis(markers: ArrayLike, *, tol: float = COLLINEAR_TOL, n_ref: int = 25) -> Basis:
    """Build the marker-trajectory basis of a group of points rigid together.

    Parameters
    ----------
    markers : (F, N, 3) ndarray
        The group's markers (and, for solvability propagation, its solved
        joints); NaN where not seen.
    tol : float
        Relative collinearity tolerance (see :data:`COLLINEAR_TOL`).
    n_ref : int
        Number of frames (all points seen) sampled for the shape checks.

    Returns
    -------
    Basis
        Falsy with a reason when N < 3, no frame sees all points, or the
        points are collinear (``special=True``, ``pair`` set).
    """
    P = _as_points(markers, "markers")
    F, N, _ = P.shape
    empty = np.full((F, 4, 3), np.nan)
    if N < 3:
        return Basis(empty, False, f"{N} point(s): a basis needs 3 non-collinear points")
    vis = _seen(P)
    full = np.flatnonzero(vis.all(1))
    if full.size == 0:
        return Basis(empty, False, f"no frame sees all {N} points of the group together")
    # n_ref positions spread over the complete frames (np.linspace's, without its overhead);
    # spacing >= 1 between them: rounded, they stay distinct
    K = min(n_ref, full.size)
    pos = np.zeros(1)
    if K > 1:
        pos = np.arange(K) * ((full.size - 1) / (K - 1))
        pos[-1] = full.size - 1
    idx = full[pos.round().astype(int)]
    Pi = P[idx]
    X = Pi - Pi.sum(1, keepdims=True) / N
    ev = np.linalg.eigvalsh(np.matmul(np.swapaxes(X, 1, 2), X))  # (K, 3) ascending
    sv = np.sqrt(np.maximum(ev[:, ::-1], 0.0))  # singular values, descending
    s1 = np.where(sv[:, 0] > 0, sv[:, 0], np.nan)
    every = bool(np.isfinite(s1).all())
    if not every and not np.isfinite(s1).any():
        return Basis(empty, False, "all points coincide", special=True)
    rs = sv[:, 1:] / s1[:, None]
    if every:  # the medians of both columns from one sort (np.median's result, without its overhead)
        srt = np.sort(rs, axis=0)
        ratios = srt[K // 2] if K % 2 else (srt[K // 2 - 1] + srt[K // 2]) / 2
        r2, r3 = float(ratios[0]), float(ratios[1])
        fref = int(idx[int(np.argmin(np.abs(rs[:, 0] - r2)))])
    else:
        r2, r3 = float(np.nanmedian(rs[:, 0])), float(np.nanmedian(rs[:, 1]))
        ratios = np.array([r2, r3])
        fref = int(idx[int(np.nanargmin(np.abs(rs[:, 0] - r2)))])
    Pf = P[fref]
    Xref = Pf - Pf.sum(0) / N
    if not r2 >= tol:
        dd = np.linalg.norm(Xref[:, None] - Xref[None], axis=-1)
        i, j = np.unravel_index(int(np.argmax(dd)), dd.shape)
        return Basis(empty, False, f"collinear points (s2/s1 = {r2:.2g} < {tol:g}): special group",
                     special=True, pair=np.array(sorted((int(i), int(j)))), ratios=ratios)
    _, svr, Vt = np.linalg.svd(Xref, full_matrices=False)
    axes = _frame(Vt[0], Vt[1])
    s = float(np.sqrt(np.einsum("ij,ij->", Xref, Xref) / N))

    out = np.full((F, 4, 3), np.nan)
    if full.size == F:
        patterns = [(np.ones(N, bool), None)]
    else:
        code = vis.astype(np.int64) @ (np.int64(1) << np.arange(N, dtype=np.int64)) if N < 63 else None
        if code is None:  # pragma: no cover - groups of 63+ points
            pats, inv = np.unique(vis, axis=0, return_inverse=True)
            inv = inv.reshape(-1)
        else:
            ucode, inv = np.unique(code, return_inverse=True)
            pats = ((ucode[:, None] >> np.arange(N)) & 1).astype(bool)
        patterns = [(vm, np.flatnonzero(inv == p)) for p, vm in enumerate(pats)]
    for vmask, fr in patterns:
        if vmask.sum() < 3:
            continue
        co = _frame_coeffs(Xref, vmask, axes, s, tol, (svr, Vt) if vmask.all() else None)
        if co is None:
            continue
        G, beta = co
        PV = P if fr is None else P[fr]
        if not vmask.all():
            PV = PV[:, vmask]  # (f, nv, 3)
        if fr is None:
            fr = slice(None)
        oV = PV.sum(1) / PV.shape[1]
        Bf = np.empty((oV.shape[0], 3, 3))  # columns b1 b2 b3
        Bf[:, :, :2] = np.matmul(np.swapaxes(PV - oV[:, None], 1, 2), G)
        Bf[:, :, 2] = _cross(Bf[:, :, 0], Bf[:, :, 1])
        # the origin o_V + B beta[0], then the axis tips origin + B beta[k]
        coef = beta.copy()
        coef[1:] += beta[0]
        out[fr] = _basis_points(Bf, oV, coef)
    if full.size == F and np.isfinite(out[:, 0, 0]).all():  # one pattern, every frame placed
        cov = 1.0
    else:
        cov = float(np.isfinite(out).all((1, 2)).mean()) if F else 0.0
    return Basis(out, True, "", False, None, ratios, bool(r3 < tol), cov)


# --------------------------------------------------------------------------- the joint


def _linear_start(o: np.ndarray, E: np.ndarray, pts: np.ndarray, valid: np.ndarray):
    """Closed-form lambda from distance constancy (exact for noise-free rigid data).

    Returns (lambda (3,), singular values (3,) of the centred system, and the
    norm of the uncentred one, for judging the rank).
    """
    F = pts.shape[0]
    every = bool(valid.all())
    v = o[:, None, :] - pts if every else np.where(valid[..., None], o[:, None, :] - pts, 0.0)  # (F, M, 3)
    x = 2.0 * np.matmul(v, E)  # (F, M, 3): E^T v per point
    y = -_sqnorm(v)
    if every:  # every point seen in every frame: weight 1/F each
        xbar = x.sum(0) / F
        ybar = y.sum(0) / F
        sw = np.sqrt(1.0 / F)
        ref = float(np.sqrt(np.einsum("fmi,fmi->", x, x) / F))
        X = (sw * (x - xbar)).reshape(-1, 3)
        Y = (sw * (y - ybar)).reshape(-1)
    else:
        n = valid.sum(0)
        w = np.where(n > 0, 1.0 / np.maximum(n, 1), 0.0)
        wv = np.where(valid, w, 0.0)
        xbar = (wv[..., None] * x).sum(0)
        ybar = (wv * y).sum(0)
        sw = np.sqrt(wv)
        ref = float(np.sqrt((wv[..., None] * x * x).sum()))
        X = (sw[..., None] * (x - xbar)).reshape(-1, 3)
        Y = (sw * (y - ybar)).reshape(-1)
    N = X.T @ X
    ev, V = np.linalg.eigh(N)  # ascending
    svals = np.sqrt(np.maximum(ev[::-1], 0.0))
    keep = ev > 1e-13 * max(ev[-1], 1e-300) if ev[-1] > 0 else np.zeros(3, bool)
    if not keep.all():
        V, ev = V[:, keep], ev[keep]
    lam = V @ ((V.T @ (X.T @ Y)) / ev)  # minimum-norm least squares
    return lam, svals, ref


def mtb_joint(
    basis_markers: ArrayLike | Basis,
    markers_a: ArrayLike,
    markers_b: ArrayLike,
    *,
    alpha: float = 0.0,
    max_iter: int = 50,
    tol: float = 1e-12,
    rank_tol: float = 1e-8,
    basis_side: str | None = None,
) -> JointFit:
    """Joint between two segments as an affine combination of a basis (Hang (6)-(8)).

    Parameters
    ----------
    basis_markers : (F, 4, 3) ndarray or Basis
        Four trajectories rigid with one of the two segments (origin first),
        such as :attr:`Basis.points` of either group; NaN frames give NaN joints.
    markers_a, markers_b : (F, Na, 3), (F, Nb, 3) ndarray
        All points of the two segments that enter Kirk's cost Q (markers,
        and solved joints when propagating); NaN where not seen.
    alpha : float
        Mean-distance penalty of Q (length units).
    max_iter : int
        Levenberg-Marquardt iteration limit.
    tol : float
        Relative decrease of Q below which the refinement stops.
    rank_tol : float
        The joint counts as undetermined (``ok`` False) when the linear start's
        smallest singular value is below ``rank_tol`` times the largest, e.g.
        a hinge moved about one axis only (and ``alpha`` is 0).
    basis_side : {"a", "b"}, optional
        The group the basis rides on. Its own points keep constant distances
        to any point of the basis, so they carry no information about
        lambda: when given, the closed-form start uses the other group's
        points only (they all still enter Q), and a joint whose other group is
        never seen with the basis is reported as such.

    Returns
    -------
    JointFit
        ``params`` holds the three lambda of the basis (origin + axes form).
    """
    B = basis_markers.points if isinstance(basis_markers, Basis) else np.asarray(basis_markers, dtype=float)
    pts = _stack(markers_a, markers_b)
    F, M, _ = pts.shape
    if B.shape != (F, 4, 3):
        raise ValueError(f"basis_markers must be ({F}, 4, 3), got {B.shape}")
    alpha = balanced_alpha(alpha, np.shape(markers_a)[1], M - np.shape(markers_a)[1])
    nan = np.full((F, 3), np.nan)
    bok = np.isfinite(np.einsum("fki->f", B))  # all four basis points seen
    valid = _seen(pts) & bok[:, None]
    if not valid.any():
        return JointFit(nan, np.inf, 0, False, "no frame sees the basis together with a marker")
    o = B[:, 0]
    E = np.swapaxes(B[:, 1:] - o[:, None, :], 1, 2)  # (F, 3, 3), columns = axes
    all_b = bool(bok.all())
    if not all_b:
        o = np.where(bok[:, None], o, 0.0)
        E = np.where(bok[:, None, None], E, 0.0)

    if basis_side is None:
        lam, svals, ref = _linear_start(o, E, pts, valid)
    else:
        if basis_side not in ("a", "b"):
            raise ValueError(f"basis_side must be 'a', 'b' or None, got {basis_side!r}")
        na = np.asarray(markers_a).shape[1]
        other = slice(na, M) if basis_side == "a" else slice(0, na)
        if not valid[:, other].any():
            return JointFit(nan, np.inf, 0, False, "no point of the other group is seen with the basis")
        lam, svals, ref = _linear_start(o, E, pts[:, other], valid[:, other])
    ranked = svals[0] > 1e-9 * ref and svals[2] >= rank_tol * svals[0]
    if all_b:  # basis size
        scale = float(np.sqrt(np.einsum("fij,fij->", E, E) / (3.0 * F)))
    else:
        scale = float(np.sqrt(np.einsum("fij,fij->f", E[bok], E[bok]).mean() / 3.0))

    c = o + E @ lam
    q, d, diff, n, dbar, used = _cost_terms(c, pts, valid, alpha)
    const = _alpha_const(alpha, used)
    mu = 1e-4
    it = 0
    # an exact fit (noise-free data): distances constant to ~1e-12 relative
    tiny = (1e-12 * max(scale, float(np.max(dbar if used.all() else np.where(used, dbar, 0.0))))) ** 2
    converged = q - const <= tiny
    if not converged:
        k = max(int(used.sum()), 1)
        w = np.where(used, 1.0 / (k * np.maximum(n, 1)), 0.0)
        wv = np.where(valid, w, 0.0)
    while not converged and it < max_iter:
        it += 1
        u = diff / np.maximum(d, 1e-300)[..., None]
        ju = np.matmul(u, E)  # (F, M, 3): d|c - m| / d lambda
        r = np.where(valid, d - (dbar - alpha / 2.0), 0.0)
        wju = wv[..., None] * ju
        H = wju.reshape(-1, 3).T @ ju.reshape(-1, 3)
        h = wju.sum(0)  # (M, 3)
        Dm = wv.sum(0)
        S = H - (h * np.where(used, 1.0 / np.maximum(Dm, 1e-300), 0.0)[:, None]).T @ h
        g = (r[..., None] * wju).sum((0, 1))
        diagS = np.maximum(np.diag(S), 1e-30 * max(np.trace(S), 1e-300))
        while True:
            try:
                step = np.linalg.solve(S + mu * np.diag(diagS), -g)
            except np.linalg.LinAlgError:
                step = np.linalg.lstsq(S + mu * np.diag(diagS), -g, rcond=None)[0]
            lam_new = lam + step
            c_new = o + E @ lam_new
            q_new, d_new, diff_new, _, dbar_new, _ = _cost_terms(c_new, pts, valid, alpha)
            if np.isfinite(q_new) and q_new <= q:
                dq = q - q_new
                lam, c, q, d, diff, dbar = lam_new, c_new, q_new, d_new, diff_new, dbar_new
                mu = max(mu / 5.0, 1e-15)
                if dq <= tol * max(q - const, 1e-300) or np.abs(step).max() <= tol * max(np.abs(lam).max(), 1.0):
                    converged = True
                break
            mu *= 10.0
            if mu > 1e16:
                converged = True  # no descent left: at a minimum to rounding
                break
    centre = c if all_b else np.where(bok[:, None], c, np.nan)
    radii = np.where(used, dbar, np.nan)
    if not ranked and not np.any(alpha):
        return JointFit(centre, q, it, False,
                        "the motion does not determine the joint (rank-deficient; e.g. a hinge): "
                        "minimum-norm solution returned", lam, radii)
    if not converged:
        return JointFit(centre, q, it, False, "iteration limit reached before convergence", lam, radii)
    return JointFit(centre, q, it, True, "", lam, radii)


def _mtb_init(a: np.ndarray, b: np.ndarray, alpha: float) -> np.ndarray | None:
    """MTB joint from the side whose fit has the lower Q; None when no side has a basis."""
    best: JointFit | None = None
    for side, name in ((a, "a"), (b, "b")):
        if side.shape[1] >= 3:
            basis = mtb_basis(side)
            if basis:
                fit = mtb_joint(basis.points, a, b, alpha=alpha, basis_side=name)
                if fit and (best is None or fit.cost < best.cost):
                    best = fit
    return None if best is None else best.centre
