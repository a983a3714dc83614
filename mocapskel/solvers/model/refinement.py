"""The refinement of a fitted skeleton and its poses together: free, then, where that leaves joints no
body has, again with a prior holding them (the held fit and its starts)."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Protocol

import numpy as np

from ...artifacts import Skeleton
from ...model.measures import visible
from .calibrate import refine_skeleton
from ..joints.hinges import _hinge_axes
from ..joint_moves import _move_joint, _repose
from ..ik.motion import _centres_by_edges, solve
from ..rules.plausible import collapsed_pairs, implausible_joints, off_the_body, slid_joints
from ..rest_pose import _rest_markers
from ..rotations import segments_seen


class Params(Protocol):
    """What the refinement reads of its parameters: the rigid stage's ``Params`` (see there)."""

    @property
    def refine_frames(self) -> int: ...
    @property
    def refine_iterations(self) -> int: ...
    @property
    def joint_prior(self) -> float: ...
    @property
    def far(self) -> float: ...
    @property
    def outside(self) -> float: ...
    @property
    def hold_tolerance(self) -> float: ...
    @property
    def slide(self) -> float: ...
    @property
    def hinge_ratio(self) -> float: ...
    @property
    def hold_hinges(self) -> bool: ...
    @property
    def hold_weight(self) -> float: ...


#: Segments up to which the refinement uses ``Params.refine_frames`` frames; beyond, fewer (see below).
REFINE_FULL_SEGMENTS = 15


#: A short take gives the refinement at most one frame in this many (its frames are close and
#: alike; a real take of a few seconds spent most of its fit here).
REFINE_STRIDE = 4


#: Markers up to which the refinement uses all its frames; beyond, fewer (see below).
REFINE_FULL_MARKERS = 48


def pick_frames(visible: np.ndarray, n: int, must: int | None = None) -> np.ndarray:
    """``n`` frames spread over the take, each the best-seen of its stretch.

    visible : (F, M) bool. The take is cut into ``n`` equal stretches and the
    frame seeing the most markers is taken from each (the first on ties);
    ``must`` is added if given. Sorted, unique.
    """
    F = visible.shape[0]
    n = max(1, min(n, F))
    edges = np.linspace(0, F, n + 1).round().astype(int)
    count = visible.sum(1)
    starts = edges[:-1]
    # argmax within each stretch: reduceat gives the maxima, then the first frame reaching it
    mx = np.maximum.reduceat(count, starts)
    stretch = np.repeat(np.arange(n), np.diff(edges))
    hit = count == mx[stretch]
    first = np.full(n, -1)
    idx = np.flatnonzero(hit)
    first[stretch[idx][::-1]] = idx[::-1]
    out = first[first >= 0]
    if must is not None:
        out = np.append(out, int(must))
    return np.unique(out)


