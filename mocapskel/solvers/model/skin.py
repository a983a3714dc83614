"""How much of a fit's marker residual follows the joint angles.

The model explains the markers by rigid segments plus noise independent of the pose. Skin that slides with
the joints breaks that: its motion is a function of the joint angles, the same in every frame of the same pose,
and does not average out over frames. Part of it is never seen in the residual (a joint centre moved by c moves
a marker by (I - R(theta)) c, about linear in the angle, and the fit takes that part into the joint's place);
the rest is: :func:`angle_share` measures that rest, from the take alone.
"""
from __future__ import annotations

import numpy as np

from ..rotations import matrix_to_rotvec
from .calibrate import _Problem


def angle_share(parent: np.ndarray, marker_segment: np.ndarray, origin: np.ndarray, marker_local: np.ndarray,
                observed: np.ndarray, rot: np.ndarray, root_pos: np.ndarray) -> float:
    """The share of the residual's variance that the joint angles explain (0: none; NaN: nothing to measure).

    parent, marker_segment, origin, marker_local : a skeleton (origins and marker offsets in the rest axes).
    observed : (F, M, 3) markers on the frames posed by ``rot`` (F, S, 3, 3) and ``root_pos`` (F, 3).

    Every marker's residual, in its segment's axes, is regressed on that segment's joint angles (the rotation
    vectors to its parent and children, centred) and their products; the explained variance less what as
    many random regressors explain on average (the adjusted R^2), pooled over markers. Markers of a segment
    without joints, or seen in fewer than three times as many frames as there are regressors, are left out.
    """
    parent = np.asarray(parent)
    S = len(parent)
    pr = _Problem(parent, marker_segment, observed)
    d = np.zeros((S, 3))
    for c in pr.kids:
        d[c] = origin[c] - origin[parent[c]]
    _, _, x = pr.fk(root_pos, rot, d, marker_local)
    res = observed[:, pr.used] - x
    total = explained = 0.0
    for s in np.unique(marker_segment[pr.used]):
        s = int(s)
        nbs = ([int(parent[s])] if parent[s] >= 0 else []) + [int(c) for c in np.flatnonzero(parent == s)]
        if not nbs:
            continue
        th = np.concatenate([matrix_to_rotvec(np.einsum("fji,fjk->fik", rot[:, s], rot[:, nb])) for nb in nbs], axis=1)
        seen = np.isfinite(th).all(1)
        iu = np.triu_indices(th.shape[1])
        for i in np.flatnonzero(marker_segment[pr.used] == s):
            r = np.einsum("fji,fj->fi", rot[:, s], res[:, i])  # in the segment's axes
            ok = seen & np.isfinite(r).all(1)
            t = th[ok] - th[ok].mean(0)
            X = np.concatenate([np.ones((t.shape[0], 1)), t, (t[:, :, None] * t[:, None, :])[:, iu[0], iu[1]]], axis=1)
            y = r[ok] - r[ok].mean(0)
            n, q = X.shape
            if n < 3 * q:
                continue
            # least squares by its normal equations (q <= 91 columns): the explained sum of squares is b^T beta
            b = X.T @ y
            beta = np.linalg.lstsq(X.T @ X, b, rcond=None)[0]
            ss = float((y * y).sum())
            total += ss
            explained += float((b * beta).sum()) - ss * (q - 1) / (n - 1)
    return explained / total if total > 0 else float("nan")
