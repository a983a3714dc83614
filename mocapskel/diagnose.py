"""Why a take cannot support a skeleton, said about the take itself.

When the segment or topology stage finds nothing to build (all markers one
rigid body, segments that cannot be joined), the cause is usually plain in the
take: too few markers, nothing moving, all markers in one plane, one marker on
every segment. :func:`explain` looks for those causes and, when it finds one,
gives the error that names it (with what to do) instead of its consequence.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from . import artifacts
from .errors import DataError

__all__ = ["explain", "take_problem"]

#: A take in which no marker's position varies by more than this (rms, mm) does not move.
STILL_MM = 2.0
#: A take whose markers all lie within this (rms, mm) of one plane is flat.
FLAT_MM = 1.0
#: Frames looked at (spread over the take).
_FRAMES = 2000


def take_problem(markers: artifacts.Markers, group: np.ndarray | None = None) -> str | None:
    """What is wrong with the take itself, as ``"<what> — <what to do>"``, or None when nothing plain is.

    Parameters
    ----------
    markers : Markers
        The take (points (F, M, 3) mm, NaN for gaps).
    group : (M,) int ndarray, optional
        The segment of every marker (-1: none), when the take has been segmented.
    """
    pts = markers.points
    F, M = pts.shape[:2]
    idx = np.unique(np.linspace(0, F - 1, min(F, _FRAMES)).round().astype(int)) if F else np.zeros(0, int)
    P = pts[idx]
    vis = np.isfinite(P).all(axis=-1)  # (f, M)
    seen = vis.any(axis=0)
    m = int(seen.sum())
    if m < 3:
        return (f"only {m} marker{'' if m == 1 else 's'} {'is' if m == 1 else 'are'} seen in the take — a joint needs at least"
                " 3 markers on its two segments (2 on one, 1 on the other): put more markers on the subject")
    # how far each marker moves: rms distance from its mean position
    with np.errstate(invalid="ignore", divide="ignore"):
        Pm = np.where(vis[..., None], P, np.nan)
        n = vis.sum(axis=0)
        mean = np.nansum(Pm, axis=0) / np.maximum(n, 1)[:, None]
        dev = np.where(vis[..., None], P - mean, 0.0)
        rms = np.sqrt((dev**2).sum(axis=(0, 2)) / np.maximum(n, 1))
    moves = float(rms[seen].max())
    if moves < STILL_MM:
        return (f"nothing moves: no marker's position varies by more than {moves:.2g} mm rms over the take"
                " — capture the subject moving each joint through its range")
    X = P[vis]  # every seen sample, (n, 3)
    X = X - X.mean(axis=0)
    s = np.linalg.svd(X, compute_uv=False) / np.sqrt(max(len(X), 1))
    if s[2] < FLAT_MM:
        return (f"the take is flat: every marker lies within {s[2]:.2g} mm rms of one plane — joints need 3-D data:"
                " check that the file holds all three coordinates (a units or export mix-up can zero one)")
    if group is not None:
        sizes = np.bincount(group[group >= 0]) if (group >= 0).any() else np.zeros(0, int)
        if sizes.size >= 2 and sizes.max() == 1:
            return (f"every segment carries a single marker ({sizes.size} segments) — a joint needs at least 3 markers"
                    " on its two segments: put 2 or 3 markers on each segment")
    return None


def explain(artifact: Any, err: DataError) -> DataError:
    """``err`` replaced by the error that names what is wrong with the take, when :func:`take_problem` finds it.

    Parameters
    ----------
    artifact : Markers or Segments
        The input of the stage that failed.
    err : DataError
        What the stage said.
    """
    try:
        markers = artifacts.markers_of(artifact)
    except (ValueError, KeyError):  # pragma: no cover - every stage input holds its markers
        return err
    group = getattr(artifact, "group", None) if getattr(artifact, "kind", "") == "segments" else None
    why = take_problem(markers, group)
    return err if why is None else DataError(why, err.path)