def refine_frame_count(frames: int, n_segments: int, take_frames: int | None = None, n_markers: int | None = None,
                       stride: int = REFINE_STRIDE) -> int:
    """Frames for the refinement of a skeleton of ``n_segments``: ``frames`` up to 15 segments, then
    fewer as (15 / S)^2, at least 100 (or ``frames`` if that is less); likewise as (48 / M)^2 above
    48 markers; and at most a quarter of a take of ``take_frames`` (at least 100).

    An iteration costs about S^3 per frame (a segment's pose couples with every other's through
    the constant offsets), and M^2 (every marker's offset couples with every other's through the
    poses): this keeps a skeleton of 27 segments (a marker set with many markers on joints, split
    into rigid groups), or of 73 markers (clusters and anatomical markers), at the cost of one of
    15 segments and 48 markers. Each frame then holds more markers to fit.
    """
    if take_frames is not None:
        frames = min(frames, max(100, take_frames // stride))
    out = frames
    if n_segments > REFINE_FULL_SEGMENTS:
        out = min(out, max(100, int(frames * (REFINE_FULL_SEGMENTS / n_segments) ** 2)))
    if n_markers is not None and n_markers > REFINE_FULL_MARKERS:
        out = min(out, max(100, int(frames * (REFINE_FULL_MARKERS / n_markers) ** 2)))
    return min(out, frames)


def refinement_frames(skel: Skeleton, frames: int, stride: int = REFINE_STRIDE) -> np.ndarray:
    """The frames a refinement of ``skel`` fits (:func:`pick_frames`, as many as
    :func:`refine_frame_count` allows for ``frames`` and ``stride``), its rest frame among them."""
    pts = skel.joints.topology.segments.markers.points
    return pick_frames(visible(pts), refine_frame_count(frames, len(skel.names), pts.shape[0],
                                                        int((skel.marker_segment >= 0).sum()), stride), must=skel.rest_frame)


def refine(skel: Skeleton, params: Params, centres: np.ndarray | None = None, partial: Skeleton | None = None,
           hold: dict[int, np.ndarray] | None = None) -> Skeleton:
    """:func:`refine_once` without the joint prior; again with it when a joint then sits implausibly far
    from its markers, or slid far from where the joints stage put it, and with those joints any other
    that holding them pushes off the body.

    partial : a refinement of ``skel`` stopped early, to go on from.
    hold : the hinge axes that refinement held (see :func:`_refine_once`), so that they are not
    found again by IK with ``skel``.
    """
    if partial is None or "refined" not in partial.info:
        out, hold = _refine_once(skel, params, centres, 0.0)
    else:
        done = partial.info["refined"]["iterations"]
        out, hold = _refine_once(partial, params, centres, 0.0, anchor=skel,
                                 iterations=max(params.refine_iterations - done, 1), hold=hold)
        info = dict(out.info)
        info["refined"] = dict(info["refined"], iterations=done + out.info["refined"]["iterations"],
                               marker_rms_mm_before=partial.info["refined"]["marker_rms_mm_before"])
        out = replace(out, info=info)
    if "refined" not in out.info:
        return out
    far = off_the_body(out, params.far, params.outside)
    bad = sorted(set(far) | set(slid_joints(skel, out, params.slide)) | set(collapsed_pairs(out)))
    if bad and params.joint_prior > 0:
        free_rms = out.info["refined"]["marker_rms_mm_after"]
        n_bad = len(implausible_joints(out, params.far, params.outside))

        def kept(h: Skeleton) -> bool:
            # held, the markers fit about as well: the joints slid along what the markers do not fix.
            # A clearly worse fit: the markers needed the move (a rough start put right), so it stays.
            # Never a hold that leaves more joints off the body than the free fit (holding two joints of a
            # real take slid three others 2 m away, within the tolerance of the free fit's residual)
            return (len(implausible_joints(h, params.far, params.outside)) <= n_bad
                    and (h.info["refined"]["marker_rms_mm_after"] <= (1.0 + params.hold_tolerance) * free_rms or bool(far)))

        # from the free fit (most of the skeleton is where it belongs), the prior holding the bad
        # joints where the joints stage put them
        held = _held_fit(out, skel, bad, params, centres, hold, kept)
        more = sorted(set(off_the_body(held, params.far, params.outside)) - set(bad))
        if more:
            # holding them pushed another joint off the body (two joints with no markers between them: the
            # one held, the other slid to make up for it): it is held too
            bad = sorted(set(bad) | set(more))
            held = _held_fit(out, skel, bad, params, centres, hold, kept)
        if kept(held):
            info = dict(held.info)
            info["refined"] = dict(info["refined"], joint_prior=params.joint_prior,
                                   held_because=[skel.names[c] for c in bad], marker_rms_mm_unheld=free_rms)
            out = replace(held, info=info)
    return out


def _held_cost(skel: Skeleton, anchor: Skeleton, joints: list[int], params: Params, centres: np.ndarray | None,
               hold: dict[int, np.ndarray] | None) -> float:
    """The held refinement's cost at ``skel`` (its poses on the refinement's frames), markers and prior
    together, as an rms (mm)."""
    return _refine_once(skel, params, centres, params.joint_prior, set(joints), anchor=anchor, iterations=0,
                        hold=hold)[0].info["refined"]["marker_rms_mm_before"]


def _held_fit(out: Skeleton, anchor: Skeleton, joints: list[int], params: Params, centres: np.ndarray | None,
              hold: dict[int, np.ndarray] | None, kept: Callable[[Skeleton], bool]) -> Skeleton:
    """The refinement of ``out`` with the prior holding ``joints`` where ``anchor`` has them, from
    :func:`held_start`. Where that start was not ``out`` and the fit from it stops at its iteration limit
    or would not be kept (``kept``: :func:`refine`'s test against the free fit), from ``out`` as well;
    of the two, the one of lower held cost among those that would be kept (or among both). Fits from
    the two starts end in nearby places along what the markers hardly fix, a few hundredths of a
    millimetre apart in marker rms, and the test against the free fit can fall between them: a generated
    reach whose fit from the joints put back came 0.03 % over its 5 % tolerance (the free fit kept, a
    forearm bone 79 % short where 0.2 %), a generated range-of-motion take whose fit from there stopped
    at 60 iterations, 5 % worse (an elbow 171 mm from the truth where 23)."""
    start = held_start(out, anchor, joints, params, centres, hold)
    held, _ = _refine_once(start, params, centres, params.joint_prior, set(joints), anchor=anchor, hold=hold)
    if start is out or (held.info["refined"]["iterations"] < params.refine_iterations and kept(held)):
        return held
    other, _ = _refine_once(out, params, centres, params.joint_prior, set(joints), anchor=anchor, hold=hold)
    both = [h for h in (held, other) if kept(h)] or [held, other]
    return min(both, key=lambda h: _held_cost(h, anchor, joints, params, centres, hold))


def held_start(out: Skeleton, anchor: Skeleton, joints: list[int], params: Params | None = None,
               centres: np.ndarray | None = None, hold: dict[int, np.ndarray] | None = None) -> Skeleton:
    """The start of a held refinement: ``out`` (the free one), or ``out`` with the joints of ``joints``
    (child segments) put back where ``anchor`` has them relative to the markers of their two segments
    (the mean of the two places), each segment keeping its markers, and the poses of its frames solved
    again; of the two, the one with the lower cost of the held fit (markers and prior together; with
    ``params`` None, the second without comparing).

    The prior of the held refinement pulls those joints to just that place (see
    :func:`~mocapskel.solvers.model.calibrate.refine_skeleton`), and a joint slid along a direction the
    markers hardly fix costs the markers little to move back: started there, the fit has little left to
    do. Started where the free fit left them, Levenberg-Marquardt crept back along that nearly flat
    direction for most of its iterations (a real full-body take of 17 segments: 54 iterations, 2 s,
    against 10). Where the markers do see the move (joints that did not slide along a free direction
    but went where the markers put them), the free fit is the better start."""
    seg = out.marker_segment
    pos_o, pos_a = _rest_markers(out), _rest_markers(anchor)
    origin, local = out.origin.copy(), out.marker_local.copy()
    for c in joints:
        targets = []
        for s_ in (int(c), int(out.parent[c])):
            if s_ < 0:
                continue
            m = np.flatnonzero((seg == s_) & np.isfinite(pos_o).all(1) & np.isfinite(pos_a).all(1))
            if m.size:
                targets.append(pos_o[m].mean(0) + (anchor.origin[c] - pos_a[m].mean(0)))
        if targets:
            origin, local = _move_joint(origin, local, seg, int(c), np.mean(targets, axis=0) - origin[c])
    if out.pose_rot is None or out.pose_frames is None:
        return replace(out, origin=origin, marker_local=local)
    # the move keeps every marker in place at rest only: a bent joint's markers move in the other frames
    pts = out.joints.topology.segments.markers.points[out.pose_frames]
    res = _repose(out, origin, local, pts)
    moved = replace(out, origin=origin, marker_local=local, pose_rot=res.rot, pose_root=res.root_pos)
    if params is None:
        return moved
    cost = [_held_cost(st, anchor, joints, params, centres, hold) for st in (out, moved)]
    return moved if cost[1] <= cost[0] else out


def refine_once(skel: Skeleton, params: Params, centres: np.ndarray | None, prior: float,
                prior_joints: set | None = None, anchor: Skeleton | None = None,
                iterations: int | None = None) -> Skeleton:
    """The whole skeleton and its poses refined together on a subsample of frames.

    See :mod:`mocapskel.solvers.model.calibrate`; the start is IK with the
    skeleton from the per-segment fits. The refined skeleton keeps the poses
    of those frames (IK starts from them where markers alone cannot).

    anchor : the unrefined skeleton when ``skel`` is a refinement of it: the fit goes on from
    ``skel``'s own poses, and the prior holds joints where ``anchor`` has them.
    """
    return _refine_once(skel, params, centres, prior, prior_joints, anchor, iterations)[0]


def _refine_once(skel: Skeleton, params: Params, centres: np.ndarray | None, prior: float,
                 prior_joints: set | None = None, anchor: Skeleton | None = None,
                 iterations: int | None = None, hold: dict[int, np.ndarray] | None = None
                 ) -> tuple[Skeleton, dict[int, np.ndarray] | None]:
    """:func:`refine_once`, and the hinge axes it held ({child segment: axis}; None when it did not run).

    hold : with ``anchor``, the hinge axes found from IK with ``anchor`` on the same frames (an earlier
    refinement of ``anchor`` returned them): that IK is not solved again.
    """
    pts = skel.joints.topology.segments.markers.points
    use = refinement_frames(skel, params.refine_frames)
    if use.size < 10:
        return skel, None
    ref = int(np.searchsorted(use, skel.rest_frame))
    centres = _centres_by_edges(skel, skel.joints.centres if centres is None else centres)
    if anchor is not None and skel.pose_frames is not None and np.array_equal(skel.pose_frames, use):
        rot, root = skel.pose_rot, skel.pose_root  # a refinement's own poses on these frames
        if hold is None:
            hold = (_hinge_axes(anchor, solve(anchor, pts[use], centres[use]).rot, params.hinge_ratio,
                                segments_seen(anchor.marker_segment, len(anchor.names), pts[use])) if params.hold_hinges else {})
    else:
        start = solve(skel, pts[use], centres[use])
        rot, root = start.rot, start.root_pos
        hold = (_hinge_axes(skel, start.rot, params.hinge_ratio,
                            segments_seen(skel.marker_segment, len(skel.names), pts[use])) if params.hold_hinges else {})
    res = refine_skeleton(skel.parent, skel.origin, skel.marker_segment, skel.marker_local, pts[use],
                          rot, root, ref_frame=ref,
                          iterations=params.refine_iterations if iterations is None else iterations,
                          hold_along=hold, hold_weight=params.hold_weight, joint_prior=prior, prior_joints=prior_joints,
                          anchor=None if anchor is None else (anchor.origin, anchor.marker_local))
    info = dict(skel.info)
    info["refined"] = {"frames": int(use.size), "iterations": res.n_iter,
                       "marker_rms_mm_before": res.rms[0], "marker_rms_mm_after": res.rms[1],
                       "hinges_held": [skel.names[c] for c in hold]}
    return replace(skel, origin=res.origin, marker_local=res.marker_local, info=info,
                   pose_frames=use, pose_rot=res.rot, pose_root=res.root_pos), hold
