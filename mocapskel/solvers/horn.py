"""Batched rigid rotations by Horn's quaternion method with Theobald's QCP eigenvalue.

Several times faster than batched 3x3 SVDs for many frames of a few points.
"""
from __future__ import annotations

import numpy as np


def _minors(a):
    """2x2 minors of rows (0, 1) and of rows (2, 3) of 4x4 matrices a[i][j] (arrays)."""
    s = (
        a[0][0] * a[1][1] - a[1][0] * a[0][1], a[0][0] * a[1][2] - a[1][0] * a[0][2],
        a[0][0] * a[1][3] - a[1][0] * a[0][3], a[0][1] * a[1][2] - a[1][1] * a[0][2],
        a[0][1] * a[1][3] - a[1][1] * a[0][3], a[0][2] * a[1][3] - a[1][2] * a[0][3],
    )
    c = (
        a[2][0] * a[3][1] - a[3][0] * a[2][1], a[2][0] * a[3][2] - a[3][0] * a[2][2],
        a[2][0] * a[3][3] - a[3][0] * a[2][3], a[2][1] * a[3][2] - a[3][1] * a[2][2],
        a[2][1] * a[3][3] - a[3][1] * a[2][3], a[2][2] * a[3][3] - a[3][2] * a[2][3],
    )
    return s, c


def _adjugate_columns(a):
    """The four columns of adj(a) for 4x4 matrices a[i][j] (arrays), by Laplace expansion."""
    s, c = _minors(a)
    return (
        (a[1][1] * c[5] - a[1][2] * c[4] + a[1][3] * c[3], -a[1][0] * c[5] + a[1][2] * c[2] - a[1][3] * c[1],
         a[1][0] * c[4] - a[1][1] * c[2] + a[1][3] * c[0], -a[1][0] * c[3] + a[1][1] * c[1] - a[1][2] * c[0]),
        (-a[0][1] * c[5] + a[0][2] * c[4] - a[0][3] * c[3], a[0][0] * c[5] - a[0][2] * c[2] + a[0][3] * c[1],
         -a[0][0] * c[4] + a[0][1] * c[2] - a[0][3] * c[0], a[0][0] * c[3] - a[0][1] * c[1] + a[0][2] * c[0]),
        (a[3][1] * s[5] - a[3][2] * s[4] + a[3][3] * s[3], -a[3][0] * s[5] + a[3][2] * s[2] - a[3][3] * s[1],
         a[3][0] * s[4] - a[3][1] * s[2] + a[3][3] * s[0], -a[3][0] * s[3] + a[3][1] * s[1] - a[3][2] * s[0]),
        (-a[2][1] * s[5] + a[2][2] * s[4] - a[2][3] * s[3], a[2][0] * s[5] - a[2][2] * s[2] + a[2][3] * s[1],
         -a[2][0] * s[4] + a[2][1] * s[2] - a[2][3] * s[0], a[2][0] * s[3] - a[2][1] * s[1] + a[2][2] * s[0]),
    )


def horn_rotation(S: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Rotations (F, 3, 3) maximising sum b.(R a), from the 9 components of S = sum a b^T.

    S is (9, F): ``S[3 i + j]`` is the (i, j) entry for every frame (centred
    points a of the reference and b of the observation).

    Horn's unit-quaternion method, vectorised over frames: the largest
    eigenvalue of the 4x4 key matrix N by Newton's method on its
    characteristic polynomial, started from the upper bound
    G = (sum |a|^2 + sum |b|^2) / 2 (Theobald's QCP), and the eigenvector as
    the largest column of adj(N - lambda I). Exact for every non-collinear
    configuration, planar ones (3 markers) included, and several times faster
    than batched 3x3 SVDs.
    """
    F = S.shape[1]
    Sxx, Sxy, Sxz, Syx, Syy, Syz, Szx, Szy, Szz = S
    n01, n02, n03 = Syz - Szy, Szx - Sxz, Sxy - Syx
    n12, n13, n23 = Sxy + Syx, Szx + Sxz, Syz + Szy
    diag = (Sxx + Syy + Szz, Sxx - Syy - Szz, Syy - Sxx - Szz, Szz - Sxx - Syy)
    off = ((None, n01, n02, n03), (n01, None, n12, n13), (n02, n12, None, n23), (n03, n13, n23, None))
    N = [[diag[i] if i == j else off[i][j] for j in range(4)] for i in range(4)]
    s, c = _minors(N)
    c0 = s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]  # det N
    c1 = -8 * (Sxx * (Syy * Szz - Syz * Szy) - Sxy * (Syx * Szz - Syz * Szx) + Sxz * (Syx * Szy - Syy * Szx))
    c2 = -2 * np.einsum("kf,kf->f", S, S)
    lam = np.array(G, dtype=float)
    for _ in range(60):  # converges monotonically from above, quadratically near the root
        l2 = lam * lam
        dp = 4 * l2 * lam + 2 * c2 * lam + c1
        step = ((l2 + c2) * l2 + c1 * lam + c0) / np.where(dp != 0, dp, 1.0)
        lam -= step
        if np.all(np.abs(step) <= 1e-15 * np.abs(lam)):
            break
    A = [[N[i][j] - lam if i == j else N[i][j] for j in range(4)] for i in range(4)]
    cols = _adjugate_columns(A)
    nrm = np.array([col[0] ** 2 + col[1] ** 2 + col[2] ** 2 + col[3] ** 2 for col in cols])  # (4, F)
    best = np.argmax(nrm, 0)
    scale = 1.0 / np.sqrt(np.choose(best, nrm))
    q0, qx, qy, qz = (np.choose(best, [col[k] for col in cols]) * scale for k in range(4))
    R = np.empty((3, 3, F))
    R[0, 0] = q0 * q0 + qx * qx - qy * qy - qz * qz
    R[0, 1] = 2 * (qx * qy - q0 * qz)
    R[0, 2] = 2 * (qx * qz + q0 * qy)
    R[1, 0] = 2 * (qy * qx + q0 * qz)
    R[1, 1] = q0 * q0 - qx * qx + qy * qy - qz * qz
    R[1, 2] = 2 * (qy * qz - q0 * qx)
    R[2, 0] = 2 * (qz * qx - q0 * qy)
    R[2, 1] = 2 * (qz * qy + q0 * qx)
    R[2, 2] = q0 * q0 - qx * qx - qy * qy + qz * qz
    return np.ascontiguousarray(R.transpose(2, 0, 1))
