"""One rigid point shape over a take: its pose in every frame, and the shape itself (generalised Procrustes).

All functions are vectorised over frames (time is the first axis) and never
raise for a frame that cannot be solved: such a frame gets NaN rotation,
translation and rms instead. :func:`shape_poses` is :func:`~mocapskel.solvers.rigid.kabsch`
for the common case of one fixed shape and unit weights, several times faster on
long takes.
"""
from __future__ import annotations

import numpy as np

from .rigid import COLLINEAR_TOL, _adj4, _best_rotation, kabsch

__all__ = ["shape_poses", "procrustes_shape"]


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
        return bool(_solvable_frames(obs[f : f + 1], vis[f : f + 1], collinear_tol)[0])

    if ref_frame is not None and solvable(ref_frame):
        start = ref_frame
    elif solvable(best):
        start = best
    else:
        # that frame's points lie in one line or on one spot (two labels on one point, a body seen
        # edge-on): start from the solvable frame with the most visible points instead (the first of them)
        cand = np.flatnonzero(_solvable_frames(obs, vis, collinear_tol))
        if not cand.size:
            return (np.full((P, 3), np.nan), np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan), np.full(F, np.nan))
        start = int(cand[np.argmax(n_vis[cand])])

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


def _solvable_frames(obs: np.ndarray, vis: np.ndarray, collinear_tol: float) -> np.ndarray:
    """(F,) whether each frame's visible points of ``obs`` (F, P, 3) can be aligned: three or more, not in
    one line nor on one spot (the second eigenvalue of their scatter above ``collinear_tol**2`` times the
    largest); all frames at once."""
    w = vis.astype(float)
    n = np.maximum(w.sum(1), 1.0)
    x = np.where(vis[..., None], obs, 0.0)
    d = (x - (x.sum(1) / n[:, None])[:, None, :]) * w[..., None]
    lam = np.linalg.eigvalsh(np.einsum("fpi,fpj->fij", d, d) / n[:, None, None])
    return (vis.sum(1) >= 3) & (lam[:, 2] > 0) & (lam[:, 1] > collinear_tol**2 * lam[:, 2])
