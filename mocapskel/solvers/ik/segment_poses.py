"""Rigid poses of many point shapes in every frame at once (the per-segment fit of
IK's starting pose), by Horn's quaternion matrix on component planes."""
from __future__ import annotations

import numpy as np

from ..allocator import keep_large_blocks
from ..parallel import run_blocks
from .planes import _c_dot, _c_mv, _c_quat_to_mat
from ..rigid import _adj4, kabsch

__all__ = ["segment_poses"]

#: The same for :func:`segment_poses`, whose working set per frame is smaller.
_POSE_BLOCK = 4096


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
    keep_large_blocks()
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

    for b, lut in enumerate(luts):  # the tables of all patterns that blocks share, made before them
        if lut is not None and lut[1] <= 12:
            _pattern_ok(*lut, np.zeros(1, dtype=np.int64), collinear_tol, luts_ok, b)
    run_blocks(block, range(0, F, _POSE_BLOCK))
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
