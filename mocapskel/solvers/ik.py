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
``R_s <- exp([d_s]x) R_s``. The normal equations are assembled from per-segment
sums (no dense Jacobian) and solved by block elimination along the tree
(leaves first), which creates no fill-in: the cost grows with the sum of squared
segment depths, not with the cube of the number of segments.
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
        Whether the last step of the frame was below the tolerance.
    """

    root_pos: np.ndarray
    rot: np.ndarray
    residual: np.ndarray
    n_iter: int
    converged: np.ndarray


# --------------------------------------------------------------------------- rotations


def _hat(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


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
    r0, r1, r2 = A[..., 0, :], A[..., 1, :], A[..., 2, :]
    c0 = np.cross(r1, r2)
    c1 = np.cross(r2, r0)
    c2 = np.cross(r0, r1)
    det = (r0 * c0).sum(-1)
    return np.stack([c0, c1, c2], -1) / det[..., None, None]


def _project_so3(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrices (polar decomposition with a proper determinant)."""
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
        self.nonroot = np.arange(1, S)
        depth = np.zeros(S, dtype=int)
        for s in range(1, S):
            depth[s] = depth[self.par[s]] + 1
        bounds = np.flatnonzero(np.diff(depth)) + 1
        starts = np.concatenate([[0], bounds])
        ends = np.concatenate([bounds, [S]])
        self.levels = [slice(int(a), int(b)) for a, b in zip(starts, ends)]
        # per level > 0: (n_level, n_previous_level) child -> parent incidence
        self.incidence = [None]
        for lv in range(1, len(self.levels)):
            cur, prev = self.levels[lv], self.levels[lv - 1]
            inc = np.zeros((cur.stop - cur.start, prev.stop - prev.start))
            inc[np.arange(cur.stop - cur.start), self.par[cur] - prev.start] = 1.0
            self.incidence.append(inc)
        self.path = []  # segments from the root to s, inclusive
        for s in range(S):
            self.path.append((self.path[self.par[s]] if s else []) + [s])


# --------------------------------------------------------------------------- the model


