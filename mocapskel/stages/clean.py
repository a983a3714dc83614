"""Clean: remove what optical systems get wrong (Kirk et al. 2005, §3).

- sporadic jumps: samples that leave the marker's own smooth path for a few
  frames are turned into gaps;
- gap edges: a few frames at both ends of every visible run that borders a
  gap are trimmed (reconstruction is poor there);
- short runs: visible runs shorter than ``min_run_s`` (ghosts, flicker) are
  dropped; a marker left with nothing is removed.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from ..artifacts import Markers
from ..errors import DataError

VERSION = 2


@dataclass(frozen=True)
class Params:
    trim_frames: int = 2
    """Frames removed at each gap-side end of a visible run."""
    min_run_s: float = 0.5
    """Visible runs shorter than this (seconds) are dropped."""
    jump_mm: float = 30.0
    """A sample farther than this from its marker's running median is a jump..."""
    jump_mad: float = 10.0
    """...and also farther than this many robust deviations (MAD) of that marker."""
    jump_window_s: float = 0.08
    """Width of the running median used to find jumps (at least 5 frames)."""


def _runs(visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label visible runs along time. Returns (labels (F, M) int, lengths (R+1,))."""
    structure = np.array([[0, 1, 0], [0, 1, 0], [0, 1, 0]], dtype=bool)
    lab, n = ndimage.label(visible, structure=structure)
    return lab, np.bincount(lab.ravel(), minlength=n + 1)


def hold_fill(points: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Fill gaps by holding the last seen value (leading gaps: the first seen value).

    points : (F, M, 3) ndarray; visible : (F, M) bool. Markers never seen stay NaN.
    """
    F = points.shape[0]
    ar = np.arange(F)[:, None]
    fwd = np.where(visible, ar, -1)
    np.maximum.accumulate(fwd, axis=0, out=fwd)
    bwd = np.where(visible, ar, F)
    bwd = np.minimum.accumulate(bwd[::-1], axis=0)[::-1]
    idx = np.where(fwd >= 0, fwd, np.minimum(bwd, F - 1))
    return np.take_along_axis(points, idx[:, :, None], axis=0)


def find_jumps(points: np.ndarray, rate: float, params: Params = Params()) -> np.ndarray:
    """Flag sporadic jumps.

    Parameters
    ----------
    points : (F, M, 3) ndarray, NaN for gaps.
    rate : frames per second.

    Returns
    -------
    (F, M) bool ndarray, True where a sample is a jump.
    """
    F, M, _ = points.shape
    vis = np.isfinite(points).all(axis=2)
    if F < 5:
        return np.zeros((F, M), dtype=bool)
    w = max(5, int(round(params.jump_window_s * rate)) | 1)
    h = w // 2
    filled = np.nan_to_num(hold_fill(points, vis), nan=0.0)
    # The running median is only needed where a jump can be: next to a step larger
    # than half the jump size (or a gap edge), plus a sparse sampling of frames
    # for each marker's robust spread (MAD).
    step = np.full((F, M), np.inf)
    step[1:] = np.linalg.norm(points[1:] - points[:-1], axis=2)
    big = ~(step <= 0.5 * params.jump_mm)  # NaN (gap edge) counts as big
    big[0] = False
    cand = ndimage.binary_dilation(big, structure=np.ones((2 * h + 3, 1), dtype=bool)) & vis
    sampled = np.zeros((F, M), dtype=bool)
    sampled[:: max(1, F // 2000)] = True
    sampled &= vis
    fi, mi = np.nonzero(cand | sampled)
    dev = np.full((F, M), np.nan)
    offs = np.arange(-h, h + 1)
    for k in range(0, fi.size, 200_000):  # chunks bound the memory of the windows
        f, m = fi[k : k + 200_000], mi[k : k + 200_000]
        win = filled[np.clip(f[:, None] + offs, 0, F - 1), m[:, None]]  # (K, w, 3)
        dev[f, m] = np.linalg.norm(points[f, m] - np.median(win, axis=1), axis=1)
    with np.errstate(invalid="ignore"):
        d_s = np.where(sampled, dev, np.nan)
        has = sampled.any(axis=0)
        mad = np.zeros(M)
        if has.any():
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                mad[has] = np.nanmedian(d_s[:, has], axis=0)
    mad = np.nan_to_num(mad, nan=0.0)
    thresh = np.maximum(params.jump_mm, params.jump_mad * 1.4826 * mad)
    with np.errstate(invalid="ignore"):
        return cand & (dev > thresh[None, :])


def run(markers: Markers, params: Params = Params()) -> Markers:
    """Clean a take: jumps to gaps, trim gap edges, drop short runs and empty markers.

    Returns a new Markers with ``stage="clean"`` and ``info["clean"]`` counting
    what was removed and why. Raises DataError when nothing is left.
    """
    pts = markers.points.copy()
    F, M, _ = pts.shape
    vis0 = np.isfinite(pts).all(axis=2)
    pts[~vis0] = np.nan

    jumps = find_jumps(pts, markers.rate, params)
    pts[jumps] = np.nan
    vis = vis0 & ~jumps

    trimmed = np.zeros_like(vis)
    if params.trim_frames > 0 and F > 2 * params.trim_frames:
        k = params.trim_frames
        kept = ndimage.binary_erosion(vis, structure=np.ones((2 * k + 1, 1), dtype=bool), border_value=1)
        trimmed = vis & ~kept
        # never trim a run away entirely: keep runs that would vanish (they are judged by length next)
        vis = kept

    lab, lengths = _runs(vis)
    min_run = max(1, int(np.ceil(params.min_run_s * markers.rate)))
    short = lengths < min_run
    short[0] = False
    short_mask = short[lab]
    vis &= ~short_mask
    pts[~vis] = np.nan

    keep = vis.any(axis=0)
    dropped = [markers.labels[i] for i in np.flatnonzero(~keep)]
    if not keep.any():
        raise DataError(
            "no marker has a visible run of at least "
            f"{params.min_run_s:g} s after cleaning — the take is too short or too broken to fit",
            markers.source or None,
        )
    info = dict(markers.info)
    info["clean"] = {
        "version": VERSION,
        "jump_samples": int(jumps.sum()),
        "trimmed_samples": int((trimmed & ~jumps).sum()),
        "short_run_samples": int((short_mask & ~trimmed).sum()),
        "short_runs": int(short[1:].sum()),
        "dropped_markers": dropped,
        "visible_before": int(vis0.sum()),
        "visible_after": int(vis.sum()),
    }
    return replace(
        markers,
        points=pts[:, keep],
        labels=tuple(l for l, k in zip(markers.labels, keep) if k),
        stage="clean",
        info=info,
    )
