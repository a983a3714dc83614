"""Component-plane kernels of the batched IK: 3-vector and 3x3 matrix arithmetic
and rotation conversions over all segments and frames at once.

The kernels work on *component planes*: a field of 3-vectors is an array
(3, ...) and a field of 3x3 matrices (3, 3, ...), frames on the last axis
(segment-major before it). Every matrix entry is then one contiguous array,
each arithmetic operation is one numpy call over all segments and frames,
and converged frames are dropped by indexing the last axis.
:func:`~mocapskel.solvers.ik.segment_poses.segment_poses`, the per-segment
rigid fit used for the starting pose, works the same way.
"""
from __future__ import annotations

import numpy as np


# --------------------------------------------------------------------------- component planes


def _c_mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Matrix products of planes: (3, 3, ...) x (3, 3, ...) -> (3, 3, ...)."""
    return np.einsum("ij...,jk...->ik...", A, B)


def _c_mmt(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B^T`` of planes."""
    return np.einsum("ik...,jk...->ij...", A, B)


def _c_mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Matrix-vector products of planes: (3, 3, ...) x (3, ...) -> (3, ...)."""
    return np.einsum("ij...,j...->i...", A, v)


def _c_mtv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``A^T @ v`` of planes."""
    return np.einsum("ji...,j...->i...", A, v)


def _c_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products of vector planes (3, ...) -> (...)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _c_cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of vector planes (3, ...)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.multiply(a1, b2, out=out[0])
    out[0] -= a2 * b1
    np.multiply(a2, b0, out=out[1])
    out[1] -= a0 * b2
    np.multiply(a0, b1, out=out[2])
    out[2] -= a1 * b0
    return out


def _c_hat(v: np.ndarray, sign: float = 1.0) -> np.ndarray:
    """(3, ...) -> cross-product matrices (3, 3, ...) times ``sign`` (1 or -1):
    ``_c_mv(_c_hat(a), b) == _c_cross(a, b)``."""
    K = np.empty((3,) + v.shape)
    x, y, z = v if sign > 0 else -v
    K[0, 0] = K[1, 1] = K[2, 2] = 0.0
    np.negative(z, out=K[0, 1])
    K[0, 2] = y
    K[1, 0] = z
    np.negative(x, out=K[1, 2])
    np.negative(y, out=K[2, 0])
    K[2, 1] = x
    return K


def _c_expm1(rv: np.ndarray) -> np.ndarray:
    """Rodrigues minus the identity: rotation vectors (3, ...) -> ``exp([v]x) - I`` (3, 3, ...).

    ``a [v]x + b [v]x^2`` with ``[v]x^2 = v v^T - |v|^2 I``, ``a = sin(t) / t`` and
    ``b = (1 - cos t) / t^2 = (sin(t/2) / (t/2))^2 / 2`` (``np.sinc``), accurate for small angles: the
    change of a rotation by a small step is exact to the rounding of the change.
    """
    th2 = _c_dot(rv, rv)
    th = np.sqrt(th2)
    a = np.sinc(th * (1 / np.pi))  # sin(t) / t, 1 at 0
    h = np.sinc(th * (0.5 / np.pi))
    b = 0.5 * h * h
    M = rv[:, None] * (b * rv)[None, :]
    bt = b * th2
    x, y, z = a * rv[0], a * rv[1], a * rv[2]
    M[0, 0] -= bt
    M[1, 1] -= bt
    M[2, 2] -= bt
    M[0, 1] -= z
    M[1, 0] += z
    M[0, 2] += y
    M[2, 0] -= y
    M[1, 2] -= x
    M[2, 1] += x
    return M


