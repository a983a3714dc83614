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

from .rotations import ORDERS, _parse_order, matrix_to_euler

__all__ = ["rotation_steps", "channel_steps", "euler_spikes", "order_spike_counts", "step_spike_counts", "RestSteps"]

#: Degrees a channel may step beyond the rotation's own turn (the BVH rule).
SPIKE_MARGIN_DEG = 5.0


def _turn(tr: np.ndarray) -> np.ndarray:
    """The turn (radians) of rotations whose relative rotation has trace ``tr``: from
    ``3 - tr = 4 sin^2(theta / 2)``, accurate for small turns where ``arccos((tr - 1) / 2)`` loses half
    the digits."""
    return 2.0 * np.arcsin(np.sqrt(np.clip((3.0 - tr) / 4.0, 0.0, 1.0)))


def _least_step(x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """(N,) the largest channel step from Euler angles ``x0`` (N, 3) to the nearer of the two Euler
    solutions of the same rotations as ``x1`` ((a, b, c) and (a + 180, 180 - b, c + 180)), modulo 360:
    the step the writer's continuous unwrapping makes."""
    y1 = x1 + np.array([180.0, 0.0, 180.0])
    y1[:, 1] = 180.0 - x1[:, 1]
    return np.minimum(channel_steps(np.stack([x0, x1])), channel_steps(np.stack([x0, y1])))[0]


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
    return np.degrees(_turn(tr))


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
    continuous unwrapping makes) exceeds the turn plus ``margin_deg``
    (:func:`step_spike_counts` of the consecutive frames).

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
    if R.shape[0] < 2 or R[0].size == 0:
        return np.zeros(len(ORDERS), dtype=np.int64)
    return step_spike_counts(R[:-1], R[1:], margin_deg)


def step_spike_counts(R0: np.ndarray, R1: np.ndarray, margin_deg: float = SPIKE_MARGIN_DEG,
                      orders: tuple[str, ...] = ORDERS) -> np.ndarray:
    """Steps from ``R0`` to ``R1`` that would be Euler spikes, counted in each of ``orders``.

    Only candidate steps are decomposed: the Euler rates are bounded, ``|db| <= w``
    and ``|da|, |dc| <= w / cos b`` for an angular speed w, and ``|b|`` grows
    by at most the turn theta within a step, so a step with
    ``theta / cos(|b|max + theta) <= theta + margin`` cannot be a spike.

    Parameters
    ----------
    R0, R1 : (N, ..., 3, 3) array_like
        The rotations before and after each step (e.g. frames f and f+1 of any set of frames).
    margin_deg : float
    orders : tuple of str

    Returns
    -------
    (len(orders),) int ndarray
    """
    R0 = np.asarray(R0, dtype=np.float64)
    R1 = np.asarray(R1, dtype=np.float64)
    out = np.zeros(len(orders), dtype=np.int64)
    if R0.size == 0:
        return out
    tr = np.einsum("n...ij,n...ij->n...", R0, R1)
    th = _turn(tr)
    cos_t, sin_t = np.cos(th), np.sin(th)
    for n, order in enumerate(orders):
        i, _, k, _ = _parse_order(order)
        top = np.minimum(np.maximum(np.abs(R0[..., i, k]), np.abs(R1[..., i, k])), 1.0)  # sin of the larger |b|
        # cos(|b| + theta), floored at 0 where |b| + theta passes 90 degrees
        cb = np.maximum(np.sqrt(1.0 - top * top) * cos_t - top * sin_t, 0.0)
        cand = th * (1.0 - cb) > np.radians(margin_deg) * cb
        if not cand.any():
            continue
        step = _least_step(matrix_to_euler(R0[cand], order), matrix_to_euler(R1[cand], order))
        out[n] = int(np.count_nonzero(step > np.degrees(th[cand]) + margin_deg))
    return out


