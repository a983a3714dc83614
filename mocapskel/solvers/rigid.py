"""Rigid alignment: batched weighted Kabsch/Horn and generalised Procrustes.

Both functions are vectorised over frames (time is the first axis) and never
raise for a frame that cannot be solved: such a frame gets NaN rotation,
translation and rms instead.
"""
from __future__ import annotations

import numpy as np

__all__ = ["kabsch", "procrustes_shape"]

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
    with the SVD method of Kabsch/Horn (proper rotations only: the reflection
    case is fixed), so that ``obs[f] ~ R[f] @ ref + t[f]``.

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
    ca = np.einsum("fp,fpi->fi", w, a) / Wsafe[:, None]
    cb = np.einsum("fp,fpi->fi", w, b) / Wsafe[:, None]
    a = np.where(usable[..., None], a - ca[:, None, :], 0.0)
    b = np.where(usable[..., None], b - cb[:, None, :], 0.0)
    wa = w[..., None] * a
    H = np.einsum("fpi,fpj->fij", wa, b)  # sum w a b^T
    C = np.einsum("fpi,fpj->fij", wa, a)  # weighted scatter of the reference

    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    V = V.copy()
    V[..., 2] *= d[:, None]
    R = V @ np.swapaxes(U, -1, -2)
    t = cb - np.einsum("fij,fj->fi", R, ca)

    res = np.einsum("fij,fpj->fpi", R, a) - b
    rms = np.sqrt(np.einsum("fp,fp->f", w, np.einsum("fpi,fpi->fp", res, res)) / Wsafe)

    lam = np.linalg.eigvalsh(C)  # ascending
    spread_ok = lam[:, 1] > (collinear_tol**2) * lam[:, 2]
    ok = (usable.sum(1) >= 3) & spread_ok & (lam[:, 2] > 0)
    R[~ok] = np.nan
    t[~ok] = np.nan
    rms[~ok] = np.nan
    return R, t, rms


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
    iteration). Finally the shape is moved rigidly onto the observation at
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
        R, t, _ = kabsch(shape, obs, collinear_tol=collinear_tol)
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