class _Model:
    """Marker model on a reordered tree, with the per-iteration kernels.

    Layouts: rotations ``R`` (S, F, 3, 3) and segment quantities (S, F, ...)
    segment-major; markers in per-segment slots, (S, F, 3, K) with K the most
    markers on one segment (padding slots have weight 0).
    """

    def __init__(self, tree: _Tree, origin: np.ndarray, seg: np.ndarray, local: np.ndarray):
        self.t = tree
        S = tree.S
        self.origin = origin
        off = np.zeros((S, 3))
        nr = tree.nonroot
        off[nr] = origin[nr] - origin[tree.par[nr]]
        self.off = off
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
        self.lpT = np.ascontiguousarray(lp.transpose(0, 2, 1))  # (S, 3, K)
        self.lp = lp  # (S, K, 3)
        self.lout = (lp[..., :, None] * lp[..., None, :]).reshape(S, K, 9)

    def pack(self, a: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(F, M, ...) marker array -> (S, F, ..., K) slots."""
        out = np.full((self.t.S, self.K) + a.shape[:1] + a.shape[2:], fill, dtype=float)
        out[self.seg, self.slot] = np.moveaxis(a, 1, 0)
        return np.ascontiguousarray(np.moveaxis(out, 1, -1))

    def unpack(self, a: np.ndarray) -> np.ndarray:
        """(S, F, K) slots -> (F, M)."""
        return a[self.seg, :, self.slot].T

    def fk(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bone vectors G (S, F, 3) (G[c] from parent(c)'s origin to c's, 0 for the root),
        origins P (S, F, 3) and marker levers L = R l (S, F, 3, K)."""
        t = self.t
        S, F = R.shape[:2]
        G = np.zeros((S, F, 3))
        if S > 1:
            G[1:] = (R[t.par[1:]] @ self.off[1:, None, :, None])[..., 0]
        P = np.empty((S, F, 3))
        P[0] = p
        for s in range(1, S):
            P[s] = P[t.par[s]] + G[s]
        L = (R.reshape(S, F * 3, 3) @ self.lpT).reshape(S, F, 3, self.K)
        return G, P, L

    def residual(
        self, p: np.ndarray, R: np.ndarray, y: np.ndarray, w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """FK, residuals r = x - y (S, F, 3, K) and the data cost (F,)."""
        G, P, L = self.fk(p, R)
        r = L + P[..., None]
        r -= y
        cost = np.einsum("sfk,sfk->f", w, (r * r).sum(2))
        return G, L, r, cost

    def step(
        self,
        R: np.ndarray,
        G: np.ndarray,
        L: np.ndarray,
        r: np.ndarray,
        w: np.ndarray,
        e: np.ndarray,
        pw: float,
        lam: np.ndarray,
        floor: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One damped Gauss-Newton step: (dp (F, 3), drot (S, F, 3)).

        Solves ``(J^T W J + pw I + damping) d = -(J^T W r + pw e)`` exactly, in
        O(S) 3x3 operations per frame: the unknowns are the root position and
        one rotation increment per segment; writing every segment's origin
        increment ``dP_s`` as an intermediate, a segment's own terms involve only
        ``(dP_s, d_s)`` and a child's origin increment is ``dP_c = dP_s - G_c x d_s``.
        Leaves first, each segment's rotation increment is eliminated, leaving
        a 3x3 quadratic in ``dP_s`` that is pushed onto the parent through
        ``[I, -[G_c]x]``; the root's 3x3 system gives ``dp``; then top-down
        back-substitution. The Levenberg-Marquardt damping adds
        ``lam * diag`` to every segment's (effective) rotation block and to
        the root position block.
        """
        t = self.t
        S, F = R.shape[:2]
        I3 = np.eye(3)
        wr = w[:, :, None, :] * r  # (S, F, 3, K)
        gP = wr.sum(-1)  # (S, F, 3)
        L0, L1, L2 = L[:, :, 0], L[:, :, 1], L[:, :, 2]
        r0, r1, r2 = wr[:, :, 0], wr[:, :, 1], wr[:, :, 2]
        gd = np.stack([(L1 * r2 - L2 * r1).sum(-1), (L2 * r0 - L0 * r2).sum(-1), (L0 * r1 - L1 * r0).sum(-1)], -1)
        gd += pw * e
        W = w.sum(-1)  # (S, F)
        Cw = (w @ self.lout).reshape(S, F, 3, 3)  # sum w l l^T
        N = R @ Cw @ np.ascontiguousarray(np.swapaxes(R, -1, -2))  # sum w L L^T
        A = (R @ (w @ self.lp)[..., None])[..., 0]  # sum w L
        HPP = W[..., None, None] * I3
        HPd = -_hat(A)
        Hdd = (N[..., 0, 0] + N[..., 1, 1] + N[..., 2, 2] + pw)[..., None, None] * I3 - N

        Dinv = np.empty_like(Hdd)
        for lv in range(len(t.levels) - 1, -1, -1):
            sl = t.levels[lv]
            la = lam[None, :, None]
            dd = np.einsum("sfii->sfi", Hdd[sl])
            Hdd[sl] += (la * dd + floor)[..., None] * I3
            Di = _inv3(Hdd[sl])
            Dinv[sl] = Di
            Z = HPd[sl] @ Di
            K = HPP[sl] - Z @ np.swapaxes(HPd[sl], -1, -2)
            k = gP[sl] - (Z @ gd[sl][..., None])[..., 0]
            if lv == 0:
                K0 = K[0] + (lam[:, None] * np.einsum("fii->fi", K[0]) + floor)[..., None] * I3
                xP0 = (_inv3(K0) @ k[0][..., None])[..., 0]
                break
            Gh = _hat(G[sl])
            KG = K @ Gh
            inc = t.incidence[lv]
            prev = t.levels[lv - 1]
            n = sl.stop - sl.start

            def push(target: np.ndarray, val: np.ndarray) -> None:
                target[prev] += np.tensordot(inc, val.reshape(n, -1), axes=(0, 0)).reshape(target[prev].shape)

            push(HPP, K)
            push(HPd, -KG)
            push(Hdd, -(Gh @ KG))
            push(gP, k)
            push(gd, np.cross(G[sl], k))
        # back-substitution, root first
        xP = np.empty((S, F, 3))
        xd = np.empty((S, F, 3))
        xP[0] = xP0
        for sl in t.levels:
            if sl.start > 0:
                pr = t.par[sl]
                xP[sl] = xP[pr] - np.cross(G[sl], xd[pr])
            rhs = gd[sl] - (np.swapaxes(HPd[sl], -1, -2) @ xP[sl][..., None])[..., 0]
            xd[sl] = (Dinv[sl] @ rhs[..., None])[..., 0]
        return -xP0, -xd


def _dense_system(
    model: _Model, p: np.ndarray, R: np.ndarray, y: np.ndarray, w: np.ndarray, e: np.ndarray, pw: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference normal equations from a dense Jacobian: H (F, n, n), g (F, n), n = 3 + 3S.

    Only for tests and benchmarks (memory grows as F * M * S). ``y`` and ``w``
    are in slot layout, ``R`` is (S, F, 3, 3), ``e`` is (S, F, 3).
    """
    t = model.t
    S, F = R.shape[:2]
    G, L, r, _ = model.residual(p, R, y, w)
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


def _initial_rotations(model: _Model, yt: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Data-driven rotations (F, S, 3, 3) for every segment and frame (all finite).

    ``yt`` (F, M, 3) observed markers, ``w`` (F, M) weights (0 where unseen).

    1. Kabsch of each segment's visible markers (>= 3, not collinear).
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
            R2, t2, _ = kabsch(np.broadcast_to(rp, (int(todo.sum()),) + rp.shape), op[todo], wp[todo])
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


def _root_from_rotations(model: _Model, R: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Root position (F, 3) given rotations R (S, F, 3, 3): the weighted mean of the
    observed markers minus the FK at p = 0; frames without markers interpolated.
    ``y`` (S, F, 3, K) and ``w`` (S, F, K) in slot layout."""
    F = R.shape[1]
    _, P, L = model.fk(np.zeros((F, 3)), R)
    d = y - L - P[..., None]
    W = w.sum((0, 2))
    p = np.einsum("sfk,sfik->fi", w, d) / np.where(W > 0, W, 1.0)[:, None]
    return _interp_fill(p, W > 0)


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
    prior_weight: float = 10.0,
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
        segment, Kabsch of its markers where at least 3 non-collinear ones
        are seen; else Kabsch of its markers plus the joints placed by the
        neighbouring segments solved in that frame; else slerp over time
        between such frames (held at the ends) or, for a segment never
        solved, its parent's rotation; finally, where the available points
        give a single direction, the smallest rotation matching it. So the
        prior agrees with the data where the data determine the rotation,
        and fills gaps and undetermined twists smoothly.
    weights : (F, M) or (M,) ndarray, optional
        Non-negative marker weights (default 1; NaN markers get 0).
    iterations : int, optional
        Maximum number of Levenberg-Marquardt iterations.
    damping : float, optional
        Initial Levenberg-Marquardt damping (relative to the diagonal).
    prior_weight : float, optional
        Weight of the rotation prior in mm^2 per rad^2: the prior pulls like
        one marker ``sqrt(prior_weight)`` mm from the rotation axis (default:
        about 3 mm). Keep it positive so that segments with too few markers
        (or none) in a frame stay determined.
    tol : float, optional
        A frame has converged when its last step moves no point of the
        skeleton by more than about ``tol`` mm.

    Returns
    -------
    IKResult
        ``root_pos`` (F, 3), ``rot`` (F, S, 3, 3), ``residual`` (F, M), ``n_iter``,
        ``converged`` (F,). All finite (``residual`` is NaN for unseen markers).

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
    if init_root is None:
        p = _root_from_rotations(model, R, y, w)
    else:
        p = np.array(init_root, dtype=float)
        if p.shape != (F, 3) or not np.isfinite(p).all():
            raise ValueError(f"init_root must be finite, ({F}, 3)")

    # length scale for the convergence test: the skeleton's extent
    pts = np.concatenate([model.origin, model.origin[seg] + model.local])
    scale = max(float(np.linalg.norm(pts - model.origin[0], axis=1).max()), 1.0)
    floor = 1e-12 * scale**2  # keeps every 3x3 block invertible

    R_prior_T = np.ascontiguousarray(np.swapaxes(R_prior, -1, -2))
    G, L, r, cost = model.residual(p, R, y, w)
    e = _log(R @ R_prior_T)  # (S, F, 3)
    cost += pw * (e * e).sum((0, 2))
    lam = np.full(F, float(damping))
    converged = np.zeros(F, dtype=bool)
    n_iter = 0
    for _ in range(int(iterations)):
        if converged.all():
            break
        n_iter += 1
        if converged.any():
            act = np.flatnonzero(~converged)
            pa, Ra, Ga, La, ra, ea = p[act], R[:, act], G[:, act], L[:, act], r[:, act], e[:, act]
            wa, ya, RpT = w[:, act], y[:, act], R_prior_T[:, act]
        else:
            act = slice(None)
            pa, Ra, Ga, La, ra, ea, wa, ya, RpT = p, R, G, L, r, e, w, y, R_prior_T
        dp, dr = model.step(Ra, Ga, La, ra, wa, ea, pw, lam[act], floor)
        p_new = pa + dp
        R_new = _exp(dr) @ Ra
        G2, L2, r2, c2 = model.residual(p_new, R_new, ya, wa)
        e2 = _log(R_new @ RpT)
        c2 += pw * (e2 * e2).sum((0, 2))
        ok = c2 <= cost[act] * (1 + 1e-12)
        step = np.maximum(np.abs(dp).max(1), scale * np.abs(dr).max((0, 2)))
        if ok.all() and isinstance(act, slice):
            p, R, G, L, r, e, cost = p_new, R_new, G2, L2, r2, e2, c2
        else:
            idx = np.arange(F)[act][ok]
            p[idx], R[:, idx], G[:, idx], L[:, idx], r[:, idx], e[:, idx], cost[idx] = (
                p_new[ok], R_new[:, ok], G2[:, ok], L2[:, ok], r2[:, ok], e2[:, ok], c2[ok]
            )
        lam[act] = np.where(ok, np.maximum(lam[act] * 0.3, 1e-12), lam[act] * 10)
        converged[act] = step <= tol

    res = np.full((F, M), np.nan)
    res[:, used] = np.where(seen, model.unpack(np.sqrt((r * r).sum(2))), np.nan)
    rot = np.empty((F, S, 3, 3))
    rot[:, tree.perm] = R.transpose(1, 0, 2, 3)
    return IKResult(root_pos=p, rot=rot, residual=res, n_iter=n_iter, converged=converged)
