"""Euler spikes: rotation channels that step by more than the rotation turns.

A BVH curve editor or a resampling importer interpolates each rotation channel
on its own. Where a channel steps by much more than the joint turns between two
frames (near gimbal lock the outer angles turn about ``1 / cos b`` times faster
than the joint, for either exact Euler solution), the interpolated pose spins
the limb. :func:`euler_spikes` finds such steps in written channels;
:func:`order_spike_counts` counts them for every rotation order before writing,
so that the writer can take the order with the fewest.
"""
from __future__ import annotations

import numpy as np

from .parallel import run_blocks
from .rotations import ORDERS, _parse_order, matrix_to_euler

__all__ = ["rotation_steps", "channel_steps", "euler_spikes", "order_spike_counts"]

#: Degrees a channel may step beyond the rotation's own turn (the BVH rule).
SPIKE_MARGIN_DEG = 5.0


def rotation_steps(R: np.ndarray) -> np.ndarray:
    """(F-1, ...) geodesic angle in degrees of ``R[f]^T R[f+1]``, the turn between consecutive frames.

    From ``3 - trace(R[f]^T R[f+1]) = 4 sin^2(theta / 2)``: accurate to about
    1e-6 degrees for small turns, where ``arccos((trace - 1) / 2)`` loses half
    the digits.

    Parameters
    ----------
    R : (F, ..., 3, 3) array_like
        Rotation matrices, axis 0 time.
    """
    R = np.asarray(R, dtype=np.float64)
    tr = np.einsum("f...ij,f...ij->f...", R[1:], R[:-1])
    return np.degrees(2.0 * np.arcsin(np.sqrt(np.clip((3.0 - tr) / 4.0, 0.0, 1.0))))


def channel_steps(angles: np.ndarray) -> np.ndarray:
    """(F-1, ...) largest change of one of the three channels between consecutive frames, modulo 360.

    Parameters
    ----------
    angles : (F, ..., 3) array_like
        Degrees, axis 0 time.
    """
    d = np.abs(np.diff(np.asarray(angles, dtype=np.float64), axis=0)) % 360.0
    return np.minimum(d, 360.0 - d).max(axis=-1)


def euler_spikes(angles: np.ndarray, R: np.ndarray, margin_deg: float = SPIKE_MARGIN_DEG) -> np.ndarray:
    """(F-1, ...) bool: frame steps where a channel steps by more than the rotation turns plus ``margin_deg``.

    Parameters
    ----------
    angles : (F, ..., 3) array_like
        The rotation channels (degrees), e.g. of one BVH joint per trailing index.
    R : (F, ..., 3, 3) array_like
        The rotations they represent.
    margin_deg : float
        Degrees a channel may step beyond the rotation step.
    """
    return channel_steps(angles) > rotation_steps(R) + margin_deg


def order_spike_counts(R: np.ndarray, margin_deg: float = SPIKE_MARGIN_DEG) -> np.ndarray:
    """(6,) joint-frame steps that would be Euler spikes in each rotation order (:data:`ORDERS`).

    A step of frame f to f+1 counts when its smallest channel step over the two
    Euler solutions of frame f+1 (modulo 360, the choice the writer's
    continuous unwrapping makes) exceeds the turn plus ``margin_deg``. Only
    candidate steps are decomposed: the Euler rates are bounded, ``|db| <= w``
    and ``|da|, |dc| <= w / cos b`` for an angular speed w, and ``|b|`` grows
    by at most the turn theta within a step, so a step with
    ``theta / cos(|b|max + theta) <= theta + margin`` cannot be a spike.

    Parameters
    ----------
    R : (F, S, 3, 3) array_like
        Each joint's rotation, axis 0 time.
    margin_deg : float

    Returns
    -------
    (6,) int ndarray
    """
    R = np.asarray(R, dtype=np.float64)
    out = np.zeros(len(ORDERS), dtype=np.int64)
    if R.shape[0] < 2 or R[0].size == 0:
        return out
    th = np.radians(rotation_steps(R))
    cos_t, sin_t = np.cos(th), np.sin(th)

    def count(n: int) -> None:  # the orders are independent: side by side on the cores
        i, _, k, _ = _parse_order(ORDERS[n])
        sb = np.abs(R[..., i, k])
        top = np.minimum(np.maximum(sb[1:], sb[:-1]), 1.0)  # sin of the larger |b| of the two frames
        # cos(|b| + theta), floored at 0 where |b| + theta passes 90 degrees
        cb = np.maximum(np.sqrt(1.0 - top * top) * cos_t - top * sin_t, 0.0)
        cand = th * (1.0 - cb) > np.radians(margin_deg) * cb
        if not cand.any():
            return
        f, *rest = np.nonzero(cand)
        x0 = matrix_to_euler(R[(f, *rest)], ORDERS[n])
        x1 = matrix_to_euler(R[(f + 1, *rest)], ORDERS[n])
        y1 = x1 + np.array([180.0, 0.0, 180.0])
        y1[:, 1] = 180.0 - x1[:, 1]
        step = np.minimum(channel_steps(np.stack([x0, x1])), channel_steps(np.stack([x0, y1])))[0]
        out[n] = int(np.count_nonzero(step > np.degrees(th[cand]) + margin_deg))

    run_blocks(count, range(len(ORDERS)))
    return out
