"""IK of a whole take with a fitted skeleton: every frame's segment rotations and root position, gaps
and limbs out of view held, residual statistics and warnings (the IK stage's motion)."""
from __future__ import annotations

import numpy as np

from ...artifacts import Motion, Skeleton
from ...model.measures import frames_text
from ...errors import DataError
from .track import track
from .segment_poses import segment_poses
from .solve import solve_ik
from .unflip import unflip
from ..rotations import hold_unobserved, observed_below, segments_seen, slerp_fill_joints


#: Defaults of the IK stage's ``Params.tol`` and ``Params.max_step_deg`` (see there).
TOL = 0.1
MAX_STEP_DEG = 45.0

#: A segment out of view (no marker of it or below it seen) in at least this fraction of the take's frames
#: is said in a warning: its motion there is made up (its joints keep the angles of the frames around).
OUT_OF_VIEW_WARN = 0.1


def initial_pose(skel: Skeleton, points: np.ndarray, centres: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per-segment Kabsch start: (rot (F, S, 3, 3), root_pos (F, 3)), gaps slerp-filled.

    points : (F, M, 3) observed markers; centres : (F, E, 3) joint centres or None.
    Every segment is fitted to its markers and the centres of its joints, all
    segments and frames at once (:func:`~mocapskel.solvers.ik.segment_poses`).
    """
    F, M = points.shape[:2]
    root = int(np.flatnonzero(skel.parent < 0)[0])
    shapes, columns = segment_shapes(skel, range(len(skel.names)), M, centres is not None)
    rot, t = segment_poses(shapes, columns, [points] if centres is None else [points, centres])
    ok = np.isfinite(rot[..., 0, 0])  # (F, S)
    root_pos = np.full((F, 3), np.nan)
    never = ~ok.any(0)
    rot[:, never] = np.eye(3)
    rot = slerp_fill_joints(skel.parent, rot, ok | never, copy=False)
    if ok[:, root].any():
        fr = np.flatnonzero(ok[:, root])
        p = np.einsum("fij,j->fi", rot[:, root], skel.origin[root]) + t[:, root]
        root_pos = p if fr.size == F else _interp_frames(p, fr)
    if not np.isfinite(root_pos).all():
        # fall back to the mean of the root's markers, offset as at rest
        mids = np.flatnonzero(skel.marker_segment == root)
        seen = np.isfinite(points[:, mids]).all(-1)  # (F, m): frames with none seen stay NaN
        n = seen.sum(1)[:, None]
        c = np.where(seen[..., None], points[:, mids], 0.0).sum(1) / np.where(n > 0, n, np.nan)
        c0 = np.mean(skel.origin[root] + skel.marker_local[mids], axis=0) if mids.size else skel.origin[root]
        root_pos = c - c0 + skel.origin[root]
        fr = np.flatnonzero(np.isfinite(root_pos).all(1))
        if not fr.size:
            raise DataError("the root segment is never seen — cannot place the skeleton", None)
        root_pos = _interp_frames(root_pos, fr)
    return rot, root_pos


def segment_shapes(skel: Skeleton, segments, M: int, joints: bool) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each of ``segments``' rest points (its markers, and with ``joints`` the centres of its joints, lab axes at the
    rest frame) and their columns among ``M`` markers followed by the joint centres in ``_edges(skel)`` order: the
    shapes :func:`~mocapskel.solvers.ik.segment_poses.segment_poses` poses."""
    edges = _edges(skel)
    shapes, columns = [], []
    for s in segments:
        mids = np.flatnonzero(skel.marker_segment == s)
        ref, cols = [skel.origin[s] + skel.marker_local[mids]], [mids]
        if joints:
            eids = np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s))
            ref.append(skel.origin[edges[eids, 1]])
            cols.append(M + eids)
        shapes.append(np.concatenate(ref))
        columns.append(np.concatenate(cols))
    return shapes, columns


