"""Rigid: fit a rigid skeleton to markers and joint centres (Kirk et al. 2005, §3.3).

One segment at a time, the segment's markers and its joint centres are
mutually aligned over all frames by Horn's absolute orientation (generalised
Procrustes); the aligned clouds give constant marker and joint offsets, the
bone lengths, and the rms residual (an estimate of the noise). The rest pose
is the subject as seen at a reference frame, so offsets are the real skeleton.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..artifacts import Joints, Skeleton
from ..errors import DataError
from ..model.leave_out import cut_off, leave_out, segment_words
from ..model.tree import depth_first_order
from ..model.naming import segment_names
from ..solvers.model.joint_map import (NOISE_FLOOR_MM, SKIN_Z, map_refine, map_setup, noise_sigma, residual_correlation,
                                       soft_joints)
from ..solvers.model.links import with_links
from ..solvers.parallel import run_forked
from ..solvers.rigid_shape import procrustes_shape
from ..solvers.rotations import rotation_between
from ..solvers.model.uncertainty import skeleton_uncertainty
from ..solvers.model.skin import skin_motion
from ..solvers.model.worth import joint_overdispersion

VERSION = 33


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
    hinge_ratio: float = 0.6
    """A joint is a hinge when the spread of its relative rotations about their second axis is at
    most this fraction of the spread about the first."""
    joint_model: str = "map"
    """How the joints are placed: ``"map"``, the only model: the refinement is the model's MAP with an explicit
    Gaussian prior on every joint (see :mod:`~mocapskel.solvers.model.joint_map`), and nothing is moved after it; of
    the starts (the joints stage's centres and its second estimate), the one of lowest negative log posterior is kept."""
    rigid_frames: int = 1800
    """Where the kept start's MAP has rigid joints (its residual does not follow the joint
    angles: the markers ride on rigid bodies and what is left is noise), it is refined again on up to this many frames,
    every frame of a short take (the caps for large skeletons still apply): with a model that fits, every frame adds
    information (generated walks with rigid markers, 1200 frames: 4.0 / 4.9 -> 2.5 / 3.1 mm; BENCHMARKS, "More frames
    where the rigid model fits"). Where the residual follows the joint angles, more frames only weigh that misfit more
    (the realistic cmu41 takes and the real references lost with them), and the fit keeps ``refine_frames``. At most
    ``refine_frames``: off. Its joints are soft by the slack measured at the rigid fit (see ``soft_sigma``)."""
    gross_errors: bool = True
    """Where the fit's joints stay rigid (its residual is noise), residuals beyond what that
    noise gives once in a million (a marker swapped or jumping in a frame,
    :func:`~mocapskel.solvers.model.skin.gross_mask`) are left out and the fit made again, each costing the posterior
    as if at that bound (a truncated quadratic). Where the residual follows the joint angles its large values are
    skin, and are kept."""
    prior_scale: float = 0.1
    """The prior's standard deviation on a joint, relative to each of its
    two segments' marker centroids, as a multiple of that segment's size seen from the joint (the rms
    distance of its markers from the joint): 15 mm for a thigh's 150. Chosen among 0.03, 0.1 and 0.3
    on generated seeds 1-3 (BENCHMARKS, "Rules against the model")."""
    prior_mean: str = "deepened+leaf"
    """Where the prior centres each joint: ``"start"``, where the joints stage
    put it; ``"deepened"``, there, but a hinge with a marker over its axis one limb half-width inside
    that marker along the axis (the geometry of :func:`deepen_joints`, as the prior's mean, not a move);
    ``"deepened+leaf"``, also a hinge at the end of a limb at its end segment's markers' middle along its
    axis where the markers do not see that move (the geometry of :func:`centre_leaf_hinges`), and the joint of a
    one-marker leaf at its parent's end (:func:`~mocapskel.solvers.model.joint_map.one_marker_ends`)."""
    data_weight: str = "sandwich"
    """What the refinement's frames are worth to the data term: ``"frames"``,
    each an independent observation; ``"effective"``, as many independent frames as their residuals'
    correlation in time allows (:func:`~mocapskel.solvers.model.effective.effective_frames`: skin motion
    makes neighbouring frames' residuals alike); ``"sandwich"``, the data term divided by how many times the
    spread of the joints' estimates that the residuals show exceeds what independent frames give
    (:func:`~mocapskel.solvers.model.worth.joint_overdispersion`, measured at a first MAP with rigid joints;
    the composite likelihood's magnitude adjustment, Pauli, Racugno and Ventura 2011). That factor is about 1 on
    the generated takes (1-2: their skin's pull on the joints averages out over a take) and 9-13 on the real
    references of people (143 on the robot arm, whose chain most likely lacks a link), so the generated takes keep
    what ``"frames"`` gave them and the real ones get about what ``"effective"`` gives: both halves of the generated
    bench and the real checking half gained (BENCHMARKS, "The data's weight from the scores' spread")."""
    bone_sigma: float = 0.03
    """Like limbs' bones (left and right) agree in length within this fraction
    of their length (a Gaussian factor per pair; 0: no such factor). 0.03: a body's left and right long
    bones differ by a few per cent; with it the model gained on both generated halves and on cmu_16_07
    (BENCHMARKS, "The data's weight, the prior's mean and like limbs": ``map-like``)."""
    hinge_scale: float = 0.01
    """A second prior, along the axis only, on the hinges whose place along their
    axis the prior's mean knows (a marker over the axis, ``prior_mean``'s deepening; a limb's end segment's
    markers' middle; with ``hinge_placed``, also the joints stage's placement on the axis), its standard
    deviation this multiple of the segment's size (as ``prior_scale``'s); 0: none. Along such an
    axis the markers' information is the small turns about the other axes, which skin motion makes as well.
    0.01 (a few mm) measured better than 0.03 and 0.1 on the tuning seeds and about as well as 0.003
    (BENCHMARKS, "A prior along a hinge's axis")."""
    hinge_placed: bool = False
    """With ``hinge_scale``: the joints stage's hinges placed on their axis (its point nearest the two segments'
    markers) get the second prior too. Off: on the generated checking half it cost 0.9 mm (a reach's still
    legs held where the joints stage put them: found grouping, seed 6, 25.6 -> 41.5 mm), though on
    opensim_test_walking it matched 6 of 6 joints at 46.5 mm where without it 4 of 6 at 50.8 (BENCHMARKS,
    "A prior along a hinge's axis")."""
    soft_sigma: float = 15.0
    """The joints between two segments of three markers or more are soft
    (``refine_skeleton``'s ``soft``): in each frame such a joint may sit off its fixed place in its parent's frame by
    a Gaussian offset of this standard deviation (mm per axis); 0: none. Marker clusters slide on the skin as a whole
    (10-30 mm on a thigh), and rigid joints pass that misfit on to the neighbours' poses. At 15 mm the generated bench
    gains on both halves over three marker sets (sliding clusters most: 46.7 -> 34.2 mm, past the rules' 41.2) and
    every real reference gains (BENCHMARKS, "Soft joints", "Sliding clusters"). Only where the take shows skin motion
    (:data:`~mocapskel.solvers.model.joint_map.SKIN_Z`): a take whose residual does not follow its joint angles keeps
    rigid joints in the fits that choose the start (the 48-marker range of motion: 4.0 -> 2.8 mm), and in its fit on
    ``rigid_frames`` its joints wander by as much as they were measured to at the rigid fit, beyond what the noise
    gives (:func:`~mocapskel.solvers.model.slack.slack_sigma`; ``info["refined"]["slack_sigma_mm"]``): a segment's
    markers moving together on the skin (the generator's 0.3 of its skin motion: 0.9 mm a joint, measured 0.7-1.0)
    move a rigid joint along the axis the motion fixes least, away from the markers (the 48-marker range of motion's
    elbows and knees, 21 of 24 deeper, by 1.8 mm on average: 2.60 / 2.32 -> 2.08 / 1.97 mm; BENCHMARKS, "Joints that
    wander as far as the take shows"). 0: no soft joints anywhere."""
    line_sigma: float = 0.01
    """A limb's middle joint (a knee between hip and ankle, an elbow between shoulder and
    wrist) lies along the axis it turns about in line with its two neighbours
    (:func:`~mocapskel.solvers.model.joint_map.limb_lines`), a Gaussian of this fraction of their distance; 0: no
    such factor. A walk leaves all three free along one axis; tied, they slide together, where their three priors
    hold them, instead of each on its own. 0.01 is a leg's: hip-knee-ankle angles of healthy adults lie within a
    few degrees of straight, the knee about 1 cm off the line. The generated halves gain in 89 of 174 rows and lose
    in 35 (gait set, true grouping: 68.0 / 58.7 -> 60.1 / 53.1 mm), the real references too (opensim_test_walking
    33.2 -> 30.2 mm) (BENCHMARKS, "A limb's middle joint in line with its neighbours")."""
    mirror_prior: bool = True
    """Like limbs' first joints (two hips on a pelvis) lie in their parent's plane of
    symmetry, their mean's distance from it a Gaussian as wide as the parent's markers are far from symmetric. With the
    data weighed by their scores' spread it gained a little on every half of the generated bench and held cmu_16_07's
    two hips where a walk leaves them free (51.3 mm over 12 joints against 59.7; BENCHMARKS, "The data's weight from
    the scores' spread"); with every frame independent it had cost a reach 34 mm and stayed off."""
    mean_ratio: float | None = 1.0
    """The hinge test of the prior's mean (which joints it deepens and centres at a leaf's
    markers), as ``hinge_ratio``; None: ``hinge_ratio``. 1: no test, every joint about the axis it turns about most, so
    that the starts of a take deepen the same joints where their poses agree on the axes (the tight prior along a
    hinge's axis, ``hinge_scale``, stays with ``hinge_ratio``'s hinges: a joint the motion fixes is not held there)
    (BENCHMARKS, "The prior's mean without a hinge test")."""
    links: bool = True
    """A joint the joints stage held where it ran off along a line becomes two joints
    with a link of no markers between them (:mod:`~mocapskel.solvers.model.links`) where the model scores that better
    (:func:`~mocapskel.solvers.model.links.with_links`): a robot arm's link that carries no marker."""
    skin_once: bool = True
    """With ``data_weight="sandwich"``: the skin test's answer (soft joints or rigid) is the first MAP's best start's,
    and every start is then fitted with that one model, so that their negative log posteriors compare (a start whose
    joints are off shows a residual that follows the joint angles where the better start's does not: on a real full
    body, z 7.9 against 1.8, and a soft fit of one start lost to a rigid fit of the other by 0.2 in 4,066). False:
    each start's own answer, tested again at its second fit."""
    pose_trust: float = 0.1
    """The fits' per-frame trust region (rad, ``refine_skeleton``'s ``pose_trust``): a
    frame whose segments turned more than this in a step is damped four times more in the next. 0: one damping."""
    like_widths: bool = True
    """The prior mean's deepening gives like limbs' joints (a left and a right knee) the
    mean of their two limb half-widths, two measures of one width (cmu_16_07's right knee, measured off a thigh marker
    4.6 mm from a slanted bone line, 75 -> 46 mm from the reference; the generated halves and the real checking half
    the same; BENCHMARKS, "Like limbs' half-widths")."""
    weight_iterations: int = 20
    """With ``data_weight="sandwich"``: the iterations of the first MAP, the one the data's weight is measured at (the
    fit that counts has ``refine_iterations``). Its factor needs no converged MAP: 20 against 60 iterations changed
    4 of 174 generated rows by 0.2 mm at most and saved 1-5 s on the longest real takes (BENCHMARKS, "The model
    path's time")."""
    mean_within: bool = True
    """The prior's mean of a joint the estimators left beyond all of its two segments'
    markers along the axis it turns about most is brought back to the nearest of them, or a limb half-width beyond it
    (:func:`~mocapskel.solvers.model.joint_map.within_markers`): along that axis the markers do not place a joint, and
    the gait set's found groupings had knees 395-446 mm out of the leg there (checking half 95.0 -> 67.9 mm, tuning
    64.8 -> 64.3, true groupings and the real checking half the same; BENCHMARKS, "A joint's prior within its limb")."""
    square_limbs: bool = True
    """The prior's mean of a shoulder hung on a two-marker upper arm, along the axis the arm swings about, level with
    the elbow: the bone square to that axis (:func:`~mocapskel.solvers.model.joint_map.square_first_joints`). The
    joints stage's guess there falls towards the thorax's middle; realistic cmu41 takes, true grouping, tuning /
    checking half: 36.97 / 39.72 -> 33.77 / 36.54 mm, the runs' shoulders 28-126 -> 21-76 mm (BENCHMARKS, "A shoulder
    level with its elbow")."""
    skin_retest: bool = True
    """Where no joint can be soft (no two joined segments of three markers or more) and the kept start's MAP says
    skin motion (``skin_z`` above :data:`~mocapskel.solvers.model.joint_map.SKIN_Z`), the test decides only the frames
    the fit keeps. A joint the fit left off makes the residual follow that joint's angle as skin does, so the rigid
    model is fitted again on ``rigid_frames`` from it (``weight_iterations``, as the first MAP) and the test made
    there; where the residual then is noise, the take takes the rigid path from that fit (BENCHMARKS, "The skin test
    at the fit on more frames")."""
    uncertainty: bool = True
    """Every joint's uncertainty (:mod:`~mocapskel.solvers.model.uncertainty`) into ``info["uncertainty"]``;
    it moves no joint."""


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


class Unfittable(DataError):
    """Segments whose markers are never seen well enough with their joints to fit a rigid shape."""

    def __init__(self, segments: list[int], labels: list[list[str]], path: str | None = None):
        self.segments = [int(s) for s in segments]
        self.labels = labels
        first = f"segment {segments[0]} (markers {', '.join(labels[0])})"
        super().__init__(f"{first} is never seen well enough to fit — its markers are too rarely seen together"
                         " with its joints; leave them out with --exclude", path)


def _tree(joints: Joints) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(parent, the edge to the parent, depth-first order) of every segment."""
    S = joints.topology.segments.n_segments
    parent = np.full(S, -1, dtype=int)
    parent_edge = np.full(S, -1, dtype=int)
    for e, (a, b) in enumerate(joints.topology.edges):
        parent[b] = a
        parent_edge[b] = e
    return parent, parent_edge, depth_first_order(parent)  # parents before children


def _rest(joints: Joints, params: Params) -> int:
    seg, mk, pts, _ = _parts(joints)
    F = pts.shape[0]
    if params.rest_frame is None:
        return choose_rest_frame(pts, joints.centres, seg.group, seg.n_segments, params.rest_search)
    rest = int(params.rest_frame)
    if not 0 <= rest < F:
        raise DataError(f"rest frame {rest} is outside the take's {F} frames — choose a frame from 0 to {F - 1}", mk.source or None)
    return rest


def without_unfittable(joints: Joints, err: Unfittable) -> Joints:
    """``joints`` without the segments of ``err`` and those that hang on the tree only through them
    (:func:`~mocapskel.model.leave_out.cut_off`), each said in a warning. A DataError when no skeleton
    of two segments and a joint would be left."""
    seg = joints.topology.segments
    S = seg.n_segments
    names = segment_names([[seg.markers.labels[i] for i in seg.members(s)] for s in range(S)])
    count = np.bincount(seg.group[seg.group >= 0], minlength=S)
    hung = cut_off(joints.topology.edges, joints.topology.root, S, err.segments, count)
    if S - len(err.segments) - len(hung) < 2:
        left = ", ".join(segment_words(lab, names[s]) for s, lab in zip(err.segments, err.labels))
        raise DataError(f"{left} never seen well enough to fit, and without {'it' if len(err.segments) == 1 else 'them'}"
                        " no two segments with a joint are left — its markers are too rarely seen together with its"
                        " joints", seg.markers.source or None) from None
    words = [segment_words([seg.markers.labels[i] for i in seg.members(s)], names[s]) for s in range(S)]
    said = [f"{words[s]} left out of the skeleton: never seen well enough to fit — no frame sees three of its"
            " markers and joint centres together, nor its markers with each of its joints (the segments it joins"
            " are seen when it is not, or never together)" for s in err.segments]
    said += [f"{words[s]} left out of the skeleton with {words[through]}: it hangs on the rest only through it,"
             " and no joint of it with the rest was found" for s, through in sorted(hung.items())]
    drops = [(s, -1) for s in list(err.segments) + list(hung)]
    return leave_out(joints, drops, said)


def run(joints: Joints, params: Params = Params()) -> Skeleton:
    """Fit constant offsets for every segment; the rest pose is ``rest_frame``'s. A segment that cannot be
    fitted is left out (see :func:`without_unfittable`), and the rest fitted."""
    if params.joint_model != "map":
        raise ValueError(f"joint_model must be 'map' (the rules were removed), not {params.joint_model!r}")
    if params.data_weight not in ("frames", "effective", "sandwich"):
        raise ValueError(f"data_weight must be 'frames', 'effective' or 'sandwich', not {params.data_weight!r}")
    while True:
        parent, parent_edge, order = _tree(joints)
        rest = _rest(joints, params)
        try:
            skel = _fit(joints, joints.centres, rest, parent, parent_edge, order, params)
            break
        except Unfittable as err:
            joints = without_unfittable(joints, err)
    if params.refine_frames > 0:
        skel = _map_fit(joints, skel, rest, parent, parent_edge, order, params)
    return _with_uncertainty(_with_lengths(skel), params)


def _with_uncertainty(skel: Skeleton, params: Params) -> Skeleton:
    """``skel`` with every joint's uncertainty in ``info["uncertainty"]``, at the refinement's poses."""
    if params.uncertainty:
        got = skeleton_uncertainty(skel)
        if got is not None:
            skel = replace(skel, info=dict(skel.info, uncertainty=got))
    return skel


def _map_fit(joints: Joints, skel: Skeleton, rest: int, parent: np.ndarray, parent_edge: np.ndarray,
             order: np.ndarray, params: Params) -> Skeleton:
    """The MAP refinement (:func:`~mocapskel.solvers.model.joint_map.map_refine`) from every start the joints
    stage offers, in forked processes; the start of lowest negative log posterior is kept."""
    starts = [(joints.centres, skel)]
    if joints.alt_centres is not None:
        try:
            starts.append((joints.alt_centres, _fit(joints, joints.alt_centres, rest, parent, parent_edge, order, params)))
        except DataError:
            pass

    pts = joints.topology.segments.markers.points
    F = pts.shape[0]
    noise = noise_sigma(pts[np.linspace(0, F - 1, min(F, params.max_frames)).round().astype(int)],
                        np.asarray(skel.marker_segment))

    rho = residual_correlation(pts, np.asarray(skel.marker_segment)) if params.data_weight == "effective" else None

    model = dict(frames=params.refine_frames, iterations=params.refine_iterations, noise=noise, scale=params.prior_scale,
                 mean=params.prior_mean, hinge_ratio=params.hinge_ratio, mean_ratio=params.mean_ratio, rho=rho,
                 bone_sigma=params.bone_sigma,
                 hinge_scale=params.hinge_scale, hinge_placed=params.hinge_placed, mirror=params.mirror_prior,
                 gross=params.gross_errors, line_sigma=params.line_sigma, like_widths=params.like_widths,
                 pose_trust=params.pose_trust, within=params.mean_within, square=params.square_limbs)

    if params.links:  # as scored by the first MAP's fit (rigid joints, ``weight_iterations``)
        starts = with_links(joints, starts, dict(model, iterations=params.weight_iterations, soft_sigma=0.0,
                                                 gross=False), params.refine_frames)

    setups: list = [None] * len(starts)  # each start's map_setup, made by its first fit and kept for the others

    def one(i: int, soft_sigma: float, inflate: float, kw: dict, skin: list | None):
        c, st = starts[i]
        setup = setups[i]
        if setup is None:
            setup = map_setup(st, c, **{k: model[k] for k in ("frames", "mean", "hinge_ratio", "mean_ratio",
                                                               "like_widths", "within", "square")})
        out = map_refine(st, c, soft_sigma=soft_sigma, data_inflate=inflate, skin=None if skin is None else skin[i],
                         setup=setup, **dict(model, **kw))
        return replace(out, joints=None), setup  # sent back from a forked process: without the take

    def fit_starts(soft_sigma: float, inflate: float = 1.0, skin: list | None = None, forked: bool = True,
                   **kw) -> tuple[list[Skeleton], list[float], int]:
        # forked: the starts side by side, one core each (fits of a fixed number of iterations take about as long
        # as each other); else one after another, each fit's frames shared out among the cores (fits that stop at a
        # tolerance: one start's fit took 60 iterations, the other's 24, and one core sat idle for the difference)
        fit = (lambda i: one(i, soft_sigma, inflate, kw, skin))
        got = run_forked(fit, range(len(starts))) if forked else [fit(i) for i in range(len(starts))]
        outs = []
        for i, (o, setup) in enumerate(got):
            outs.append(replace(o, joints=joints))
            setups[i] = setup
        if any("refined" not in o.info for o in outs):  # too few frames to refine: the first start as it is
            return outs, [], 0
        nlp = [o.info["refined"]["neg_log_posterior"] for o in outs]
        return outs, nlp, int(np.argmin(nlp))

    sandwich = params.data_weight == "sandwich"
    # with "sandwich", a first MAP with rigid joints measures how much the frames overstate what they say about
    # the joints (:func:`joint_overdispersion`; soft joints would take up the very misfit it measures), and the fit
    # is made again with the data term weighed down by that factor
    if sandwich:
        # rigid joints, the skin test made but no soft fit, no second fit without gross residuals: the factor is
        # measured at this MAP, and the skin test's answer kept for the fit that follows
        outs, nlp, win = fit_starts(params.soft_sigma, iterations=params.weight_iterations, soft_fit=False, gross=False)
    else:
        outs, nlp, win = fit_starts(params.soft_sigma)
    kappa = 1.0
    if sandwich and nlp:
        kappa = joint_overdispersion(outs[win])
        if params.skin_once:
            z1 = outs[win].info["refined"]["skin_z"]
            outs, nlp, win = fit_starts(params.soft_sigma, kappa, skin=[z1] * len(outs), retest=False, forked=False)
        else:
            outs, nlp, win = fit_starts(params.soft_sigma, kappa, skin=[o.info["refined"]["skin_z"] for o in outs],
                                        forked=False)
    if not nlp:
        return outs[0]
    best = outs[win]
    z = best.info["refined"]["skin_z"]  # NaN where the skin test was not made (soft_sigma 0)
    c, st = starts[win]
    fitted, first = best, None
    if (np.isfinite(z) and z > SKIN_Z and params.skin_retest and not soft_joints(st, 1.0)
            and params.rigid_frames > params.refine_frames):
        # no joint can be soft here, so the test decides only the frames; and a joint the fit left off makes the
        # residual follow its angle as skin does: the rigid model on more frames, and the test again at its fit
        again = map_refine(st, c, fitted=best, more=params.rigid_frames, setup=setups[win], soft_sigma=0.0,
                           **dict(model, iterations=params.weight_iterations))
        z2 = skin_motion(again.parent, again.marker_segment, again.origin, again.marker_local,
                         pts[again.pose_frames], again.pose_rot, again.pose_root, noise=NOISE_FLOOR_MM).z
        if z2 <= SKIN_Z and again.info["refined"]["frames"] > best.info["refined"]["frames"]:
            fitted = replace(again, info=dict(again.info, refined=dict(again.info["refined"], skin_z=z2)))
            z, first = z2, z
        else:  # skin there too: the fit on the refinement's frames stays
            best = replace(best, info=dict(best.info, refined=dict(best.info["refined"], skin_z_retest=z2)))
    if np.isfinite(z) and z <= SKIN_Z and params.rigid_frames > params.refine_frames:
        # every frame at full weight: the residual does not follow the pose here (the skin test), and the factor was
        # measured on the refinement's frames (with it, a functional knee trial whose still body is not rigid, factor 21,
        # lost 15 mm)
        more = map_refine(st, c, fitted=fitted, more=params.rigid_frames, setup=setups[win],
                          soft_sigma=params.soft_sigma, **model)
        if more.info["refined"]["frames"] > best.info["refined"]["frames"]:
            extra = {} if first is None else {"skin_z_first": first}
            best = replace(more, info=dict(more.info, refined=dict(
                more.info["refined"], neg_log_posterior=best.info["refined"]["neg_log_posterior"],
                frames_scored=best.info["refined"]["frames"], **extra)))
    info = dict(best.info)
    info["refined"] = dict(info["refined"], start=("joints", "framework")[win],
                           neg_log_posterior_starts=dict(zip(("joints", "framework"), nlp)), data_inflate=kappa)
    return replace(best, info=info)


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
    unfit: list[int] = []
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
            unfit.append(s)
            continue
        noise[s] = float(np.sqrt(np.nanmean(rms**2))) if np.isfinite(rms).any() else np.nan
        shapes[s] = (mids, shape[: mids.size])
        for j, e in enumerate(eids):
            joint_in[(s, e)] = shape[mids.size + j]
    if unfit:
        raise Unfittable(unfit, [[mk.labels[i] for i in seg.members(s)] for s in unfit], mk.source or None)

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
