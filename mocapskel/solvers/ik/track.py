"""IK of a whole take coarse to fine in time, from poses known at a few key frames: where markers alone
leave a pose ambiguous, the start slerped from frames already solved decides which solution IK finds."""
from __future__ import annotations

import numpy as np

from .solve import solve_ik
from ..rotations import slerp_fill_joints

__all__ = ["track"]


def track(
    parent: np.ndarray,
    origin: np.ndarray,
    marker_segment: np.ndarray,
    marker_local: np.ndarray,
    observed: np.ndarray,
    key_frames: np.ndarray,
    key_rot: np.ndarray,
    key_root: np.ndarray,
    *,
    factor: int = 4,
    iterations: int = 10,
    prior_weight: float = 1.0,
    chunk: int = 2048,
):
    """IK of every frame, coarse to fine in time from poses known at ``key_frames``.

    Where markers alone leave a pose ambiguous (segments with one or two
    markers, held only by their joints), a good start decides which solution
    IK finds. Starting from the key poses, frames ever closer together are
    solved — every ``stride / factor``-th frame, the start and the rotation
    prior slerped between the frames already solved, joint by joint
    (:func:`~mocapskel.solvers.rotations.slerp_fill_joints`) — until every
    frame is.
    Returns :class:`~mocapskel.solvers.ik.solve.IKResult`-like (rot (F, S, 3, 3),
    root_pos (F, 3), residual (F, M)).
    """
    F, M, _ = observed.shape
    S = len(parent)
    key_frames = np.asarray(key_frames, dtype=int)
    known = np.zeros(F, dtype=bool)
    rot = np.tile(np.eye(3), (F, S, 1, 1))
    root = np.zeros((F, 3))
    resid = np.full((F, M), np.nan)
    rot[key_frames], root[key_frames], known[key_frames] = key_rot, key_root, True
    stride = max(1, int(np.ceil(F / max(len(key_frames), 1))))
    while True:
        stride = max(1, stride // factor)
        todo = np.zeros(F, dtype=bool)
        todo[::stride] = True
        todo &= ~known
        if stride == 1:
            todo = ~known | np.isin(np.arange(F), key_frames)  # the key frames get residuals too
        frames = np.flatnonzero(todo | known)
        kf = known[frames]
        R0 = slerp_fill_joints(parent, rot[frames], np.broadcast_to(kf[:, None], (frames.size, S)))
        p0 = np.stack([np.interp(frames, frames[kf], root[frames[kf], i]) for i in range(3)], axis=1)
        new = np.flatnonzero(todo[frames])
        for a in range(0, new.size, chunk):
            sel = new[a : a + chunk]
            res = solve_ik(parent, origin, marker_segment, marker_local, observed[frames[sel]],
                           init_rot=R0[sel], init_root=p0[sel], prior_rot=R0[sel], iterations=iterations,
                           prior_weight=prior_weight)
            f = frames[sel]
            rot[f], root[f], resid[f] = res.rot, res.root_pos, res.residual
        known[frames] = True
        if stride == 1:
            break
    return rot, root, resid
