"""Euler channels that step no more than the rotation turns, and the measure of it.

A BVH curve editor or a resampling importer interpolates each rotation channel
on its own. Where a channel steps by much more than the joint turns between two
frames (near gimbal lock, where the first and third angles are ill-determined
individually), the interpolated pose spins the limb. :func:`euler_spikes` finds
such steps.
"""
from __future__ import annotations

import numpy as np

__all__ = ["rotation_steps", "channel_steps", "euler_spikes"]


def rotation_steps(R: np.ndarray) -> np.ndarray:
    """(F-1, ...) geodesic angle in degrees of ``R[f]^T R[f+1]``, the turn between consecutive frames.

    Parameters
    ----------
    R : (F, ..., 3, 3) array_like
        Rotation matrices, axis 0 time.
    """
    R = np.asarray(R, dtype=np.float64)
    tr = np.einsum("f...ij,f...ij->f...", R[1:], R[:-1])  # trace(R[f]^T R[f+1])
    # half-angle form: accurate for small turns, where arccos((tr - 1) / 2) loses digits
    d = R[1:] - R[:-1]
    chord = np.sqrt(np.einsum("f...ij,f...ij->f...", d, d))  # |R1 - R0|_F = 2 sqrt(2) sin(theta / 2)
    small = np.degrees(2.0 * np.arcsin(np.clip(chord / (2.0 * np.sqrt(2.0)), 0.0, 1.0)))
    big = np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
    return np.where(small < 90.0, small, big)


def channel_steps(angles: np.ndarray) -> np.ndarray:
    """(F-1, ...) largest change of one of the three channels between consecutive frames, modulo 360.

    Parameters
    ----------
    angles : (F, ..., 3) array_like
        Degrees, axis 0 time.
    """
    d = np.abs(np.diff(np.asarray(angles, dtype=np.float64), axis=0)) % 360.0
    return np.minimum(d, 360.0 - d).max(axis=-1)


def euler_spikes(angles: np.ndarray, R: np.ndarray, margin_deg: float = 5.0) -> np.ndarray:
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