def _c_exp(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (3, ...) -> rotation matrices (3, 3, ...)."""
    R = _c_expm1(rv)
    for i in range(3):
        R[i, i] += 1.0
    return R


def _c_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (3, 3, ...) -> rotation vectors (3, ...), angle in [0, pi]."""
    v = np.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = R[0, 0] + R[1, 1] + R[2, 2] - 1  # 2 cos(angle)
    n = np.sqrt(_c_dot(v, v))  # 2 sin(angle)
    big = n > 1e-12
    v *= np.where(big, np.arctan2(n, c) / np.where(big, n, 1.0), 0.5)
    near_pi = c < -1.9  # angle > ~162 deg: the antisymmetric part loses the axis; use quaternions
    if np.any(near_pi):
        q = _mat_to_quat(np.moveaxis(R[:, :, near_pi], -1, 0))
        w, u = q[:, 0], q[:, 1:]
        un = np.linalg.norm(u, axis=-1)
        v[:, near_pi] = (u * (2 * np.arctan2(un, w) / np.where(un > 0, un, 1.0))[:, None]).T
    return v


def _c_inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of (3, 3, ...) matrices by cofactors."""
    (a, b, c), (d, e, f), (g, h, i) = A
    out = np.empty(A.shape)
    np.multiply(e, i, out=out[0, 0])
    out[0, 0] -= f * h
    np.multiply(f, g, out=out[1, 0])
    out[1, 0] -= d * i
    np.multiply(d, h, out=out[2, 0])
    out[2, 0] -= e * g
    det = a * out[0, 0]
    det += b * out[1, 0]
    det += c * out[2, 0]
    np.multiply(c, h, out=out[0, 1])
    out[0, 1] -= b * i
    np.multiply(a, i, out=out[1, 1])
    out[1, 1] -= c * g
    np.multiply(b, g, out=out[2, 1])
    out[2, 1] -= a * h
    np.multiply(b, f, out=out[0, 2])
    out[0, 2] -= c * e
    np.multiply(c, d, out=out[1, 2])
    out[1, 2] -= a * f
    np.multiply(a, e, out=out[2, 2])
    out[2, 2] -= b * d
    out *= 1.0 / det
    return out


def _c_inv3_sym(A9: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Inverse of symmetric 3x3 matrices given as flattened planes (9, ...) (upper triangle read)."""
    a, b, c, _, e, f, _, _, i = A9
    o = np.empty(A9.shape) if out is None else out
    np.multiply(e, i, out=o[0])
    o[0] -= f * f
    np.multiply(c, f, out=o[1])
    o[1] -= b * i
    np.multiply(b, f, out=o[2])
    o[2] -= c * e
    np.multiply(a, i, out=o[4])
    o[4] -= c * c
    np.multiply(b, c, out=o[5])
    o[5] -= a * f
    np.multiply(a, e, out=o[8])
    o[8] -= b * b
    det = a * o[0]
    det += b * o[1]
    det += c * o[2]
    r = 1.0 / det
    for k in (0, 1, 2, 4, 5, 8):
        o[k] *= r
    o[3], o[6], o[7] = o[1], o[2], o[5]
    return o


def _push(dst: np.ndarray, src: np.ndarray, ops: list[tuple[int, int, int, bool]]) -> None:
    """Add children's terms ``src`` (..., n, F) of one tree level to their parents in ``dst``
    (..., S, F), by the operations of ``_Tree.push``."""
    for a, b, p, total in ops:
        if total:
            dst[..., p, :] += src[..., a:b, :].sum(-2)
        elif b - a == 1:
            dst[..., p, :] += src[..., a, :]
        else:
            dst[..., p : p + b - a, :] += src[..., a:b, :]


def _planes(M: np.ndarray) -> np.ndarray:
    """(..., 3, 3) matrices -> planes (3, 3, ...)."""
    return np.moveaxis(M, (-2, -1), (0, 1))


def _unplanes(M: np.ndarray) -> np.ndarray:
    """Planes (3, 3, ...) -> (..., 3, 3) matrices."""
    return np.moveaxis(M, (0, 1), (-2, -1))


# --------------------------------------------------------------------------- rotations (frames first)


def _exp(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (..., 3) -> rotation matrices (..., 3, 3)."""
    return np.ascontiguousarray(_unplanes(_c_exp(np.moveaxis(np.asarray(rv, dtype=float), -1, 0))))


def _log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3), angle in [0, pi]."""
    return np.ascontiguousarray(np.moveaxis(_c_log(_planes(np.asarray(R, dtype=float))), 0, -1))


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of (..., 3, 3) matrices by cofactors."""
    return np.ascontiguousarray(_unplanes(_c_inv3(_planes(np.asarray(A, dtype=float)))))


def _mat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) as (w, x, y, z), w >= 0."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([tr, m00, m11, m22], -1)
    k = np.argmax(cand, -1)
    # Shepperd: use the largest of 4 (w, x, y, z) candidates
    s0 = np.sqrt(np.maximum(1 + tr, 1e-300)) * 2
    s1 = np.sqrt(np.maximum(1 + m00 - m11 - m22, 1e-300)) * 2
    s2 = np.sqrt(np.maximum(1 + m11 - m00 - m22, 1e-300)) * 2
    s3 = np.sqrt(np.maximum(1 + m22 - m00 - m11, 1e-300)) * 2
    r21, r12 = R[..., 2, 1], R[..., 1, 2]
    r02, r20 = R[..., 0, 2], R[..., 2, 0]
    r10, r01 = R[..., 1, 0], R[..., 0, 1]
    q0 = np.stack([s0 / 4, (r21 - r12) / s0, (r02 - r20) / s0, (r10 - r01) / s0], -1)
    q1 = np.stack([(r21 - r12) / s1, s1 / 4, (r01 + r10) / s1, (r02 + r20) / s1], -1)
    q2 = np.stack([(r02 - r20) / s2, (r01 + r10) / s2, s2 / 4, (r12 + r21) / s2], -1)
    q3 = np.stack([(r10 - r01) / s3, (r02 + r20) / s3, (r12 + r21) / s3, s3 / 4], -1)
    q = np.choose(k[..., None], [q0, q1, q2, q3])
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) (w, x, y, z) -> rotation matrices (..., 3, 3)."""
    return np.ascontiguousarray(_unplanes(_c_quat_to_mat(np.moveaxis(q, -1, 0))))


def _c_quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (4, ...) (w, x, y, z) -> rotation matrices (3, 3, ...)."""
    w, x, y, z = q
    R = np.empty((3, 3) + q.shape[1:])
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    R[0, 0] = ww + xx - yy - zz
    R[1, 1] = ww - xx + yy - zz
    R[2, 2] = ww - xx - yy + zz
    xy, wz, xz, wy, yz, wx = x * y, w * z, x * z, w * y, y * z, w * x
    R[0, 1] = 2 * (xy - wz)
    R[1, 0] = 2 * (xy + wz)
    R[0, 2] = 2 * (xz + wy)
    R[2, 0] = 2 * (xz - wy)
    R[1, 2] = 2 * (yz - wx)
    R[2, 1] = 2 * (yz + wx)
    return R


def _project_so3(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrices (..., 3, 3) (polar decomposition with a proper determinant).

    Returned as they are when they already are rotations to 1e-9."""
    if _c_is_rotation(_planes(R)):
        return np.array(R, dtype=float)
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., 2] *= d[..., None]
    return U @ Vt


def _c_is_rotation(R: np.ndarray) -> bool:
    """Whether all the planes (3, 3, ...) are proper rotations to 1e-9."""
    E = np.einsum("ki...,kj...->ij...", R, R)
    for i in range(3):
        E[i, i] -= 1.0
    det = _c_dot(R[0], _c_cross(R[1], R[2]))
    return bool(np.abs(E).max(initial=0.0) < 1e-9 and np.all(det > 0))


def _swing(ref_rot: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smallest rotation taking ``ref_rot @ u`` to ``v``, composed with ``ref_rot``.

    ref_rot (N, 3, 3), u and v (N, 3) unit vectors -> (N, 3, 3).
    """
    a = np.einsum("nij,nj->ni", ref_rot, u)
    cr = np.cross(a, v)
    s = np.linalg.norm(cr, axis=-1)
    c = (a * v).sum(-1)
    ang = np.arctan2(s, c)
    # axis: a x v, or any perpendicular to a when a and v are (anti)parallel
    e = np.eye(3)[np.argmin(np.abs(a), -1)]
    perp = np.cross(a, e)
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    axis = np.where((s > 1e-12)[:, None], cr / np.where(s > 1e-12, s, 1.0)[:, None], perp)
    return _exp(axis * ang[:, None]) @ ref_rot
