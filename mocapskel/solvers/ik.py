"""Batched skeleton inverse kinematics: segment rotations and root position per frame.

The skeleton is a tree of rigid segments. Segment ``s`` has a rest-pose origin
``origin[s]`` (a child's origin is its joint with the parent) and carries
markers at ``origin[s] + marker_local[m]`` at rest. At frame ``f`` every segment
has a *global* rotation ``R_s`` (rest pose -> pose at ``f``) and the root
segment's origin is at ``p``. Forward kinematics::

    P_root = p
    P_c    = P_parent + R_parent @ (origin[c] - origin[parent])
    x_m    = P_s + R_s @ marker_local[m]          (m on segment s)

:func:`solve_ik` minimises, for every frame independently but vectorised over
all frames,

    sum_m w_m |x_m - y_m|^2  +  prior_weight * sum_s |log(R_s R_prior,s^T)|^2

by Levenberg-Marquardt with global left-multiplicative increments
``R_s <- exp([d_s]x) R_s``. No Jacobian is formed: a segment's gradient and
Gauss-Newton Hessian come from a few per-frame sums over its markers
(weighted centroids and cross-covariances, computed once), and the damped
normal equations are solved by eliminating the segments leaves first, each
leaving a 3x3 stiffness on its joint for the parent (the articulated-body
recursion). An iteration is O(S) 3x3 operations per frame, whatever the
number of markers and the depth of the tree; so is the change of the cost
that decides whether a step is taken, computed from the same sums and the
increments themselves (exact to rounding of the change, not of the cost).
A frame leaves the iteration as soon as it has converged.

The kernels work on *component planes*: a field of 3-vectors is an array
(3, ...) and a field of 3x3 matrices (3, 3, ...), frames on the last axis
(segment-major before it). Every matrix entry is then one contiguous array,
each arithmetic operation is one numpy call over all segments and frames,
and converged frames are dropped by indexing the last axis.
:func:`segment_poses`, the per-segment rigid fit used for the starting pose,
works the same way.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .parallel import run_blocks
from .rigid import _adj4, kabsch
from .rotations import fill_joint

__all__ = ["IKResult", "segment_poses", "solve_ik"]

#: Frames solved together: large enough that numpy's per-call overhead is
#: small, small enough that the working arrays stay in the processor's cache.
_BLOCK = 2048
#: The same for :func:`segment_poses`, whose working set per frame is smaller.
_POSE_BLOCK = 4096


def _recycle_large_blocks() -> None:
    """Let the C allocator recycle the kernels' large temporaries (once per process).

    numpy takes every array from malloc. glibc serves blocks above its mmap
    threshold (128 KiB at first) straight from the system, every page a fault
    on first touch, and hands back free memory at the top of its heap beyond
    twice that threshold; the kernels' arrays (a few MiB, many per
    iteration) would pay that each time, doubling their cost. Freeing one
    mmap-served 32 MiB block raises both thresholds (to that size, glibc's
    ceiling), after which such arrays are recycled. Elsewhere it costs one
    allocation.
    """
    global _RECYCLING
    if not _RECYCLING:
        _RECYCLING = True
        np.ones(1 << 22)  # 32 MiB, freed at once


_RECYCLING = False


@dataclass(frozen=True, eq=False)
class IKResult:
    """The result of :func:`solve_ik`.

    root_pos : (F, 3) ndarray
        Root segment origin per frame (mm).
    rot : (F, S, 3, 3) ndarray
        Global segment rotations relative to the rest pose.
    residual : (F, M) ndarray
        Distance of each marker from its model position after the fit (mm);
        NaN where the marker is not seen or belongs to no segment.
    n_iter : int
        Number of iterations run (at most ``iterations``; the most any frame needed).
    converged : (F,) ndarray of bool
        Whether the frame converged: its last step was below the tolerance,
        or the linearised model could no longer lower its cost.
    """

    root_pos: np.ndarray
    rot: np.ndarray
    residual: np.ndarray
    n_iter: int
    converged: np.ndarray


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


def _interp_fill(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Linear interpolation over time of (F, D) values at invalid frames (hold at ends)."""
    F = x.shape[0]
    idx = np.flatnonzero(valid)
    out = x.copy()
    if idx.size == 0 or idx.size == F:
        return out
    bad = np.flatnonzero(~valid)
    for d in range(x.shape[1]):
        out[bad, d] = np.interp(bad, idx, x[idx, d])
    return out


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


# --------------------------------------------------------------------------- tree bookkeeping


class _Tree:
    """Breadth-first order of the segments (parents first, depth levels contiguous)."""

    def __init__(self, parent: np.ndarray):
        S = len(parent)
        roots = np.flatnonzero(parent < 0)
        if np.any(parent >= S) or np.any((parent < 0) & (parent != -1)):
            raise ValueError("parent indices must be -1 or a segment index")
        if len(roots) != 1:
            raise ValueError(f"the skeleton must have exactly one root (parent -1), it has {len(roots)}")
        children: list[list[int]] = [[] for _ in range(S)]
        for s, p in enumerate(parent):
            if p >= 0:
                children[p].append(s)
        order: list[int] = [int(roots[0])]
        i = 0
        while i < len(order):
            order.extend(children[order[i]])
            i += 1
        if len(order) != S:
            raise ValueError("parent does not describe a tree (a cycle or an unreachable segment)")
        self.perm = np.array(order)  # new -> old
        inv = np.empty(S, dtype=int)
        inv[self.perm] = np.arange(S)
        self.S = S
        self.par = np.array([inv[parent[o]] if parent[o] >= 0 else -1 for o in order])  # new indices
        self.children = [[int(inv[c]) for c in children[o]] for o in order]
        self.child_slot = np.zeros(S, dtype=int)  # rank of a segment among its siblings
        for ch in self.children:
            self.child_slot[ch] = np.arange(len(ch))
        self.max_children = max(len(ch) for ch in self.children)
        depth = np.zeros(S, dtype=int)
        for s in range(1, S):
            depth[s] = depth[self.par[s]] + 1
        bounds = np.flatnonzero(np.diff(depth)) + 1
        starts = np.concatenate([[0], bounds]).astype(int)
        ends = np.concatenate([bounds, [S]]).astype(int)
        self.levels = [slice(int(a), int(b)) for a, b in zip(starts, ends)]
        # per level below the root: how to add the children's terms to their parents, as a
        # few operations on contiguous runs (breadth-first order: the children of one parent
        # are contiguous, and so are the parents of consecutive only children): (a, b, p, sum)
        # adds children a:b of the level to parent p (summed), or to parents p:p+b-a
        self.push: list[list[tuple[int, int, int, bool]]] = [[]]
        for sl in self.levels[1:]:
            par = self.par[sl]
            ops: list[tuple[int, int, int, bool]] = []
            i = 0
            while i < len(par):
                j = i + 1
                while j < len(par) and par[j] == par[i]:
                    j += 1
                if j - i > 1:
                    ops.append((i, j, int(par[i]), True))
                elif ops and not ops[-1][3] and ops[-1][1] == i and ops[-1][2] + (i - ops[-1][0]) == par[i]:
                    ops[-1] = (ops[-1][0], j, ops[-1][2], False)  # extends a run of only children
                else:
                    ops.append((i, j, int(par[i]), False))
                i = j
            self.push.append(ops)
        self.path: list[list[int]] = []  # segments from the root to s, inclusive
        for s in range(S):
            self.path.append((self.path[self.par[s]] if s else []) + [s])


# --------------------------------------------------------------------------- the model


