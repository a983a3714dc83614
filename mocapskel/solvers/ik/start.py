"""IK's starting point: data-driven segment rotations (the default prior) and root positions."""
from __future__ import annotations

import numpy as np

from .problem import _Model
from .planes import _c_mv, _swing
from ..rigid import kabsch
from ..rotations import fill_joint


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
