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
number of markers and the depth of the tree.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rigid import kabsch

__all__ = ["IKResult", "solve_ik"]


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
        Number of iterations run (at most ``iterations``).
    converged : (F,) ndarray of bool
        Whether the frame converged: its last step was below the tolerance,
        or the linearised model could no longer lower its cost.
    """

    root_pos: np.ndarray
    rot: np.ndarray
    residual: np.ndarray
    n_iter: int
    converged: np.ndarray


# --------------------------------------------------------------------------- rotations


def _hat(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices: ``_hat(a) @ b == cross(a, b)``."""
    K = np.zeros(v.shape + (3,))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    K[..., 0, 1] = -z
    K[..., 0, 2] = y
    K[..., 1, 0] = z
    K[..., 1, 2] = -x
    K[..., 2, 0] = -y
    K[..., 2, 1] = x
    return K


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (faster than np.cross for large batches)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Batched matrix-vector product (..., 3, 3) x (..., 3) -> (..., 3)."""
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    out = np.empty(np.broadcast_shapes(A.shape[:-1], v.shape))
    for i in range(3):
        out[..., i] = A[..., i, 0] * v0 + A[..., i, 1] * v1 + A[..., i, 2] * v2
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _exp(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (..., 3) -> rotation matrices (..., 3, 3)."""
    th2 = np.einsum("...i,...i->...", rv, rv)
    small = th2 < 1e-8
    th = np.sqrt(np.where(small, 1.0, th2))
    a = np.where(small, 1 - th2 / 6, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24, (1 - np.cos(th)) / (th * th))
    # R = I + a [v]x + b [v]x^2,  [v]x^2 = v v^T - |v|^2 I
    R = b[..., None, None] * (rv[..., :, None] * rv[..., None, :])
    d = 1 - b * th2
    x, y, z = rv[..., 0] * a, rv[..., 1] * a, rv[..., 2] * a
    R[..., 0, 0] += d
    R[..., 1, 1] += d
    R[..., 2, 2] += d
    R[..., 0, 1] -= z
    R[..., 1, 0] += z
    R[..., 0, 2] += y
    R[..., 2, 0] -= y
    R[..., 1, 2] -= x
    R[..., 2, 1] += x
    return R


def _mat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) as (w, x, y, z), w >= 0."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([tr, m00, m11, m22], -1)
    k = np.argmax(cand, -1)
    q = np.empty(R.shape[:-2] + (4,))
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
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3), angle in [0, pi]."""
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    c = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1  # 2 cos(angle)
    n = np.sqrt((v * v).sum(-1))  # 2 sin(angle)
    ang = np.arctan2(n, c)
    out = v * np.where(n > 1e-12, ang / np.where(n > 1e-12, n, 1.0), 0.5)[..., None]
    near_pi = c < -1.9  # angle > ~162 deg: the antisymmetric part loses the axis; use quaternions
    if np.any(near_pi):
        q = _mat_to_quat(R[near_pi])
        w, u = q[:, 0], q[:, 1:]
        un = np.linalg.norm(u, axis=-1)
        out[near_pi] = u * (2 * np.arctan2(un, w) / np.where(un > 0, un, 1.0))[:, None]
    return out


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of (..., 3, 3) matrices by cofactors."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    g, h, i = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    out = np.empty(A.shape)
    out[..., 0, 0] = e * i - f * h
    out[..., 1, 0] = f * g - d * i
    out[..., 2, 0] = d * h - e * g
    det = a * out[..., 0, 0] + b * out[..., 1, 0] + c * out[..., 2, 0]
    out[..., 0, 1] = c * h - b * i
    out[..., 1, 1] = a * i - c * g
    out[..., 2, 1] = b * g - a * h
    out[..., 0, 2] = b * f - c * e
    out[..., 1, 2] = c * d - a * f
    out[..., 2, 2] = a * e - b * d
    out /= det[..., None, None]
    return out


def _project_so3(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrices (polar decomposition with a proper determinant).

    Returned as they are when they already are rotations to 1e-9."""
    RtR = np.swapaxes(R, -1, -2) @ R
    if np.abs(RtR - np.eye(3)).max(initial=0.0) < 1e-9 and np.all(np.linalg.det(R) > 0):
        return np.array(R, dtype=float)
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., 2] *= d[..., None]
    return U @ Vt


