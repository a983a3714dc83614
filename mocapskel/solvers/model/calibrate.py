"""Skeleton calibration: every constant offset and every pose, fitted together.

The joints stage places each joint from the two segments it links, and the
rigid stage makes each segment's shape from its own markers and joints. When a
segment carries few markers (two, or one), both steps see too little: a joint
between two 2-marker segments is pinned only by four distances per frame. The
whole skeleton sees much more — a segment's two markers, its parent joint and
its child joints must all stay rigid together, frame after frame — so the
skeleton is refined here as one least-squares problem over a subsample of
frames (bundle adjustment)::

    minimise  sum_f sum_m w_fm |x_m(p_f, R_f; d, l) - y_fm|^2

over the per-frame root positions ``p_f`` and global segment rotations
``R_f`` (the model of :mod:`mocapskel.solvers.ik.solve`) and the constant bone
offsets ``d_c`` (child ``c``'s joint relative to its parent's origin, in the
parent's rest frame) and marker offsets ``l_m``. Given the rotations the
marker positions are linear in ``p``, ``d`` and ``l``; the problem is solved
by Levenberg–Marquardt, the per-frame pose blocks eliminated frame by frame
(Schur complement), with no Python loop over frames. The elimination follows
the tree: segments of different limbs share no marker, so each limb's block is
factored on its own and only the trunk's few rows (the root and the segments
that branch) meet every constant unknown; an iteration costs about
O(F · (3T + 3) · G^2) for G constant unknowns and T trunk segments, plus the
limbs' small products, instead of O(F · 3S · G^2).

The gauge (each segment's local frame, and where the root's origin sits) is
fixed afterwards: every segment's rotation is the identity at the reference
frame, and the root's origin is the mean of its children's joints, as the
rigid stage defines them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...model.tree import depth_first_order
from ..parallel import Shares, WorkerLost
from .ties import tie_rows

__all__ = ["CalibrationResult", "refine_skeleton"]


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Refined skeleton offsets and the poses of the frames used.

    origin : (S, 3) rest-pose segment origins (the root's kept as given)
    marker_local : (M, 3) marker offsets from their segment's origin (unused markers unchanged)
    rot : (F, S, 3, 3) global segment rotations, the identity at the reference frame
    root_pos : (F, 3) root origin per frame
    rms : (2,) marker rms (mm) before and after
    n_iter : iterations run
    objective : the minimised cost at the end (mm^2): squared marker residuals plus the weighted priors
    """

    origin: np.ndarray
    marker_local: np.ndarray
    rot: np.ndarray
    root_pos: np.ndarray
    rms: tuple[float, float]
    n_iter: int
    objective: float = float("nan")


def _hat(v: np.ndarray) -> np.ndarray:
    K = np.zeros(v.shape + (3,))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def _exp(rv: np.ndarray) -> np.ndarray:
    th2 = np.einsum("...i,...i->...", rv, rv)
    small = th2 < 1e-10
    th = np.sqrt(np.where(small, 1.0, th2))
    a = np.where(small, 1 - th2 / 6, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24, (1 - np.cos(th)) / (th * th))
    K = _hat(rv)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