class _Model:
    """Marker model on a reordered tree, with the per-iteration kernels.

    Layout (component planes, frames last): rotations ``R`` (3, 3, S, F),
    segment vectors (3, S, F), the root position (3, F); markers in
    per-segment slots, observations ``y`` (K, 3, S, F) and weights ``w``
    (K, S, F), K the most markers on one segment, padding slots with weight 0.

    The Gauss-Newton steps never touch single markers: for fixed observations
    and weights, a segment's gradient, Hessian and cost are functions of a few
    per-frame sums (:meth:`stats`), so a step costs O(S) 3x3 operations per
    frame whatever the number of markers.
    """

    def __init__(self, tree: _Tree, origin: np.ndarray, seg: np.ndarray, local: np.ndarray):
        self.t = tree
        S = tree.S
        self.origin = origin
        self.seg = seg  # (M,) segment of every used marker
        self.local = local  # (M, 3)
        self.members = [np.flatnonzero(seg == s) for s in range(S)]
        K = max(1, max(len(ms) for ms in self.members))
        self.K = K
        self.slot = np.zeros(len(seg), dtype=int)
        lp = np.zeros((K, 3, S))
        for s, ms in enumerate(self.members):
            self.slot[ms] = np.arange(len(ms))
            lp[: len(ms), :, s] = local[ms]
        self.lp = lp  # (K, 3, S) rest offsets by slot
        self.lout = lp[:, :, None] * lp[:, None, :]  # (K, 3, 3, S)
        # every segment's offset from its parent's origin, (3, S) (0 for the root)
        off = np.zeros((3, S))
        off[:, 1:] = (origin[1:] - origin[tree.par[1:]]).T
        self.off = off

    # ---- layout
    def planes(self, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observations (F, M, 3) and weights (F, M) -> slots (K, 3, S, F) and (K, S, F)."""
        F = y.shape[0]
        yk = np.zeros((self.K, 3, self.t.S, F))
        yk[self.slot, :, self.seg] = y.transpose(1, 2, 0)
        wk = np.zeros((self.K, self.t.S, F))
        wk[self.slot, self.seg] = w.T
        return yk, wk

    def unpack(self, a: np.ndarray) -> np.ndarray:
        """(K, S, F) slots -> (F, M)."""
        return a[self.slot, self.seg].T

    # ---- kinematics
    def bones(self, R: np.ndarray) -> np.ndarray:
        """Bone vectors (3, S, F): from the parent's origin to the segment's (0 for the root)."""
        t = self.t
        G = np.zeros(R.shape[1:])
        if t.S > 1:
            G[:, 1:] = np.einsum("ijsf,js->isf", R[:, :, t.par[1:]], self.off[:, 1:])
        return G

    def chain(self, p: np.ndarray, G: np.ndarray) -> np.ndarray:
        """Origins (3, S, F) from the root position (3, F) and bone vectors, root first."""
        t = self.t
        P = np.empty(G.shape)
        P[:, 0] = p
        for sl in t.levels[1:]:
            np.add(P[:, t.par[sl]], G[:, sl], out=P[:, sl])
        return P

    def fk(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bone vectors G and origins P, (3, S, F) each."""
        G = self.bones(R)
        return G, self.chain(p, G)

    def markers(self, p: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Model marker positions (K, 3, S, F)."""
        _, P = self.fk(p, R)
        return np.einsum("ijsf,kjs->kisf", R, self.lp) + P

    # ---- sufficient statistics of the data
    def stats(self, y: np.ndarray, w: np.ndarray) -> dict[str, np.ndarray]:
        """Per segment and frame sums of the data that the iterations need.

        W = sum w; lbar and ybar, the weighted centroids of the rest offsets and
        of the observations (3, S, F); Cc = sum w (y - ybar)(l - lbar)^T and
        Cw = sum w l l^T (3, 3, S, F); c0 = sum w (|y - ybar|^2 + |l - lbar|^2).
        ``y`` (K, 3, S, F) and ``w`` (K, S, F) in slot layout.
        """
        W = w.sum(0)
        Wd = np.where(W > 0, W, 1.0)
        lbar = np.einsum("kis,ksf->isf", self.lp, w) / Wd
        ybar = np.einsum("kisf,ksf->isf", y, w) / Wd
        yc = y - ybar
        lc = self.lp[..., None] - lbar
        wlc = lc * w[:, None]
        Cc = np.einsum("kisf,kjsf->ijsf", yc, wlc)
        Cw = np.einsum("kijs,ksf->ijsf", self.lout, w)
        c0 = np.einsum("kisf,kisf->sf", yc * w[:, None], yc) + np.einsum("kisf,kisf->sf", lc, wlc)
        return {"W": W, "lbar": lbar, "ybar": ybar, "Cc": Cc, "Cw": Cw, "c0": c0}

    def cost(self, p: np.ndarray, R: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
        """The data cost sum_m w |x_m - y_m|^2 (F,), evaluated marker by marker."""
        r = self.markers(p, R) - y
        return np.einsum("ksf,kisf,kisf->f", w, r, r)

    def step(
        self,
        R: np.ndarray,
        G: np.ndarray,
        a: np.ndarray,
        d: np.ndarray,
        st: dict[str, np.ndarray],
        e: np.ndarray,
        pw: float,
        lam: np.ndarray,
        floor: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One damped Gauss-Newton step: (dp (3, F), drot (3, S, F), predicted cost decrease (F,)).

        ``G`` the bone vectors, ``a = R lbar`` and ``d = P + a - ybar`` (3, S, F)
        (the offset of the model's centroid of a segment's markers from the
        observed one), ``e`` the prior's rotation vectors (3, S, F). The
        composition of :meth:`gradient`, :meth:`factor`, :meth:`solve` and
        :meth:`predicted`.
        """
        gP0, gd0, A = self.gradient(R, a, d, st)
        fac = self.factor(R, G, A, st, pw, lam, floor)
        gd = gd0 + pw * e
        xP, xd, q = self.solve(fac, gP0, gd)
        return -xP[:, 0], -xd, self.predicted(xP, xd, q, gP0, gd, lam, floor)

    def gradient(
        self, R: np.ndarray, a: np.ndarray, d: np.ndarray, st: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every segment's own data gradient (3, S, F) with respect to its origin
        (sum w r) and rotation (sum w L x r), and A = sum w L (L = R l)."""
        W = st["W"]
        A = W * a
        gP0 = W * d
        Cr = _c_mmt(st["Cc"], R)
        gd0 = _c_cross(A, d)
        gd0[0] += Cr[1, 2] - Cr[2, 1]
        gd0[1] += Cr[2, 0] - Cr[0, 2]
        gd0[2] += Cr[0, 1] - Cr[1, 0]
        return gP0, gd0, A

    def factor(
        self, R: np.ndarray, G: np.ndarray, A: np.ndarray, st: dict[str, np.ndarray], pw: float, lam: np.ndarray, floor: float
    ) -> dict[str, np.ndarray]:
        """Eliminate the damped Gauss-Newton system's rotation blocks, leaves first.

        The unknowns are the root position and one rotation increment per
        segment; with every segment's origin increment ``dP_s`` as an
        intermediate, a segment's own terms involve only ``(dP_s, d_s)`` and a
        child's origin moves by ``dP_c = dP_s - G_c x d_s``. Leaves first, each
        segment's rotation increment is eliminated, leaving a 3x3 quadratic in
        ``dP_s`` that is pushed onto the parent through ``[I, -[G_c]x]``; the
        root's 3x3 system gives ``dp``. The Levenberg-Marquardt damping scales
        each segment's (effective) 3x3 rotation block and the root position
        block by ``1 + lam``: each direction is damped in proportion to its own
        curvature, so that weakly determined twists are not frozen by the
        stiff directions of the block. O(S) 3x3 operations per frame; the
        result serves :meth:`solve`.
        """
        t = self.t
        S, F = R.shape[2:]
        W = st["W"]
        N = _c_mmt(_c_mm(R, st["Cw"]), R)  # sum w L L^T
        trN = N[0, 0] + N[1, 1] + N[2, 2]
        Hdd = -N
        HPP = np.zeros((3, 3, S, F))
        for i in range(3):
            Hdd[i, i] += trN + pw
            HPP[i, i] = W
        HPd = _c_hat(A, -1.0)
        Gh = _c_hat(G)
        s1 = 1 + lam
        Dinv = np.empty_like(Hdd)
        Zs = np.empty_like(Hdd)
        D9, Dinv9 = Hdd.reshape(9, S, F), Dinv.reshape(9, S, F)
        for lv in range(len(t.levels) - 1, -1, -1):
            sl = t.levels[lv]
            D = D9[:, sl] * s1
            D[::4] += floor
            _c_inv3_sym(D, out=Dinv9[:, sl])
            Hs = HPd[:, :, sl]
            Z = np.einsum("ij...,jk...->ik...", Hs, Dinv[:, :, sl], out=Zs[:, :, sl])
            K = HPP[:, :, sl] - _c_mmt(Z, Hs)  # symmetric
            if lv == 0:
                K0 = K[:, :, 0] * s1
                for i in range(3):
                    K0[i, i] += floor
                K0inv = _c_inv3_sym(K0.reshape(9, F)).reshape(3, 3, F)
                break
            KG = _c_mm(K, Gh[:, :, sl])
            _push(HPP, K, t.push[lv])
            _push(HPd, -KG, t.push[lv])
            _push(Hdd, -_c_mm(Gh[:, :, sl], KG), t.push[lv])
        return {"Gh": Gh, "Dinv": Dinv, "Z": Zs, "HPd": HPd, "K0inv": K0inv}

    def solve(
        self, fac: dict[str, np.ndarray], gP0: np.ndarray, gd: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Solve the factored system for gradients ``gP0``, ``gd`` (3, S, F).

        Returns xP, xd (3, S, F), every segment's origin and rotation increments
        with the opposite sign, and q (F,): the sum over the eliminated 3x3
        systems ``B x = b`` of ``x . b`` (for :meth:`predicted`).
        """
        t = self.t
        Gh, Zs, Dinv, HPd = fac["Gh"], fac["Z"], fac["Dinv"], fac["HPd"]
        gP = gP0.copy()
        gd = gd.copy()
        for lv in range(len(t.levels) - 1, 0, -1):
            sl = t.levels[lv]
            k = gP[:, sl] - _c_mv(Zs[:, :, sl], gd[:, sl])
            _push(gP, k, t.push[lv])
            _push(gd, _c_mv(Gh[:, :, sl], k), t.push[lv])
        xP = np.empty(gP.shape)
        xd = np.empty(gd.shape)
        k0 = gP[:, 0] - _c_mv(Zs[:, :, 0], gd[:, 0])
        xP[:, 0] = _c_mv(fac["K0inv"], k0)
        q = _c_dot(xP[:, 0], k0)
        for sl in t.levels:  # back-substitution, root first
            if sl.start > 0:
                pr = t.par[sl]
                xP[:, sl] = xP[:, pr] - _c_mv(Gh[:, :, sl], xd[:, pr])
            b = gd[:, sl] - _c_mtv(HPd[:, :, sl], xP[:, sl])
            xd[:, sl] = _c_mv(Dinv[:, :, sl], b)
            q += _c_dot(xd[:, sl], b).sum(0)
        return xP, xd, q

    @staticmethod
    def predicted(
        xP: np.ndarray, xd: np.ndarray, q: np.ndarray, gP0: np.ndarray, gd: np.ndarray, lam: np.ndarray, floor: float
    ) -> np.ndarray:
        """Decrease (F,) of the linearised cost for the step ``-(xP, xd)`` of :meth:`solve`.

        With the cost ``c + 2 g.h + h^T H h`` near the iterate and the step
        solving ``(H + E) h = -g``, where E is what the damping added to the
        eliminated blocks (``lam`` times the block plus ``floor``), the
        decrease is ``-g.h + h^T E h``: ``g.h`` from every segment's own
        terms (its origin and rotation increments, ``gP0`` and ``gd``), and
        ``h^T E h`` from the eliminated systems (``q``).
        """
        x2 = _c_dot(xd, xd).sum(0) + _c_dot(xP[:, 0], xP[:, 0])
        gh = (_c_dot(gP0, xP) + _c_dot(gd, xd)).sum(0)
        return gh + lam / (1 + lam) * (q - floor * x2) + floor * x2


def _dense_system(
    model: _Model, p: np.ndarray, R: np.ndarray, y: np.ndarray, w: np.ndarray, e: np.ndarray, pw: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference normal equations from a dense Jacobian: H (F, n, n), g (F, n), n = 3 + 3S.

    Only for tests and benchmarks (memory grows as F * M * S). All inputs in
    the kernels' layout: ``p`` (3, F), ``R`` (3, 3, S, F), ``y`` and ``w`` in
    slots, ``e`` (3, S, F). Unknowns ordered root position, then segments.
    """
    t = model.t
    S, F = R.shape[2:]
    G, P = model.fk(p, R)
    x = model.markers(p, R)  # (K, 3, S, F)
    rows_J, rows_r, rows_w = [], [], []
    for s in range(S):
        for k in range(model.K):
            J = np.zeros((F, 3, S + 1, 3))
            J[:, :, 0, :] = np.eye(3)
            path = t.path[s]
            for i, a in enumerate(path):
                u = (x[k, :, s] - P[:, s]) if a == s else G[:, path[i + 1]]
                J[:, :, a + 1, :] = -np.moveaxis(_c_hat(u), -1, 0)
            rows_J.append(J.reshape(F, 3, 3 * (S + 1)))
            rows_r.append((x[k, :, s] - y[k, :, s]).T)
            rows_w.append(np.repeat(w[k, s, :, None], 3, axis=1))
    J = np.concatenate(rows_J, axis=1)
    rv = np.concatenate(rows_r, axis=1)
    wv = np.concatenate(rows_w, axis=1)
    H = np.einsum("fki,fk,fkj->fij", J, wv, J)
    g = np.einsum("fki,fk->fi", J, wv * rv)
    H[:, 3:, 3:] += pw * np.eye(3 * S)
    g[:, 3:] += pw * e.transpose(2, 1, 0).reshape(F, 3 * S)
    return H, g


# --------------------------------------------------------------------------- initialisation


#: Kabsch fits whose points spread less than this fraction across their main
#: axis fix the twist about it poorly; the initialisation does not trust them.
_INIT_SPREAD = 0.05


def _initial_rotations(model: _Model, yt: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Data-driven rotations (F, S, 3, 3) for every segment and frame (all finite).

    ``yt`` (F, M, 3) observed markers, ``w`` (F, M) weights (0 where unseen).

    1. Kabsch of each segment's visible markers (>= 3, spread across their
       main axis by at least ``_INIT_SPREAD`` of their extent along it).
    2. Twice, for frames still unsolved: Kabsch of the segment's markers plus
       its joints placed by the neighbours solved in that frame (the parent's
       pose places the segment's origin, a child's pose places the child's joint).
    3. Segments solved in some frames, parents first: the rotation relative
       to the parent (the joint's rotation) slerped over time between solved
       frames (held at the ends), so that a limb the data lose keeps its joint
       angles and moves with the body; the root's own rotation slerped.
       Segments never solved: the parent's rotation (identity for the root).
    4. Frames still unsolved where the available points give one direction
       (two points, or collinear ones): the smallest rotation of the step-3
       rotation that matches that direction.
    """
    t = model.t
    F, S = yt.shape[0], t.S
    rest = model.origin[model.seg] + model.local  # (M, 3)
    Pmax = max((len(ms) for ms in model.members), default=0)
    # step 1, all segments in one batched call (padding has weight 0)
    ref = np.full((S, max(Pmax, 1), 3), np.nan)
    obs = np.full((F, S, max(Pmax, 1), 3), np.nan)
    ww = np.zeros((F, S, max(Pmax, 1)))
    for s, ms in enumerate(model.members):
        ref[s, : len(ms)] = rest[ms]
        obs[:, s, : len(ms)] = yt[:, ms]
        ww[:, s, : len(ms)] = w[:, ms]
    Rk, tk, _ = kabsch(
        np.broadcast_to(ref, (F, S) + ref.shape[1:]).reshape(F * S, -1, 3),
        obs.reshape(F * S, -1, 3),
        ww.reshape(F * S, -1),
        collinear_tol=_INIT_SPREAD,
    )
    Rk = Rk.reshape(F, S, 3, 3)
    tk = tk.reshape(F, S, 3)
    solved = np.isfinite(Rk[..., 0, 0])

    def augmented(s: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rest points, observed points, weights of segment s's markers and joints."""
        ms = model.members[s]
        r_pts = [rest[ms]]
        o_pts = [yt[:, ms]]
        wts = [w[:, ms]]
        nb = ([t.par[s]] if t.par[s] >= 0 else []) + t.children[s]
        for n in nb:
            j = s if n == t.par[s] else n  # the joint between s and n is the origin of the child
            pos = np.einsum("fij,j->fi", Rk[:, n], model.origin[j]) + tk[:, n]
            r_pts.append(model.origin[j][None])
            o_pts.append(pos[:, None])
            wts.append(solved[:, n, None].astype(float))
        return np.concatenate(r_pts), np.concatenate(o_pts, axis=1), np.concatenate(wts, axis=1)

    # step 2
    for _ in range(2):
        for s in range(S):
            todo = ~solved[:, s]
            if not todo.any():
                continue
            rp, op, wp = augmented(s)
            R2, t2, _ = kabsch(
                np.broadcast_to(rp, (int(todo.sum()),) + rp.shape), op[todo], wp[todo], collinear_tol=_INIT_SPREAD
            )
            ok = np.isfinite(R2[:, 0, 0])
            idx = np.flatnonzero(todo)[ok]
            Rk[idx, s], tk[idx, s] = R2[ok], t2[ok]
            solved[idx, s] = True
    # steps 3 and 4, parents first
    Rf = Rk.copy()
    for s in range(S):
        Rf[:, s] = fill_joint(Rf[:, t.par[s]] if t.par[s] >= 0 else None, Rk[:, s], solved[:, s])
        todo = ~solved[:, s]
        if not todo.any():
            continue
        rp, op, wp = augmented(s)
        op, wp = op[todo], wp[todo] * np.isfinite(op[todo]).all(-1)
        opz = np.where(wp[..., None] > 0, op, 0.0)
        W = wp.sum(1)
        Ws = np.where(W > 0, W, 1.0)[:, None]
        a = rp[None] - (wp @ rp / Ws)[:, None]
        b = opz - (np.einsum("fp,fpi->fi", wp, opz) / Ws)[:, None]
        Hc = np.einsum("fp,fpi,fpj->fij", wp, a, b)
        U, sv, Vt = np.linalg.svd(Hc)
        spread = np.einsum("fp,fpi,fpi->f", wp, a, a)
        use = ((wp > 0).sum(1) >= 2) & (sv[:, 0] > 1e-9 * spread) & (spread > 0)
        if use.any():
            idx = np.flatnonzero(todo)[use]
            Rf[idx, s] = _swing(Rf[idx, s], U[use, :, 0], Vt[use, 0, :])
    return Rf


def _root_from_rotations(model: _Model, R: np.ndarray, st: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Root position (3, n) given rotations R (3, 3, S, n): the weighted mean offset of
    the observed markers from the model at p = 0; and whether any marker is seen (n,)."""
    P = model.chain(np.zeros((3, R.shape[-1])), model.bones(R))
    W = st["W"]
    d = st["ybar"] - _c_mv(R, st["lbar"]) - P
    Wt = W.sum(0)
    return (W * d).sum(1) / np.where(Wt > 0, Wt, 1.0), Wt > 0


# --------------------------------------------------------------------------- solver


def solve_ik(
    parent: np.ndarray,
    origin: np.ndarray,
    marker_segment: np.ndarray,
    marker_local: np.ndarray,
    observed: np.ndarray,
    *,
    init_rot: np.ndarray | None = None,
    init_root: np.ndarray | None = None,
    prior_rot: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    iterations: int = 10,
    damping: float = 1e-3,
    prior_weight: float = 100.0,
    tol: float = 1e-6,
    out: np.ndarray | None = None,
) -> IKResult:
    """Segment rotations and root position that best fit the markers, every frame.

    Minimises, per frame (all frames at once, no loop over frames),
    ``sum_m w_m |x_m - y_m|^2 + prior_weight * sum_s |log(R_s R_prior,s^T)|^2``
    where ``x_m`` is the forward-kinematics position of marker ``m`` (see the
    module docstring), by Levenberg-Marquardt with a damping adapted per frame.

    Parameters
    ----------
    parent : (S,) int ndarray
        Parent of every segment, -1 for the (single) root. Any order; it is
        sorted topologically inside.
    origin : (S, 3) ndarray
        Rest-pose segment origins (mm); a child's origin is its joint with the parent.
    marker_segment : (M,) int ndarray
        Segment carrying each marker, -1 for markers to ignore.
    marker_local : (M, 3) ndarray
        Marker rest position minus its segment's origin (mm).
    observed : (F, M, 3) ndarray
        Observed markers (mm), NaN where not seen.
    init_rot : (F, S, 3, 3) ndarray, optional
        Starting rotations (projected onto rotations). Default: ``prior_rot``.
    init_root : (F, 3) ndarray, optional
        Starting root positions. Default: from the starting rotations, the
        weighted mean offset of the observed markers from the model; frames
        without markers are interpolated linearly over time.
    prior_rot : (F, S, 3, 3) ndarray, optional
        Target of the rotation prior. Default: built from the data — per
        segment, Kabsch of its markers where at least 3 are seen and spread
        across their main axis by at least 5% of their extent along it;
        else Kabsch of its markers plus the joints placed by the neighbouring
        segments solved in that frame; else its rotation relative to its
        parent slerped over time between such frames (held at the ends) or,
        for a segment never solved, its parent's rotation; finally, where
        the available points give a single direction, the smallest rotation
        of that guess matching it. So the
        prior agrees with the data where the data determine the rotation,
        and fills gaps and undetermined twists smoothly. Where it is only
        a guess (gaps, chains of poorly marked segments) it pulls the
        solution slightly away from the data's optimum: about
        ``prior_weight * angle / stiffness`` rad.
    weights : (F, M) or (M,) ndarray, optional
        Non-negative marker weights (default 1; NaN markers get 0).
    iterations : int, optional
        Maximum number of Levenberg-Marquardt iterations.
    damping : float, optional
        Initial Levenberg-Marquardt damping: every segment's rotation block
        and the root block are scaled by ``1 + damping``; adapted per frame
        from the gain ratio (Nielsen).
    prior_weight : float, optional
        Weight of the rotation prior in mm^2 per rad^2: the prior pulls like
        one marker ``sqrt(prior_weight)`` mm from the rotation axis (default:
        10 mm; a marker 100 mm from its joint weighs 10^4). Keep it positive
        so that segments with too few markers (or none) in a frame stay
        determined.
    tol : float, optional
        A frame has converged (and leaves the iteration) when its pose is
        estimated to be within ``tol`` mm of the solution, or when the
        linearised model can no longer lower its cost. A step's size is how
        far it moves the skeleton (the root position's change, or a rotation's
        change times the skeleton's extent); the distance left is estimated as
        the next step's size: the last step times the ratio of the last two
        (Gauss-Newton converges linearly, fast here), or after a first or
        rejected step the step itself. With a motion-capture start (a few
        degrees off), ``0.1`` stops most frames after 2 iterations, the rest
        after 3, with joints within a few hundredths of a millimetre of the
        fully converged solution.
    out : (F, S, 3, 3) ndarray, optional
        Where to write the rotations (returned as ``rot``). It may be
        ``prior_rot`` or ``init_rot`` itself: frames are read before they are
        overwritten. Saves allocating (and the system mapping in) a large array.

    Returns
    -------
    IKResult
        ``root_pos`` (F, 3), ``rot`` (F, S, 3, 3) in the caller's segment
        order, ``residual`` (F, M), ``n_iter``, ``converged`` (F,). Pose
        arrays are finite in every frame, including frames where nothing is
        seen (held or interpolated); ``residual`` is NaN for unseen markers.

    Raises
    ------
    ValueError
        Inconsistent shapes, a parent array that is not a tree, or no marker
        on any segment seen in any frame.
    """
    parent = np.asarray(parent).astype(int)
    origin = np.asarray(origin, dtype=float)
    marker_segment = np.asarray(marker_segment).astype(int)
    marker_local = np.asarray(marker_local, dtype=float)
    observed = np.asarray(observed, dtype=float)
    S = len(parent)
    if parent.ndim != 1 or S == 0:
        raise ValueError("parent must be a non-empty 1-d array")
    if origin.shape != (S, 3):
        raise ValueError(f"origin must be ({S}, 3), got {origin.shape}")
    M = len(marker_segment)
    if marker_local.shape != (M, 3):
        raise ValueError(f"marker_local must be ({M}, 3), got {marker_local.shape}")
    if observed.ndim != 3 or observed.shape[1:] != (M, 3):
        raise ValueError(f"observed must be (F, {M}, 3), got {observed.shape}")
    if np.any(marker_segment < -1) or np.any(marker_segment >= S):
        raise ValueError("marker_segment must be -1 or a segment index")
    if not (np.isfinite(origin).all() and np.isfinite(marker_local[marker_segment >= 0]).all()):
        raise ValueError("origin and marker_local must be finite")
    F = observed.shape[0]
    tree = _Tree(parent)
    inv = np.empty(S, dtype=int)
    inv[tree.perm] = np.arange(S)

    used = np.flatnonzero(marker_segment >= 0)
    seg = inv[marker_segment[used]]
    model = _Model(tree, origin[tree.perm], seg, marker_local[used])
    # which markers are seen: finite coordinates (a NaN or inf in any of them makes the sum non-finite)
    seen = np.isfinite(observed[:, :, 0] + observed[:, :, 1] + observed[:, :, 2])[:, used]
    if weights is None:
        w_all = None
        any_seen = F > 0 and bool(seen.any())
    else:
        w_all = np.broadcast_to(np.asarray(weights, dtype=float), (F, M))[:, used]
        if not np.all(np.isfinite(w_all)) or np.any(w_all < 0):
            raise ValueError("weights must be finite and non-negative")
        any_seen = F > 0 and bool(np.any(seen & (w_all > 0)))
    if not any_seen:
        raise ValueError("no marker on any segment is seen in any frame: nothing to solve")

    def data(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Observations (0 where unseen) and weights (0 where unseen) of frames lo:hi, in slots."""
        yb = observed[lo:hi][:, used]
        sb = seen[lo:hi]
        yb[~sb] = 0.0
        wb = sb.astype(float) if w_all is None else np.where(sb, w_all[lo:hi], 0.0)
        return model.planes(yb, wb)

    pw = float(prior_weight)
    if pw < 0 or damping < 0:
        raise ValueError("prior_weight and damping must be non-negative")

    # prior and starting point: per block, in the tree's order, as component planes
    if prior_rot is None:
        yt = np.where(seen[..., None], observed[:, used], 0.0)
        wt = seen.astype(float) if w_all is None else np.where(seen, w_all, 0.0)
        R_prior, prior_perm = _initial_rotations(model, yt, wt), None
        del yt, wt
    else:
        R_prior, prior_perm = np.asarray(prior_rot, dtype=float), tree.perm
        if R_prior.shape != (F, S, 3, 3) or not np.isfinite(R_prior).all():
            raise ValueError(f"prior_rot must be finite, ({F}, {S}, 3, 3)")
    if init_rot is not None:
        init_rot = np.asarray(init_rot, dtype=float)
        if init_rot.shape != (F, S, 3, 3) or not np.isfinite(init_rot).all():
            raise ValueError(f"init_rot must be finite, ({F}, {S}, 3, 3)")
    start, start_perm = (R_prior, prior_perm) if init_rot is None else (init_rot, tree.perm)
    _recycle_large_blocks()
    blocks = [(lo, min(lo + _BLOCK, F)) for lo in range(0, F, _BLOCK)]
    if init_root is None:
        p0 = np.empty((F, 3))
        has = np.empty(F, dtype=bool)
        for lo, hi in blocks:
            st = model.stats(*data(lo, hi))
            pb, has[lo:hi] = _root_from_rotations(model, _rotation_planes(start, start_perm, lo, hi), st)
            p0[lo:hi] = pb.T
        p0 = _interp_fill(p0, has)
    else:
        p0 = np.array(init_root, dtype=float)
        if p0.shape != (F, 3) or not np.isfinite(p0).all():
            raise ValueError(f"init_root must be finite, ({F}, 3)")

    # length scale for the convergence test: the skeleton's extent
    pts = np.concatenate([model.origin, model.origin[seg] + model.local])
    scale = max(float(np.linalg.norm(pts - model.origin[0], axis=1).max()), 1.0)
    floor = 1e-12 * scale**2  # keeps every 3x3 block invertible

    if out is None:
        rot = np.empty((F, S, 3, 3))
    elif out.shape != (F, S, 3, 3) or out.dtype != np.float64:
        raise ValueError(f"out must be a float64 ({F}, {S}, 3, 3) array")
    else:
        rot = out
    root_pos = np.empty((F, 3))
    res = np.full((F, M), np.nan)
    converged = np.zeros(F, dtype=bool)

    def solve_block(block: tuple[int, int]) -> int:
        """Solve frames lo:hi (blocks are independent: each reads and writes its own frames only)."""
        lo, hi = block
        yk, wk = data(lo, hi)
        st = model.stats(yk, wk)
        Rp = _rotation_planes(R_prior, prior_perm, lo, hi)
        R = Rp if init_rot is None else _rotation_planes(init_rot, tree.perm, lo, hi)
        p = np.ascontiguousarray(p0[lo:hi].T)
        R, p, converged[lo:hi], it = _iterate(model, R, p, st, Rp, pw, int(iterations), damping, tol, floor, scale)
        r = model.markers(p, R) - yk
        dist = model.unpack(np.sqrt(np.einsum("kisf,kisf->ksf", r, r)))
        res[lo:hi, used] = np.where(seen[lo:hi], dist, np.nan)
        Rs = _unplanes(R)  # (S, n, 3, 3) view
        for j in range(S):  # one strided copy per segment (faster than a gather and a transpose)
            rot[lo:hi, j] = Rs[inv[j]]
        root_pos[lo:hi] = p.T
        return it

    n_iter = max(run_blocks(solve_block, blocks), default=0)
    return IKResult(root_pos=root_pos, rot=rot, residual=res, n_iter=n_iter, converged=converged)


def _rotation_planes(R: np.ndarray, perm: np.ndarray | None, lo: int, hi: int) -> np.ndarray:
    """Frames lo:hi of rotations (F, S, 3, 3), segments reordered by ``perm``, as planes
    (3, 3, S, n), projected onto rotations where they are not rotations to 1e-9."""
    Rt = R[lo:hi].transpose(2, 3, 1, 0)
    Rc = np.ascontiguousarray(Rt) if perm is None else np.take(Rt, perm, axis=2)
    if _c_is_rotation(Rc):
        return Rc
    return np.ascontiguousarray(_planes(_project_so3(_unplanes(Rc))))


def _iterate(
    model: _Model,
    R: np.ndarray,
    p: np.ndarray,
    st: dict[str, np.ndarray],
    R_prior: np.ndarray,
    pw: float,
    iterations: int,
    damping: float,
    tol: float,
    floor: float,
    scale: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Levenberg-Marquardt on one block of frames: (R, p, converged, iterations run).

    ``R`` (3, 3, S, n) and ``p`` (3, n) the start, ``st`` the data's sums,
    ``R_prior`` (3, 3, S, n). A frame leaves as soon as it has converged:
    its pose is kept and every array is cut down to the frames still
    iterating. The change of the cost is computed from the change of the pose
    itself (``R' - R = (exp([d]x) - I) R`` and the bones and origins it moves),
    so that its rounding is that of the change, not of the cost.
    """
    n = p.shape[-1]
    RpT = np.ascontiguousarray(R_prior.transpose(1, 0, 2, 3))
    W, lbar, ybar, Cc = st["W"], st["lbar"], st["ybar"], st["Cc"]
    G, P = model.fk(p, R)
    a = _c_mv(R, lbar)
    d = P + a - ybar
    e = np.zeros(a.shape) if R is R_prior else _c_log(_c_mm(R, RpT))
    cost = (st["c0"] + W * _c_dot(d, d) - 2 * np.einsum("ijsf,ijsf->sf", R, Cc) + pw * _c_dot(e, e)).sum(0)
    st = {k: v for k, v in st.items() if k != "c0"}
    lam = np.full(n, float(damping))
    nu = np.full(n, 2.0)
    R_out = np.empty_like(R)
    p_out = np.empty_like(p)
    conv = np.zeros(n, dtype=bool)
    idx = np.arange(n)  # the frames still iterating
    n_iter = 0
    last = np.full(n, np.inf)  # the last step, if it was taken
    for _ in range(iterations):
        n_iter += 1
        gP0, gd0, A = model.gradient(R, a, d, st)
        fac = model.factor(R, G, A, st, pw, lam, floor)
        gd = gd0 + pw * e
        xP, xd, q = model.solve(fac, gP0, gd)
        dp, dr = -xP[:, 0], -xd
        dR = _c_mm(_c_expm1(dr), R)
        dG = model.bones(dR)
        dP = model.chain(dp, dG)
        da = _c_mv(dR, lbar)
        dd = da + dP
        R2 = R + dR
        e2 = _c_log(_c_mm(R2, RpT))
        # cost change: data W |d|^2 - 2 <R, Cc> (+ constants) and prior pw |e|^2
        dc = (W * _c_dot(dd, 2 * d + dd) - 2 * np.einsum("ijsf,ijsf->sf", dR, Cc) + pw * _c_dot(e2 - e, e2 + e)).sum(0)
        eps = 1e-12 * np.maximum(cost, 0.0) + 1e-18  # the rounding level of the cost
        ok = dc <= eps
        step = np.sqrt(np.maximum(_c_dot(dp, dp), scale**2 * _c_dot(dr, dr).max(0)))
        # the distance left to the solution: about the next step, i.e. this one times the rate
        # at which the (accepted) steps shrink; without a rate, the step itself
        left = np.where(ok & (last < np.inf), step * np.minimum(1.0, step / np.maximum(last, 1e-300)), step)
        last = np.where(ok, step, np.inf)
        pred = model.predicted(xP, xd, q, gP0, gd, lam, floor)
        # Nielsen's damping update from the gain ratio (actual / predicted decrease)
        rho = np.where(pred <= eps, 1.0, -dc / np.maximum(pred, 1e-300))  # rounding level: trust the model
        lam = np.where(ok, np.maximum(lam * np.maximum(1 / 3, 1 - (2 * np.minimum(rho, 1) - 1) ** 3), 1e-12), lam * nu)
        nu = np.where(ok, 2.0, nu * 2)
        # converged: the step is below tol, or the linear model can no longer lower the cost
        done = (left <= tol) | (ok & (pred <= eps))
        if not ok.all():  # rejected steps: nothing moves
            bad = ~ok
            for x in (dp, dG, dP, da, dd):
                x[..., bad] = 0.0
            dc[bad] = 0.0
            R2[..., bad] = R[..., bad]
            e2[..., bad] = e[..., bad]
        p = p + dp
        R, e = R2, e2
        G += dG
        P += dP
        a += da
        d += dd
        cost += dc
        if done.any():
            R_out[..., idx[done]] = R[..., done]
            p_out[:, idx[done]] = p[:, done]
            conv[idx[done]] = True
            keep = np.flatnonzero(~done)
            idx = idx[keep]
            if not idx.size:
                break
            p, R, G, P, a, d, e, RpT, cost, lam, nu, last = (
                np.take(x, keep, axis=-1) for x in (p, R, G, P, a, d, e, RpT, cost, lam, nu, last)
            )
            st = {k: np.take(v, keep, axis=-1) for k, v in st.items()}
            W, lbar, ybar, Cc = st["W"], st["lbar"], st["ybar"], st["Cc"]
    if idx.size:
        R_out[..., idx] = R
        p_out[:, idx] = p
    return R_out, p_out, conv, n_iter


# --------------------------------------------------------------------------- rigid poses of the segments


def segment_poses(
    shapes: list[np.ndarray],
    columns: list[np.ndarray],
    points: np.ndarray | list[np.ndarray],
    *,
    collinear_tol: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid pose of several point shapes in every frame, all at once.

    For every shape ``b`` and frame ``f``, the same problem and result (to
    rounding) as ``kabsch(shapes[b], points[:, columns[b]])`` of
    :mod:`mocapskel.solvers.rigid` (unit weights): ``points[f, columns[b]] ~
    R[f, b] @ shapes[b] + t[f, b]`` over the points seen in frame ``f``. Laid
    out for long takes: the cross-covariances of all shapes and frames come
    from a few matrix products, the rotations from Horn's quaternion matrix
    by its characteristic polynomial (Theobald 2005: coefficients in closed
    form, Newton's method from the upper bound ``(G_a + G_b) / 2`` on the
    largest eigenvalue, the eigenvector from a column of the adjugate), on
    component planes over all shapes and frames. Which frames can be solved
    depends only on which points are seen, so it is decided once per
    visibility pattern. Problems whose top eigenvalue is not well apart from
    the next, and shapes of more than 50 points, are handed to
    :func:`~mocapskel.solvers.rigid.kabsch`.

    Parameters
    ----------
    shapes : list of (P_b, 3) ndarray
        Reference points of every shape; NaN rows are left out.
    columns : list of (P_b,) int ndarray
        The column of ``points`` observing each reference point (no repeats
        within a shape).
    points : (F, Q, 3) ndarray, or a list of (F, Q_i, 3) ndarrays
        Observed points, NaN where not seen; a list is read as the arrays
        side by side (columns numbered through them in turn), without
        joining them.
    collinear_tol : float, optional
        As in :func:`~mocapskel.solvers.rigid.kabsch`.

    Returns
    -------
    R : (F, B, 3, 3) ndarray
        Rotations; NaN for frames with fewer than 3 usable points or collinear ones.
    t : (F, B, 3) ndarray
        Translations; NaN likewise.
    """
    parts = [np.asarray(x, dtype=float) for x in (points if isinstance(points, (list, tuple)) else [points])]
    if any(x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] != parts[0].shape[0] for x in parts):
        raise ValueError("points must be (F, Q, 3), or a list of such arrays with the same F")
    F = parts[0].shape[0]
    Q = sum(x.shape[1] for x in parts)
    B = len(shapes)
    if len(columns) != B:
        raise ValueError("one column list per shape")
    # per shape: centred reference points as matrices over the columns of ``points``
    Ob = np.zeros((B, Q))  # membership
    Aw = np.zeros((B, 3, Q))  # centred reference points
    A2 = np.zeros((B, Q))  # their squared norms
    bits = np.zeros((B, Q))  # 2^(rank in the shape): visibility patterns as numbers
    a0 = np.zeros((B, 3))
    luts = []
    for b, (ref, cols) in enumerate(zip(shapes, columns)):
        ref = np.asarray(ref, dtype=float).reshape(-1, 3)
        cols = np.asarray(cols, dtype=int).reshape(-1)
        if len(ref) != len(cols) or len(np.unique(cols)) != len(cols) or np.any((cols < 0) | (cols >= Q)):
            raise ValueError(f"shape {b}: one distinct column of points per reference point")
        have = np.isfinite(ref).all(1)
        ref, cols = ref[have], cols[have]
        if len(cols) > 50:  # too many for the visibility patterns as numbers: rigid.kabsch
            luts.append(None)
            continue
        a0[b] = ref.mean(0) if len(ref) else 0.0
        a = ref - a0[b]
        Ob[b, cols] = 1.0
        Aw[b][:, cols] = a.T
        A2[b, cols] = (a * a).sum(1)
        bits[b, cols] = 2.0 ** np.arange(len(cols))
        luts.append((a, len(cols)))
    Aw2 = Aw.reshape(3 * B, Q)
    _recycle_large_blocks()
    luts_ok: dict[int, np.ndarray] = {}  # per shape, whether each visibility pattern can be solved

    R = np.empty((F, B, 3, 3))
    t = np.empty((F, B, 3))
    todo: list[tuple[int, np.ndarray]] = []

    def block(lo: int) -> None:  # frames lo:hi (blocks read and write their own frames only)
        hi = min(lo + _POSE_BLOCK, F)
        X = np.empty((3, Q, hi - lo))
        c = 0
        for x in parts:
            X[:, c : c + x.shape[1]] = x[lo:hi].transpose(2, 1, 0)
            c += x.shape[1]
        vis = np.isfinite(X[0] + X[1] + X[2])  # (Q, n)
        X[:, ~vis] = 0.0
        visf = vis.astype(float)
        W = Ob @ visf  # (B, n)
        Wd = np.where(W > 0, W, 1.0)
        ca = (Aw2 @ visf).reshape(B, 3, -1).transpose(1, 0, 2) / Wd  # (3, B, n)
        cb = np.matmul(Ob, X) / Wd  # (3, B, n)
        Hu = np.matmul(Aw2, X).reshape(3, B, 3, -1)  # [j, b, i]: sum w a_i x_j
        H = Hu.transpose(2, 0, 1, 3) - W * ca[:, None] * cb[None, :]  # sum w (a - ca)(x - cb)^T
        Ga = A2 @ visf - W * _c_dot(ca, ca)
        Gb = Ob @ _c_dot(X, X) - W * _c_dot(cb, cb)
        code = (bits @ visf).astype(np.int64)  # (B, n)
        ok = np.stack([
            np.zeros(hi - lo, dtype=bool) if lut is None else _pattern_ok(*lut, code[b], collinear_tol, luts_ok, b)
            for b, lut in enumerate(luts)
        ])  # fmt: skip
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            q, good = _c_horn(H, 0.5 * (Ga + Gb), ok)
        Rb = _c_quat_to_mat(q)
        tb = cb - _c_mv(Rb, ca + a0.T[:, :, None])
        use = ok & good
        if not use.all():
            Rb[:, :, ~use] = np.nan
            tb[:, ~use] = np.nan
            for b in range(B):
                redo = np.flatnonzero(ok[b] & ~good[b])
                if redo.size:
                    todo.append((b, lo + redo))
        for b in range(B):  # one strided copy per shape (faster than one transposing copy)
            R[lo:hi, b] = Rb[:, :, b].transpose(2, 0, 1)
        t[lo:hi] = tb.transpose(2, 1, 0)

    starts = list(range(0, F, _POSE_BLOCK))
    if starts:
        block(starts[0])  # alone first: it makes the pattern tables that the threads then share
        run_blocks(block, starts[1:])
    todo.sort(key=lambda bf: (bf[0], int(bf[1][0])))  # the same order whatever the threads did
    todo += [(b, np.arange(F)) for b, lut in enumerate(luts) if lut is None]
    if todo:  # not certified by the fast path, or too many points: rigid.kabsch
        for b, fr in todo:
            cols = np.asarray(columns[b], dtype=int).reshape(-1)
            obs = np.concatenate([x[fr] for x in parts], axis=1)[:, cols]
            R[fr, b], t[fr, b], _ = kabsch(np.asarray(shapes[b], dtype=float).reshape(-1, 3), obs, collinear_tol=collinear_tol)
    return R, t


def _pattern_ok(a: np.ndarray, P: int, code: np.ndarray, collinear_tol: float, cache: dict, key: int) -> np.ndarray:
    """Whether the points of ``a`` (P, 3) selected by the bits of ``code`` can be aligned.

    As in :func:`~mocapskel.solvers.rigid.kabsch`: 3 or more points whose
    second principal spread is at least ``collinear_tol`` times the first.
    Shapes of up to 12 points: a table of all patterns, made once (in ``cache``).
    """
    if P <= 12:
        if key not in cache:
            cache[key] = _patterns_ok(a, np.arange(1 << P), collinear_tol)
        return cache[key][code]
    pats, inv = np.unique(code, return_inverse=True)
    return _patterns_ok(a, pats, collinear_tol)[inv.reshape(code.shape)]


def _patterns_ok(a: np.ndarray, pats: np.ndarray, collinear_tol: float) -> np.ndarray:
    """:func:`_pattern_ok` for distinct patterns ``pats``."""
    sel = ((pats[:, None] >> np.arange(len(a))) & 1).astype(float)  # (patterns, P)
    n = sel.sum(1)
    c = (sel @ a) / np.maximum(n, 1.0)[:, None]
    dev = (a[None] - c[:, None]) * sel[..., None]
    lam = np.linalg.eigvalsh(np.swapaxes(dev, 1, 2) @ dev)  # ascending
    return (n >= 3) & (lam[:, 1] > collinear_tol**2 * lam[:, 2]) & (lam[:, 2] > 0)


def _c_horn(H: np.ndarray, lam0: np.ndarray, need: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit quaternions (4, ...) of the rotations maximising tr(R H), and which are certified.

    ``H`` (3, 3, ...) = sum w a b^T of centred points (so that ``R a ~ b``);
    ``lam0`` an upper bound on the largest eigenvalue of Horn's matrix N;
    ``need`` the problems that matter (the others may not converge).
    The largest eigenvalue is the largest root of N's characteristic
    polynomial ``l^4 + c2 l^2 + c1 l + c0``, ``c2 = -2 |H|^2``, ``c1 = -8 det H``,
    ``c0 = det N``, found by Newton's method from ``lam0`` (monotone from
    above); the quaternion is a column of adj(N - l I): the first, or where
    its scalar part is small (a turn of more than 120 degrees) the column
    with the largest diagonal entry. Certified (``good``): Newton's method
    settled and the top eigenvalue stands apart from the next, so that the
    column is accurate to rounding.
    """
    (Sxx, Sxy, Sxz), (Syx, Syy, Syz), (Szx, Szy, Szz) = H
    n00 = Sxx + Syy + Szz
    n11 = Sxx - Syy - Szz
    n22 = Syy - Sxx - Szz
    n33 = Szz - Sxx - Syy
    n01, n02, n03 = Syz - Szy, Szx - Sxz, Sxy - Syx
    n12, n13, n23 = Sxy + Syx, Szx + Sxz, Syz + Szy
    c2 = -2.0 * np.einsum("ij...,ij...->...", H, H)
    c1 = -8.0 * (Sxx * (Syy * Szz - Syz * Szy) - Sxy * (Syx * Szz - Syz * Szx) + Sxz * (Syx * Szy - Syy * Szx))
    # det N from the 2x2 minors of rows (0, 1) and (2, 3)
    s0 = n00 * n11 - n01 * n01
    s1 = n00 * n12 - n01 * n02
    s2 = n00 * n13 - n01 * n03
    s3 = n01 * n12 - n11 * n02
    s4 = n01 * n13 - n11 * n03
    s5 = n02 * n13 - n12 * n03
    m01 = n02 * n13 - n12 * n03
    m23 = n22 * n33 - n23 * n23
    c0 = s0 * m23 - s1 * (n12 * n33 - n13 * n23) + s2 * (n12 * n23 - n13 * n22)
    c0 += s3 * (n02 * n33 - n03 * n23) - s4 * (n02 * n23 - n03 * n22) + s5 * m01

    def newton(lam: np.ndarray, c2: np.ndarray, c1: np.ndarray, c0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        l2 = lam * lam
        dP = (4.0 * l2 + 2.0 * c2) * lam + c1
        step = ((l2 + c2) * l2 + c1 * lam + c0) / dP
        step[~np.isfinite(step)] = 0.0
        lam -= step
        return np.abs(step) <= 1e-14 * np.abs(lam), dP

    lam = np.array(lam0, dtype=float)
    for _ in range(8):  # from the bound, a few steps suffice where the top eigenvalue stands apart
        settled, dP = newton(lam, c2, c1, c0)
        if settled[need].all():
            break
    slow = np.flatnonzero(need & ~settled)
    if slow.size:  # the rest, on their own
        sub = lam.ravel()[slow]
        args = [x.ravel()[slow] for x in (c2, c1, c0)]
        for _ in range(100):
            st_sub, dP_sub = newton(sub, *args)
            if st_sub.all():
                break
        lam.ravel()[slow], settled.ravel()[slow], dP.ravel()[slow] = sub, st_sub, dP_sub
    # the first column of adj(N - lam I), by the 2x2 minors of its rows 2 and 3
    a11, a22, a33 = n11 - lam, n22 - lam, n33 - lam
    m02 = n02 * n23 - a22 * n03
    m03 = n02 * a33 - n23 * n03
    m12 = n12 * n23 - a22 * n13
    m13 = n12 * a33 - n23 * n13
    m23 = a22 * a33 - n23 * n23
    q = np.stack([
        a11 * m23 - n12 * m13 + n13 * m12,
        n12 * m03 - n01 * m23 - n13 * m02,
        n01 * m13 - a11 * m03 + n13 * m01,
        a11 * m02 - n01 * m12 - n12 * m01,
    ])  # fmt: skip
    nq = np.sqrt(_c_dot(q[1:], q[1:]) + q[0] * q[0])
    good = settled & (lam > 0) & (dP > 0.1 * lam**3)
    redo = np.flatnonzero(good & ~(np.abs(q[0]) > 0.5 * nq))
    if redo.size:  # the column with the largest diagonal entry, whose |q_k| >= 1/2
        lr = lam.ravel()[redo]
        A = [[x.ravel()[redo] for x in row] for row in ((n00, n01, n02, n03), (n01, n11, n12, n13),
                                                      (n02, n12, n22, n23), (n03, n13, n23, n33))]  # fmt: skip
        for i in range(4):
            A[i][i] = A[i][i] - lr
        C, _ = _adj4(A)
        k = np.argmax(np.abs(np.stack([C[i][i] for i in range(4)])), axis=0)
        col = np.stack([np.choose(k, C[i]) for i in range(4)])
        q4 = q.reshape(4, -1)
        q4[:, redo] = col
        nq.ravel()[redo] = np.sqrt((col * col).sum(0))
    q /= np.where(good, nq, 1.0)
    return q, good




# --------------------------------------------------------------------------- continuity in time


def _step_angles(R: np.ndarray) -> np.ndarray:
    """(F-1, ...) angle (deg) between consecutive rotations of (F, ..., 3, 3)."""
    c = (np.einsum("f...ij,f...ij->f...", R[1:], R[:-1]) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _frame_rms(resid: np.ndarray) -> np.ndarray:
    """(F,) rms of the seen markers' residuals per frame (0 where none is seen)."""
    seen = np.isfinite(resid)
    n = seen.sum(1)
    return np.sqrt(np.where(seen, resid, 0.0).__pow__(2).sum(1) / np.maximum(n, 1))


def _worst_turn(steps: np.ndarray, F: int) -> np.ndarray:
    """(F,) the largest turn (over segments) of each frame from its previous or to its next frame."""
    w = steps.max(axis=1) if steps.size else np.zeros(max(F - 1, 0))
    out = np.zeros(F)
    out[1:] = w
    out[:-1] = np.maximum(out[:-1], w)
    return out


def unflip(
    parent: np.ndarray,
    origin: np.ndarray,
    marker_segment: np.ndarray,
    marker_local: np.ndarray,
    observed: np.ndarray,
    rot: np.ndarray,
    root_pos: np.ndarray,
    residual: np.ndarray,
    *,
    max_step_deg: float = 45.0,
    max_run: int = 60,
    rel_tol: float = 0.1,
    abs_tol_mm: float = 0.5,
    passes: int = 2,
    iterations: int = 10,
    prior_weight: float = 100.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Make IK continuous in time where the markers allow more than one good pose.

    Where a segment's markers leave its rotation undetermined (one or two
    markers, or nearly collinear ones: the twist about their line is held only
    by the joints), per-frame IK can land on either of two equivalent
    solutions, or wander along the free twist, from one frame to the next: a
    joint turns by up to 180 degrees, or pops by hundreds of millimetres, while
    its markers move by a few. Here every stretch of at most ``max_run`` frames
    that a segment spends between two turns of more than ``max_step_deg`` in
    one frame is solved again, started from and held (``prior_weight``) by the
    segment's rotation slerped across it from the frames around it; a frame
    takes the new pose when its marker rms is no worse than ``(1 + rel_tol)``
    times the old one plus ``abs_tol_mm``: of two equally good solutions, the
    one near its neighbours. A stretch the markers really turn in keeps its
    poses (the new ones fit worse). Vectorised over frames: one solve per pass.

    Parameters
    ----------
    parent, origin, marker_segment, marker_local, observed
        As :func:`solve_ik`.
    rot : (F, S, 3, 3) ndarray
        Solved global rotations (changed in place and returned).
    root_pos : (F, 3) ndarray
    residual : (F, M) ndarray
    max_step_deg, max_run, rel_tol, abs_tol_mm, passes, iterations, prior_weight
        See above.

    Returns
    -------
    rot, root_pos, residual, info
        ``info``: ``{"steps_before": n, "steps_after": n, "frames_changed": n}``
        (segment-frames with a turn above ``max_step_deg``; frames given a new pose).
    """
    from .rotations import slerp_fill

    F, S = rot.shape[:2]
    info = {"steps_before": 0, "steps_after": 0, "frames_changed": 0}
    if F < 3:
        return rot, root_pos, residual, info
    steps = _step_angles(rot)  # (F-1, S)
    info["steps_before"] = info["steps_after"] = int((steps > max_step_deg).sum())
    if not info["steps_before"]:
        return rot, root_pos, residual, info
    changed = np.zeros(F, dtype=bool)
    rms = _frame_rms(residual)
    used = np.asarray(marker_segment) >= 0
    any_seen = np.isfinite(observed[:, used].sum(axis=2)).any(axis=1)  # frames IK can solve again
    for _ in range(passes):
        big = steps > max_step_deg
        bad = np.zeros((F, S), dtype=bool)
        for s in np.flatnonzero(big.any(axis=0)):
            rid = np.r_[0, np.cumsum(big[:, s])]  # stretch of every frame
            length = np.bincount(rid)
            bad[:, s] = length[rid] <= max_run
            if bad[:, s].all():  # nothing steady to hold it to
                bad[:, s] = False
        frames = np.flatnonzero(bad.any(axis=1) & any_seen)
        if not frames.size:
            break
        # the start and prior: every segment as solved, those in a short stretch slerped across it
        start = rot[frames]  # a copy
        for s in np.flatnonzero(bad.any(axis=0)):
            start[:, s] = slerp_fill(rot[:, s], ~bad[:, s])[frames]
        res = solve_ik(parent, origin, marker_segment, marker_local, observed[frames], init_rot=start,
                       init_root=root_pos[frames], prior_rot=start, iterations=iterations, prior_weight=prior_weight)
        del start
        new_rms = _frame_rms(res.residual)
        ok = new_rms <= (1.0 + rel_tol) * rms[frames] + abs_tol_mm
        # ...and where the frame's largest turn from or to its neighbours does not grow
        # (judged with every equally good frame taken)
        where = np.full(F, -1)
        where[frames[ok]] = np.flatnonzero(ok)

        def taken(f: np.ndarray) -> np.ndarray:  # rotations of frames f with the equally good ones taken
            k = where[f]
            return np.where((k >= 0)[:, None, None, None], res.rot[np.maximum(k, 0)], rot[f])

        worst_new = np.zeros(frames.size)
        mine = taken(frames)
        for nb in (frames - 1, frames + 1):
            inside = (nb >= 0) & (nb < F)
            turn = _step_angles(np.stack([mine[inside], taken(nb[inside])]))[0].max(axis=-1)
            worst_new[inside] = np.maximum(worst_new[inside], turn)
        del mine
        worst_old = _worst_turn(steps, F)[frames]
        ok &= worst_new <= np.maximum(worst_old, max_step_deg)
        if not ok.any():
            break
        f = frames[ok]
        rot[f], root_pos[f], residual[f], rms[f] = res.rot[ok], res.root_pos[ok], res.residual[ok], new_rms[ok]
        changed[f] = True
        steps = _step_angles(rot)
    info["steps_after"] = int((steps > max_step_deg).sum())
    info["frames_changed"] = int(changed.sum())
    return rot, root_pos, residual, info