def _slerp_fill(R: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill rotations over time: slerp between the nearest valid frames, hold at the ends.

    Parameters
    ----------
    R : (F, K, 3, 3) ndarray
        Rotations; values at invalid frames are ignored.
    valid : (F, K) ndarray of bool

    Returns
    -------
    (F, K, 3, 3) ndarray
        Filled rotations; NaN for columns ``k`` with no valid frame.
    """
    F = R.shape[0]
    q = np.where(valid[..., None], _mat_to_quat(np.where(valid[..., None, None], R, np.eye(3))), 0.0)
    fr = np.arange(F)[:, None]
    prev = np.maximum.accumulate(np.where(valid, fr, -1), axis=0)
    nxt = np.minimum.accumulate(np.where(valid, fr, F)[::-1], axis=0)[::-1]
    has_p, has_n = prev >= 0, nxt < F
    pi, ni = np.clip(prev, 0, F - 1), np.clip(nxt, 0, F - 1)
    cols = np.arange(R.shape[1])[None, :]
    qa, qb = q[pi, cols], q[ni, cols]
    qb = np.where((qa * qb).sum(-1, keepdims=True) < 0, -qb, qb)
    span = np.where(has_p & has_n & (nxt > prev), nxt - prev, 1)
    alpha = np.where(has_p & has_n, (fr - prev) / span, 0.0)
    alpha = np.where(~has_p, 1.0, alpha)  # before the first valid frame: hold the next
    c = np.clip((qa * qb).sum(-1), -1.0, 1.0)
    th = np.arccos(c)
    st = np.sin(th)
    lin = st < 1e-6
    sts = np.where(lin, 1.0, st)
    wa = np.where(lin, 1 - alpha, np.sin((1 - alpha) * th) / sts)
    wb = np.where(lin, alpha, np.sin(alpha * th) / sts)
    qi = wa[..., None] * qa + wb[..., None] * qb
    nq = np.linalg.norm(qi, axis=-1, keepdims=True)
    qi = qi / np.where(nq > 0, nq, 1.0)
    out = _quat_to_mat(qi)
    out[~(has_p | has_n)] = np.nan
    return np.where(valid[..., None, None], R, out)


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
        # per level: groups of (positions in the level, parents) with distinct parents,
        # so that children's terms can be added to their parents without collisions
        self.groups: list[list[tuple[np.ndarray, np.ndarray]]] = []
        for sl in self.levels:
            idx = np.arange(sl.start, sl.stop)
            rank = self.child_slot[idx]
            self.groups.append(
                [(np.flatnonzero(rank == r), self.par[idx[rank == r]]) for r in range(int(rank.max()) + 1)]
                if sl.start > 0
                else []
            )
        self.path: list[list[int]] = []  # segments from the root to s, inclusive
        for s in range(S):
            self.path.append((self.path[self.par[s]] if s else []) + [s])


# --------------------------------------------------------------------------- the model


class _Model:
    """Marker model on a reordered tree, with the per-iteration kernels.

    Layouts: rotations ``R`` (S, F, 3, 3) and segment quantities (S, F, ...)
    segment-major; markers in per-segment slots (S, F, 3, K), K the most
    markers on one segment, padding slots with weight 0.

    The Gauss-Newton steps never touch single markers: for fixed observations
    and weights, a segment's gradient and Hessian are functions of a few
    per-frame sums (:meth:`stats`), so a step costs O(S) 3x3 operations per
    frame whatever the number of markers. (The cost, which decides whether a
    step is taken, is evaluated marker by marker: one BLAS product.)
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
        lp = np.zeros((S, K, 3))
        for s, ms in enumerate(self.members):
            self.slot[ms] = np.arange(len(ms))
            lp[s, : len(ms)] = local[ms]
        self.lp = lp  # (S, K, 3)
        self.lpT = np.ascontiguousarray(lp.transpose(0, 2, 1))  # (S, 3, K)
        self.lout = (lp[..., :, None] * lp[..., None, :]).reshape(S, K, 9)
        # children's offsets from their parent's origin, by parent: (S, 3, C)
        C = max(tree.max_children, 1)
        offT = np.zeros((S, 3, C))
        for c in range(1, S):
            offT[tree.par[c], :, tree.child_slot[c]] = origin[c] - origin[tree.par[c]]
        self.offT = offT

    # ---- layout
    def pack(self, a: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(F, M, ...) marker array -> (S, F, ..., K) slots."""
        out = np.full((self.t.S, self.K) + a.shape[:1] + a.shape[2:], fill, dtype=float)
        out[self.seg, self.slot] = np.moveaxis(a, 1, 0)
        return np.ascontiguousarray(np.moveaxis(out, 1, -1))

    def unpack(self, a: np.ndarray) -> np.ndarray:
        """(S, F, K) slots -> (F, M)."""
        return a[self.seg, :, self.slot].T

    # ---- kinematics
    def fk(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bone vectors G (S, F, 3) (G[c] from parent(c)'s origin to c's, 0 for the root)
        and origins P (S, F, 3)."""
        t = self.t
        S, F = R.shape[:2]
        G = np.zeros((S, F, 3))
        if S > 1:
            B = (R.reshape(S, F * 3, 3) @ self.offT).reshape(S, F, 3, -1)
            G[1:] = B[t.par[1:], :, :, t.child_slot[1:]]
        P = np.empty((S, F, 3))
        P[0] = p
        for s in range(1, S):
            P[s] = P[t.par[s]] + G[s]
        return G, P

    def markers(self, p: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Model marker positions (S, F, 3, K)."""
        S, F = R.shape[:2]
        _, P = self.fk(p, R)
        return (R.reshape(S, F * 3, 3) @ self.lpT).reshape(S, F, 3, self.K) + P[..., None]

    # ---- sufficient statistics of the data
    def stats(self, y: np.ndarray, w: np.ndarray) -> dict[str, np.ndarray]:
        """Per segment and frame sums of the data that the iterations need.

        W = sum w; lbar and ybar, the weighted centroids of the rest offsets and
        of the observations; Cc = sum w (y - ybar)(l - lbar)^T; Cw = sum w l l^T.
        ``y`` (S, F, 3, K) and ``w`` (S, F, K) in slot layout.
        """
        S, F = w.shape[:2]
        W = w.sum(-1)
        Wd = np.where(W > 0, W, 1.0)
        lbar = (w @ self.lp) / Wd[..., None]
        ybar = (y @ w[..., None])[..., 0] / Wd[..., None]
        yc = y - ybar[..., None]  # (S, F, 3, K)
        lc = self.lp[:, None] - lbar[:, :, None, :]  # (S, F, K, 3)
        Cc = (yc * w[:, :, None, :]) @ lc
        Cw = (w @ self.lout).reshape(S, F, 3, 3)
        return {"W": W, "lbar": lbar, "ybar": ybar, "Cc": Cc, "Cw": Cw}

    def cost(
        self, p: np.ndarray, R: np.ndarray, y: np.ndarray, w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bones G, origins P and the data cost sum_m w |x_m - y_m|^2 (F,).

        Evaluated marker by marker (not from the sums of :meth:`stats`, whose
        rounding would blur the small cost changes near convergence).
        """
        S, F = R.shape[:2]
        G, P = self.fk(p, R)
        r = (R.reshape(S, F * 3, 3) @ self.lpT).reshape(S, F, 3, self.K)
        r += P[..., None]
        r -= y
        r *= r
        c = np.einsum("sfk,sfk->f", w, r[:, :, 0] + r[:, :, 1] + r[:, :, 2])
        return G, P, c

    def step(
        self,
        R: np.ndarray,
        G: np.ndarray,
        P: np.ndarray,
        st: dict[str, np.ndarray],
        e: np.ndarray,
        pw: float,
        lam: np.ndarray,
        floor: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One damped Gauss-Newton step: (dp (F, 3), drot (S, F, 3), predicted cost decrease (F,)).

        Solves ``(J^T W J + pw I + damping) d = -(J^T W r + pw e)`` exactly in
        O(S) 3x3 operations per frame. The unknowns are the root position and
        one rotation increment per segment; with every segment's origin
        increment ``dP_s`` as an intermediate, a segment's own terms involve
        only ``(dP_s, d_s)`` and a child's origin moves by
        ``dP_c = dP_s - G_c x d_s``. Leaves first, each segment's rotation
        increment is eliminated, leaving a 3x3 quadratic in ``dP_s`` that is
        pushed onto the parent through ``[I, -[G_c]x]``; the root's 3x3 system
        gives ``dp``; back-substitution runs root first. The
        Levenberg-Marquardt damping scales each segment's (effective) 3x3
        rotation block and the root position block by ``1 + lam``: each
        direction is damped in proportion to its own curvature, so that weakly
        determined twists are not frozen by the stiff directions of the block.
        """
        t = self.t
        S, F = R.shape[:2]
        I3 = np.eye(3)
        W = st["W"]
        a = _mv(R, st["lbar"])  # R lbar
        d = P + a - st["ybar"]
        A = W[..., None] * a  # sum w L
        Rt = np.ascontiguousarray(np.swapaxes(R, -1, -2))
        Cr = st["Cc"] @ Rt
        gP = W[..., None] * d  # sum w r
        gd = _cross(A, d)  # sum w L x r
        gd[..., 0] += Cr[..., 1, 2] - Cr[..., 2, 1]
        gd[..., 1] += Cr[..., 2, 0] - Cr[..., 0, 2]
        gd[..., 2] += Cr[..., 0, 1] - Cr[..., 1, 0]
        gP0, gd0 = gP.copy(), gd.copy()  # own data terms, for the predicted decrease
        gd += pw * e
        N = R @ st["Cw"] @ Rt  # sum w L L^T
        HPP = W[..., None, None] * I3
        HPd = -_hat(A)
        Hdd = -N
        tr = N[..., 0, 0] + N[..., 1, 1] + N[..., 2, 2] + pw
        for i in range(3):
            Hdd[..., i, i] += tr

        Dinv = np.empty_like(Hdd)
        HdP = np.empty_like(HPd)
        xP0 = np.zeros((F, 3))
        for lv in range(len(t.levels) - 1, -1, -1):
            sl = t.levels[lv]
            D = Hdd[sl]
            D *= (1 + lam)[:, None, None]
            for i in range(3):
                D[..., i, i] += floor
            Di = _inv3(D)
            Dinv[sl] = Di
            HdP[sl] = np.swapaxes(HPd[sl], -1, -2)
            Z = HPd[sl] @ Di
            K = HPP[sl] - Z @ HdP[sl]
            k = gP[sl] - _mv(Z, gd[sl])
            if lv == 0:
                K0 = K[0] * (1 + lam)[:, None, None]
                for i in range(3):
                    K0[..., i, i] += floor
                xP0 = _mv(_inv3(K0), k[0])
                break
            Gs = G[sl]
            Gh = _hat(Gs)
            KG = K @ Gh
            GKG = Gh @ KG
            Gk = _cross(Gs, k)
            for pos, par in t.groups[lv]:
                HPP[par] += K[pos]
                HPd[par] -= KG[pos]
                Hdd[par] -= GKG[pos]
                gP[par] += k[pos]
                gd[par] += Gk[pos]
        # back-substitution, root first
        xP = np.empty((S, F, 3))
        xd = np.empty((S, F, 3))
        xP[0] = xP0
        for sl in t.levels:
            if sl.start > 0:
                pr = t.par[sl]
                xP[sl] = xP[pr] - _cross(G[sl], xd[pr])
            xd[sl] = _mv(Dinv[sl], gd[sl] - _mv(HdP[sl], xP[sl]))
        # decrease of the linearised cost: every segment's own markers and prior
        u, dl = -xP, -xd
        Nd = _mv(N, dl)
        lin = (
            2 * (_dot(gP0, u) + _dot(gd0, dl))
            + W * _dot(u, u)
            + 2 * _dot(u, _cross(dl, A))
            + (N[..., 0, 0] + N[..., 1, 1] + N[..., 2, 2]) * _dot(dl, dl)
            - _dot(dl, Nd)
            + pw * (2 * _dot(e, dl) + _dot(dl, dl))
        )
        return -xP0, -xd, -lin.sum(0)


def _dense_system(
    model: _Model, p: np.ndarray, R: np.ndarray, y: np.ndarray, w: np.ndarray, e: np.ndarray, pw: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference normal equations from a dense Jacobian: H (F, n, n), g (F, n), n = 3 + 3S.

    Only for tests and benchmarks (memory grows as F * M * S). ``y`` and ``w``
    are in slot layout, ``R`` is (S, F, 3, 3), ``e`` is (S, F, 3).
    """
    t = model.t
    S, F = R.shape[:2]
    G, P = model.fk(p, R)
    x = model.markers(p, R)
    L = x - P[..., None]
    r = x - y
    rows_J, rows_r, rows_w = [], [], []
    for s in range(S):
        for k in range(model.K):
            J = np.zeros((F, 3, S + 1, 3))
            J[:, :, 0, :] = np.eye(3)
            path = t.path[s]
            for i, a in enumerate(path):
                u = L[s, :, :, k] if a == s else G[path[i + 1]]
                J[:, :, a + 1, :] = -_hat(u)
            rows_J.append(J.reshape(F, 3, 3 * (S + 1)))
            rows_r.append(r[s, :, :, k])
            rows_w.append(np.repeat(w[s, :, k, None], 3, axis=1))
    J = np.concatenate(rows_J, axis=1)
    rv = np.concatenate(rows_r, axis=1)
    wv = np.concatenate(rows_w, axis=1)
    H = np.einsum("fki,fk,fkj->fij", J, wv, J)
    g = np.einsum("fki,fk->fi", J, wv * rv)
    H[:, 3:, 3:] += pw * np.eye(3 * S)
    g[:, 3:] += pw * e.transpose(1, 0, 2).reshape(F, 3 * S)
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
    3. Segments solved in some frames: slerp over time between solved frames
       (held at the ends). Segments never solved: the parent's rotation
       (identity for the root).
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
    Rf = _slerp_fill(Rk, solved)
    for s in range(S):
        if not solved[:, s].any():
            Rf[:, s] = Rf[:, t.par[s]] if t.par[s] >= 0 else np.eye(3)
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


def _root_from_rotations(model: _Model, R: np.ndarray, st: dict[str, np.ndarray]) -> np.ndarray:
    """Root position (F, 3) given rotations R (S, F, 3, 3): the weighted mean offset of
    the observed markers from the model at p = 0; frames without markers interpolated."""
    F = R.shape[1]
    _, P = model.fk(np.zeros((F, 3)), R)
    W = st["W"]
    d = st["ybar"] - _mv(R, st["lbar"]) - P
    Wt = W.sum(0)
    p = np.einsum("sf,sfi->fi", W, d) / np.where(Wt > 0, Wt, 1.0)[:, None]
    return _interp_fill(p, Wt > 0)


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
        segments solved in that frame; else slerp over time between such
        frames (held at the ends) or, for a segment never solved, its
        parent's rotation; finally, where the available points give a single
        direction, the smallest rotation of that guess matching it. So the
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
        A frame has converged (and leaves the iteration) when its last step
        moves no point of the skeleton by more than about ``tol`` mm, or when
        the linearised model can no longer lower its cost.

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
    y = observed[:, used]
    if weights is None:
        w = np.ones((F, len(used)))
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=float), (F, M))[:, used].copy()
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative")
    seen = np.isfinite(y).all(-1)
    w = np.where(seen, w, 0.0)
    if F == 0 or not np.any(w > 0):
        raise ValueError("no marker on any segment is seen in any frame: nothing to solve")
    yt = np.where(seen[..., None], y, 0.0)  # (F, M, 3)
    pw = float(prior_weight)
    if pw < 0 or damping < 0:
        raise ValueError("prior_weight and damping must be non-negative")

    # prior and starting point; internally rotations are segment-major (S, F, 3, 3)
    if prior_rot is None:
        R_prior = _initial_rotations(model, yt, w)
    else:
        prior_rot = np.asarray(prior_rot, dtype=float)
        if prior_rot.shape != (F, S, 3, 3) or not np.isfinite(prior_rot).all():
            raise ValueError(f"prior_rot must be finite, ({F}, {S}, 3, 3)")
        R_prior = _project_so3(prior_rot[:, tree.perm])
    R_prior = np.ascontiguousarray(R_prior.transpose(1, 0, 2, 3))
    if init_rot is None:
        R = R_prior.copy()
    else:
        init_rot = np.asarray(init_rot, dtype=float)
        if init_rot.shape != (F, S, 3, 3) or not np.isfinite(init_rot).all():
            raise ValueError(f"init_rot must be finite, ({F}, {S}, 3, 3)")
        R = np.ascontiguousarray(_project_so3(init_rot[:, tree.perm]).transpose(1, 0, 2, 3))
    y = model.pack(yt)  # (S, F, 3, K)
    w = model.pack(w)  # (S, F, K)
    st = model.stats(y, w)
    if init_root is None:
        p = _root_from_rotations(model, R, st)
    else:
        p = np.array(init_root, dtype=float)
        if p.shape != (F, 3) or not np.isfinite(p).all():
            raise ValueError(f"init_root must be finite, ({F}, 3)")

    # length scale for the convergence test: the skeleton's extent
    pts = np.concatenate([model.origin, model.origin[seg] + model.local])
    scale = max(float(np.linalg.norm(pts - model.origin[0], axis=1).max()), 1.0)
    floor = 1e-12 * scale**2  # keeps every 3x3 block invertible

    R_prior_T = np.ascontiguousarray(np.swapaxes(R_prior, -1, -2))
    G, P, cost = model.cost(p, R, y, w)
    e = _log(R @ R_prior_T)  # (S, F, 3)
    cost += pw * _dot(e, e).sum(0)
    lam = np.full(F, float(damping))
    nu = np.full(F, 2.0)
    converged = np.zeros(F, dtype=bool)
    n_iter = 0
    for _ in range(int(iterations)):
        if converged.all():
            break
        n_iter += 1
        if converged.any():
            act = np.flatnonzero(~converged)
            pa, Ra, Ga, Pa, ea, RpT = p[act], R[:, act], G[:, act], P[:, act], e[:, act], R_prior_T[:, act]
            sta = {k: v[:, act] for k, v in st.items()}
            ya, wa = y[:, act], w[:, act]
        else:
            act = slice(None)
            pa, Ra, Ga, Pa, ea, RpT, sta, ya, wa = p, R, G, P, e, R_prior_T, st, y, w
        dp, dr, pred = model.step(Ra, Ga, Pa, sta, ea, pw, lam[act], floor)
        p_new = pa + dp
        R_new = _exp(dr) @ Ra
        G2, P2, c2 = model.cost(p_new, R_new, ya, wa)
        e2 = _log(R_new @ RpT)
        c2 += pw * _dot(e2, e2).sum(0)
        c1 = cost[act]
        eps = 1e-12 * c1 + 1e-18  # the rounding level of the cost
        ok = c2 <= c1 + eps
        step = np.sqrt(np.maximum(_dot(dp, dp), scale**2 * _dot(dr, dr).max(0)))
        # Nielsen's damping update from the gain ratio (actual / predicted decrease)
        rho = np.where(pred <= eps, 1.0, (c1 - c2) / np.maximum(pred, 1e-300))  # rounding level: trust the model
        la, na = lam[act], nu[act]
        lam[act] = np.where(ok, np.maximum(la * np.maximum(1 / 3, 1 - (2 * np.minimum(rho, 1) - 1) ** 3), 1e-12), la * na)
        nu[act] = np.where(ok, 2.0, na * 2)
        # converged: the step is below tol, or the linear model can no longer lower the cost
        converged[act] = (step <= tol) | (ok & (pred <= eps))
        if ok.all() and isinstance(act, slice):
            p, R, G, P, e, cost = p_new, R_new, G2, P2, e2, c2
        else:
            idx = np.arange(F)[act][ok]
            p[idx], R[:, idx], G[:, idx], P[:, idx], e[:, idx], cost[idx] = (
                p_new[ok], R_new[:, ok], G2[:, ok], P2[:, ok], e2[:, ok], c2[ok]
            )

    r = model.markers(p, R) - y
    res = np.full((F, M), np.nan)
    res[:, used] = np.where(seen, model.unpack(np.sqrt((r * r).sum(2))), np.nan)
    rot = np.empty((F, S, 3, 3))
    rot[:, tree.perm] = R.transpose(1, 0, 2, 3)
    return IKResult(root_pos=p, rot=rot, residual=res, n_iter=n_iter, converged=converged)