class RestSteps:
    """Frame steps of a skeleton's motion, prepared to count their Euler spikes under other rest poses.

    Re-posing the rest by ``Q[s]`` (each joint's global rotation from the old rest
    to the new one) turns joint s's rotation relative to its parent into
    ``Q[parent] L Q[s]^T`` (the root's into ``L Q[root]^T``): the same turns,
    on another path through the rotations, nearer gimbal lock or farther. The
    bound of :func:`step_spike_counts` is evaluated from the one entry of
    the new rotation each order needs (``Q[p][i] . L . Q[s][k]``, for all rests
    at once); only the steps it cannot clear are re-posed in full and decomposed.

    Parameters
    ----------
    local : (F, S, 3, 3) array_like
        Rotations relative to the parents (the root: to the world), axis 0 time.
    parent : (S,) int array_like
        -1 for the root; parents precede children.
    steps : (N,) int array_like, optional
        Only the steps from these frames to the next (default: every step).
    margin_deg : float
    """

    def __init__(self, local: np.ndarray, parent: np.ndarray, steps: np.ndarray | None = None,
                 margin_deg: float = SPIKE_MARGIN_DEG):
        L = np.asarray(local, dtype=np.float64)
        self.parent = np.asarray(parent, dtype=np.int64)
        self.margin_deg = float(margin_deg)
        if steps is None:
            R0, R1 = L[:-1], L[1:]
        else:
            f = np.asarray(steps, dtype=np.int64)
            R0, R1 = L[f], L[f + 1]
        N, S = R0.shape[0], L.shape[1]
        # both ends of every step, joint by joint: (S, 2N, 9), one copy of the take
        A = np.empty((S, 2 * N, 9))
        A[:, :N] = R0.reshape(N, S, 9).transpose(1, 0, 2)
        A[:, N:] = R1.reshape(N, S, 9).transpose(1, 0, 2)
        self.A, self.N, self.S = A, N, S
        tr = np.einsum("snx,snx->sn", A[:, :N], A[:, N:])
        self.th = _turn(tr)  # (S, N), the same for every rest
        # the bound of step_spike_counts as a floor on |sin b|: a step can spike only where
        # |b| > arccos(theta / (theta + margin)) - theta (everywhere when that is negative)
        lim = np.arccos(self.th / (self.th + np.radians(margin_deg))) - self.th
        self.tau = np.where(lim > 0.0, np.sin(np.clip(lim, 0.0, 0.5 * np.pi)), -1.0)[..., None]  # (S, N, 1)

    def count(self, Q: np.ndarray, orders: tuple[str, ...] = ORDERS) -> tuple[np.ndarray, np.ndarray]:
        """Spikes with each of K rest poses, in each order.

        Parameters
        ----------
        Q : (K, S, 3, 3) array_like
            The rests' global rotations (from the motion's own rest).
        orders : tuple of str

        Returns
        -------
        spikes : (K, len(orders)) int ndarray
        near : (K, len(orders)) int ndarray
            Steps the bound could not clear (joints moving near lock): fewer is farther from a spike.
        """
        Q = np.asarray(Q, dtype=np.float64)
        K, S, N = Q.shape[0], self.S, self.N
        spikes = np.zeros((K, len(orders)), dtype=np.int64)
        near = np.zeros((K, len(orders)), dtype=np.int64)
        if N == 0 or K == 0 or S == 0:
            return spikes, near
        par = self.parent
        Qp = np.where((par >= 0)[None, :, None, None], Q[:, np.maximum(par, 0)], np.eye(3))
        for n, order in enumerate(orders):
            i, _, k, _ = _parse_order(order)
            # entry (i, k) of Qp L Qs^T = sum_ab Qp[i, a] L[a, b] Qs[k, b]: one 9-vector per joint and rest
            W = np.einsum("ksa,ksb->skab", Qp[:, :, i, :], Q[:, :, k, :]).reshape(S, K, 9).transpose(0, 2, 1).copy()
            e = np.abs(np.matmul(self.A, W))  # (S, 2N, K)
            cand = np.maximum(e[:, :N], e[:, N:]) > self.tau
            ss, nn, kk = np.nonzero(cand)
            near[:, n] = np.bincount(kk, minlength=K)
            if ss.size == 0:
                continue
            P, C = Qp[kk, ss], np.swapaxes(Q[kk, ss], -1, -2)
            step = _least_step(matrix_to_euler(P @ self.A[ss, nn].reshape(-1, 3, 3) @ C, order),
                               matrix_to_euler(P @ self.A[ss, nn + N].reshape(-1, 3, 3) @ C, order))
            bad = step > np.degrees(self.th[ss, nn]) + self.margin_deg
            spikes[:, n] = np.bincount(kk[bad], minlength=K)
        return spikes, near

