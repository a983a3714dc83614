"""The IK problem's structure: the skeleton's tree in breadth-first order and the
marker model with its Gauss-Newton kernels (gradient, elimination leaves first, solve)."""
from __future__ import annotations

import numpy as np

from .planes import _c_cross, _c_dot, _c_hat, _c_inv3_sym, _c_mm, _c_mmt, _c_mtv, _c_mv, _push


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

    def reach(self, scale: float) -> np.ndarray:
        """(S,) how far a turn of each segment moves what it carries: the farthest of its markers and
        its children's origins from its own origin; ``scale`` for a segment that carries neither."""
        r = np.sqrt((self.lp**2).sum(1)).max(0)
        bone = np.sqrt((self.off**2).sum(0))
        np.maximum.at(r, self.t.par[1:], bone[1:])
        return np.where(r > 0, r, scale)

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
