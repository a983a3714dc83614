"""Batched rotations of the synthetic human: Rodrigues' formula, 3x3 products, mirroring through the sagittal plane."""
from __future__ import annotations

import numpy as np

__all__ = ["rotvec_to_matrix"]


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation matrices from rotation vectors (Rodrigues), batched.

    Parameters
    ----------
    v : (..., 3) ndarray
        Rotation vectors (axis times angle, radians).

    Returns
    -------
    R : (..., 3, 3) ndarray
    """
    v = np.asarray(v, dtype=float)
    th2 = np.einsum("...i,...i->...", v, v)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / np.where(small, 1.0, th2))
    # R = I + a K + b K^2 with K = [v]x and K^2 = v v^T - |v|^2 I
    R = (b[..., None, None] * v[..., :, None]) * v[..., None, :]
    diag = 1.0 - b * th2
    R[..., 0, 0] += diag
    R[..., 1, 1] += diag
    R[..., 2, 2] += diag
    av = a[..., None] * v
    R[..., 0, 1] -= av[..., 2]
    R[..., 1, 0] += av[..., 2]
    R[..., 0, 2] += av[..., 1]
    R[..., 2, 0] -= av[..., 1]
    R[..., 1, 2] -= av[..., 0]
    R[..., 2, 1] += av[..., 0]
    return R


def _matmul33(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(..., 3, 3) @ (..., 3, 3) as three broadcast products (faster than batched matmul)."""
    return (
        A[..., :, 0, None] * B[..., None, 0, :]
        + A[..., :, 1, None] * B[..., None, 1, :]
        + A[..., :, 2, None] * B[..., None, 2, :]
    )


def _apply33(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations applied to (P, 3) points -> (F, P, 3)."""
    return (
        A[:, None, :, 0] * x[None, :, 0, None]
        + A[:, None, :, 1] * x[None, :, 1, None]
        + A[:, None, :, 2] * x[None, :, 2, None]
    )


def _rot_z(angle: np.ndarray) -> np.ndarray:
    """(F,) radians -> (F, 3, 3) rotations about Z."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    R[..., 2, 2] = 1.0
    return R


def _mirror(v: np.ndarray) -> np.ndarray:
    """Mirror through the sagittal (XZ) plane: points negate y, axial vectors x and z."""
    return np.asarray(v, dtype=float) * np.array([1.0, -1.0, 1.0])


def _mirror_axial(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) * np.array([-1.0, 1.0, -1.0])