class _Problem:
    def __init__(self, parent, seg, observed, soft=(), soft_weights=None):
        S = len(parent)
        self.S = S
        self.parent = np.asarray(parent)
        self.order = [int(s) for s in depth_first_order(self.parent)]
        self.root = int(np.flatnonzero(self.parent < 0)[0])
        path = {}
        for s in self.order:
            path[s] = ([] if self.parent[s] < 0 else path[int(self.parent[s])]) + [s]
        self.path = path
        vis = np.isfinite(observed).all(-1)
        self.used = np.flatnonzero((np.asarray(seg) >= 0) & vis.any(0))
        self.seg = np.asarray(seg)
        self.y = np.where(vis[..., None], observed, 0.0)
        self.w = vis.astype(float)
        # soft joints: each frame's pose also has, for each of these child segments, the joint's offset
        # from its fixed place in the parent's frame (3 unknowns after the rotations)
        self.soft = [int(c) for c in soft]
        self.nf = 3 + 3 * S + 3 * len(self.soft)
        # their prior's weights (per unknown; see refine_skeleton's ``soft``) and rows in a frame's pose
        self.ws = np.repeat(np.zeros(len(self.soft)) if soft_weights is None else np.asarray(soft_weights, float), 3)
        self.se = 3 + 3 * S + np.arange(self.ws.size)
        kids = [s for s in range(S) if self.parent[s] >= 0]
        self.gi = {c: 3 * i for i, c in enumerate(kids)}
        base = 3 * len(kids)
        self.nd = base
        self.gl = {int(m): base + 3 * i for i, m in enumerate(self.used)}
        self.ng = base + 3 * len(self.used)
        self.kids = kids
        # the Jacobian's non-zero blocks, one entry per (used marker, segment on its path): the
        # marker's rows in that segment's rotation columns, and in the bone offset columns of the
        # segment's joint (all but the root)
        fi, fs, fn, di, dc, dp = [], [], [], [], [], []
        for i, m in enumerate(self.used):
            t = int(self.seg[m])
            pth = path[t]
            for k, s_ in enumerate(pth):
                fi.append(i)
                fs.append(s_)
                fn.append(pth[k + 1] if s_ != t else -1)
            for c in pth[1:]:
                di.append(i)
                dc.append(self.gi[c] // 3)
                dp.append(int(self.parent[c]))
        self.fi, self.fs, self.fn = np.array(fi, dtype=int), np.array(fs, dtype=int), np.array(fn, dtype=int)
        self.di, self.dc, self.dp = np.array(di, dtype=int), np.array(dc, dtype=int), np.array(dp, dtype=int)
        self.kid_parent = self.parent[kids]
        # sub[i, k]: joint k (of kids) is on used marker i's path; sub2[i, k, k']: both are
        self.sub = np.zeros((self.used.size, len(kids)))
        self.sub[self.di, self.dc] = 1.0
        self.below = self.sub[:, [self.gi[c] // 3 for c in self.soft]]  # (U, ns): marker below soft joint
        self.sub2 = self.sub[:, :, None] * self.sub[:, None, :]
        self.sub_mask = np.repeat(np.repeat(self.sub.T, 3, axis=0), 3, axis=1)  # (nd, 3U)
        j_, c_, k_ = np.meshgrid(np.arange(3), np.arange(len(kids)), np.arange(3), indexing="ij")
        self.bd_rows, self.bd_cols = (j_ * len(kids) + c_).ravel(), (c_ * 3 + k_).ravel()
        # flat positions (within one frame's block) of the (marker, path segment) 3x3 blocks: in the
        # transposed pose Jacobian (S + 1, 3, 3, U) and in X's marker columns (rows (S + 1) * 3, columns
        # ng + 1): one take along a flat axis instead of a scatter through two index arrays (the same
        # values, in half the time)
        a_, b_ = np.arange(3)[None, :, None], np.arange(3)[None, None, :]
        fs1, fi_ = (self.fs + 1)[:, None, None], self.fi[:, None, None]
        U = self.used.size
        self.jac_at = (((fs1 * 3 + a_) * 3 + b_) * U + fi_).ravel()
        self.xl_at = ((fs1 * 3 + a_) * (self.ng + 1) + self.nd + fi_ * 3 + b_).ravel()
        self._limbs()

    def _limbs(self) -> None:
        """The pose unknowns split into the trunk and the limbs, for :meth:`eliminate`.

        The trunk: the root, every segment with two or more children and their ancestors; a limb:
        a child of the trunk outside it, with everything below. Two segments of different limbs
        share no marker below both, so their block of a frame's pose Hessian is zero, and a limb's
        rows of ``X`` are zero outside the columns of its markers and of the joints on their paths
        (plus the right-hand side): ``trunk`` (pose indices) and ``limbs`` [(pose indices, columns
        of X, those columns' runs of consecutive ones as (first, end, place among them))] say which.
        """
        S, parent = self.S, self.parent
        trunk = set()
        for s_ in range(S):
            if parent[s_] < 0 or np.count_nonzero(parent == s_) >= 2:
                while s_ >= 0 and s_ not in trunk:
                    trunk.add(s_)
                    s_ = int(parent[s_])

        def rows(segs):
            out = [np.arange(3 + 3 * x, 6 + 3 * x) for x in segs]
            out += [3 + 3 * S + 3 * i + np.arange(3) for i, c in enumerate(self.soft) if c in segs]
            return np.concatenate(out).astype(int)

        t_used = self.seg[self.used]
        self.trunk = np.concatenate([np.arange(3), rows(sorted(trunk))])
        self.limbs = []
        for head in (c for c in range(S) if parent[c] >= 0 and int(parent[c]) in trunk and c not in trunk):
            segs = [x for x in range(S) if head in self.path[x]]
            mk = np.flatnonzero(np.isin(t_used, segs))
            bones = np.flatnonzero(self.sub[mk].any(0)) if mk.size else np.zeros(0, dtype=int)
            cols = np.concatenate([(3 * bones[:, None] + np.arange(3)).ravel(),
                                   (self.nd + 3 * mk[:, None] + np.arange(3)).ravel(), [self.ng]]).astype(int)
            cut = np.flatnonzero(np.diff(cols) != 1) + 1
            starts = np.concatenate([[0], cut])
            ends = np.concatenate([cut, [cols.size]])
            runs = [(int(cols[i]), int(cols[j - 1]) + 1, int(i)) for i, j in zip(starts, ends)]
            self.limbs.append((rows(segs), cols, runs))

    def eliminate(self, D: np.ndarray, X: np.ndarray):
        """Schur complement of a chunk's pose blocks: ``X^T D^-1 X`` summed over its frames.

        D (n, nf, nf) the damped pose blocks, X (n, nf, ng + 1) = [Hfg | bf]. With the trunk's pose
        unknowns last, D = L L^T has L = [[L_A, 0], [W^T, L_C]] (L_A block diagonal over the limbs,
        L_A W = the limbs' blocks with the trunk), and Y = L^-1 X has a limb's rows L_k^-1 X_k on
        that limb's columns only and the trunk's rows L_C^-1 (X_C - W^T Y_A): X^T D^-1 X = Y^T Y
        is then a product over the trunk's dozen rows and a small one for each limb, instead of
        one over all nf rows (a fraction of the work, the same sums). Returns (that (ng+1, ng+1)
        sum, the factors for :meth:`back_substitute`).
        """
        rc = self.trunk
        Dc = D[:, rc[:, None], rc[None, :]]
        Xc = X[:, rc]
        YY = np.zeros((X.shape[2], X.shape[2]))
        parts = []
        for rk, ck, runs in self.limbs:
            Lki = np.linalg.inv(np.linalg.cholesky(D[:, rk[:, None], rk[None, :]]))
            Wk = Lki @ D[:, rk[:, None], rc[None, :]]
            Yk = Lki @ X[:, rk[:, None], ck[None, :]]
            WkT = Wk.transpose(0, 2, 1)
            Dc = Dc - WkT @ Wk
            M = WkT @ Yk
            for a, b, i in runs:  # ck's runs of consecutive columns: slices, not a gather and a scatter
                Xc[:, :, a:b] -= M[:, :, i : i + b - a]
            Y2 = Yk.reshape(-1, ck.size)
            YY[ck[:, None], ck[None, :]] += Y2.T @ Y2
            parts.append((Lki, Wk, Yk))
        Lci = np.linalg.inv(np.linalg.cholesky(Dc))
        Yc = Lci @ Xc
        Y2 = Yc.reshape(-1, X.shape[2])
        YY += Y2.T @ Y2
        return YY, (Lci, Yc, parts)

    def back_substitute(self, factors, dg1: np.ndarray) -> np.ndarray:
        """The pose steps ``-D^-1 X dg1`` (n, nf) from :meth:`eliminate`'s factors: ``-L^-T (Y dg1)``."""
        Lci, Yc, parts = factors
        n = Yc.shape[0]
        out = np.empty((n, self.nf))
        zc = (Lci.transpose(0, 2, 1) @ (Yc @ dg1)[..., None])[..., 0]
        out[:, self.trunk] = -zc
        for (rk, ck, _), (Lki, Wk, Yk) in zip(self.limbs, parts):
            v = Yk @ dg1[ck] - (Wk @ zc[..., None])[..., 0]
            out[:, rk] = -(Lki.transpose(0, 2, 1) @ v[..., None])[..., 0]
        return out

    def offsets(self, origin) -> np.ndarray:  # (S, 3) the bone offsets d of the rest-pose origins (S, 3)
        d = np.zeros((self.S, 3))
        d[self.kids] = np.asarray(origin)[self.kids] - np.asarray(origin)[self.kid_parent]
        return d

    def soft_offsets(self, root, R, d, l) -> tuple[np.ndarray, float]:
        """(p (F, 3 + 3 ns): ``root`` (F, 3) and each frame's soft joints' offsets that minimise its marker residual
        plus their prior at poses ``R``, the offsets' effective number of unknowns over the frames): the markers are
        linear in the offsets, so one solve per frame."""
        p = np.hstack([np.asarray(root, dtype=float), np.zeros((root.shape[0], self.ws.size))])
        if not self.soft:
            return p, 0.0
        JfT, _, _, r = self.jacobian(slice(None), p, R, d, l)
        Jo = JfT[:, self.se]
        N = Jo @ Jo.transpose(0, 2, 1)
        H = N + np.eye(self.ws.size) * self.ws
        p[:, 3:] = -np.linalg.solve(H, Jo @ r.transpose(0, 2, 1).reshape(r.shape[0], -1, 1))[..., 0]
        return p, float(np.trace(np.linalg.solve(H, N), axis1=1, axis2=2).sum())

    def fk(self, p, R, d, l):
        """p (F, 3 + 3 ns): the root's origin, then each soft joint's offset (see ``soft``)."""
        F = p.shape[0]
        P = np.empty((F, self.S, 3))
        G = np.zeros((F, self.S, 3))
        off = {c: d[c] + p[:, 3 + 3 * i : 6 + 3 * i] for i, c in enumerate(self.soft)}
        for s in self.order:
            if self.parent[s] < 0:
                P[:, s] = p[:, :3]
            else:
                G[:, s] = (R[:, self.parent[s]] @ off[s][..., None])[..., 0] if s in off else R[:, self.parent[s]] @ d[s]
                P[:, s] = P[:, self.parent[s]] + G[:, s]
        t = self.seg[self.used]
        x = P[:, t] + np.einsum("fmij,mj->fmi", R[:, t], l[self.used])
        return P, G, x

    def residual(self, p, R, d, l):
        _, _, x = self.fk(p, R, d, l)
        return (x - self.y[:, self.used]) * self.w[:, self.used, None]

    def cost(self, p, R, d, l) -> float:
        r = self.residual(p, R, d, l)
        return float(np.einsum("fmi,fmi->", r, r))

    def jacobian(self, sl, p, R, d, l):
        """The pose Jacobian and residual for frames ``sl``.

        Returns JfT (n, nf, 3U), the pose Jacobian transposed, its residual rows ordered by
        coordinate, then marker (column ``U k + i`` is marker ``i``'s coordinate ``k``); Rw
        (n, U, 3, 3) the weighted rotation that carries each marker's own offset (its Jacobian
        block: it touches only that marker's rows); the blocks hat(u) w (n, E, 3, 3) of JfT,
        one per (marker, segment on its path) (see ``fi``, ``fs``); the residual r (n, U, 3).
        The non-zero blocks are scattered into place, with no loop over markers. The bone
        offsets' Jacobian is not formed: its block for marker ``m`` and joint ``c`` is
        ``R_parent(c) w`` wherever ``c`` is on ``m``'s path (see :meth:`normal_equations`).
        """
        p, R = p[sl], R[sl]
        P, G, x = self.fk(p, R, d, l)
        n = p.shape[0]
        U = self.used.size
        S, nf = self.S, self.nf
        t_all = self.seg[self.used]
        w = self.w[sl][:, self.used]  # (n, U)
        Rw = R[:, t_all] * w[..., None, None]
        own = x - P[:, t_all]  # (n, U, 3): R_t l_m
        u = np.where((self.fn >= 0)[None, :, None], G[:, np.maximum(self.fn, 0)], own[:, self.fi])
        # the rows of marker m in segment s's rotation columns are -hat(u) w, so in JfT hat(u) w
        Hu = _hat(u) * w[:, self.fi, None, None]  # (n, E, 3, 3)
        JfT = np.zeros((n, S + 1 + len(self.soft), 3, 3, U))
        for k in range(3):
            JfT[:, 0, k, k, :] = w
        JfT.reshape(n, -1)[:, self.jac_at] = Hu.reshape(n, -1)
        if self.soft:  # a soft joint's offset moves every marker below it by R_parent times it
            Rs = R[:, self.parent[self.soft]]  # (n, ns, 3, 3)
            JfT[:, S + 1 :] = Rs.transpose(0, 1, 3, 2)[..., None] * (w[:, None, :] * self.below.T[None])[:, :, None, None, :]
        r = (x - self.y[sl][:, self.used]) * w[..., None]
        return JfT.reshape(n, nf, 3 * U), Rw, Hu, r

    def normal_equations(self, sl, p, R, d, l):
        """Per-frame blocks (Hff, X) and the frames' share of (Hgg, bg).

        Unknowns g = (bone offsets, marker offsets); X (n, nf, ng + 1) is [Hfg | bf]. A marker
        offset's Jacobian is the marker's rotation, so its blocks come in closed form: sum_f w R^T R
        is the marker's visible count times I, and its column block of Hfg is the marker's rows
        of Jf (zero outside the root and the segments on its path) times its rotation. A bone
        offset's Jacobian is its parent's rotation on the rows of every marker below it, so its
        blocks come from sums over each joint's subtree (``sub``) instead of a product with the
        mostly zero (3U, nd) Jacobian.
        """
        JfT, Rw, Hu, r = self.jacobian(sl, p, R, d, l)
        n, U = Rw.shape[:2]
        S, nf, nd, ng, nk = self.S, self.nf, self.nd, self.ng, self.nd // 3
        w = self.w[sl][:, self.used]
        Rp = R[sl][:, self.kid_parent]  # (n, nk, 3, 3) each joint's parent rotation
        Hff = JfT @ JfT.transpose(0, 2, 1)
        X = np.empty((n, nf, ng + 1))
        # bone columns: the Jf rows of a joint's subtree summed, times the parent's rotation
        A = (JfT.reshape(n, nf * 3, U) @ self.sub).reshape(n, nf, 3, nk)
        # ... as one product with a block-diagonal matrix of those rotations (rows (axis, joint),
        # columns (joint, axis)): a few wasted zeros, far fewer small products
        BD = np.zeros((n, nd, nd))
        BD[:, self.bd_rows, self.bd_cols] = Rp.transpose(0, 2, 1, 3).reshape(n, -1)
        np.matmul(A.reshape(n, nf, nd), BD, out=X[..., :nd])
        X[..., ng] = (JfT @ r.transpose(0, 2, 1).reshape(n, 3 * U, 1))[..., 0]
        # marker columns: root rows w R_t, a path segment's rows hat(u) w R_t, zero elsewhere
        Xl = X[:, : 3 * (S + 1), nd:ng].reshape(n, S + 1, 3, U, 3)
        Xl[:] = 0.0
        Xl[:, 0] = Rw.transpose(0, 2, 1, 3)
        X.reshape(n, -1)[:, self.xl_at] = (Hu @ Rw[:, self.fi]).reshape(n, -1)
        if self.soft:  # a soft joint's rows: R_parent^T w R_t for each marker below it
            Rs = R[sl][:, self.parent[self.soft]]
            ns = len(self.soft)
            El = (Rs.transpose(0, 1, 3, 2).reshape(n, 3 * ns, 3) @ Rw.transpose(0, 2, 1, 3).reshape(n, 3, 3 * U))
            X[:, 3 * (S + 1) :, nd:ng] = (El.reshape(n, ns, 3, U, 3) * self.below.T[None, :, None, :, None]).reshape(
                n, 3 * ns, 3 * U)
        Hgg = np.zeros((ng, ng))
        # bone-bone: joints c, e share the visible markers below both
        both = (w @ self.sub2.reshape(U, nk * nk)).reshape(n, nk, 1, nk, 1)
        Rs = Rp.transpose(0, 1, 3, 2).reshape(n, nd, 3)  # rows (joint, axis)
        RR = (Rs @ Rs.transpose(0, 2, 1)).reshape(n, nk, 3, nk, 3)
        Hgg[:nd, :nd] = (RR * both).sum(0).reshape(nd, nd)
        # bone-marker: joint c and a marker m below it, sum_f R_parent(c)^T w R_t(m), every pair in
        # one product, then kept where c is on m's path
        Hdl = Rs.transpose(1, 0, 2).reshape(nd, 3 * n) @ Rw.transpose(0, 2, 1, 3).reshape(3 * n, 3 * U)
        Hgg[:nd, nd:] = Hdl * self.sub_mask
        Hgg[nd:, :nd] = Hgg[:nd, nd:].T
        idx = np.arange(nd, ng)
        Hgg[idx, idx] = np.repeat(w.sum(0), 3)
        bg = np.empty(ng)
        bg[:nd] = np.einsum("fcja,fcj->ca", Rp, np.einsum("fmj,mc->fcj", r, self.sub)).reshape(-1)
        bg[nd:] = np.einsum("fmji,fmj->mi", Rw, r).reshape(-1)
        if self.soft:  # the soft joints' offsets: their prior
            Hff[:, self.se, self.se] += self.ws
            X[:, self.se, ng] += self.ws * p[sl][:, 3:]
        return Hff, X, Hgg, bg


def refine_skeleton(
    parent: np.ndarray,
    origin: np.ndarray,
    marker_segment: np.ndarray,
    marker_local: np.ndarray,
    observed: np.ndarray,
    rot: np.ndarray,
    root_pos: np.ndarray,
    *,
    ref_frame: int = 0,
    iterations: int = 30,
    tol: float = 1e-5,
    chunk: int = 128,
    hold_along: dict[int, np.ndarray] | None = None,
    anchor: tuple[np.ndarray, np.ndarray] | None = None,
    prior_weights: np.ndarray | None = None,
    like_bones: list[tuple[int, int, float]] | None = None,
    hold_weights: dict[int, tuple[float, float]] | None = None,
    soft: dict[int, float] | None = None,
    planes: list[tuple[tuple[int, ...], np.ndarray, float]] | None = None,
    lines: list[tuple[int, int, np.ndarray, float, float]] | None = None,
    pose_trust: float = 0.0,
) -> CalibrationResult:
    """Refine a skeleton's constant offsets together with the poses of ``observed``'s frames.

    parent, origin, marker_segment, marker_local : the skeleton (as :func:`~mocapskel.solvers.ik.solve.solve_ik`).
    observed : (F, M, 3) markers (NaN unseen) on a subsample of frames (a few hundred).
    rot, root_pos : (F, S, 3, 3), (F, 3) the starting poses (e.g. IK with the skeleton).
    ref_frame : the frame (index into ``observed``) whose pose becomes the rest pose.
    iterations, tol : Levenberg–Marquardt limits; stops when the cost falls by less than ``tol`` (relative).
    chunk : most frames whose normal equations are formed and eliminated together (on one thread).
    hold_along : {child segment: unit axis (3,) in the rest pose's axes}: joints (hinges) whose position along
        that axis, relative to the marker centroid of each of their two segments, is held where it starts (where
        ``anchor`` has it): relative to the markers, not to the parent's origin, or a chain of hinges about one
        axis (a walk's hip, knee and ankle) slides along it together (a real walk's knee went 90 mm out of the leg);
        its weights are ``hold_weights``.
    anchor : (origin, marker_local) of the skeleton whose joints the prior holds, when the fit starts
        from another (a refinement of it); None: the start.
    prior_weights : (S, 2) the weight (whole fit, not per frame) of the prior that holds child c's joint where it
        starts relative to its parent's marker centroid ([c, 0]) and its own ([c, 1]); a Gaussian of sigma (mm, per
        axis) against marker noise sigma_n weighs sigma_n^2 / sigma^2. None: no prior.
    like_bones : (a, b, weight) for two child segments whose offsets from their parents' origins (their
        parents' bones) should be as long as each other: ``weight`` (whole fit) x the squared difference of
        their lengths, each length linearised along its direction at the start.
    hold_weights : {child segment: (weight relative to its parent's markers, to its own)} for the joints of
        ``hold_along``: the hold's weight for the whole fit, joint by joint (a Gaussian of sigma against marker
        noise sigma_n weighs sigma_n^2 / sigma^2).
    soft : {child segment c: weight per frame}: c's joint is soft: in each frame it may sit off its fixed place in
        the parent's frame by e_cf, weight x |e_cf|^2 (a Gaussian of sigma against marker noise sigma_n weighs
        sigma_n^2 / sigma^2): a joint that is no fixed point (a shoulder on its girdle, a spine's turn over many
        vertebrae) wanders about its place instead of pulling its segments' poses. The result's offsets are the
        fixed places.
    planes : (children, unit normal at rest, weight): the mean of those children's joints lies in the plane through
        their (common) parent's marker centroid, normal to that: weight (whole fit) x its squared distance from it.
    lines : (k, j, unit axis u at rest, t, weight): joint k (a knee: child segment k) lies, along u, where the line
        from its parent's joint (the hip) to its child j's joint (the ankle) passes at the fraction t of the way:
        weight (whole fit) x ((1 - t) u . d_k - t u . d_j)^2, d the joints' offsets from their parents' origins.
    pose_trust : rad; a frame whose step turned a segment more than this (beyond where a turn is about linear in its
        rotation vector) has its damping multiplied by 4 for the next step, and halved back towards the common
        damping after a step within it: one frame whose pose is nearly free (a segment of two markers whose twist
        its joints hardly fix) no longer holds the whole fit's damping high. 0: one damping for every frame.
    """
    parent = np.asarray(parent)
    S = len(parent)
    F = observed.shape[0]
    soft_c = [int(c) for c in sorted(soft or {}) if parent[int(c)] >= 0 and soft[c] > 0]
    pr = _Problem(parent, np.asarray(marker_segment), observed, soft_c, [float(soft[c]) for c in soft_c])
    ws = pr.ws
    p = np.hstack([np.asarray(root_pos, dtype=float), np.zeros((F, ws.size))])
    R = np.array(rot, dtype=float)
    d = pr.offsets(origin)
    l = np.array(marker_local, dtype=float)
    nf, ng = pr.nf, pr.ng
    W = max(pr.w.sum(), 1.0)
    held = [(int(c), np.asarray(a, dtype=float) / np.linalg.norm(a)) for c, a in (hold_along or {}).items()
            if parent[int(c)] >= 0]
    if held and hold_weights is None:
        raise ValueError("hold_along needs hold_weights")
    A = np.zeros((0, ng)) if prior_weights is None else _joint_prior_operator(
        pr, parent, weights=np.asarray(prior_weights, dtype=float))
    # the held joints' positions along their axes relative to each of their segments' marker centroids
    rows = []
    for c, a in held:
        wc = np.zeros((S, 2))
        wc[c] = hold_weights[c]
        Ac = _joint_prior_operator(pr, parent, {c}, weights=wc)
        rows.extend(a @ Ac[k : k + 3] for k in range(0, Ac.shape[0], 3))
    Hh = np.array(rows).reshape(-1, ng)
    if anchor is None:
        g0 = _pack(pr, d, l)
    else:
        a_origin, a_local = (np.asarray(x, dtype=float) for x in anchor)
        g0 = _pack(pr, pr.offsets(a_origin), a_local)
    u0 = A @ g0 if A.shape[0] else np.zeros(0)
    h0 = Hh @ g0
    T = tie_rows(pr, d, like_bones, planes, lines)

    def total(p_, R_, d_, l_) -> float:
        c = pr.cost(p_, R_, d_, l_) + float(np.sum(ws * p_[:, 3:] ** 2))
        if Hh.shape[0]:
            r = Hh @ _pack(pr, d_, l_) - h0
            c += float(r @ r)
        if A.shape[0]:
            r = A @ _pack(pr, d_, l_) - u0
            c += float(r @ r)
        if T.shape[0]:
            r = T @ _pack(pr, d_, l_)
            c += float(r @ r)
        return c

    c0 = total(p, R, d, l)
    # gauge: the root's origin is fixed in the root by one of its joints (or markers)
    rk0 = [c for c in pr.kids if parent[c] == pr.root]
    fix_g = np.zeros(ng, dtype=bool)
    if rk0:
        fix_g[pr.gi[rk0[0]] : pr.gi[rk0[0]] + 3] = True
    else:
        m0 = [int(m) for m in pr.used if marker_segment[m] == pr.root]
        if m0:
            fix_g[pr.gl[m0[0]] : pr.gl[m0[0]] + 3] = True
    # an even number of equal chunks of at most ``chunk`` frames: two threads (or four) get equal
    # shares (128 + 49 frames kept one core idle most of every iteration); the split depends on F only
    n_chunks = 2 * -(-F // (2 * chunk))
    cut = np.linspace(0, F, n_chunks + 1).round().astype(int)
    chunks = [slice(int(a), int(b)) for a, b in zip(cut[:-1], cut[1:]) if b > a]
    store: dict[int, list] = {}  # each chunk's (Hff, X, elimination factors), in the process that owns it

    def work(j: int, msg: tuple):
        """Chunk ``j``'s part of an iteration, in the process that owns it: (0, p, R, d, l) forms its
        normal equations and returns its share of (Hgg, bg); (1, lam) eliminates its poses with that
        damping and returns its Y^T Y; (2, dg1, lam) returns its pose steps and their share of the
        predicted decrease."""
        sl = chunks[j]
        if msg[0] == 0:
            Hff, X, Hgg_f, bg_f = pr.normal_equations(sl, *msg[1:])
            _hold_reference(Hff, X, sl, ref_frame, S)
            X[:, :, :ng][:, :, fix_g] = 0.0
            store[j] = [Hff, X, None]
            return Hgg_f, bg_f
        Hff, X, factors = store[j]
        if msg[0] == 1:
            # D = L L^T: with Y = L^-1 [Hfg | bf], Hgf D^-1 Hfg = Yg^T Yg and Hgf D^-1 bf = Yg^T Yb,
            # both from Y^T Y over the chunk's frames (see _Problem.eliminate)
            D = Hff + (msg[1] * msg[2][:, None, None] * np.diagonal(Hff, axis1=1, axis2=2)[..., None] + 1e-9) * np.eye(nf)
            YtY, store[j][2] = pr.eliminate(D, X)
            return YtY
        _, dg1_, lam_, k_ = msg
        lam_ = lam_ * k_[:, None]  # each frame's damping
        h = pr.back_substitute(factors, dg1_)
        # the chunk's share of the decrease the damped linear model predicts (below)
        return h, float(np.einsum("fi,fi->", h, (lam_ * np.diagonal(Hff, axis1=1, axis2=2) + 1e-9) * h - X[..., ng]))

    def iterate(processes: int | None) -> tuple:
        """Levenberg-Marquardt from the start, the chunks shared among ``processes`` (None: as many as
        the cores allow): the final (p, R, d, l, cost) and the iterations taken."""
        p, R, d, l, cost = p0, R0, d0, l0, c0
        lam, nu = 1e-4, 2.0
        kf = np.ones(F)  # each frame's damping, a multiple of lam
        store.clear()
        it = 0
        system = None
        with Shares(work, len(chunks), processes) as shares:
            for it in range(1, iterations + 1):
                if system is None:
                    Hgg = np.zeros((ng, ng))
                    bg = np.zeros(ng)
                    for Hgg_f, bg_f in shares.call([(0, p, R, d, l)] * len(chunks)):  # summed in chunk order
                        Hgg += Hgg_f
                        bg += bg_f
                    if Hh.shape[0]:
                        Hgg += Hh.T @ Hh
                        bg += Hh.T @ (Hh @ _pack(pr, d, l) - h0)
                    if A.shape[0]:
                        Hgg += A.T @ A
                        bg += A.T @ (A @ _pack(pr, d, l) - u0)
                    if T.shape[0]:
                        Hgg += T.T @ T
                        bg += T.T @ (T @ _pack(pr, d, l))
                    Hgg[fix_g, :] = 0.0
                    Hgg[:, fix_g] = 0.0
                    Hgg[fix_g, fix_g] = 1.0
                    bg[fix_g] = 0.0
                    system = (Hgg, bg)
                Hgg, bg = system
                while True:
                    Sg = Hgg + np.diag(lam * np.diag(Hgg) + 1e-9)
                    rhs = -bg.copy()
                    for YtY in shares.call([(1, lam, kf[c_]) for c_ in chunks]):  # summed in chunk order
                        Sg -= YtY[:ng, :ng]
                        rhs += YtY[:ng, ng]
                    dg = np.linalg.solve(Sg, rhs)
                    dg1 = np.append(dg, 1.0)
                    steps = shares.call([(2, dg1, lam, kf[c_]) for c_ in chunks])
                    df = np.concatenate([h for h, _ in steps])
                    p1 = p + np.hstack([df[:, :3], df[:, 3 + 3 * S :]])
                    R1 = _exp(df[:, 3 : 3 + 3 * S].reshape(F, S, 3)) @ R
                    d1, l1 = _step(pr, d, l, dg)
                    c1 = total(p1, R1, d1, l1)
                    # the decrease the damped linear model predicts, h^T (lam diag(H) h - b) (Madsen, Nielsen &
                    # Tingleff 2004, eq. 3.10, for a cost of sum r^2 and b = J^T r)
                    pred = float(dg @ ((lam * np.diag(Hgg) + 1e-9) * dg - bg))
                    for _, share in steps:
                        pred += share
                    if c1 < cost:
                        break
                    lam *= nu  # Nielsen's update: a growing factor while steps fail
                    nu *= 2.0
                    if lam > 1e8:
                        c1 = cost
                        break
                if c1 >= cost:
                    break
                rel = (cost - c1) / max(cost, 1e-300)
                rho = (cost - c1) / pred if pred > 0 else 1.0
                p, R, d, l, cost = p1, R1, d1, l1, c1
                system = None
                if pose_trust > 0:  # a frame that turned beyond its trust region is damped four times more next step
                    turn = np.linalg.norm(df[:, 3 : 3 + 3 * S].reshape(F, S, 3), axis=-1).max(1)
                    kf = np.where(turn > pose_trust, 4.0 * kf, np.maximum(0.5 * kf, 1.0))
                lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-9)
                nu = 2.0
                if rel < tol:
                    break
        return p, R, d, l, cost, it

    p0, R0, d0, l0 = p, R, d, l
    try:
        # no iteration (the cost at the start only): no worker processes to fork
        p, R, d, l, cost, it = iterate(None) if iterations > 0 else (p, R, d, l, c0, 0)
    except WorkerLost:
        # a lost worker process (killed, out of memory): the whole fit again in this process alone,
        # which gives the same result
        p, R, d, l, cost, it = iterate(1)
    objective = float(cost)
    cost = pr.cost(p, R, d, l)  # the markers' part (without the penalty of held axes)
    p = p[:, :3].copy()  # the root's origin; the soft joints' offsets about their fixed places are not kept
    # fix the gauge: identity rotations at the reference frame, the root's origin among its children
    Q = R[ref_frame].copy()  # (S, 3, 3)
    R = R @ np.swapaxes(Q, -1, -2)[None]
    for c in pr.kids:
        d[c] = Q[parent[c]] @ d[c]
    for m in pr.used:
        l[m] = Q[marker_segment[m]] @ l[m]
    root = pr.root
    rk = [c for c in pr.kids if parent[c] == root]
    if rk:
        v = d[rk].mean(0)
        d[rk] -= v
        for m in pr.used:
            if marker_segment[m] == root:
                l[m] -= v
        p = p + R[:, root] @ v
    new_origin = np.array(origin, dtype=float).copy()
    new_origin[root] = p[ref_frame]  # the rest pose is the subject as seen at the reference frame
    for s in pr.order:
        if parent[s] >= 0:
            new_origin[s] = new_origin[parent[s]] + d[s]
    return CalibrationResult(
        origin=new_origin, marker_local=l, rot=R, root_pos=p,
        rms=(float(np.sqrt(c0 / W)), float(np.sqrt(cost / W))), n_iter=it, objective=objective,
    )


def _hold_reference(Hff: np.ndarray, X: np.ndarray | None, sl: slice, ref_frame: int, S: int) -> None:
    """The reference frame's ``S`` rotations held in the pose blocks of frames ``sl`` (the gauge of the segments'
    frames), in place; a soft joint's offsets there stay free."""
    if sl.start <= ref_frame < sl.stop:
        i, rot = ref_frame - sl.start, slice(3, 3 + 3 * S)
        Hff[i, rot, :] = 0.0
        Hff[i, :, rot] = 0.0
        Hff[i, rot, rot] = np.eye(3 * S)
        if X is not None:
            X[i, rot] = 0.0


def _pack(pr: _Problem, d: np.ndarray, l: np.ndarray) -> np.ndarray:
    """The constant unknowns (bone offsets, then used markers' offsets) as one vector."""
    return np.concatenate([np.asarray(d)[pr.kids].ravel(), np.asarray(l)[pr.used].ravel()])


def _step(pr: _Problem, d: np.ndarray, l: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``d`` and ``l`` moved by ``g``, a step of the constant unknowns laid out as :func:`_pack` lays them."""
    d1, l1 = np.array(d, dtype=float), np.array(l, dtype=float)
    d1[pr.kids] += g[: pr.nd].reshape(-1, 3)
    l1[pr.used] += g[pr.nd : pr.ng].reshape(-1, 3)
    return d1, l1


def _joint_prior_operator(pr: _Problem, parent: np.ndarray, only: set | None = None,
                          weights: np.ndarray | None = None) -> np.ndarray:
    """(3K, ng) linear map from the constant unknowns to every joint's position relative to the
    marker centroid of each of its two segments (in that segment's frame).

    In the parent ``p``'s frame the joint of child ``c`` sits at ``d_c`` from ``p``'s origin,
    so ``d_c - mean(l_m, m in p)``; in ``c``'s frame it is ``c``'s origin, ``-mean(l_m, m in c)``.
    weights : (S, 2) each block of three rows scaled by the square root of child ``c``'s weight in its
    parent's frame ([c, 0]) or its own ([c, 1]), blocks of weight 0 left out.
    """
    rows = []
    for c in pr.kids:
        if only is not None and c not in only:
            continue
        p = int(parent[c])
        for j, (s, with_d) in enumerate(((p, True), (c, False))):
            ms = [int(m) for m in pr.used if pr.seg[m] == s]
            w = 1.0 if weights is None else float(weights[c, j])
            if not ms or not w > 0:
                continue
            for k in range(3):
                row = np.zeros(pr.ng)
                if with_d:
                    row[pr.gi[c] + k] = 1.0
                for m in ms:
                    row[pr.gl[m] + k] -= 1.0 / len(ms)
                rows.append(np.sqrt(w) * row)
    return np.array(rows).reshape(-1, pr.ng)
