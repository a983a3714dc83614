"""Rigid alignment: batched weighted Kabsch/Horn, the best rigid motion between two point sets in every frame.

All functions are vectorised over frames (time is the first axis) and never
raise for a frame that cannot be solved: such a frame gets NaN rotation,
translation and rms instead.
"""
from __future__ import annotations

import numpy as np

__all__ = ["kabsch"]

#: Default for ``collinear_tol``: usable points whose second principal spread is
#: below this fraction of the first are treated as collinear.
COLLINEAR_TOL = 1e-6


def kabsch(
    ref: np.ndarray,
    obs: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    collinear_tol: float = COLLINEAR_TOL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best rigid motion carrying ``ref`` onto ``obs``, for every frame at once.

    Solves ``min_{R, t} sum_p w[f, p] |R ref[p] + t - obs[f, p]|^2`` per frame
    over proper rotations (the reflection case of Kabsch's SVD solution is
    excluded), so that ``obs[f] ~ R[f] @ ref + t[f]``. The rotation comes from
    Horn's quaternion matrix, solved in closed form and polished by Newton's
    method on SO(3) (about twice as fast as a batched 3x3 SVD, whose per-matrix
    overhead dominates); a frame whose optimum cannot be certified that way
    is solved by the SVD (Kabsch, with the reflection fix). Both give the
    same rotation to rounding.

    Parameters
    ----------
    ref : (P, 3) or (F, P, 3) ndarray
        Reference points: one set for all frames, or one per frame. NaN rows
        are left out (weight 0).
    obs : (F, P, 3) ndarray
        Observed points; NaN where a point is not seen (weight 0 there).
    weights : (F, P) or (P,) ndarray, optional
        Non-negative weights (default 1).
    collinear_tol : float, optional
        A frame whose usable reference points have a second principal spread
        (standard deviation) below ``collinear_tol`` times the first is
        treated as collinear, hence unsolvable.

    Returns
    -------
    R : (F, 3, 3) ndarray
        Rotations; NaN for frames that cannot be solved (fewer than 3 usable
        points, or collinear ones).
    t : (F, 3) ndarray
        Translations; NaN likewise.
    rms : (F,) ndarray
        Weighted root-mean-square residual ``sqrt(sum w |R ref + t - obs|^2 / sum w)``;
        NaN likewise.
    """
    obs = np.asarray(obs, dtype=float)
    ref = np.asarray(ref, dtype=float)
    if obs.ndim != 3 or obs.shape[-1] != 3:
        raise ValueError(f"obs must be (F, P, 3), got {obs.shape}")
    F, P, _ = obs.shape
    if ref.shape == (P, 3):
        ref = np.broadcast_to(ref, (F, P, 3))
    elif ref.shape != (F, P, 3):
        raise ValueError(f"ref must be ({P}, 3) or ({F}, {P}, 3), got {ref.shape}")
    if weights is None:
        w = np.ones((F, P))
    else:
        w = np.array(np.broadcast_to(np.asarray(weights, dtype=float), (F, P)))
        if np.any(w < 0) or not np.all(np.isfinite(w)):
            raise ValueError("weights must be finite and non-negative")
    usable = np.isfinite(obs).all(-1) & np.isfinite(ref).all(-1) & (w > 0)
    w = np.where(usable, w, 0.0)
    a = np.where(usable[..., None], ref, 0.0)
    b = np.where(usable[..., None], obs, 0.0)

    W = w.sum(1)  # (F,)
    Wsafe = np.where(W > 0, W, 1.0)
    ca = (w[:, None, :] @ a)[:, 0] / Wsafe[:, None]
    cb = (w[:, None, :] @ b)[:, 0] / Wsafe[:, None]
    a = np.where(usable[..., None], a - ca[:, None, :], 0.0)
    b = np.where(usable[..., None], b - cb[:, None, :], 0.0)
    waT = np.swapaxes(w[..., None] * a, 1, 2)  # (F, 3, P)
    H = waT @ b  # sum w a b^T
    C = waT @ a  # weighted scatter of the reference

    lam = _sym3_eigvals(C)  # ascending
    spread_ok = lam[:, 1] > (collinear_tol**2) * lam[:, 2]
    ok = (usable.sum(1) >= 3) & spread_ok & (lam[:, 2] > 0)

    R = np.full((F, 3, 3), np.nan)
    t = np.full((F, 3), np.nan)
    rms = np.full(F, np.nan)
    if ok.any():
        Rk = _best_rotation(H[ok])
        R[ok] = Rk
        t[ok] = cb[ok] - (Rk @ ca[ok][:, :, None])[:, :, 0]
        res = a[ok] @ np.swapaxes(Rk, 1, 2) - b[ok]
        rms[ok] = np.sqrt((w[ok] * (res * res).sum(-1)).sum(1) / W[ok])
    return R, t, rms


def _sym3_eigvals(C: np.ndarray) -> np.ndarray:
    """Eigenvalues (n, 3), ascending, of symmetric 3x3 matrices (closed form, Smith 1961)."""
    a, e, i = C[:, 0, 0], C[:, 1, 1], C[:, 2, 2]
    b, c, f = C[:, 0, 1], C[:, 0, 2], C[:, 1, 2]
    q = (a + e + i) / 3
    p1 = b * b + c * c + f * f
    aq, eq, iq = a - q, e - q, i - q
    p = np.sqrt((aq * aq + eq * eq + iq * iq + 2 * p1) / 6)
    ps = np.where(p > 0, p, 1.0)
    # r = det((C - q I) / p) / 2
    r = (aq * (eq * iq - f * f) - b * (b * iq - f * c) + c * (b * f - eq * c)) / (2 * ps**3)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3
    l3 = q + 2 * p * np.cos(phi)
    l1 = q + 2 * p * np.cos(phi + 2 * np.pi / 3)
    l2 = 3 * q - l1 - l3
    return np.stack([l1, l2, l3], -1)


def _svd_rotation(H: np.ndarray) -> np.ndarray:
    """Proper rotations R (n, 3, 3) maximising tr(R H) (Kabsch: SVD with the reflection fixed)."""
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2).copy()
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    V[..., 2] *= np.where(d == 0, 1.0, d)[:, None]
    return V @ np.swapaxes(U, -1, -2)


def _adj4(a: list[list[np.ndarray]]) -> tuple[list[list[np.ndarray]], np.ndarray]:
    """Adjugate and determinant of 4x4 matrices given as 4x4 nested lists of (n,) arrays."""
    s0 = a[0][0] * a[1][1] - a[1][0] * a[0][1]
    s1 = a[0][0] * a[1][2] - a[1][0] * a[0][2]
    s2 = a[0][0] * a[1][3] - a[1][0] * a[0][3]
    s3 = a[0][1] * a[1][2] - a[1][1] * a[0][2]
    s4 = a[0][1] * a[1][3] - a[1][1] * a[0][3]
    s5 = a[0][2] * a[1][3] - a[1][2] * a[0][3]
    c5 = a[2][2] * a[3][3] - a[3][2] * a[2][3]
    c4 = a[2][1] * a[3][3] - a[3][1] * a[2][3]
    c3 = a[2][1] * a[3][2] - a[3][1] * a[2][2]
    c2 = a[2][0] * a[3][3] - a[3][0] * a[2][3]
    c1 = a[2][0] * a[3][2] - a[3][0] * a[2][2]
    c0 = a[2][0] * a[3][1] - a[3][0] * a[2][1]
    B = [
        [
            a[1][1] * c5 - a[1][2] * c4 + a[1][3] * c3,
            -a[0][1] * c5 + a[0][2] * c4 - a[0][3] * c3,
            a[3][1] * s5 - a[3][2] * s4 + a[3][3] * s3,
            -a[2][1] * s5 + a[2][2] * s4 - a[2][3] * s3,
        ],
        [
            -a[1][0] * c5 + a[1][2] * c2 - a[1][3] * c1,
            a[0][0] * c5 - a[0][2] * c2 + a[0][3] * c1,
            -a[3][0] * s5 + a[3][2] * s2 - a[3][3] * s1,
            a[2][0] * s5 - a[2][2] * s2 + a[2][3] * s1,
        ],
        [
            a[1][0] * c4 - a[1][1] * c2 + a[1][3] * c0,
            -a[0][0] * c4 + a[0][1] * c2 - a[0][3] * c0,
            a[3][0] * s4 - a[3][1] * s2 + a[3][3] * s0,
            -a[2][0] * s4 + a[2][1] * s2 - a[2][3] * s0,
        ],
        [
            -a[1][0] * c3 + a[1][1] * c1 - a[1][2] * c0,
            a[0][0] * c3 - a[0][1] * c1 + a[0][2] * c0,
            -a[3][0] * s3 + a[3][1] * s1 - a[3][2] * s0,
            a[2][0] * s3 - a[2][1] * s1 + a[2][2] * s0,
        ],
    ]
    det = s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0
    return B, det


def _best_rotation(H: np.ndarray) -> np.ndarray:
    """Proper rotations R (n, 3, 3) maximising tr(R H), H = sum w a b^T, so that R a ~ b.

    Horn's quaternion method without a general eigen-solver (LAPACK's per-matrix
    overhead dominates for many 3x3 problems): the largest eigenvalue of Horn's
    symmetric 4x4 matrix by Newton's method on its characteristic polynomial
    (from above, so monotone), the eigenvector from the adjugate of
    (N - lambda I), then two Newton steps on SO(3) to polish. Matrices where the
    result cannot be certified optimal (a nearly repeated top eigenvalue) are
    redone with the SVD.
    """
    n = H.shape[0]
    Hc = np.ascontiguousarray(H.transpose(1, 2, 0))  # component planes (3, 3, n)
    Sxx, Sxy, Sxz = Hc[0]
    Syx, Syy, Syz = Hc[1]
    Szx, Szy, Szz = Hc[2]
    d01, d02, d03 = Syz - Szy, Szx - Sxz, Sxy - Syx
    d12, d13, d23 = Sxy + Syx, Szx + Sxz, Syz + Szy
    N = [
        [Sxx + Syy + Szz, d01, d02, d03],
        [d01, Sxx - Syy - Szz, d12, d13],
        [d02, d12, -Sxx + Syy - Szz, d23],
        [d03, d13, d23, -Sxx - Syy + Szz],
    ]
    # characteristic polynomial l^4 + c2 l^2 + c1 l + c0 (N is traceless): c2 = -tr(N^2)/2,
    # c1 = -tr(N^3)/3, c0 = det N
    fro2 = sum(N[i][j] * N[i][j] for i in range(4) for j in range(4))
    N2 = [[sum(N[i][k] * N[k][j] for k in range(4)) for j in range(4)] for i in range(4)]
    tr3 = sum(N2[i][j] * N[j][i] for i in range(4) for j in range(4))
    c2, c1 = -0.5 * fro2, -tr3 / 3
    _, c0 = _adj4(N)
    lam = np.sqrt(fro2)  # >= the largest eigenvalue
    active = np.arange(n)
    for _ in range(100):
        la = lam[active]
        l2 = la * la
        P = (l2 + c2[active]) * l2 + c1[active] * la + c0[active]
        dP = (4 * l2 + 2 * c2[active]) * la + c1[active]
        new = la - np.where(dP > 0, P / np.where(dP > 0, dP, 1.0), 0.0)
        moved = new < la
        lam[active] = np.where(moved, new, la)
        active = active[moved & (la - new > 1e-15 * np.abs(la))]
        if active.size == 0:
            break
    A = [[N[i][j] - lam if i == j else N[i][j] for j in range(4)] for i in range(4)]
    B, _ = _adj4(A)
    Bd = np.stack([np.abs(B[i][i]) for i in range(4)])
    k = np.argmax(Bd, axis=0)
    q = np.stack([np.choose(k, [B[i][j] for j in range(4)]) for i in range(4)])  # column k
    nq = np.sqrt((q * q).sum(0))
    good = nq > 0
    w, x, y, z = q / np.where(good, nq, 1.0)
    R = np.empty((n, 3, 3))
    R[:, 0, 0] = w * w + x * x - y * y - z * z
    R[:, 1, 1] = w * w - x * x + y * y - z * z
    R[:, 2, 2] = w * w - x * x - y * y + z * z
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 1] = 2 * (y * z + w * x)
    # polish: Newton on max tr(exp([d]x) R H)
    scale = np.sqrt(np.einsum("nij,nij->n", H, H))
    for _ in range(2):
        Y = np.ascontiguousarray((R @ H).transpose(1, 2, 0))
        gx, gy, gz = Y[1, 2] - Y[2, 1], Y[2, 0] - Y[0, 2], Y[0, 1] - Y[1, 0]
        tr = Y[0, 0] + Y[1, 1] + Y[2, 2]
        # Hs = tr(Y) I - sym(Y), positive definite at the maximum
        a, e, i = tr - Y[0, 0], tr - Y[1, 1], tr - Y[2, 2]
        b, c, f = -0.5 * (Y[0, 1] + Y[1, 0]), -0.5 * (Y[0, 2] + Y[2, 0]), -0.5 * (Y[1, 2] + Y[2, 1])
        A0, A1, A2 = e * i - f * f, c * f - b * i, b * f - c * e  # cofactors
        B1, B2, C2 = a * i - c * c, c * b - a * f, a * e - b * b
        m3 = a * A0 + b * A1 + c * A2
        tiny = 1e-8 * scale
        pd = (a > tiny) & (C2 > tiny * a) & (m3 > tiny * C2)  # Sylvester's criterion
        good &= pd
        inv_det = np.where(pd, 1.0 / np.where(pd, m3, 1.0), 0.0)
        d = np.stack([A0 * gx + A1 * gy + A2 * gz, A1 * gx + B1 * gy + B2 * gz, A2 * gx + B2 * gy + C2 * gz], -1)
        d *= inv_det[:, None]
        R = _rodrigues(d) @ R
    good &= np.einsum("ni,ni->n", d, d) < 1e-12
    if not good.all():
        R[~good] = _svd_rotation(H[~good])
    return R


def _rodrigues(rv: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) -> rotation matrices (n, 3, 3): I + a [v]x + b [v]x^2."""
    x, y, z = rv[:, 0], rv[:, 1], rv[:, 2]
    th2 = x * x + y * y + z * z
    small = th2 < 1e-8
    th = np.sqrt(np.where(small, 1.0, th2))
    a = np.where(small, 1 - th2 / 6, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24, (1 - np.cos(th)) / (th * th))
    R = np.empty(rv.shape + (3,))
    bx, by = b * x, b * y
    ax, ay, az = a * x, a * y, a * z
    R[:, 0, 0] = 1 - b * (y * y + z * z)
    R[:, 1, 1] = 1 - b * (x * x + z * z)
    R[:, 2, 2] = 1 - b * (x * x + y * y)
    R[:, 0, 1] = bx * y - az
    R[:, 1, 0] = bx * y + az
    R[:, 0, 2] = bx * z + ay
    R[:, 2, 0] = bx * z - ay
    R[:, 1, 2] = by * z - ax
    R[:, 2, 1] = by * z + ax
    return R
