"""Rigid: fit a rigid skeleton to markers and joint centres (Kirk et al. 2005, §3.3).

One segment at a time, the segment's markers and its joint centres are
mutually aligned over all frames by Horn's absolute orientation (generalised
Procrustes); the aligned clouds give constant marker and joint offsets, the
bone lengths, and the rms residual (an estimate of the noise). The rest pose
is the subject as seen at a reference frame, so offsets are the real skeleton.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..artifacts import Joints, Skeleton
from ..errors import DataError
from ..model.tree import depth_first_order
from ..model.naming import segment_names
from ..solvers.parallel import run_forked
from ..solvers.calibrate import pick_frames, refine_skeleton
from ..solvers.hull import beyond_hull
from ..solvers.ik_solve import solve_ik
from ..solvers.rigid_shape import procrustes_shape
from ..solvers.rotations import matrix_to_rotvec, project_to_so3, rotation_between, segments_seen

VERSION = 23


@dataclass(frozen=True)
class Params:
    rest_frame: int | None = None
    """Frame whose pose is the rest pose; None: a well-visible frame near the start."""
    rest_search: float = 0.25
    """Fraction of the take (from the start) searched for the rest frame."""
    iters: int = 5
    max_frames: int = 600
    """Frames used to fit the shapes (spread over the take, the rest frame among them);
    more add nothing measurable to constant offsets and cost time."""
    refine_frames: int = 300
    """Frames (the best-seen of equal stretches of the take) on which the whole
    skeleton and its poses are then refined together; 0: no refinement."""
    refine_iterations: int = 60
    trial_iterations: int = 60
    """With two starts (see :func:`run`), the iterations each gets before the better is chosen and
    alone refined to the end. Fewer pick the wrong start on two-marker skeletons: their residuals
    cross late (a generated two-marker take, 1 min with gaps: 2.00 against 1.85 mm after 20
    iterations, 1.74 against 1.78 mm after 60; chosen at 20, its joints are 54 mm off instead of
    6 mm). On real takes the choice at 20 differs from the one at 60 only where the two are within
    0.4 % of each other, and would make the refinement a third cheaper."""
    joint_prior: float = 0.01
    """Weight (per frame) of the prior that holds each joint where the joints stage put it
    relative to the markers of its two segments (see
    :func:`~mocapskel.solvers.calibrate.refine_skeleton`), used when the refinement without
    it leaves a joint implausibly far from its segments' markers (it slid along a direction
    the markers do not fix). Without need it stays off: on a skeleton of two-marker segments
    the joints stage's centres are rough, and only the whole skeleton's rigidity, unheld,
    puts them right."""
    far: float = 0.5
    """A joint is implausible when it sits farther than this fraction of the subject's marker
    extent from the nearest marker of one of its two segments."""
    outside: float = 0.15
    """...or outside the convex hull of all the subject's markers at rest by more than this fraction
    of its marker extent (joints sit inside the body, markers on its skin: a real gait take's knee
    slid 440 mm out of the body, a generated walk's hip 240 mm, while joints of plausible fits on
    43 real takes sit at most 0.14 of the extent outside, the most outside ones centres of a
    wheelchair's wheels). Not a check of the output: sparse marker sets outline no body (a
    generated two-link chain with three markers a link has its exact joint 0.19 outside), and
    there holding the joint where the joints stage put it costs nothing."""
    hold_tolerance: float = 0.05
    """The held refinement is kept when its marker rms is at most this fraction above the unheld
    one's (the slide was free), or when the unheld one leaves a joint implausibly far."""
    slide: float = 0.1
    """...or when the refinement moved it, relative to the markers of one of its segments, by
    more than this fraction of that extent from where the joints stage put it (a slide along
    a direction the markers do not fix; the refinement corrects rough starts by less)."""
    mirror_pairs: bool = True
    """Like limbs on one segment have their first joints moved together until their midpoint lies in
    the plane of symmetry of that segment's markers (see :func:`centre_mirrored_pairs`)."""
    joint_depth: bool = True
    """A hinge between two limbs with a marker over its axis (a knee marker) has its centre put one
    limb half-width inside that marker, along the axis (see :func:`deepen_joints`)."""
    leaf_centre: bool = True
    """A hinge at the end of a limb whose child's markers lie nearer it than the parent's (a foot on
    a shank) has its centre put, along the axis, at the mean position of the child's markers (see
    :func:`centre_leaf_hinges`)."""
    hinge_ratio: float = 0.6
    """A joint is a hinge when the spread of its relative rotations about their second axis is at
    most this fraction of the spread about the first."""
    hold_hinges: bool = True
    """Joints the joints stage placed as hinges, and joints SCoRE fixed in full whose motion turns
    about one axis (``hinge_ratio``), keep their position along that axis, relative to their two
    segments' markers, in the refinement (the markers hardly fix it; the joints stage put it in
    the plane of the neighbouring joints, or SCoRE where its least squares put it)."""
    hold_weight: float = 0.01
    """Weight (per frame, as ``joint_prior``) of that hold: a prior the markers outweigh
    wherever they fix the position."""


def choose_rest_frame(points: np.ndarray, joints: np.ndarray, group: np.ndarray, n_seg: int, search: float) -> int:
    """A frame near the start where every segment is best seen.

    points : (F, M, 3); joints : (F, E, 3); group : (M,) segment per marker.
    """
    F = points.shape[0]
    n = max(1, int(np.ceil(F * search)))
    vis = np.isfinite(points[:n]).all(-1)  # (n, M)
    per_seg = np.zeros((n, n_seg), dtype=int)
    for s in range(n_seg):
        per_seg[:, s] = vis[:, group == s].sum(1)
    full = (per_seg >= np.minimum(3, np.bincount(group[group >= 0], minlength=n_seg))).sum(1)
    jvis = np.isfinite(joints[:n]).all(-1).sum(1)
    score = full * 10_000 + jvis * 100 + vis.sum(1)
    return int(np.argmax(score))