def _interp_frames(x: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """x (F, 3) known at ``frames``: linear in between, held at the ends."""
    F = x.shape[0]
    return np.stack([np.interp(np.arange(F), frames, x[frames, i]) for i in range(3)], axis=1)


def _edges(skel: Skeleton) -> np.ndarray:
    kids = np.flatnonzero(skel.parent >= 0)
    return np.stack([skel.parent[kids], kids], axis=1) if kids.size else np.zeros((0, 2), dtype=int)


def solve(
    skel: Skeleton, points: np.ndarray, centres: np.ndarray | None = None, *, iterations: int = 10,
    rate: float = 0.0, source: str = "", chunk: int = 2048, tol: float = TOL,
    key_poses: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, max_step_deg: float = MAX_STEP_DEG,
    version: int | None = None,
) -> Motion:
    """IK of ``points`` (F, M, 3) with a fitted skeleton (markers ordered as ``skel.labels``).

    centres : (F, E, 3) joint centres (edges in ``_edges(skel)`` order) for the
    start, or None (the solver then starts from the markers alone). Stretches
    of ``chunk`` frames (from the start) where nothing is seen hold the
    nearest solved pose. ``tol`` (mm) is the solver's convergence tolerance.
    key_poses : (frames (K,), rot (K, S, 3, 3), root_pos (K, 3)) poses known at
    some frames: IK is then solved coarse to fine in time from them
    (:func:`~mocapskel.solvers.ik.track.track`) and ``centres`` is not used.
    version : the IK stage's ``VERSION``, noted in the motion's info.
    """
    if not np.isfinite(points).any():
        raise DataError("no marker is seen in any frame", source or None)
    F = points.shape[0]
    if key_poses is not None:  # coarse to fine in time from known poses
        kf, krot, kroot = key_poses
        rot, root_pos, resid = track(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, points,
                                     kf, krot, kroot, iterations=iterations, chunk=chunk)
    else:
        kw = {}
        if centres is not None:  # a start (and prior) from markers and joint centres, gaps bridged over the whole take
            rot0, root0 = initial_pose(skel, points, centres)
            kw = {"init_root": root0, "prior_rot": rot0, "out": rot0}  # the start is not needed after
        res = solve_ik(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, points, iterations=iterations, tol=tol, **kw)
        rot, root_pos, resid = res.rot, res.root_pos, res.residual
    flips = None
    if max_step_deg > 0:  # of two equally good poses, the one near its neighbours
        rot, root_pos, resid, flips = unflip(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, points,
                                             rot, root_pos, resid, max_step_deg=max_step_deg, iterations=iterations,
                                             max_run=max(2, int(round(0.5 * rate))) if rate and rate > 0 else 60)
    # stretches where nothing of a limb is seen: its joints keep their angles (slerped across, held at the ends)
    sseen = segments_seen(skel.marker_segment, len(skel.parent), points)
    rot = hold_unobserved(skel.parent, rot, sseen, copy=False)
    # out of view while something else is seen (frames where nothing is, held below, are not counted)
    observed = observed_below(skel.parent, sseen) | ~sseen.any(axis=1, keepdims=True)
    out_of_view = (~observed).sum(0)
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
    # residual statistics from per-marker sums (one pass over the residuals)
    seen = np.isfinite(resid)
    r2 = np.where(seen, resid, 0.0)
    r2 *= r2
    sum2, count = r2.sum(0), seen.sum(0)

    def rms(cols: np.ndarray | slice) -> float | None:
        n = int(count[cols].sum())
        return float(np.sqrt(sum2[cols].sum() / n)) if n else None

    warnings = []
    for sg in np.flatnonzero(out_of_view >= max(1, OUT_OF_VIEW_WARN * F)):
        labels = [skel.labels[m] for m in np.flatnonzero(skel.marker_segment == sg)]
        warnings.append(f"segment {skel.names[sg]} ({', '.join(labels[:6])}{' …' if len(labels) > 6 else ''}) is out of view in "
                        f"{int(out_of_view[sg])} of {F} frames ({100.0 * out_of_view[sg] / F:.0f} %: frames "
                        f"{frames_text(np.flatnonzero(~observed[:, sg]), most=4)}): no marker "
                        "of it or below it is seen there, and it keeps the joint angles of the frames around — its motion "
                        "there is made up")
    info = {
        "version": version,
        "rms_mm": rms(slice(None)),
        "rms_mm_per_segment": {name: rms(skel.marker_segment == s) for s, name in enumerate(skel.names)},
        "filled_fraction": float(1.0 - count.sum() / resid.size) if resid.size else 0.0,
        "unflip": flips,
        # frames where nothing of a segment or below it is seen but something else is (its joints' angles held
        # there), segments with any
        "out_of_view_frames": {skel.names[s]: int(n) for s, n in enumerate(out_of_view) if n},
        "warnings": warnings,
    }
    return Motion(skeleton=skel, root_pos=root_pos, rot=rot, residual=resid, rate=rate, source=source, info=info)


def _centres_by_edges(skel: Skeleton, centres: np.ndarray) -> np.ndarray:
    """Reorder joint-centre trajectories from the topology's edge order to ``_edges(skel)`` order; a joint the
    topology has no edge for (the two ends of a link of no markers, :mod:`~mocapskel.solvers.model.links`) gets NaN."""
    topo_edges = skel.joints.topology.edges
    child_to_e = {(int(a), int(b)): e for e, (a, b) in enumerate(topo_edges)}
    kids = np.flatnonzero(skel.parent >= 0)
    order = [child_to_e.get((int(skel.parent[k]), int(k)), -1) for k in kids]
    if order == list(range(centres.shape[1])):  # already in that order (a copy of a whole take saved)
        return centres
    out = centres[:, order]
    out[:, [i for i, e in enumerate(order) if e < 0]] = np.nan
    return out
