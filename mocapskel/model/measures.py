"""Small measures and words the stages and the checks share: the subject's size, frames as runs."""
from __future__ import annotations

import numpy as np


def frames_text(frames: tuple[int, ...] | np.ndarray, most: int = 8) -> str:
    """Frames as runs, e.g. ``"12-14, 30 (+5 more runs)"``; ``""`` for none."""
    f = np.unique(np.asarray(frames, dtype=np.int64))
    if f.size == 0:
        return ""
    brk = np.flatnonzero(np.diff(f) > 1)
    starts = np.r_[f[0], f[brk + 1]]
    ends = np.r_[f[brk], f[-1]]
    parts = [str(a) if a == b else f"{a}-{b}" for a, b in zip(starts[:most].tolist(), ends[:most].tolist())]
    more = starts.size - most
    return ", ".join(parts) + (f" (+{more} more runs)" if more > 0 else "")


def visible(points: np.ndarray) -> np.ndarray:
    """(...,) bool: where points (..., 3) have all three coordinates finite: ``np.isfinite(points).all(-1)``,
    bit for bit, one pass per coordinate (a reduction over a last axis of length 3 is five times slower on a
    long take)."""
    return np.isfinite(points[..., 0]) & np.isfinite(points[..., 1]) & np.isfinite(points[..., 2])


def marker_extent(points: np.ndarray, n_frames: int = 400, columns: np.ndarray | None = None) -> float:
    """The subject's size: median over (up to ``n_frames`` evenly spread) frames of the
    largest distance between two markers seen in that frame (mm; NaN if no frame shows two).
    ``columns``: only those markers of ``points`` (F, M, 3) (indices or a mask); only the frames read are
    gathered."""
    F = points.shape[0]
    idx = np.unique(np.linspace(0, F - 1, min(F, n_frames)).astype(np.int64)) if F else np.zeros(0, dtype=np.int64)
    if columns is not None:
        points = points[idx][:, columns]
        idx = np.arange(idx.size)
    d = []
    for f in idx:  # a few hundred frames, each a small pairwise matrix
        p = points[f]
        p = p[np.isfinite(p).all(1)]
        if p.shape[0] >= 2:
            diff = p[:, None, :] - p[None, :, :]
            d.append(float(np.sqrt((diff * diff).sum(-1)).max()))
    return float(np.median(d)) if d else float("nan")
