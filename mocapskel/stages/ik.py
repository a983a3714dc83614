"""IK: per-frame segment rotations and root translation that best fit the markers.

Started from per-segment Horn/Kabsch fits of markers and joint centres
(gaps bridged by slerp), then refined jointly for the whole skeleton by a
batched Gauss–Newton over all frames at once. Segments with 1–2 markers are
held by their joints; gaps are filled by the skeleton.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..artifacts import Motion, Skeleton, markers_of
from ..errors import DataError
from ..solvers.ik import solve_ik
from ..solvers.rigid import kabsch
from ..solvers.rotations import slerp_fill

VERSION = 2


@dataclass(frozen=True)
class Params:
    iterations: int = 10
    use_joint_centres: bool = True
    """Start from Kabsch fits that include the estimated joint centres."""


def initial_pose(skel: Skeleton, points: np.ndarray, centres: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per-segment Kabsch start: (rot (F, S, 3, 3), root_pos (F, 3)), gaps slerp-filled.

    points : (F, M, 3) observed markers; centres : (F, E, 3) joint centres or None.
    """
    F = points.shape[0]
    S = len(skel.names)
    rot = np.full((F, S, 3, 3), np.nan)
    root = int(np.flatnonzero(skel.parent < 0)[0])
    root_pos = np.full((F, 3), np.nan)
    edges = _edges(skel)
    for s in range(S):
        mids = np.flatnonzero(skel.marker_segment == s)
        ref = [skel.origin[s] + skel.marker_local[mids]]
        obs = [points[:, mids]]
        if centres is not None:
            eids = np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s))
            ref.append(skel.origin[edges[eids, 1]])
            obs.append(centres[:, eids])
        R, t, _ = kabsch(np.concatenate(ref), np.concatenate(obs, axis=1))
        ok = np.isfinite(R).all(axis=(1, 2))
        if ok.any():
            rot[:, s] = slerp_fill(np.where(ok[:, None, None], R, np.eye(3)), ok)
        else:
            rot[:, s] = np.eye(3)
        if s == root:
            p = np.einsum("fij,j->fi", R, skel.origin[s]) + t
            if ok.any():
                fr = np.flatnonzero(ok)
                root_pos = _interp_frames(p, fr)
    if not np.isfinite(root_pos).all():
        # fall back to the mean of the root's markers, offset as at rest
        mids = np.flatnonzero(skel.marker_segment == root)
        c = np.nanmean(points[:, mids], axis=1) if mids.size else np.full((F, 3), np.nan)
        c0 = np.mean(skel.origin[root] + skel.marker_local[mids], axis=0) if mids.size else skel.origin[root]
        root_pos = c - c0 + skel.origin[root]
        fr = np.flatnonzero(np.isfinite(root_pos).all(1))
        if not fr.size:
            raise DataError("the root segment is never seen — cannot place the skeleton", None)
        root_pos = _interp_frames(root_pos, fr)
    return rot, root_pos


def _interp_frames(x: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """x (F, 3) known at ``frames``: linear in between, held at the ends."""
    F = x.shape[0]
    return np.stack([np.interp(np.arange(F), frames, x[frames, i]) for i in range(3)], axis=1)


def _edges(skel: Skeleton) -> np.ndarray:
    kids = np.flatnonzero(skel.parent >= 0)
    return np.stack([skel.parent[kids], kids], axis=1) if kids.size else np.zeros((0, 2), dtype=int)


def solve(
    skel: Skeleton, points: np.ndarray, centres: np.ndarray | None = None, *, iterations: int = 10,
    rate: float = 0.0, source: str = "", chunk: int = 2048,
) -> Motion:
    """IK of ``points`` (F, M, 3) with a fitted skeleton (markers ordered as ``skel.labels``).

    centres : (F, E, 3) joint centres (edges in ``_edges(skel)`` order) for the
    start, or None (the solver then starts from the markers alone).
    """
    if not np.isfinite(points).any():
        raise DataError("no marker is seen in any frame", source or None)
    F = points.shape[0]
    S = len(skel.names)
    rot = np.empty((F, S, 3, 3))
    root_pos = np.empty((F, 3))
    resid = np.empty((F, points.shape[1]))
    rot0 = root0 = None
    if centres is not None:  # a start (and prior) from markers and joint centres, gaps bridged over the whole take
        rot0, root0 = initial_pose(skel, points, centres)
    for a in range(0, F, chunk):  # chunks keep the working arrays in cache and memory bounded
        b = min(F, a + chunk)
        if not np.isfinite(points[a:b]).any():
            continue  # nothing seen in this stretch: filled below
        kw = {} if rot0 is None else {"init_rot": rot0[a:b], "init_root": root0[a:b], "prior_rot": rot0[a:b]}
        res = solve_ik(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, points[a:b], iterations=iterations, **kw)
        rot[a:b], root_pos[a:b], resid[a:b] = res.rot, res.root_pos, res.residual
    empty = [a for a in range(0, F, chunk) if not np.isfinite(points[a : min(F, a + chunk)]).any()]
    if empty:  # whole chunks with nothing seen: hold the nearest solved pose
        solved = np.ones(F, dtype=bool)
        for a in empty:
            solved[a : min(F, a + chunk)] = False
        idx = np.where(solved, np.arange(F), -1)
        np.maximum.accumulate(idx, out=idx)
        first = int(np.flatnonzero(solved)[0])
        idx[idx < 0] = first
        rot, root_pos = rot[idx], root_pos[idx]
        resid[~solved] = np.nan
    info = {
        "version": VERSION,
        "rms_mm": float(np.sqrt(np.nanmean(resid**2))) if np.isfinite(resid).any() else None,
        "rms_mm_per_segment": {},
        "filled_fraction": float(1.0 - np.isfinite(resid).mean()) if resid.size else 0.0,
    }
    for s, name in enumerate(skel.names):
        r = resid[:, skel.marker_segment == s]
        info["rms_mm_per_segment"][name] = float(np.sqrt(np.nanmean(r**2))) if np.isfinite(r).any() else None
    return Motion(skeleton=skel, root_pos=root_pos, rot=rot, residual=resid, rate=rate, source=source, info=info)


def run(skel: Skeleton, params: Params = Params()) -> Motion:
    """Solve every frame of the take the skeleton was fitted on."""
    mk = markers_of(skel)
    centres = skel.joints.centres if (params.use_joint_centres and skel.joints is not None) else None
    # joint centres are per tree edge in the joints artifact's edge order; map to child segments
    if centres is not None:
        centres = _centres_by_edges(skel, centres)
    return solve(skel, mk.points, centres, iterations=params.iterations, rate=mk.rate, source=mk.source)


def _centres_by_edges(skel: Skeleton, centres: np.ndarray) -> np.ndarray:
    """Reorder joint-centre trajectories from the topology's edge order to ``_edges(skel)`` order."""
    topo_edges = skel.joints.topology.edges
    child_to_e = {int(b): e for e, (a, b) in enumerate(topo_edges)}
    kids = np.flatnonzero(skel.parent >= 0)
    return centres[:, [child_to_e[int(k)] for k in kids]]
