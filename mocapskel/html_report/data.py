"""What the HTML report gathers from a fit's artifacts: the chain a motion came from, and the per-frame
joint and segment residual series."""
from __future__ import annotations

import numpy as np

from ..artifacts import Markers, Motion, Segments, Topology, markers_of

__all__ = ["joint_residual_series", "segment_residual_series"]


# --------------------------------------------------------------------------- data


def _chain(motion: Motion) -> tuple[Markers | None, Segments | None, Topology | None]:
    """The markers, segments and topology a motion was computed from (None where it carries none)."""
    joints = motion.skeleton.joints
    topo = joints.topology if joints is not None else None
    segs = topo.segments if topo is not None else None
    try:
        mk = markers_of(motion)
    except (ValueError, AttributeError):
        mk = None
    return mk, segs, topo


def _rms_rows(x: np.ndarray) -> np.ndarray:
    """Per row of ``x`` (F, N), the rms over its finite entries; NaN for a row with none."""
    ok = np.isfinite(x)
    n = ok.sum(axis=1)
    ss = np.where(ok, x, 0.0) ** 2
    out = np.full(x.shape[0], np.nan)
    has = n > 0
    out[has] = np.sqrt(ss[has].sum(axis=1) / n[has])
    return out


def joint_residual_series(motion: Motion) -> np.ndarray:
    """Per frame and joint, how far the markers are from keeping their distance to the joint.

    For the joint between segments ``a`` and ``b`` (a tree edge) and every marker
    ``m`` of either segment, ``d[f, m] = |marker(f, m) - joint(f)|`` with the
    joint centre estimated by the joints stage; the series is, per frame, the rms
    over the markers seen of ``d[f, m] - mean_f d[f, m]``. A perfect joint on rigid
    segments gives zero. Its rms over frames is close to the joint's reported
    residual.

    Parameters
    ----------
    motion : Motion
        The IK artifact (it carries the joints, segments and markers).

    Returns
    -------
    (F, E) ndarray
        mm; NaN where the joint is not placed or none of its markers is seen.
        ``(F, 0)`` when the motion carries no joints.
    """
    F = motion.root_pos.shape[0]
    joints = motion.skeleton.joints
    mk, segs, topo = _chain(motion)
    if joints is None or segs is None or topo is None or mk is None:
        return np.zeros((F, 0))
    pts = mk.points
    out = np.full((F, topo.edges.shape[0]), np.nan)
    for e, (a, b) in enumerate(topo.edges.tolist()):
        idx = np.concatenate([segs.members(a), segs.members(b)])
        if idx.size == 0:
            continue
        d = np.linalg.norm(pts[:, idx] - joints.centres[:, e, None, :], axis=-1)  # (F, n), NaN where unseen
        ok = np.isfinite(d)
        cnt = ok.sum(axis=0)
        mean = np.where(cnt > 0, np.where(ok, d, 0.0).sum(axis=0) / np.maximum(cnt, 1), np.nan)
        out[:, e] = _rms_rows(d - mean)
    return out


def segment_residual_series(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and segment, the rms IK residual of the segment's markers, and where it has gaps.

    Parameters
    ----------
    motion : Motion
        The IK artifact.

    Returns
    -------
    rms : (F, S) ndarray
        mm; NaN where none of the segment's markers is seen.
    gap : (F, S) bool ndarray
        True where at least one of the segment's markers is not seen (the
        skeleton fills it in).
    """
    sk = motion.skeleton
    F, S = motion.rot.shape[:2]
    rms = np.full((F, S), np.nan)
    gap = np.zeros((F, S), dtype=bool)
    for s in range(S):
        idx = np.flatnonzero(sk.marker_segment == s)
        if idx.size == 0:
            continue
        r = motion.residual[:, idx]
        rms[:, s] = _rms_rows(r)
        gap[:, s] = ~np.isfinite(r).all(axis=1)
    return rms, gap
