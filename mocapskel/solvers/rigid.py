"""Rigid alignment: batched weighted Kabsch/Horn and generalised Procrustes.

All functions are vectorised over frames (time is the first axis) and never
raise for a frame that cannot be solved: such a frame gets NaN rotation,
translation and rms instead. :func:`shape_poses` is :func:`kabsch` for the
common case of one fixed shape and unit weights, several times faster on
long takes.
"""
from __future__ import annotations

import numpy as np

__all__ = ["kabsch", "shape_poses", "procrustes_shape", "beyond_hull"]

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


def shape_poses(
    shape: np.ndarray,
    obs: np.ndarray,
    *,
    collinear_tol: float = COLLINEAR_TOL,
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of one rigid point shape in every frame: ``kabsch(shape, obs)`` without the rms, faster.

    The same problem and result (to rounding) as :func:`kabsch` with one
    reference shape and unit weights: ``obs[f] ~ R[f] @ shape + t[f]`` over
    the points seen in frame ``f``. The work is laid out for long takes: in
    blocks of frames, one matrix product gives the centroids and
    cross-covariances of all frames that see the whole shape, and the
    rotation comes from Horn's quaternion matrix by the quaternion
    characteristic polynomial (Theobald 2005: its coefficients in closed
    form, Newton's method from the upper bound ``(G_a + G_b) / 2`` on the
    largest eigenvalue, the eigenvector from a column of the adjugate), all
    on per-frame component arrays. Frames missing some points are solved
    the same way with masked sums; frames whose largest eigenvalue is not well
    apart from the next (nearly collinear points) by :func:`kabsch`'s solver.
    Shapes of more than 20 points go to :func:`kabsch`.

    Parameters
    ----------
    shape : (P, 3) ndarray
        The shape; NaN rows are left out.
    obs : (F, P, 3) ndarray
        Observed points; NaN where a point is not seen.
    collinear_tol : float, optional
        As in :func:`kabsch`.

    Returns
    -------
    R : (F, 3, 3) ndarray
        Rotations; NaN for frames with fewer than 3 usable, non-collinear points.
    t : (F, 3) ndarray
        Translations; NaN likewise.
    """
    obs = np.asarray(obs, dtype=float)
    shape = np.asarray(shape, dtype=float)
    if obs.ndim != 3 or obs.shape[-1] != 3:
        raise ValueError(f"obs must be (F, P, 3), got {obs.shape}")
    F, P, _ = obs.shape
    if shape.shape != (P, 3):
        raise ValueError(f"shape must be ({P}, 3), got {shape.shape}")
    if P > 20:
        R, t, _ = kabsch(shape, obs, collinear_tol=collinear_tol)
        return R, t
    have = np.isfinite(shape).all(1)
    nh = int(have.sum())
    if not _solvable(shape, have[None].astype(float), collinear_tol)[0]:
        return np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan)  # no subset of the shape can be solved either
    R = np.empty((F, 3, 3))  # every frame is written below
    t = np.empty((F, 3))
    a0 = shape[have].mean(0)
    a = np.where(have[:, None], shape - a0, 0.0)  # centred, so that H below has no cancellation
    # frames seeing the whole shape: X @ M gives the 9 components of H = sum (a - ca)(b - cb)^T
    # (row-major) and the centroid cb, for all frames of a block in one product
    cols = np.flatnonzero(np.repeat(have, 3))
    ah = a[have]
    ca = ah.mean(0)
    M = np.zeros((nh, 3, 12))
    for k in range(3):
        M[:, k, k:9:3] = ah - ca
        M[:, k, 9 + k] = 1.0 / nh
    Mt = M.reshape(3 * nh, 12).T
    ga = float(((ah - ca) ** 2).sum())
    Y = np.empty((12, min(F, _BLOCK)))
    step = max(64, _SMALL_PRODUCT // (36 * nh))
    redo, part = [], []
    for lo in range(0, F, _BLOCK):
        hi = min(lo + _BLOCK, F)
        X = obs[lo:hi].reshape(hi - lo, 3 * P)
        if nh < P:
            X = X[:, cols]
        Yb = Y[:, : hi - lo]
        with np.errstate(invalid="ignore", over="ignore"):  # frames with a missing point (inf - inf): solved below
            for c in range(0, hi - lo, step):  # products small enough for BLAS to stay on this thread
                Yb[:, c : c + step] = Mt @ X[c : c + step].T
            cb = Yb[9:]
            gb = np.einsum("fi,fi->f", X, X) - nh * np.einsum("if,if->f", cb, cb)
        q, lam, apart, col0 = _qcp(Yb[:9], 0.5 * (ga + gb))
        Rb = _quat_to_matrix(q, R[lo:hi])
        t[lo:hi] = cb.T - _rotate(Rb, ca + a0)
        fin = np.isfinite(lam)
        r = np.flatnonzero(~(apart & col0) & fin)
        if r.size:
            redo.append((lo + r, Yb[:, r], np.where(apart[r], lam[r], np.nan)))
        if not fin.all():
            part.append(lo + np.flatnonzero(~fin))
    if redo:  # nearly a half-turn from the shape's pose (a small quaternion w), or not certified
        idx, Yr, lam = (np.concatenate(x, axis=-1) for x in zip(*redo))
        R[idx] = Rr = _redo_rotations(Yr[:9], lam)
        t[idx] = Yr[9:].T - _rotate(Rr, ca + a0)
    # frames missing points of the shape: masked sums, where the visible points can be solved
    if part:
        _partial_poses(np.concatenate(part), obs, shape, have, a, a0, collinear_tol, R, t)
    return R, t


#: Frames per block in :func:`shape_poses` (the per-frame temporaries stay in cache).
_BLOCK = 8192

#: Matrix products of long stacks are cut into pieces below OpenBLAS's thresholds for
#: threads (m n k <= 2^18 multiply-adds for a product of matrices, m n <= 9216 for a
#: matrix and a vector): its threads cost more than they bring for these thin products,
#: and much more on a busy machine.
_SMALL_PRODUCT = 1 << 18
_SMALL_GEMV = 9216


def _rotate(R: np.ndarray, x: np.ndarray) -> np.ndarray:
    """R[f] @ x for all frames (R (F, 3, 3), x (3,)) -> (F, 3), as matrix-vector products of the (3F, 3) stack.

    Callers set frames with an unknown R to NaN themselves (whether a NaN in R
    reaches the product where x has a zero is up to BLAS).
    """
    A = R.reshape(-1, 3)
    rows = _SMALL_GEMV // 3
    if A.shape[0] <= rows:
        return (A @ x).reshape(-1, 3)
    out = np.empty(A.shape[0])
    for lo in range(0, A.shape[0], rows):
        np.dot(A[lo : lo + rows], x, out=out[lo : lo + rows])
    return out.reshape(-1, 3)


def _partial_poses(part, obs, shape, have, a, a0, collinear_tol, R, t) -> None:
    """R[part], t[part] for frames missing points of the shape: masked sums over the visible points
    (NaN where they cannot be solved). ``a`` is the shape centred by ``a0``."""
    P = a.shape[0]
    R[part] = np.nan
    t[part] = np.nan
    seen = np.isfinite(obs[part].sum(-1)) & have
    pats, inv = np.unique(seen @ (1 << np.arange(P)), return_inverse=True)
    good = _solvable(shape, ((pats[:, None] >> np.arange(P)) & 1).astype(float), collinear_tol)[inv.reshape(-1)]
    part, seen = part[good], seen[good]
    K = np.zeros((P, 3, 3, 3))  # H (9 components) = b (3P) @ K: H_jk = sum_p a_pj b_pk
    for k in range(3):
        K[:, k, :, k] = a
    K = K.reshape(3 * P, 9)
    step = max(64, _SMALL_PRODUCT // (27 * P))
    for lo in range(0, part.size, step):
        sl, sn = part[lo : lo + step], seen[lo : lo + step]
        ws = sn.astype(float)
        W = ws.sum(1)
        b = np.where(sn[..., None], obs[sl], 0.0)
        cb = b.sum(1) / W[:, None]
        b -= cb[:, None, :]
        b[~sn] = 0.0
        cw = (ws @ a) / W[:, None]  # centroid of the seen part of the (centred) shape
        bf = b.reshape(-1, 3 * P)
        Ht = np.ascontiguousarray((bf @ K).T)  # sum_p w a_p (b_p - cb)^T = sum_p w (a_p - cw)(b_p - cb)^T
        G = ws @ (a * a).sum(1) - W * (cw * cw).sum(1) + np.einsum("fi,fi->f", bf, bf)
        q, lam, apart, col0 = _qcp(Ht, 0.5 * G)
        Rp = _quat_to_matrix(q)
        r = np.flatnonzero(~(apart & col0))
        if r.size:
            Rp[r] = _redo_rotations(Ht[:, r], np.where(apart[r], lam[r], np.nan))
        R[sl] = Rp
        t[sl] = cb - np.einsum("fij,fj->fi", Rp, cw + a0)


def _solvable(shape: np.ndarray, w: np.ndarray, collinear_tol: float) -> np.ndarray:
    """Which 0/1 weightings w (n, P) of the points of ``shape`` (P, 3) kabsch can solve (its test)."""
    pts = np.where(np.isfinite(shape), shape, 0.0)
    W = w.sum(1)
    c = (w @ pts) / np.maximum(W, 1.0)[:, None]
    dev = (pts[None] - c[:, None, :]) * w[..., None]
    lam = np.linalg.eigvalsh(np.swapaxes(dev, 1, 2) @ dev)
    return (W >= 3) & (lam[:, 1] > (collinear_tol**2) * lam[:, 2]) & (lam[:, 2] > 0)


def _redo_rotations(Ht: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Rotations (n, 3, 3) for the frames :func:`_qcp` leaves: ``lam`` its eigenvalue, NaN where not certified.

    With a certified eigenvalue, the column of adj(N - lam I) with the largest
    diagonal entry (its quaternion component is at least 1/2, so it is exact
    to rounding); otherwise :func:`_best_rotation` (polished, SVD fallback).
    """
    R = np.empty((lam.size, 3, 3))
    ok = np.isfinite(lam)
    if ok.any():
        n00, n11, n22, n33, n01, n02, n03, n12, n13, n23 = _horn(Ht[:, ok])
        lm = lam[ok]
        B, _ = _adj4([[n00 - lm, n01, n02, n03], [n01, n11 - lm, n12, n13],
                      [n02, n12, n22 - lm, n23], [n03, n13, n23, n33 - lm]])
        k = np.argmax(np.abs(np.stack([B[i][i] for i in range(4)])), axis=0)
        q = np.stack([np.choose(k, B[i]) for i in range(4)])
        R[ok] = _quat_to_matrix(q / np.sqrt(np.einsum("in,in->n", q, q)))
    if not ok.all():
        R[~ok] = _best_rotation(np.ascontiguousarray(Ht[:, ~ok].T).reshape(-1, 3, 3))
    return R


def _horn(Ht: np.ndarray) -> tuple[np.ndarray, ...]:
    """The 10 distinct entries of Horn's symmetric 4x4 matrix N (as in _best_rotation) from H's components."""
    Sxx, Sxy, Sxz, Syx, Syy, Syz, Szx, Szy, Szz = Ht
    return (Sxx + Syy + Szz, Sxx - Syy - Szz, Syy - Sxx - Szz, Szz - Sxx - Syy,
            Syz - Szy, Szx - Sxz, Sxy - Syx, Sxy + Syx, Szx + Sxz, Syz + Szy)


def _qcp(Ht: np.ndarray, lam0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Quaternions of the rotations maximising tr(R H) by the characteristic polynomial (Theobald 2005).

    The largest eigenvalue ``lam`` of Horn's matrix N is the largest root of
    ``l^4 + c2 l^2 + c1 l + c0`` with ``c2 = -2 |H|^2``, ``c1 = -8 det H``,
    ``c0 = det N``, found by Newton's method from ``lam0``; the eigenvector is
    the first column of adj(N - lam I), ``q q_w prod_i (lam_i - lam)``, or
    the second, ``q q_x prod_i (lam_i - lam)``, where |q_x| > |q_w|.
    Returns (q (4, n) unit, scalar first; lam (n,); apart: the top eigenvalue
    is settled and well apart from the others, so that its eigenvector is exact
    to rounding; col0: also the column's component max(|q_w|, |q_x|) >= 1/4,
    so that the column gives it to rounding). Where not ``apart & col0`` the
    quaternion is arbitrary.
    """
    Sxx, Sxy, Sxz, Syx, Syy, Syz, Szx, Szy, Szz = Ht
    n00, n11, n22, n33, n01, n02, n03, n12, n13, n23 = _horn(Ht)
    c2 = -2.0 * np.einsum("in,in->n", Ht, Ht)
    c1 = -8.0 * (Sxx * (Syy * Szz - Syz * Szy) - Sxy * (Syx * Szz - Syz * Szx) + Sxz * (Syx * Szy - Syy * Szx))
    # det N by the 2x2 minors of its rows 0, 1 (s) and 2, 3 (m)
    s0 = n00 * n11 - n01 * n01
    s1 = n00 * n12 - n01 * n02
    s2 = n00 * n13 - n01 * n03
    s3 = n01 * n12 - n11 * n02
    s4 = n01 * n13 - n11 * n03
    s5 = n02 * n13 - n12 * n03
    m0 = n02 * n13 - n03 * n12
    m1 = n02 * n23 - n03 * n22
    m2 = n02 * n33 - n03 * n23
    m3 = n12 * n23 - n13 * n22
    m4 = n12 * n33 - n13 * n23
    m5 = n22 * n33 - n23 * n23
    c0 = s0 * m5 - s1 * m4 + s2 * m3 + s3 * m2 - s4 * m1 + s5 * m0
    lam = lam0.copy()
    c2x2 = 2.0 * c2
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for it in range(12):
            l2 = lam * lam
            step = ((l2 + c2) * l2 + c1 * lam + c0) / ((4.0 * l2 + c2x2) * lam + c1)
            lam -= step
            if it >= 2:
                rel = np.abs(step) / lam
                if np.fmax.reduce(rel) <= 1e-14:  # (frames gone NaN are not waited for)
                    break
        dP = (4.0 * lam * lam + c2x2) * lam + c1  # prod_i (lam - lam_i)
        apart = (rel <= 1e-14) & (lam > 0) & (dP > 0.1 * lam * lam * lam)
        # the first two columns of adj(N - lam I) (as _adj4), from the 2x2 minors of its rows 2 and 3
        a00, a11, a22, a33 = n00 - lam, n11 - lam, n22 - lam, n33 - lam
        k5 = a22 * a33 - n23 * n23
        k4 = n12 * a33 - n13 * n23
        k3 = n12 * n23 - n13 * a22
        k2 = n02 * a33 - n03 * n23
        k1 = n02 * n23 - n03 * a22
        q = np.empty((4,) + lam.shape)
        q[0] = a11 * k5 - n12 * k4 + n13 * k3
        q[1] = n12 * k2 - n01 * k5 - n13 * k1
        q[2] = n01 * k4 - a11 * k2 + n13 * m0
        q[3] = a11 * k1 - n01 * k3 - n12 * m0
        b11 = a00 * k5 - n02 * k2 + n03 * k1
        x = np.abs(b11) > np.abs(q[0])  # the second column is the longer: |q_x| > |q_w|
        if x.any():
            q[0] = np.where(x, n02 * k4 - n01 * k5 - n03 * k3, q[0])
            q[1] = np.where(x, b11, q[1])
            q[2] = np.where(x, n01 * k2 - a00 * k4 - n03 * m0, q[2])
            q[3] = np.where(x, a00 * k3 - n01 * k1 + n02 * m0, q[3])
            diag = np.where(x, b11, q[0])
        else:
            diag = q[0]
        nq = np.sqrt(np.einsum("in,in->n", q, q))
        col0 = np.abs(diag) >= 0.25 * nq  # its component >= 1/4: the rounding error grows as 1 / that
        q /= nq
    return q, lam, apart, col0


def _quat_to_matrix(q: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Unit quaternions (4, n), scalar first -> rotation matrices (n, 3, 3) (into ``out`` when given)."""
    w, x, y, z = q
    R = np.empty((q.shape[1], 3, 3)) if out is None else out
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    R[:, 0, 0] = ww + xx - yy - zz
    R[:, 1, 1] = ww - xx + yy - zz
    R[:, 2, 2] = ww - xx - yy + zz
    xy, wz, xz, wy, yz, wx = x * y, w * z, x * z, w * y, y * z, w * x
    R[:, 0, 1] = 2 * (xy - wz)
    R[:, 1, 0] = 2 * (xy + wz)
    R[:, 0, 2] = 2 * (xz + wy)
    R[:, 2, 0] = 2 * (xz - wy)
    R[:, 1, 2] = 2 * (yz - wx)
    R[:, 2, 1] = 2 * (yz + wx)
    return R


def procrustes_shape(
    obs: np.ndarray,
    ref_frame: int | None = None,
    iters: int = 5,
    *,
    collinear_tol: float = COLLINEAR_TOL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Constant point shape that best fits every frame (generalised Procrustes).

    Points may be missing in some frames. The shape starts as the observation
    at the start frame; every iteration aligns all frames to the current shape
    (:func:`kabsch`), brings them back into the shape's frame and averages each
    point over the frames where it is seen and the frame could be aligned.
    Points missing from the start frame are thus filled in from other frames
    (frames sharing fewer than 3 points with the current shape join at a later
    iteration; the alignments are :func:`shape_poses`). Finally the shape is moved rigidly onto the observation at
    ``ref_frame``, so that it is that frame's pose up to noise.

    Parameters
    ----------
    obs : (F, P, 3) ndarray
        Observed points, NaN where not seen.
    ref_frame : int, optional
        The frame whose pose the shape takes. Default: the frame with the most
        visible points (the first such frame). When ``ref_frame`` cannot be
        aligned (fewer than 3 usable points), the iteration starts from the
        frame with the most visible points and the shape keeps that frame's pose.
    iters : int, optional
        Number of align-and-average iterations (stops early once the shape
        no longer changes).
    collinear_tol : float, optional
        Passed to :func:`kabsch`.

    Returns
    -------
    shape : (P, 3) ndarray
        The shape; NaN rows for points never seen in an aligned frame.
        All NaN when no frame has 3 non-collinear visible points.
    R : (F, 3, 3) ndarray
        Per-frame rotation with ``obs[f] ~ R[f] @ shape + t[f]``; NaN for
        frames that cannot be aligned.
    t : (F, 3) ndarray
        Per-frame translation; NaN likewise.
    rms : (F,) ndarray
        Per-frame rms residual; NaN likewise.
    """
    obs = np.asarray(obs, dtype=float)
    if obs.ndim != 3 or obs.shape[-1] != 3:
        raise ValueError(f"obs must be (F, P, 3), got {obs.shape}")
    F, P, _ = obs.shape
    if F == 0:
        raise ValueError("obs has no frames")
    vis = np.isfinite(obs).all(-1)
    n_vis = vis.sum(1)
    best = int(np.argmax(n_vis))
    if ref_frame is not None:
        ref_frame = int(ref_frame)
        if not -F <= ref_frame < F:
            raise ValueError(f"ref_frame {ref_frame} out of range for {F} frames")
        ref_frame %= F

    def solvable(f: int) -> bool:
        pts = obs[f][vis[f]]
        if len(pts) < 3:
            return False
        lam = np.linalg.eigvalsh(np.cov(pts.T, bias=True))
        return bool(lam[2] > 0 and lam[1] > collinear_tol**2 * lam[2])

    start = ref_frame if ref_frame is not None and solvable(ref_frame) else best
    nan_out = (
        np.full((P, 3), np.nan),
        np.full((F, 3, 3), np.nan),
        np.full((F, 3), np.nan),
        np.full(F, np.nan),
    )
    if not solvable(start):
        return nan_out

    shape = np.where(vis[start][:, None], obs[start], np.nan)
    for _ in range(max(int(iters), 1)):
        R, t = shape_poses(shape, obs, collinear_tol=collinear_tol)  # kabsch's poses, faster
        ok = np.isfinite(R[:, 0, 0])
        Rk, tk = R[ok], t[ok]
        # back into the shape's frame: R^T (obs - t)
        back = np.einsum("fji,fpj->fpi", Rk, obs[ok] - tk[:, None, :])
        m = vis[ok]
        cnt = m.sum(0)
        tot = np.where(m[..., None], back, 0.0).sum(0)
        new = np.where(cnt[:, None] > 0, tot / np.maximum(cnt, 1)[:, None], np.nan)
        seen = np.isfinite(new[:, 0])
        # keep the previous estimate of points not seen in any aligned frame
        new = np.where(seen[:, None], new, shape)
        both = np.isfinite(new[:, 0]) & np.isfinite(shape[:, 0])
        same_support = np.array_equal(np.isfinite(new[:, 0]), np.isfinite(shape[:, 0]))
        change = np.abs(new[both] - shape[both]).max() if both.any() else np.inf
        scale = np.abs(new[both]).max() if both.any() else 1.0
        shape = new
        if same_support and change <= 1e-13 * max(scale, 1.0):
            break

    # put the shape into the pose of the reference frame
    anchor = ref_frame if ref_frame is not None and solvable(ref_frame) else start
    R0, t0, _ = kabsch(shape, obs[anchor][None], collinear_tol=collinear_tol)
    if np.isfinite(R0[0, 0, 0]):
        shape = shape @ R0[0].T + t0[0]
    R, t, rms = kabsch(shape, obs, collinear_tol=collinear_tol)
    return shape, R, t, rms


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


def beyond_hull(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """How far each of ``queries`` (Q, 3) lies outside the convex hull of ``points`` (N, 3) (NaN rows
    left out): its distance beyond the hull's farthest facet plane, negative inside. A lower bound
    of the distance to the hull, exact where the nearest point of the hull lies on a facet. All
    -inf when fewer than 5 points or all in a plane (no inside to be outside of)."""
    P = points[np.isfinite(points).all(1)]
    q = np.asarray(queries, dtype=float).reshape(-1, 3)
    planes = hull_planes(P) if len(P) >= 5 else None
    if planes is None:
        return np.full(len(q), -np.inf)
    return (q @ planes[:, :3].T + planes[:, 3]).max(axis=1)


#: Points nearer a facet plane than this fraction of the points' size count as on it (the hull's
#: own rounding); a set whose thickness is below it is flat.
HULL_TOL = 1e-10


def hull_planes(points: np.ndarray) -> np.ndarray | None:
    """The facet planes (K, 4) of the convex hull of ``points`` (N, 3), rows ``(n, d)`` with ``n`` the
    outward unit normal and ``n . x + d <= 0`` inside; None for fewer than 4 points or points all in a
    plane or a line.

    Incremental (Clarkson-Shor / quickhull-like): a tetrahedron of extreme points, then every point
    outside the hull so far replaces the facets it sees by a fan from it to their horizon. The same
    planes as Qhull's (``scipy.spatial.ConvexHull(points).equations``, triangulated facets) to
    rounding; here because importing ``scipy.spatial`` costs a third of a second of every fit. A
    Python loop over the points (tens to hundreds of markers), never over frames.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 4:
        return None
    size = float(np.abs(P - P.mean(0)).max())
    if not size > 0:
        return None
    eps = HULL_TOL * size
    i0 = int(np.argmin(P[:, 0]))
    i1 = int(np.argmax(np.linalg.norm(P - P[i0], axis=1)))
    u = P[i1] - P[i0]
    if not np.linalg.norm(u) > eps:
        return None
    u = u / np.linalg.norm(u)
    off = (P - P[i0]) - np.outer((P - P[i0]) @ u, u)
    i2 = int(np.argmax(np.linalg.norm(off, axis=1)))
    if not np.linalg.norm(off[i2]) > eps:
        return None
    nrm = np.cross(P[i1] - P[i0], P[i2] - P[i0])
    nrm /= np.linalg.norm(nrm)
    h = (P - P[i0]) @ nrm
    i3 = int(np.argmax(np.abs(h)))
    if not abs(h[i3]) > eps:
        return None
    inner = P[[i0, i1, i2, i3]].mean(0)
    faces = []
    for a, b, c in ((i0, i1, i2), (i0, i1, i3), (i0, i2, i3), (i1, i2, i3)):
        n_ = np.cross(P[b] - P[a], P[c] - P[a])
        faces.append((a, b, c) if n_ @ (inner - P[a]) < 0 else (a, c, b))

    def planes_of(fs: list) -> np.ndarray:
        F = np.array(fs)
        n_ = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
        n_ /= np.linalg.norm(n_, axis=1, keepdims=True)
        return np.column_stack([n_, -np.einsum("ki,ki->k", n_, P[F[:, 0]])])

    pl = planes_of(faces)
    done = {i0, i1, i2, i3}
    for p in range(len(P)):
        if p in done:
            continue
        seen = P[p] @ pl[:, :3].T + pl[:, 3] > eps
        if not seen.any():
            continue  # inside (or on) the hull so far
        vis = [f for f, s_ in zip(faces, seen) if s_]
        edges = {(f[k], f[(k + 1) % 3]) for f in vis for k in range(3)}
        horizon = [(a, b) for a, b in edges if (b, a) not in edges]
        faces = [f for f, s_ in zip(faces, seen) if not s_] + [(a, b, p) for a, b in sorted(horizon)]
        pl = planes_of(faces)
    return pl