def run(joints: Joints, params: Params = Params()) -> Skeleton:
    """Fit constant offsets for every segment; the rest pose is ``rest_frame``'s."""
    seg, mk, pts, edges = _parts(joints)
    F = pts.shape[0]
    S = seg.n_segments
    parent = np.full(S, -1, dtype=int)
    parent_edge = np.full(S, -1, dtype=int)
    for e, (a, b) in enumerate(edges):
        parent[b] = a
        parent_edge[b] = e
    order = depth_first_order(parent)  # parents before children

    if params.rest_frame is None:
        rest = choose_rest_frame(pts, joints.centres, seg.group, S, params.rest_search)
    else:
        rest = int(params.rest_frame)
        if not 0 <= rest < F:
            raise DataError(f"rest frame {rest} is outside the take's {F} frames — choose a frame from 0 to {F - 1}", mk.source or None)
    skel = _fit(joints, joints.centres, rest, parent, parent_edge, order, params)
    if params.refine_frames > 0:
        if joints.alt_centres is None:
            skel = refine(skel, params, joints.centres)
        else:
            # a second start (the joints stage's framework trajectories): both are refined for a few
            # iterations side by side, in two processes, and the better is refined to the end
            def trial(which: int) -> tuple[Skeleton, Skeleton, dict] | None:
                c = joints.centres if which == 0 else joints.alt_centres
                try:
                    st = skel if which == 0 else _fit(joints, c, rest, parent, parent_edge, order, params)
                except DataError:
                    return None
                return (st, *_refine_once(st, params, c, 0.0, iterations=params.trial_iterations))

            def light(which: int):
                # sent back from a forked process: without the take (the same ``joints`` here)
                got = trial(which)
                return None if got is None else (replace(got[0], joints=None), replace(got[1], joints=None), got[2])

            one, two = [None if got is None else (replace(got[0], joints=joints), replace(got[1], joints=joints), got[2])
                        for got in run_forked(light, [0, 1])]
            if "refined" in one[1].info:
                a = one[1].info["refined"]["marker_rms_mm_after"]
                b = two[1].info.get("refined", {}).get("marker_rms_mm_after") if two is not None else None
                # never a lower residual bought with a joint off its markers
                bad_one = len(implausible_joints(one[1], params.far, params.outside))
                bad_two = np.inf if two is None else len(implausible_joints(two[1], params.far, params.outside))
                if bad_one != bad_two:
                    win = 1 if bad_one > bad_two else 0
                elif b is not None and abs(b - a) <= START_TIE * min(a, b) and (
                        (ca := len(collapsed_pairs(one[0]))) != (cb := len(collapsed_pairs(two[0])))):
                    # residuals the markers do not tell apart: the start whose like limbs' joints have
                    # not slid together (both trials slid a real jump's hips together, 13 mm apart, from
                    # starts 154 and 79 mm apart, 0.01 % apart in residual: the refinement that holds
                    # them holds them where the start had them)
                    win = 1 if ca > cb else 0
                elif b is not None and abs(b - a) <= START_TIE * min(a, b) and (
                        (ua := unlike_limb_bones(one[1])) != (ub := unlike_limb_bones(two[1]))):
                    # ... or the start whose like limbs' bones are alike: a real walk's two starts 0.3 % apart,
                    # the one of lower residual with its right thigh 323 mm against the left's 469 (two bones
                    # of the legs more than 20 % apart, none in the other)
                    win = 1 if ua > ub else 0
                else:
                    win = 1 if b is not None and b < a else 0
                st, part, hold = (one, two)[win]
                out = refine(st, params, (joints.centres, joints.alt_centres)[win], part, hold)
                info = dict(out.info)
                info["refined"] = dict(info["refined"], start=("joints", "framework")[win],
                                       marker_rms_mm_starts={"joints": a, "framework": b},
                                       trial_iterations=params.trial_iterations)
                skel = replace(out, info=info)
            else:
                skel = one[1]
    if params.mirror_pairs:
        skel = centre_mirrored_pairs(skel)
    if params.joint_depth and skel.pose_rot is not None:
        skel = deepen_joints(skel, params.hinge_ratio)
    if params.leaf_centre and skel.pose_rot is not None:
        skel = centre_leaf_hinges(skel, params.hinge_ratio)
    return _with_lengths(skel)


def _parts(joints: Joints):
    """(segments, markers, their points, the tree's edges) of a joints artifact."""
    seg = joints.topology.segments
    return seg, seg.markers, seg.markers.points, joints.topology.edges


def _fit(joints: Joints, centres: np.ndarray, rest: int, parent: np.ndarray, parent_edge: np.ndarray,
         order: np.ndarray, params: Params) -> Skeleton:
    """Per-segment rigid fits of markers and joint ``centres`` (F, E, 3) into one skeleton (no refinement)."""
    seg, mk, pts, edges = _parts(joints)
    F, M, _ = pts.shape
    S = seg.n_segments
    use = np.unique(np.concatenate([np.linspace(0, F - 1, min(F, params.max_frames)).round().astype(int), [rest]]))
    rest_i = int(np.searchsorted(use, rest))
    origin = np.full((S, 3), np.nan)
    marker_local = np.full((M, 3), np.nan)
    end_site = np.zeros((S, 3))
    bone_length = np.full(S, np.nan)
    noise = np.full(S, np.nan)
    joint_in = {}  # (segment, edge) -> joint position in that segment's rest shape
    shapes = {}
    for s in range(S):
        mids = seg.members(s)
        eids = np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s))
        obs = np.concatenate([pts[use][:, mids], centres[use][:, eids]], axis=1)
        shape, R, t, rms = procrustes_shape(obs, ref_frame=rest_i, iters=params.iters)
        if not np.isfinite(shape).all():
            shape = _fallback_shape(obs, rest_i, shape)
        if not np.isfinite(shape).all() and use.size < F:
            # the subsample sees this segment too rarely with its joints: every frame
            obs = np.concatenate([pts[:, mids], centres[:, eids]], axis=1)
            shape, R, t, rms = procrustes_shape(obs, ref_frame=rest, iters=params.iters)
            if not np.isfinite(shape).all():
                shape = _fallback_shape(obs, rest, shape)
        if not np.isfinite(shape).all() and mids.size == 2:
            shape = _place_about_axis(obs, rest, shape)
        if not np.isfinite(shape).all():
            raise DataError(
                f"segment {s} (markers {', '.join(mk.labels[i] for i in mids)}) is never seen well enough to fit"
                " — its markers are too rarely seen together with its joints; leave them out with --exclude",
                mk.source or None,
            )
        noise[s] = float(np.sqrt(np.nanmean(rms**2))) if np.isfinite(rms).any() else np.nan
        shapes[s] = (mids, shape[: mids.size])
        for j, e in enumerate(eids):
            joint_in[(s, e)] = shape[mids.size + j]

    for s in order:
        if parent[s] < 0:
            own = [joint_in[(s, e)] for e in np.flatnonzero(edges[:, 0] == s)]
            origin[s] = np.mean(own, axis=0)
            o_shape = origin[s]
        else:
            e = parent_edge[s]
            origin[s] = origin[parent[s]] + (joint_in[(parent[s], e)] - _shape_origin(parent[s], parent, parent_edge, joint_in, edges))
            o_shape = joint_in[(s, e)]
        mids, mshape = shapes[s]
        marker_local[mids] = mshape - o_shape

    names = segment_names([[mk.labels[i] for i in seg.members(s)] for s in range(S)])
    info = {"version": VERSION, "rest_frame": rest, "noise_mm": {names[s]: noise[s] for s in range(S)}}
    skel = Skeleton(
        names=tuple(names), parent=parent, origin=origin, marker_segment=seg.group.copy(),
        marker_local=marker_local, end_site=end_site, bone_length=bone_length, noise=noise,
        rest_frame=rest, labels=mk.labels, joints=joints, info=info,
    )
    return skel


