"""How many independent frames residuals that correlate in time are worth.

Skin motion follows the joint angles, so a marker's residual in one frame is nearly its residual in the next: n frames
are not n independent observations. Both the data's weight in the model (:mod:`~mocapskel.solvers.model.joint_map`,
:mod:`~mocapskel.solvers.model.uncertainty`) and the skin test (:mod:`~mocapskel.solvers.model.skin`) count them as
``n^2 / sum_ij rho(|t_i - t_j|)`` with rho measured from the residuals themselves.
"""
from __future__ import annotations

import numpy as np


def correlation_in_time(backs: list[np.ndarray]) -> np.ndarray:
    """rho (L,): the correlation of residuals between frames ``k`` apart (rho[0] = 1), from a list of (F, P, 3)
    arrays over the same consecutive frames (NaN where unseen), each series' mean taken out, pooled over every
    series; cut at its first lag that is not positive (Geyer's initial positive sequence), 0 beyond."""
    if not backs:
        return np.ones(1)
    F = backs[0].shape[0]
    n = 1 << int(np.ceil(np.log2(max(2 * F, 2))))
    num, cnt = np.zeros(F), np.zeros(F)
    for back in backs:
        x = back.reshape(F, -1)
        m = np.isfinite(x)
        mu = np.where(m, x, 0.0).sum(0) / np.maximum(m.sum(0), 1)
        x = np.where(m, x - mu, 0.0)
        X, Mk = np.fft.rfft(x, n, axis=0), np.fft.rfft(m.astype(float), n, axis=0)
        num += np.fft.irfft(X * X.conj(), n, axis=0)[:F].sum(1)
        cnt += np.fft.irfft(Mk * Mk.conj(), n, axis=0)[:F].round().sum(1)
    if cnt[0] <= 0 or num[0] <= 0:
        return np.ones(1)
    rho = np.where(cnt > 0, num / np.maximum(cnt, 1), 0.0) / (num[0] / cnt[0])
    stop = np.flatnonzero(rho <= 0)
    return rho[: stop[0]] if stop.size else rho


def effective_frames(rho: np.ndarray, frames: np.ndarray) -> float:
    """How many independent frames the frames ``frames`` (indices into the take) are worth when their
    residuals correlate as ``rho`` (:func:`correlation_in_time`): n^2 / sum_ij rho(|t_i - t_j|), the
    count whose mean has the variance of theirs. n for uncorrelated residuals, 1 for identical ones."""
    t = np.asarray(frames, dtype=np.int64)
    if t.size == 0:
        return 0.0
    if np.all(np.diff(t) == 1):  # consecutive: n - k pairs at lag k
        k = np.arange(min(rho.size, t.size))
        return float(t.size**2 / (t.size * rho[0] + 2.0 * np.sum((t.size - k[1:]) * rho[k[1:]])))
    lag = np.abs(t[:, None] - t[None, :])
    r = np.where(lag < rho.size, rho[np.minimum(lag, rho.size - 1)], 0.0)
    return float(t.size**2 / r.sum())


#: Frames (the middle of the take) on which the residuals' correlation in time is measured: lags of a few
#: seconds at most matter, and a long take's refinement frames lie farther apart than that.
CORRELATION_FRAMES = 512


def frames_per_independent(skel) -> float:
    """How many of the refinement's frames one independent observation is worth: ``n / n_eff``
    (:func:`~mocapskel.solvers.model.effective.effective_frames`), the residuals' correlation in time
    (:func:`~mocapskel.solvers.model.effective.correlation_in_time`) measured on the middle
    ``CORRELATION_FRAMES`` frames of the take: every segment of three or more markers posed on its fitted
    shape in each frame (:func:`~mocapskel.solvers.ik.segment_poses.segment_poses`), its markers' residuals
    taken in its frame. Skin that slides with the joint angles keeps a marker's residual alike from one
    frame to the next; counted as independent, the frames make the data look surer than they are. 1 when
    it cannot be measured."""
    from ..ik.segment_poses import segment_poses

    pts = skel.joints.topology.segments.markers.points
    F = pts.shape[0]
    lo = max(0, F // 2 - CORRELATION_FRAMES // 2)
    win = pts[lo : lo + CORRELATION_FRAMES]
    seg = np.asarray(skel.marker_segment)
    shapes, cols = [], []
    for s in np.unique(seg[seg >= 0]):
        ms = np.flatnonzero(seg == s)
        if ms.size >= 3:
            shapes.append(skel.origin[s] + skel.marker_local[ms])
            cols.append(ms)
    if not shapes:
        return 1.0
    R, t = segment_poses(shapes, cols, win)
    backs = [np.einsum("fji,fpj->fpi", R[:, b], win[:, ms] - t[:, b, None, :]) - shapes[b] for b, ms in enumerate(cols)]
    n_eff = effective_frames(correlation_in_time(backs), skel.pose_frames)
    return max(1.0, skel.pose_frames.size / n_eff) if n_eff > 0 else 1.0
