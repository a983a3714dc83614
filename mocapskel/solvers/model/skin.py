"""How much of a fit's marker residual follows the joint angles, and how far such skin motion can move a joint.

The model explains the markers by rigid segments plus noise independent of the pose. Skin that slides with
the joints breaks that: its motion is a function of the joint angles, the same in every frame of the same pose,
and does not average out over frames. Part of it is never seen in the residual (a joint centre moved by c moves
a marker by (I - R(theta)) c, about linear in the angle, and the fit takes that part into the joint's place);
the rest is: :func:`skin_motion` measures that rest, from the take alone, and from it the size of the part
that moved the joint (:attr:`SkinMotion.joint_sd`). Gross residuals (:func:`gross_mask`: a marker swapped or jumping
in a frame) are no skin and are left out.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rotations import matrix_to_rotvec
from .calibrate import _Problem
from .effective import correlation_in_time, effective_frames


#: A residual whose squared length is beyond this many times the noise variance per axis (chi-square with 3 degrees
#: of freedom at 1 - 1e-6: once in a million under the model's noise) is a gross error, not skin: a marker swapped or
#: jumping in one frame. Left out of the regression: one frame of a passive take with four such markers (up to 51 mm,
#: against a median of 1.8) turned z from -8.8 to 21.6.
GROSS_CHI2 = 30.66

#: The median of chi-square with 3 degrees of freedom: the noise variance per axis is the residuals' median squared
#: length over this.
CHI2_3_MEDIAN = 2.366


def gross_mask(res: np.ndarray) -> tuple[np.ndarray, float]:
    """((F, M) bool: the residuals of ``res`` (F, M, 3) beyond ``GROSS_CHI2`` times the noise variance per axis,
    that variance from the residuals' median squared length, which a few gross errors do not move; the squared
    length beyond which they are, mm^2)."""
    d2 = np.sum(res * res, axis=-1)
    s2 = float(np.nanmedian(d2)) / CHI2_3_MEDIAN if np.isfinite(d2).any() else float("nan")
    if not s2 > 0:
        return np.zeros(d2.shape, dtype=bool), float("inf")
    with np.errstate(invalid="ignore"):
        return d2 > GROSS_CHI2 * s2, GROSS_CHI2 * s2


def gross_out(res: np.ndarray) -> np.ndarray:
    """``res`` (F, M, 3) with its gross residuals (:func:`gross_mask`) set to NaN."""
    mask, _ = gross_mask(res)
    return np.where(mask[..., None], np.nan, res)


@dataclass(frozen=True)
class SkinMotion:
    """share : the share of the residual's variance that the joint angles explain (NaN: nothing to measure).
    explained : (S,) per segment, the variance per coordinate (mm^2) of its markers' residual that its joint
        angles explain (NaN where not measured).
    angle_var : (S,) per child segment, the variance (rad^2) of its joint's turn about its mean over the frames
        (the trace of the rotation vectors' covariance; NaN for the root or where never seen).
    z : how far the explained variance lies above what chance explains, in standard deviations of chance: each
        marker's R^2 with q regressors a Beta((q - 1) / 2, (n' - q) / 2) variable for n' independent frames, n' the
        frames' effective number from the correlation in time of the regression's residual (noise that is
        correlated in time is explained by smooth regressors more often than white noise)."""

    share: float
    explained: np.ndarray
    angle_var: np.ndarray
    z: float = float("nan")

    def joint_sd(self, parent: np.ndarray) -> np.ndarray:
        """(S,) mm: how far skin that slides with child c's joint angle can have moved that joint unseen, the
        standard deviation of an isotropic Gaussian; 0 where nothing is measured.

        A marker's skin motion taken as a theta + b (theta^2 - <theta^2>) in the joint's turn theta: the
        quadratic part shows in the residual, with variance 2 b^2 Theta^4 for a turn of variance Theta^2
        (``explained``, the mean over the joint's two segments); the linear part does not, the fit moves the
        joint by about a instead. The assumption: a is as large as b per radian (the skin slides as far in
        proportion as it curves over a radian of turn). So sd = sqrt(explained / 2) / Theta^2."""
        parent = np.asarray(parent)
        out = np.zeros(len(parent))
        for c in np.flatnonzero(parent >= 0):
            e = self.explained[[c, int(parent[c])]]
            e = e[np.isfinite(e)]
            t2 = self.angle_var[c]
            if e.size and np.isfinite(t2) and t2 > 0:
                out[c] = float(np.sqrt(max(float(e.mean()), 0.0) / 2.0) / t2)
        return out


def skin_motion(parent: np.ndarray, marker_segment: np.ndarray, origin: np.ndarray, marker_local: np.ndarray,
                observed: np.ndarray, rot: np.ndarray, root_pos: np.ndarray, soft: tuple = (),
                noise: float = 0.0) -> SkinMotion:
    """The residual's part that the joint angles explain, from the take alone (see :class:`SkinMotion`).

    parent, marker_segment, origin, marker_local : a skeleton (origins and marker offsets in the rest axes).
    observed : (F, M, 3) markers on the frames posed by ``rot`` (F, S, 3, 3) and ``root_pos``: (F, 3), or (F, 3 + 3 ns)
        with each frame's offsets of the ``soft`` joints (child segments) after the root's origin.

    Every marker's residual, in its segment's axes, is regressed on that segment's joint angles (the rotation
    vectors to its parent and children, centred) and their products; the explained variance less what as
    many random regressors explain on average (the adjusted R^2). Markers of a segment without joints, or seen
    in fewer than three times as many frames as there are regressors, are left out.

    ``noise`` (mm, per axis): a floor under the residual. ``z`` tests the explained part against what chance explains of
    a residual at least that large: a residual below what any optical system resolves (a noise-free take, whose fit
    leaves only the priors' pull, a smooth function of the pose) shows no skin motion, however well the angles
    explain it.
    """
    parent = np.asarray(parent)
    marker_segment = np.asarray(marker_segment)
    S = len(parent)
    pr = _Problem(parent, marker_segment, observed, soft)
    _, _, x = pr.fk(root_pos, rot, pr.offsets(origin), marker_local)
    res = gross_out(observed[:, pr.used] - x)
    total = explained = z_ex = z_var = 0.0
    per_seg = np.full(S, np.nan)
    angle_var = np.full(S, np.nan)
    turns: dict[int, np.ndarray] = {}  # child c: its joint's rotation vectors, in c's axes

    def turn(c: int) -> np.ndarray:
        if c not in turns:
            turns[c] = matrix_to_rotvec(np.einsum("fji,fjk->fik", rot[:, int(parent[c])], rot[:, c]))
        return turns[c]

    for c in pr.kids:
        th = turn(int(c))
        th = th[np.isfinite(th).all(1)]
        if th.shape[0] > 1:
            angle_var[c] = float(np.sum(th.var(0)))
    for s in np.unique(marker_segment[pr.used]):
        s = int(s)
        kids = [int(c) for c in np.flatnonzero(parent == s)]
        if parent[s] < 0 and not kids:
            continue
        th = np.concatenate(([turn(s)] if parent[s] >= 0 else []) + [turn(c) for c in kids], axis=1)
        seen = np.isfinite(th).all(1)
        iu = np.triu_indices(th.shape[1])
        seg_ss = seg_ex = 0.0
        seg_n = 0
        for i in np.flatnonzero(marker_segment[pr.used] == s):
            r = np.einsum("fji,fj->fi", rot[:, s], res[:, i])  # in the segment's axes
            ok = seen & np.isfinite(r).all(1)
            if ok.sum() < 3:  # too few frames for any regression (and no mean of nothing)
                continue
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
            raw = float((b * beta).sum())
            ex = raw - ss * (q - 1) / (n - 1)
            ne = effective_frames(correlation_in_time([(y - X @ beta)[:, None, :]]), np.arange(n))
            if ne > q + 1:
                null = np.maximum((y * y).sum(0), n * noise**2)  # each axis's sum of squares under chance
                z_ex += raw - float(null.sum()) * (q - 1) / (ne - 1)
                z_var += float((null**2).sum()) * 2.0 * (q - 1) * (ne - q) / ((ne - 1) ** 2 * (ne + 1))
            seg_ss += ss
            seg_ex += ex
            seg_n += 3 * n
        if seg_n:
            per_seg[s] = max(seg_ex, 0.0) / seg_n
            total += seg_ss
            explained += seg_ex
    return SkinMotion(share=explained / total if total > 0 else float("nan"), explained=per_seg, angle_var=angle_var,
                      z=z_ex / np.sqrt(z_var) if z_var > 0 else float("nan"))