#: Segments up to which the refinement uses ``Params.refine_frames`` frames; beyond, fewer (see below).
REFINE_FULL_SEGMENTS = 15


#: A short take gives the refinement at most one frame in this many (its frames are close and
#: alike; a real take of a few seconds spent most of its fit here).
REFINE_STRIDE = 4


#: Markers up to which the refinement uses all its frames; beyond, fewer (see below).
REFINE_FULL_MARKERS = 48


def refine_frame_count(frames: int, n_segments: int, take_frames: int | None = None, n_markers: int | None = None) -> int:
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
        frames = min(frames, max(100, take_frames // REFINE_STRIDE))
    out = frames
    if n_segments > REFINE_FULL_SEGMENTS:
        out = min(out, max(100, int(frames * (REFINE_FULL_SEGMENTS / n_segments) ** 2)))
    if n_markers is not None and n_markers > REFINE_FULL_MARKERS:
        out = min(out, max(100, int(frames * (REFINE_FULL_MARKERS / n_markers) ** 2)))
    return min(out, frames)


def _rest_markers(skel: Skeleton) -> np.ndarray:
    """(M, 3) every marker's rest-pose position (NaN for markers on no segment or without an offset)."""
    seg = skel.marker_segment
    ok = (seg >= 0) & np.isfinite(skel.marker_local).all(1)
    pos = np.full(skel.marker_local.shape, np.nan)
    pos[ok] = skel.origin[seg[ok]] + skel.marker_local[ok]
    return pos


def _extent(pos: np.ndarray) -> float:
    """The largest distance between two of the markers ``pos`` (M, 3) (NaN rows left out); 0 for fewer than 2."""
    P = pos[np.isfinite(pos).all(1)]
    return float(np.sqrt(((P[:, None] - P[None]) ** 2).sum(-1)).max()) if len(P) > 1 else 0.0


def far_joints(skel: Skeleton, far: float) -> list[int]:
    """Segments whose joint to their parent sits implausibly far from its markers, in the rest pose.

    Far: farther than ``far`` times the subject's marker extent (the largest distance between two
    markers at rest) from the nearest marker of the parent or of the child segment.
    """
    pos = _rest_markers(skel)
    ok = np.isfinite(pos).all(1)
    if ok.sum() < 2:
        return []
    lim = far * _extent(pos)
    out = []
    for c in np.flatnonzero(skel.parent >= 0):
        for s_ in (int(skel.parent[c]), int(c)):
            m = pos[ok & (skel.marker_segment == s_)]
            if len(m) and float(np.linalg.norm(m - skel.origin[c], axis=1).min()) > lim:
                out.append(int(c))
                break
    return out


def outside_joints(skel: Skeleton, frac: float) -> list[int]:
    """Segments whose joint to their parent sits outside the convex hull of all markers at rest by more
    than ``frac`` times the marker extent (the largest distance between two markers at rest)."""
    pos = _rest_markers(skel)
    kids = np.flatnonzero(skel.parent >= 0)
    out = beyond_hull(pos, skel.origin[kids])
    lim = frac * _extent(pos)
    return [int(c) for c, d in zip(kids, out) if d > lim]


def off_the_body(skel: Skeleton, far: float, outside: float) -> list[int]:
    """Segments whose joint to their parent is off the body: :func:`far_joints` or :func:`outside_joints`."""
    return sorted(set(far_joints(skel, far)) | set(outside_joints(skel, outside)))


#: Two refinement starts whose trial residuals agree within this fraction are a tie the markers do not
#: decide (a real jump's: 0.01 %; a generated two-marker subject's, where the lower is the better start: 1.3 %).
START_TIE = 0.005

#: Like limbs' first joints nearer each other than this fraction of the distance between the two limbs'
#: first segments' marker centroids at rest have slid together. Measured: fitted hips sit at 0.44-0.53 of
#: it (a real jump, a real walk, a generated range-of-motion subject), shoulders at 0.66; a real jump's
#: hips slid together, 0.04, and one of its starts, 0.24.
COLLAPSED = 0.3


def collapsed_pairs(skel: Skeleton, frac: float = COLLAPSED) -> list[int]:
    """Like limbs (two children of one segment whose subtrees have the same shape, segment for segment
    as many markers, each of two segments or more: two legs, two arms) whose joints sit nearer each
    other than ``frac`` times the distance between the two limbs' first segments' marker centroids at
    rest. Legs that move alike (a two-footed jump) do not fix their hips along the line between them,
    and a fit can slide both to the middle of the pelvis: no body has two hips at one point."""
    pos, seg, count = _rest_groups(skel)
    out: set[int] = set()
    for _, a, b in _like_limb_pairs(skel.parent, count):
        if count[a] == 0:
            continue
        ca, cb = pos[seg == a].mean(0), pos[seg == b].mean(0)
        if float(np.linalg.norm(skel.origin[a] - skel.origin[b])) < frac * float(np.linalg.norm(ca - cb)):
            out |= {a, b}
    return sorted(out)


def unlike_limb_bones(skel: Skeleton, tol: float = 0.2) -> int:
    """How many bones of like limbs (two children of one segment that are chains of as many segments, two or
    more: two legs, two arms) differ by more than ``tol`` of the shorter, compared segment for segment down the
    chains (the ``limb_asymmetry`` check's rule, on the tree's shape alone)."""
    from ..model.tree import like_limb_pairs, unlike_bones

    return len(unlike_bones(skel, [(a, b) for a, b, _ in like_limb_pairs(np.asarray(skel.parent))], tol))


def implausible_joints(skel: Skeleton, far: float, outside: float) -> list[int]:
    """Segments whose joint to their parent no body has: :func:`off_the_body`, or a bone (the joint's
    distance from the parent's joint) longer than the subject's marker extent at rest (the
    ``bone_length`` check's rule)."""
    lim = _extent(_rest_markers(skel))
    long = [int(c) for c in np.flatnonzero(skel.parent >= 0)
            if float(np.linalg.norm(skel.origin[c] - skel.origin[skel.parent[c]])) > lim]
    return sorted(set(off_the_body(skel, far, outside)) | set(long))


def slid_joints(before: Skeleton, after: Skeleton, slide: float) -> list[int]:
    """Segments whose joint to their parent moved, relative to the markers of the parent or of the child,
    by more than ``slide`` times the subject's marker extent between two fits (rest-pose axes)."""
    lim = slide * _extent(_rest_markers(before))
    out = []
    for c in np.flatnonzero(before.parent >= 0):
        p = int(before.parent[c])
        for s_, own in ((p, False), (int(c), True)):
            m = (before.marker_segment == s_) & np.isfinite(before.marker_local).all(1) & np.isfinite(after.marker_local).all(1)
            if not m.any():
                continue
            # the joint relative to the segment's marker centroid: -mean(l) in the child, d_c - mean(l) in the parent
            rel = [(sk.origin[c] - sk.origin[p] if not own else 0.0) - sk.marker_local[m].mean(0) for sk in (before, after)]
            if float(np.linalg.norm(rel[1] - rel[0])) > lim:
                out.append(int(c))
                break
    return out


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
    :func:`~mocapskel.solvers.calibrate.refine_skeleton`), and a joint slid along a direction the
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

    See :mod:`mocapskel.solvers.calibrate`; the start is IK with the
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
    from .ik import _centres_by_edges, solve

    pts = skel.joints.topology.segments.markers.points
    vis = np.isfinite(pts).all(-1)
    use = pick_frames(vis, refine_frame_count(params.refine_frames, len(skel.names), pts.shape[0],
                                              int((skel.marker_segment >= 0).sum())), must=skel.rest_frame)
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


def _relative_rotations(rot: np.ndarray, p: int, c: int, seen: np.ndarray | None = None,
                        least: int = 10) -> np.ndarray | None:
    """``R_p^T R_c`` of poses ``rot`` (F, S, 3, 3) on the frames where both are known, or None when they
    are fewer than ``least`` (too few to tell how a joint turns).

    seen : (F, S) whether each segment has a marker seen in each frame
    (:func:`~mocapskel.solvers.rotations.segments_seen`): frames where either has none are left out (IK
    filled its pose there: a guess, not a measurement).
    """
    rel = np.swapaxes(rot[:, p], 1, 2) @ rot[:, c]
    ok = np.isfinite(rel).all((1, 2))
    if seen is not None:
        ok &= seen[:, p] & seen[:, c]
    rel = rel[ok]
    return rel if len(rel) >= least else None


def _relative_rotvecs(rel: np.ndarray) -> np.ndarray:
    """(F, 3) rotation vectors of the rotations ``rel`` (F, 3, 3) about their chordal mean."""
    return matrix_to_rotvec(np.swapaxes(project_to_so3(rel.sum(0)), 0, 1)[None] @ rel)


def _hinge_direction(rel: np.ndarray, hinge_ratio: float, twist: np.ndarray | None = None,
                     rv: np.ndarray | None = None) -> np.ndarray | None:
    """The axis the relative rotations ``rel`` (F, 3, 3) turn about when they turn about one (their
    spread about the second axis at most ``hinge_ratio`` of the first: a hinge); None otherwise.

    twist : the child's long axis (its rest-pose bone direction), or None: the rotations' part about
    it is left out (a limb segment of one or two markers along its bone hardly fixes its own twist,
    and a hinge turns across its bone, not about it).
    rv : ``_relative_rotvecs(rel)`` when the caller has them.
    """
    rv = _relative_rotvecs(rel) if rv is None else rv
    if twist is not None:
        rv = rv - np.outer(rv @ twist, twist)
    _, sv, Vt = np.linalg.svd(rv, full_matrices=False)
    if not sv[0] > 0 or sv[1] > hinge_ratio * sv[0]:
        return None
    return Vt[0]


def _bone_line(skel: Skeleton, s: int) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Segment ``s``'s joint, the unit direction to the mean of its child joints and that length;
    None for a root, a leaf or a zero length."""
    kids = np.flatnonzero(skel.parent == s)
    if skel.parent[s] < 0 or kids.size == 0:
        return None
    a = skel.origin[s]
    v = skel.origin[kids].mean(0) - a
    n = float(np.linalg.norm(v))
    return (a, v / n, n) if n > 0 else None


def _limb_radius(skel: Skeleton, s: int, pos: np.ndarray, skip: set) -> float | None:
    """Median distance of segment ``s``'s markers (but ``skip``) from its bone line (its joint to the
    mean of its child joints), over markers along its middle 70 %; None for a root or a leaf."""
    line = _bone_line(skel, s)
    if line is None:
        return None
    a, u, n = line
    r = []
    for m in np.flatnonzero(skel.marker_segment == s):
        if m in skip or not np.isfinite(pos[m]).all():
            continue
        v = pos[m] - a
        t = float(v @ u)
        if 0.15 * n < t < 0.85 * n:
            r.append(float(np.linalg.norm(v - t * u)))
    return float(np.median(r)) if r else None


#: A limb's half-width is at most this fraction of its length (adult thigh, shank, upper arm and
#: forearm: 0.10-0.15).
LIMB_WIDTH = 0.2


def _half_width(skel: Skeleton, origin: np.ndarray, c: int, point: np.ndarray, pos: np.ndarray,
                skip: set) -> tuple[float, float] | None:
    """(half-width, length) of the limbs on either side of segment ``c``'s joint put at ``point``
    (``origin`` the skeleton's rest origins otherwise): the mean of :func:`_limb_radius` of the parent
    and of ``c`` (markers ``skip`` left out), and the shorter of their bone lengths. None when one of
    them gives none, the two disagree by more than a factor of 2, or the half-width is more than
    ``LIMB_WIDTH`` of the length (no limb has it)."""
    lv = origin.copy()
    lv[c] = point
    at = replace(skel, origin=lv)
    p = int(skel.parent[c])
    radii = [r for s_ in (p, c) if (r := _limb_radius(at, s_, pos, skip)) is not None]
    if len(radii) < 2 or max(radii) > 2.0 * min(radii):
        return None
    r = float(np.mean(radii))
    length = min(line[2] for s_ in (p, c) if (line := _bone_line(at, s_)) is not None)
    return None if r > LIMB_WIDTH * length else (r, length)


def deepen_joints(skel: Skeleton, hinge_ratio: float) -> Skeleton:
    """Hinges between two limbs with a marker over their axis get their centre one limb half-width
    inside that marker.

    A knee marker sits on the skin over the flexion axis; the joint centre lies on that axis, about
    half the joint's width deeper. Along the axis the markers hardly fix the centre (the fit leaves it
    near the marker, or slides it past). For a joint whose relative rotations (the refinement's poses)
    turn about one axis (spread about the second axis at most ``hinge_ratio`` of the first, their part
    about the child's bone line left out: a limb segment of one or two markers hardly fixes its own
    twist) and a marker of its two segments within one limb half-width of that axis and, along it,
    within a quarter of the shorter limb's length (or one and a half half-widths, if more) of the
    centre, the centre is moved along the axis, away from the marker towards the subject's middle, to
    one limb half-width from it. The half-width is the median distance of the two limbs' other
    markers from their bone lines, drawn through the axis at the level of that marker; both limbs
    must give one and agree within a factor of 2 (a leaf, such as a foot or a forearm that carries
    the hand's markers, has no bone line: ankles deepened by the shank's half-width alone came out
    from 25 mm nearer to 51 mm farther from the truth on generated kicks and walks). A second marker
    on the axis (both nearer it than a quarter of their distance apart), one to three half-widths
    along it from the first (a medial and a lateral knee marker), puts it between the two, wherever
    the fit left it. Each segment keeps its markers where they were; the move is along the axis the
    joint turns about, so the poses still fit.
    """
    R = skel.pose_rot
    vis = None if skel.pose_frames is None else segments_seen(
        skel.marker_segment, len(skel.names), skel.joints.topology.segments.markers.points[skel.pose_frames])
    pos = _rest_markers(skel)
    ok_m = np.isfinite(pos).all(1)
    if ok_m.sum() < 3:
        return skel
    centre = pos[ok_m].mean(0)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    moved = {}
    for c in np.flatnonzero(skel.parent >= 0):
        p = int(skel.parent[c])
        if skel.parent[p] < 0 or not (skel.parent == c).any():
            continue  # the root or a leaf on one side: one limb to measure a half-width on
        rel = _relative_rotations(R, p, int(c), vis)
        if rel is None:
            continue
        J = origin[c]
        near = [int(m) for m in np.flatnonzero(ok_m & np.isin(skel.marker_segment, [p, c]))]
        if not near:
            continue
        # the axis, and the bone lines the half-widths are measured from, through the axis at the level
        # of the marker nearest it: a centre the fit slid along the axis, past that marker, would tilt
        # them. Twice: the child's twist is left out about its bone line through that level.
        level = origin.copy()
        for _ in range(2):
            at = replace(skel, origin=level)
            line = _bone_line(at, int(c))
            ax = _hinge_direction(rel, hinge_ratio, None if line is None else line[1])
            if ax is None:
                break
            t = {m: float((pos[m] - J) @ ax) for m in near}
            off = {m: float(np.linalg.norm(pos[m] - J - t[m] * ax)) for m in near}
            over = sorted(near, key=lambda m: off[m])
            level = origin.copy()
            level[c] = J + t[over[0]] * ax
        if ax is None:
            continue

        # a second marker on the axis (nearer it than a quarter of their distance apart) a joint's width
        # from the first (one to three half-widths, measured at either marker's level): a medial and
        # a lateral knee marker. The centre goes between them, wherever the fit left it along the axis
        m0, pair = over[0], None
        for m1 in over[1:]:
            gap = abs(t[m1] - t[m0])
            if max(off[m0], off[m1]) > 0.25 * gap:
                continue
            got = (_half_width(skel, origin, c, J + t[m0] * ax, pos, {m0, m1})
                   or _half_width(skel, origin, c, J + t[m1] * ax, pos, {m0, m1}))
            if got is not None and got[0] <= gap <= 3.0 * got[0]:
                pair = m1
                break
        if pair is not None:
            shift = 0.5 * (t[m0] + t[pair])
        else:
            got = _half_width(skel, origin, c, J + t[m0] * ax, pos, {m0})
            if got is None:
                continue
            r, length = got
            # over the joint: on the axis, and along it within a limb's reach (where along it the fit
            # put the centre, the markers hardly said)
            on = [m for m in over if off[m] <= r and abs(t[m]) <= max(1.5 * r, 0.25 * length)]
            if not on:
                continue
            m = on[0]
            inward = np.sign(float((centre - pos[m]) @ ax)) or 1.0
            shift = t[m] + inward * r
        origin, local = _move_joint(origin, local, skel.marker_segment, c, shift * ax)
        moved[skel.names[c]] = round(float(abs(shift)), 1)
    if not moved:
        return skel
    # hinges between two limbs: none is a child of the root, whose origin stays
    return _with_moves(skel, origin, local, set(), "deepened", moved)


def _rest_groups(skel: Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The markers at rest (M, 3), each one's segment (-1 where unplaced) and each segment's count."""
    pos = _rest_markers(skel)
    seg = np.where(np.isfinite(pos).all(1), skel.marker_segment, -1)
    return pos, seg, np.bincount(seg[seg >= 0], minlength=len(skel.parent))


def _like_limb_pairs(parent: np.ndarray, count: np.ndarray) -> list[tuple[int, int, int]]:
    """(parent, a, b) for every two children of one segment that are like limbs: subtrees of the same
    shape, segment for segment as many markers (``count``), each of two segments or more (two legs,
    two arms; not a head and an arm). By parent, then in child order."""
    parent = np.asarray(parent)
    out = []
    for p in range(len(parent)):
        kids = [int(k) for k in np.flatnonzero(parent == p)]
        shape = {c: _subtree_shape(parent, count, c) for c in kids}
        out += [(p, a, b) for i, a in enumerate(kids) for b in kids[i + 1:] if shape[a] == shape[b] and shape[a][1]]
    return out


def _subtree_shape(parent: np.ndarray, count: np.ndarray, s: int) -> tuple:
    """A canonical form of the subtree below segment ``s``: its marker count and its children's
    forms, sorted."""
    return (int(count[s]), tuple(sorted(_subtree_shape(parent, count, int(k)) for k in np.flatnonzero(parent == s))))


#: A segment's markers are symmetric about a plane when each, reflected in it, lies within this
#: fraction of the distance between the two limbs' joints from one of them.
MIRROR_MATCH = 0.25

#: A step is taken when it raises the mean squared marker residual (poses solved again) by at most
#: this fraction of its own square: the markers hardly see it. Measured: hips the markers fix,
#: 0.0044-0.0094 (generated range-of-motion subjects, three and two markers a segment); hips that
#: slid, 0.00013-0.00054 (a real jump, generated walks and a kick); the bar sits a factor 2-4 from each.
MIRROR_SEEN = 0.002


def _symmetry_normal(points: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, float]:
    """The normal of the plane through the centroid of ``points`` (n, 3) that best mirrors them onto
    themselves, among ``guess`` and the directions between two of them (a mirror pair's direction is
    the plane's normal); and how far the worst reflected point lands from the nearest point."""
    cen = points.mean(0)
    cand = [guess] + [points[j] - points[i] for i in range(len(points)) for j in range(i + 1, len(points))]
    best, miss = guess, np.inf
    for c in cand:
        norm = float(np.linalg.norm(c))
        if not norm > 0:
            continue
        m = _mirror_miss(points, cen, c / norm)
        if m < miss:
            best, miss = c / norm, m
    return best, miss


def _mirror_miss(points: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> float:
    """How far the worst of ``points`` (n, 3), reflected in the plane through ``centre`` normal to the
    unit ``normal``, lands from the nearest of them (0 for a set symmetric about that plane)."""
    refl = points - 2.0 * ((points - centre) @ normal)[:, None] * normal
    return float(np.linalg.norm(refl[:, None] - points[None], axis=2).min(1).max())


def centre_mirrored_pairs(skel: Skeleton, seen: float = MIRROR_SEEN, match: float = MIRROR_MATCH) -> Skeleton:
    """Like limbs on one segment: their first joints moved together into the segment's plane of
    symmetry (:func:`mirror_shifts`), where the markers hardly see the step. Each limb keeps its
    markers where they were, and the root's origin stays the mean of its children's joints.

    The steps under one segment are kept when they raise the mean squared marker residual on the
    refinement's frames (poses solved again from the refinement's) by at most ``seen`` times the
    square of the step: a slide along what the markers do not fix is put back; a joint they fix is
    not moved. (The rise itself does not tell: a free fit slides joints into skin motion, and putting
    them back raised the rms by 8 % on a real jump whose hips came 90 mm nearer the reference, 9-14 %
    on generated walks, 24 % where a generated range-of-motion subject's fixed hips would have
    moved 18 mm; per squared step the two differ tenfold.)"""
    if skel.pose_rot is None or skel.pose_frames is None:
        return skel
    shifts = mirror_shifts(skel, match, loose_joints(skel))
    if not shifts:
        return skel
    parent = np.asarray(skel.parent)
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    base = _pose_ms(skel, origin, local, pts)
    kept: dict[int, np.ndarray] = {}
    for p in sorted({int(parent[c]) for c in shifts}):
        group = {c: d for c, d in shifts.items() if parent[c] == p}
        o2, l2 = origin, local
        for c, d in group.items():
            o2, l2 = _move_joint(o2, l2, skel.marker_segment, c, d)
        step2 = max(float(d @ d) for d in group.values())
        if _pose_ms(skel, o2, l2, pts) - base <= seen * step2:
            origin, local = o2, l2
            kept.update(group)
    if not kept:
        return skel
    moved = {skel.names[c]: round(float(np.linalg.norm(d)), 1) for c, d in kept.items()}
    return _with_moves(skel, origin, local, set(kept), "mirrored", moved)


#: The end of a limb is a short segment: its markers' centroid at most this fraction of its parent's
#: bone length from the joint (a foot's heel, toe and metatarsal markers: 0.15-0.3 of the shank; a
#: forearm carrying its markers at the wrist, a head band on a neck: 0.5 and more).
LEAF_SHORT = 0.5
#: ...and its markers lie across the hinge axis from the joint: their centroid's step along the axis at
#: most this fraction of its distance (45 degrees; feet whose centre sat at the ankle marker: 0.3-0.6;
#: two-marker toe and heel-toe groups that turn about an axis along them: 0.8-1.0).
LEAF_ACROSS = 0.7
#: ...and its motion is not exercised in every direction: the spread of its relative rotations about
#: the third axis at most this fraction of that about the second (walks', runs' and kicks' ankles,
#: generated and real, turn mostly about the flexion axis and one other: 0.30-0.79; a generated
#: range-of-motion take's ankles, turned alike every way across the flexion axis, 0.91-0.96: there
#: the motion fixes the centre (the takes' joints 3-6 mm rms from the truth), and the foot's markers
#: sit anywhere on it).
LEAF_PLANAR = 0.85


def centre_leaf_hinges(skel: Skeleton, hinge_ratio: float, seen: float | None = None) -> Skeleton:
    """Hinges at the end of a limb get their centre, along the axis, at the mean position of the child's
    markers.

    Along a hinge's axis the markers hardly fix its centre. The joints stage puts it at the point of
    the axis nearest the centroid of both segments' markers, and a limb's end is where that goes wrong:
    an axis tilted by a few degrees carries the parent's markers far up the limb tens of millimetres
    along it (a real walk's ankle, under a shank cluster, came out 46 mm medial), and markers on one
    side (a malleolus and a lateral shank marker) pull it outward (generated kicks' and walks' ankles
    sat at the ankle marker, 30-44 mm lateral). The child's markers, when they lie nearer the joint
    than the parent's (a foot's heel, toe and metatarsal markers around the ankle; not a forearm whose
    markers are at the wrist), surround the end segment's middle, which lies under the joint centre.
    For a leaf segment with two or more markers whose parent is not the root, whose relative rotations
    turn about one axis (a hinge the refinement held, or a spread about the second axis at most
    ``hinge_ratio`` of the first) and not exercised in every direction (``LEAF_PLANAR``), short beside its parent (``LEAF_SHORT``) and with its markers across
    the axis from the joint (``LEAF_ACROSS``), the centre is moved along that axis to the mean axial
    position of the child's markers, unless a marker of the parent over the axis (nearer it than half the child's
    markers' distance from the centre) shows the centre already lies farther from that skin marker
    than from the child's middle (inside the limb, where the fit put it), and unless the markers see
    the move: it is made only when it raises the mean squared marker residual on the refinement's
    frames (poses solved again) by at most ``seen`` (mm^2; None: the square of the take's own level of
    skin motion and noise, measured by the segment stage). Moved so, the ankles of generated walks,
    runs and kicks raised it by 0.004-0.1 of that, a real walk's 0.9; the left wrist of a generated
    range-of-motion take, whose markers sit anywhere on the hand and whose motion fixes it better,
    would have moved 105 mm (12 times it). Each segment keeps its markers where they
    were; the move is along the axis the joint turns about, so the poses still fit.
    """
    if skel.pose_rot is None or skel.pose_frames is None:
        return skel
    if seen is None:
        level = skel.joints.topology.segments.info.get("skin_level_mm")
        if not level or not np.isfinite(level):
            return skel
        seen = float(level) ** 2
    R = skel.pose_rot
    pts = skel.joints.topology.segments.markers.points[skel.pose_frames]
    vis = segments_seen(skel.marker_segment, len(skel.names), pts)
    base = None
    pos = _rest_markers(skel)
    ok_m = np.isfinite(pos).all(1)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    held = None
    moved = {}
    for c in np.flatnonzero(skel.parent >= 0):
        p = int(skel.parent[c])
        if skel.parent[p] < 0 or (skel.parent == c).any():
            continue  # on the root (not the end of a limb), or not a leaf
        mk = np.flatnonzero(ok_m & (skel.marker_segment == c))
        mp = np.flatnonzero(ok_m & (skel.marker_segment == p))
        if mk.size < 2 or mp.size == 0:
            continue
        J = origin[c]
        dc = float(np.linalg.norm(pos[mk].mean(0) - J))
        if not dc < float(np.linalg.norm(pos[mp].mean(0) - J)):
            continue  # the child's markers are no nearer the joint than the parent's
        rel = _relative_rotations(R, p, int(c), vis)
        if rel is None:
            continue
        if held is None:
            held = _hinge_axes(skel, R, hinge_ratio, vis)
        rv = _relative_rotvecs(rel)
        ax = held.get(int(c))
        if ax is None:
            ax = _hinge_direction(rel, hinge_ratio, rv=rv)
        if ax is None:
            continue
        sv = np.linalg.svd(rv, compute_uv=False)
        if not sv[1] > 0 or sv[2] > LEAF_PLANAR * sv[1]:
            continue  # it turns alike about every axis across the main one: exercised in every direction
        shift = float(np.mean((pos[mk] - J) @ ax))
        line = _bone_line(skel, p)
        if line is None or dc > LEAF_SHORT * line[2] or abs(shift) > LEAF_ACROSS * dc:
            continue  # not a short end segment whose markers lie across the axis from the joint
        t = (pos[mp] - J) @ ax
        off = np.linalg.norm(pos[mp] - J - t[:, None] * ax, axis=1)
        over = np.flatnonzero(off <= 0.5 * dc)
        if over.size and abs(float(t[over[np.argmin(off[over])]])) >= abs(shift):
            continue  # already inside the limb: farther from its skin marker than from the child's middle
        o2, l2 = _move_joint(origin, local, skel.marker_segment, c, shift * ax)
        if base is None:
            base = _pose_ms(skel, origin, local, pts)
        ms = _pose_ms(skel, o2, l2, pts)
        if ms - base > seen:
            continue  # the markers see the move: they fix the centre along the axis
        origin, local, base = o2, l2, ms
        moved[skel.names[c]] = round(abs(shift), 1)
    if not moved:
        return skel
    # ends of limbs: none is a child of the root, whose origin stays
    return _with_moves(skel, origin, local, set(), "leaf_centred", moved)


def _with_moves(skel: Skeleton, origin: np.ndarray, local: np.ndarray, kids_moved: set, key: str,
                moved: dict) -> Skeleton:
    """``skel`` with rest offsets ``origin``, ``local`` after the joints of ``kids_moved`` were moved
    (each with its segment's markers kept where they were), ``moved`` ({name: mm}) noted in its info
    under ``key`` and in the refinement's section as ``key``_mm. The root's origin stays the mean of
    its children's joints (the refinement's gauge)."""
    parent = np.asarray(skel.parent)
    root = int(np.flatnonzero(parent < 0)[0])
    kids = np.flatnonzero(parent == root)
    origin, local = origin.copy(), local.copy()
    pose_root = skel.pose_root
    if any(int(k) in kids_moved for k in kids):
        m = origin[kids].mean(0) - skel.origin[kids].mean(0)
        origin[root] = origin[root] + m
        local[skel.marker_segment == root] -= m
        pose_root = pose_root + skel.pose_rot[:, root] @ m
    info = dict(skel.info, **{key: moved})
    if "refined" in info:  # the report's refinement section names them
        info["refined"] = dict(info["refined"], **{f"{key}_mm": moved})
    return replace(skel, origin=origin, marker_local=local, info=info, pose_root=pose_root)


def _move_joint(origin: np.ndarray, local: np.ndarray, seg: np.ndarray, c: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Copies of rest offsets with segment ``c``'s joint moved by ``d``, its markers kept where they were."""
    o2, l2 = origin.copy(), local.copy()
    o2[c] = o2[c] + d
    l2[seg == c] -= d
    return o2, l2


def _repose(skel: Skeleton, origin: np.ndarray, local: np.ndarray, pts: np.ndarray):
    """IK of a skeleton with rest offsets ``origin``, ``local`` on ``pts`` (F, M, 3), the refinement's
    frames, from the refinement's poses, with no prior."""
    return solve_ik(skel.parent, origin, skel.marker_segment, local, pts, init_rot=skel.pose_rot,
                    init_root=skel.pose_root, prior_weight=0.0)


def _pose_ms(skel: Skeleton, origin: np.ndarray, local: np.ndarray, pts: np.ndarray) -> float:
    """Mean squared marker residual (mm^2) of a skeleton with rest offsets ``origin``, ``local`` on
    ``pts`` (F, M, 3), the refinement's frames: :func:`_repose`."""
    res = _repose(skel, origin, local, pts)
    r = res.residual[np.isfinite(res.residual)]
    return float(np.mean(r * r)) if r.size else np.inf


def loose_joints(skel: Skeleton) -> set[int]:
    """Child segments whose joint the markers may leave free along some direction: all but those SCoRE
    fixed in full (3+ markers on both segments, motion not hinge-like)."""
    edges = skel.joints.topology.edges
    return {int(b) for e, (_, b) in enumerate(edges) if skel.joints.method[e] != "score"}


def mirror_shifts(skel, match: float = MIRROR_MATCH, loose: set | None = None) -> dict[int, np.ndarray]:
    """{child segment: step (3,)} that puts the first joints of like limbs in their parent's plane of symmetry.

    A body is mirror-symmetric: two legs hang from the pelvis, two arms from the thorax, at mirror
    places about its middle plane. When both legs move alike (a two-footed jump, a squat) or about
    one axis (a walk), the markers fix neither hip along the line between them, and the fit can
    slide both together at almost no cost: a real jump's hips came out 90-100 mm to one side, one
    beside the other side of the pelvis. For two children of one segment with subtrees of the same
    shape, segment for segment as many markers, each of two segments or more (two legs of thigh,
    shank and foot; not a head and an arm, nor the two ends of a chain held by its middle), when the
    parent's markers are symmetric about a plane through their centroid (each, reflected in it,
    within ``match`` times the joints' distance of another: :func:`_symmetry_normal`) that lies
    across the line between the two joints (at most 60 degrees from its normal) with one limb's
    markers on either side, both joints get the same step along its normal, the one that puts
    their midpoint in the plane. The distance between them, which the markers fix, is kept. Another
    child of that parent whose own markers mirror onto themselves in that plane (a trunk's midline
    markers on a pelvis) has its joint moved along the normal into it. A parent whose markers are not
    symmetric (a thorax with a marker on one shoulder blade) says nothing. The limbs' own markers are
    not compared: marker sets place them asymmetrically on purpose (a thigh marker higher on one side).

    Only joints the markers may leave free are candidates: both of the pair in ``loose`` (child
    segments; None: any; see :func:`loose_joints`). Where the markers fix a joint (a range-of-motion
    take's hips) they know better than the symmetry of a body, whose markers are never placed exactly
    mirror-wise (a generated subject's hips, well fixed, were moved 18 mm off and its shoulders 43 mm);
    :func:`centre_mirrored_pairs` also asks the markers.

    skel : anything with ``origin``, ``marker_local``, ``marker_segment`` and ``parent`` (rest pose).
    """
    pos, seg, count = _rest_groups(skel)
    parent = np.asarray(skel.parent)
    origin = skel.origin
    out: dict[int, np.ndarray] = {}
    for p, a, b in _like_limb_pairs(parent, count):
        mk = pos[seg == p]
        if len(mk) < 2 or a in out or b in out:
            continue
        if loose is not None and not {a, b} <= loose:
            continue  # the markers fix one of them
        v = origin[b] - origin[a]
        sep = float(np.linalg.norm(v))
        if not sep > 0 or count[a] == 0:  # (like shapes: as many markers on b)
            continue
        cen = mk.mean(0)
        n, miss = _symmetry_normal(mk, v / sep)
        if miss > match * sep or abs(float(n @ v)) < 0.5 * sep:
            continue  # no plane of symmetry, or not one across the line between the two joints
        sides = [float((pos[seg == c].mean(0) - cen) @ n) for c in (a, b)]
        if not sides[0] * sides[1] < 0:
            continue  # not one limb on either side
        d = float((cen - 0.5 * (origin[a] + origin[b])) @ n) * n
        out[a], out[b] = d, d.copy()
        # a child on the middle line (a trunk on the pelvis: its markers mirror onto themselves
        # in the same plane) has its joint in the plane too
        for c in (int(k) for k in np.flatnonzero(parent == p)):
            own = pos[seg == c]
            if c in out or not len(own) or loose is not None and c not in loose:
                continue
            if _mirror_miss(own, cen, n) <= match * sep:
                out[c] = float((cen - origin[c]) @ n) * n
    return out


def _hinge_axes(skel: Skeleton, rot: np.ndarray, hinge_ratio: float, seen: np.ndarray | None = None
                ) -> dict[int, np.ndarray]:
    """{child segment: hinge axis (rest-pose axes)} of the joints whose centre the markers hardly fix
    along one axis: those the joints stage placed as hinges, and those SCoRE fixed in full whose
    relative rotations ``R_parent^T R_child`` of ``rot`` (F, S, 3, 3) turn about one axis (spread
    about the second axis at most ``hinge_ratio`` of the first: :func:`_hinge_direction`): a walk's
    ankle, which SCoRE solves by least squares along an axis its motion barely fixes.

    The axis is the direction the relative rotations leave most nearly fixed: the eigenvector of
    SCoRE's ``[[I, -M], [-M^T, I]]`` (``M`` their mean) of the smallest eigenvalue. ``seen``: as
    :func:`_relative_rotations` takes it.
    """
    joints = skel.joints
    per = joints.info.get("per_joint") or []
    out = {}
    for e, (a, b) in enumerate(joints.topology.edges):
        placed = e < len(per) and per[e].get("hinge")
        if not placed and joints.method[e] != "score":
            continue  # a joint of a one- or two-marker segment: its start is too rough to hold
        c = int(b) if skel.parent[int(b)] == int(a) else int(a)
        p = int(skel.parent[c])
        rel = _relative_rotations(rot, p, c, seen)
        if rel is None:
            continue
        if not placed and _hinge_direction(rel, hinge_ratio) is None:
            continue
        M = rel.mean(0)
        N = np.eye(6)
        N[:3, 3:] = -M
        N[3:, :3] = -M.T
        v = np.linalg.eigh(N)[1][:, 0]
        axis = v[:3] + v[3:]
        if np.linalg.norm(axis) > 0:
            out[c] = axis / np.linalg.norm(axis)
    return out


def _with_lengths(skel: Skeleton) -> Skeleton:
    """Bone lengths and End Sites from the skeleton's offsets."""
    S = len(skel.names)
    origin, parent = skel.origin, skel.parent
    end_site = np.zeros((S, 3))
    bone_length = np.full(S, np.nan)
    for s in range(S):
        kids = np.flatnonzero(parent == s)
        if parent[s] < 0 and kids.size == 2:  # a root between two joints: the joint-to-joint length
            bone_length[s] = float(np.linalg.norm(origin[kids[0]] - origin[kids[1]]))
        elif kids.size and parent[s] >= 0:
            bone_length[s] = float(np.mean(np.linalg.norm(origin[kids] - origin[s], axis=1)))
        if kids.size == 0:
            end_site[s] = _end_site(skel.marker_local[skel.marker_segment == s])
            bone_length[s] = float(np.linalg.norm(end_site[s]))
    return replace(skel, end_site=end_site, bone_length=bone_length)


def _shape_origin(s, parent, parent_edge, joint_in, edges) -> np.ndarray:
    """A segment's origin in its own rest shape."""
    if parent[s] < 0:
        return np.mean([joint_in[(s, e)] for e in np.flatnonzero(edges[:, 0] == s)], axis=0)
    return joint_in[(s, parent_edge[s])]


def _end_site(local: np.ndarray) -> np.ndarray:
    """End Site of a leaf: along its markers' mean direction, as far as its farthest marker."""
    c = local.mean(axis=0)
    n = np.linalg.norm(c)
    if n < 1e-6:
        return np.array([0.0, 0.0, 10.0])
    u = c / n
    return u * max(float((local @ u).max()), n)


def _place_about_axis(obs: np.ndarray, rest: int, shape: np.ndarray) -> np.ndarray:
    """A two-marker segment's joints that are never seen together (nor with a third point), placed
    about its marker axis: each at its median distance along and from the axis, turned about it as
    seen at its visible frame nearest ``rest``. Two markers do not fix the turn about their axis, so
    the joints' relative turn is a choice, not a measurement (IK turns the segment to each joint)."""
    out = shape.copy()
    if not (np.isfinite(out[0]).all() and np.isfinite(out[1]).all()):
        return out
    u = out[1] - out[0]
    if not np.linalg.norm(u) > 0:
        return out
    u = u / np.linalg.norm(u)
    vis = np.isfinite(obs).all(-1)
    for p in range(2, obs.shape[1]):
        if np.isfinite(out[p]).all():
            continue
        fr = np.flatnonzero(vis[:, 0] & vis[:, 1] & vis[:, p])
        if not fr.size:
            continue
        a = obs[fr, 1] - obs[fr, 0]
        ok = np.linalg.norm(a, axis=1) > 0
        if not ok.any():
            continue
        fr, a = fr[ok], a[ok] / np.linalg.norm(a[ok], axis=1)[:, None]
        d = obs[fr, p] - obs[fr, 0]
        along = np.einsum("fi,fi->f", d, a)
        radial = np.linalg.norm(d - along[:, None] * a, axis=1)
        k = int(np.argmin(np.abs(fr - rest)))
        perp = rotation_between(a[k], u) @ (d[k] - along[k] * a[k])
        perp = perp - (perp @ u) * u
        n = np.linalg.norm(perp)
        side = perp / n if n > 0 else np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        side = side / np.linalg.norm(side)
        out[p] = out[0] + float(np.median(along)) * u + float(np.median(radial)) * side
    return out


def _fallback_shape(obs: np.ndarray, rest: int, shape: np.ndarray) -> np.ndarray:
    """Shape for segments Procrustes cannot align (fewer than 3 non-collinear points).

    Each point is placed relative to the last point (the segment's joint) as seen
    at the visible frame nearest ``rest``, at its median distance over the take.
    """
    F, P, _ = obs.shape
    out = shape.copy()
    anchor = P - 1
    vis = np.isfinite(obs).all(-1)
    for p in range(P):
        if np.isfinite(out[p]).all():
            continue
        both = vis[:, p] & vis[:, anchor]
        if p == anchor:
            fr = np.flatnonzero(vis[:, p])
            if fr.size:
                out[p] = obs[fr[np.argmin(np.abs(fr - rest))], p]
            continue
        fr = np.flatnonzero(both)
        if not fr.size:
            continue
        f = fr[np.argmin(np.abs(fr - rest))]
        d = obs[fr, p] - obs[fr, anchor]
        length = np.median(np.linalg.norm(d, axis=1))
        v = obs[f, p] - obs[f, anchor]
        nv = np.linalg.norm(v)
        if nv > 0:
            out[p] = v / nv * length  # relative to the anchor; anchor placed below
    if np.isfinite(out[anchor]).all():
        a = out[anchor]
        for p in range(P):
            if p != anchor and not np.isfinite(shape[p]).all() and np.isfinite(out[p]).all():
                out[p] = a + out[p]
    return out
