"""Joints by the model's MAP: the whole skeleton refined with explicit Gaussian priors as factors.

The model of a take (DESIGN, "One model, not rules"): markers are points fixed on rigid segments,
the segments meet at fixed joint centres, and what is left is noise of standard deviation
``sigma_n`` per axis, measured from the take (:func:`noise_sigma`). Where the
markers do not fix a joint (a hinge's centre along its axis, a shoulder along its swing axis), a
prior says where it is:

    joint c, relative to the marker centroid of each of its two segments s (in s's frame),
    ~ N(mean_c, sigma_cs^2 I),  sigma_cs = ``scale`` x size_cs,

size_cs being the rms distance of segment s's markers from the joint at rest (how far the segment
reaches from it), mean_c where the joints stage put the joint (``mean="start"``) or there, but a
hinge with a marker over its axis one limb half-width inside that marker along the axis
(``mean="deepened"``: the geometry of :func:`~mocapskel.solvers.priors.deepen.deepen_joints`, a surface
marker sitting outside the bone, as the prior's mean; like limbs' joints at the mean of their two
half-widths). The MAP minimises

    (n_eff / n) sum |marker residual|^2 / sigma_n^2 + sum_cs |joint_cs - mean_cs|^2 / sigma_cs^2
        [+ sum_pairs (|bone_x| - |bone_y|)^2 / sigma_b^2] [+ sum_hinges,s (a_c . (joint_cs - mean_cs))^2 / sigma_hs^2]

over the refinement's n frames (:func:`~mocapskel.solvers.model.calibrate.refine_skeleton` with
``prior_weights`` = (n / n_eff) sigma_n^2 / sigma_cs^2). Each prior term is one factor for the whole
fit, while the markers add a term in every frame: where the motion fixes a joint, the data win; along
a direction they leave free, the prior decides. Nothing is moved after the fit. ``sigma_n`` comes from
the markers alone, so that every start is scored by the same model.

The data's weight. Skin slides with the joint angles, so a marker's residual in one frame is nearly
its residual in the next: n frames are not n independent observations, and counted as such they
make the data look sure along directions the motion does not fix (a knee along its axis) and the
joints slide there into the skin motion. With ``data_weight="effective"`` the frames count as
n_eff = n^2 / sum_ij rho(|t_i - t_j|) (:func:`effective_frames`), rho the correlation in time of the
markers' residuals in their segments' frames, measured from the take (:func:`residual_correlation`);
``"frames"`` keeps n_eff = n.

Like limbs (optional, ``bone_sigma`` > 0): the two bones of a left/right pair (:func:`like_bone_pairs`)
differ in length by N(0, sigma_b^2), sigma_b = ``bone_sigma`` x their length: one factor per pair.

A shoulder on a two-marker upper arm that swings about one axis has its mean level with its elbow along that axis
(optional, ``square``, :func:`square_first_joints`): an arm swings across its bone, and the joints stage's guess there
falls towards the thorax's middle.

Hinges whose place along their axis the mean knows (optional, ``hinge_scale`` > 0: a marker over the axis,
the deepening's geometry; a limb's end segment's markers' middle, ``mean="deepened+leaf"``, which also puts a
one-marker leaf's joint at its parent's end, :func:`one_marker_ends`): a second Gaussian
along the axis ``a_c`` alone, sigma_hs = ``hinge_scale`` x the segment's size (:func:`_hinge_priors`). Along it
the markers' information is the joint's small turns about the other axes, which skin motion makes as well.

Soft joints (optional, ``soft_sigma`` > 0, :func:`soft_joints`): in each frame a joint between two segments of
three markers or more may sit off its fixed place by a Gaussian offset, a model of marker clusters sliding on the
skin. Only where the take shows skin motion: the residual of the rigid MAP follows its joint angles (the skin
regression's ``z``, :func:`~mocapskel.solvers.model.skin.skin_motion`, above ``SKIN_Z``), and the soft MAP is then
run from the start as the rigid one was; a take whose residual is noise alone keeps the rigid MAP, and its fit on
more frames (``fitted``) lets the joints wander by one sigma for the take measured at that rigid MAP: the moments of
the joints' least-squares offsets less what the noise gives them (:func:`~mocapskel.solvers.model.slack.slack_sigma`),
a variance component that is about 0 where the markers ride on rigid bodies and 0.7-1.0 mm where a generated skin
moves each segment's markers together. (The start's residual is no test: a joint off its place moves the markers
by (I - R) c, a function of the joint angles, and a rigid-marker walk scored z = 52 there.)

Gross errors: where the joints stay rigid, the noise model is the residual's: a residual beyond what it gives once in a
million (:func:`~mocapskel.solvers.model.skin.gross_mask`: a marker swapped or jumping in one frame) is left out and
the fit made again from where it ended, each such residual costing the posterior its bound (a truncated quadratic).
The skin test leaves them out too: one frame of them turned a rigid take's z from -8.8 to 21.6.

Like limbs' first joints (optional, ``mirror``) lie in their parent's plane of symmetry: one factor
per pair (:func:`~mocapskel.solvers.priors.mirror.mirror_planes`).

A limb's middle joint in line with its neighbours (``line_sigma`` > 0, :func:`limb_lines`): a knee between hip and
ankle, an elbow between shoulder and wrist, lies, along the axis it turns about, where the line between its two
neighbours passes, within ``line_sigma`` x their distance: one factor per such joint, linear in the two bones'
offsets. A walk turns hip, knee and ankle about one axis and leaves each free along it; tied, the three move
together, and the joint the prior places worst no longer slides on its own.

Several starts (the joints stage's centres and its second estimate) are each refined with a prior
centred on its own start (a mixture prior of equal weights); the start of lowest negative log
posterior is kept.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...artifacts import Skeleton
from ...model.tree import like_subtrees, subtree_shape
from .calibrate import _Problem, refine_skeleton
from .effective import correlation_in_time, effective_frames
from ..priors.deepen import _half_width, deepen_joints
from ..priors.leaf_hinges import centre_leaf_hinges
from ..priors.mirror import mirror_planes
from ..ik.motion import _centres_by_edges, solve
from .refinement import refinement_frames
from .skin import gross_mask, skin_motion
from .slack import slack_sigma
from ..joint_moves import _move_joint, _with_moves
from ..rest_pose import _bone_line, _rest_groups, _rest_markers
from ..rigid_shape import procrustes_shape
from ..joints.centres import MIN_TURN_DEG, relative_turn_deg
from ..joints.hinges import _hinge_direction, _relative_rotations
from ..rotations import segments_seen

#: Noise (mm, per axis) below which no optical system resolves a marker; the model's noise is at least
#: this, so that a noise-free take does not turn the priors' weights to zero.
NOISE_FLOOR_MM = 0.1

#: The skin regression's z (standard deviations of chance) above which a take shows skin motion: a test at about
#: the 0.1 % level. Measured at the rigid MAP: generated takes the rigid model describes -12 to -0.6, a rigid-marker
#: run whose shoulder centres move on the thorax 23, takes with skin motion 34-72.
SKIN_Z = 3.0


def noise_sigma(points: np.ndarray, group: np.ndarray) -> float:
    """The take's marker noise per axis (mm), from the markers alone (not the joints, which differ
    between starts): every segment of three or more markers fitted as one rigid shape over the frames
    ``points`` (F, M, 3), the residual sum of squares over its degrees of freedom (3 per seen marker,
    less 6 for each frame's pose). Where no segment has three, the two-marker segments' distances: noise of
    sigma per axis on both markers spreads their distance by 2 sigma^2 (its component along their line), so
    half the squared deviations from the mean distance, over the frames seen less one. At least
    :data:`NOISE_FLOOR_MM`."""
    sse, dof = np.zeros(2), np.zeros(2)  # [segments of three or more, pairs]
    for s in np.unique(group[group >= 0]):
        obs = points[:, group == s]
        if obs.shape[1] >= 3:
            _, _, _, rms = procrustes_shape(obs)
            n = np.isfinite(obs).all(-1).sum(1)
            ok = np.isfinite(rms) & (n >= 3)
            sse[0] += float(np.sum(rms[ok] ** 2 * n[ok]))
            dof[0] += float(np.sum(3 * n[ok] - 6))
        elif obs.shape[1] == 2:
            d = np.linalg.norm(obs[:, 0] - obs[:, 1], axis=-1)
            d = d[np.isfinite(d)]
            if d.size > 1:
                sse[1] += 0.5 * float(np.sum((d - d.mean()) ** 2))
                dof[1] += d.size - 1
    k = 0 if dof[0] > 0 else 1  # the pairs only where no segment has three
    return max(float(np.sqrt(sse[k] / dof[k])) if dof[k] > 0 else 0.0, NOISE_FLOOR_MM)


def residual_correlation(points: np.ndarray, group: np.ndarray) -> np.ndarray:
    """rho (L,): the correlation of the markers' residuals between frames ``k`` apart (rho[0] = 1), pooled
    over every marker and axis of every segment of three or more markers, each segment's markers fitted
    as one rigid shape over the consecutive frames ``points`` (F, M, 3) and its residuals taken in the
    segment's frame. Skin motion follows the joint angles, so these residuals are smooth in time. rho is
    cut at its first lag that is not positive (Geyer's initial positive sequence) and is 0 beyond."""
    backs = []
    for s in np.unique(group[group >= 0]):
        obs = points[:, group == s]
        if obs.shape[1] < 3:
            continue
        shape, R, t, _ = procrustes_shape(obs)
        backs.append(np.einsum("fji,fpj->fpi", R, obs - t[:, None, :]) - shape)
    return correlation_in_time(backs)


def prior_sigmas(mean: Skeleton, scale: float) -> np.ndarray:
    """(S, 2) the prior's standard deviation (mm) on child c's joint in its parent's frame ([c, 0]) and in
    its own ([c, 1]): ``scale`` x the rms distance of that segment's markers from the joint at rest in
    ``mean``; NaN where the segment has no marker or c is the root."""
    pos = _rest_markers(mean)
    seg = mean.marker_segment
    S = len(mean.names)
    out = np.full((S, 2), np.nan)
    for c in range(S):
        p = int(mean.parent[c])
        if p < 0:
            continue
        for j, s in enumerate((p, c)):
            m = (seg == s) & np.isfinite(pos).all(1)
            if m.any():
                size = float(np.sqrt(np.mean(np.sum((pos[m] - mean.origin[c]) ** 2, axis=1))))
                if size > 0:
                    out[c, j] = scale * size
    return out


def like_bone_pairs(skel: Skeleton) -> list[tuple[int, int]]:
    """(x, y): segments of two like limbs (:func:`~mocapskel.model.tree.like_subtrees`: subtrees of the same
    shape and marker counts) that match, segment for segment, their children taken in order of their
    subtrees' shapes; each x's offset from its parent's origin is the like of y's (the first joints from
    the common parent, then the limbs' bones)."""
    parent = np.asarray(skel.parent)
    count = np.bincount(skel.marker_segment[skel.marker_segment >= 0], minlength=len(parent))
    out: list[tuple[int, int]] = []

    def match(x: int, y: int) -> None:
        out.append((x, y))
        kx = sorted((int(k) for k in np.flatnonzero(parent == x)), key=lambda k: subtree_shape(parent, count, k))
        ky = sorted((int(k) for k in np.flatnonzero(parent == y)), key=lambda k: subtree_shape(parent, count, k))
        for u, v in zip(kx, ky):
            match(u, v)

    for _, a, b in like_subtrees(parent, count):
        match(a, b)
    return out


def _hinge_priors(start: Skeleton, centre: Skeleton, rot: np.ndarray, pts: np.ndarray, hinge_ratio: float,
                  scale: float, unit: float, only: set[int]) -> tuple[dict[int, np.ndarray], dict[int, tuple[float, float]]]:
    """({child: hinge axis at rest}, {child: (weight in its parent's frame, in its own)}): a second prior on
    each joint of ``only`` whose relative rotations ``rot`` turn about one axis (:func:`_hinge_direction`, the
    child's twist about its bone left out), along that axis only, of sigma ``scale`` times its segments' sizes
    (:func:`prior_sigmas` of ``centre``), weighed against the data's ``unit`` (the noise variance per frame)."""
    seen = segments_seen(start.marker_segment, len(start.names), pts)
    sig = prior_sigmas(centre, scale)
    hold, w = {}, {}
    for c in sorted(only):
        rel = _relative_rotations(rot, int(start.parent[c]), c, seen)
        if rel is None or not np.isfinite(sig[c]).any():
            continue
        line = _bone_line(centre, c)
        ax = _hinge_direction(rel, hinge_ratio, None if line is None else line[1])
        if ax is None:
            continue
        hold[c] = ax
        w[c] = tuple(float(unit / s**2) if np.isfinite(s) else 0.0 for s in sig[c])
    return hold, w


def one_marker_ends(skel: Skeleton) -> Skeleton:
    """``skel`` with the joint of every leaf segment of one marker at the mean of its parent's markers on that marker's
    side of their own centroid (along the line from the centroid to it: the parent's end, a forearm's two wrist
    markers, a foot's metatarsal markers), each segment's markers kept where they are; the prior's mean there.

    One marker turning with its segment places the joint only where the segment turns enough to draw a sphere (a
    hand through a range of motion); where it hardly turns (a walk's hand) the joints stage's sphere fit is anywhere
    along the forearm (a generated walk's wrists 52 and 62 mm off), and a joint the data leave free should stay by its
    markers: at the parent's end, on which marker sets put markers to mark the joint."""
    pos, seg, count = _rest_groups(skel)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    for c in range(len(skel.names)):
        p = int(skel.parent[c])
        if p < 0 or count[c] != 1 or (skel.parent == c).any() or count[p] < 2:
            continue
        m, own = pos[seg == c][0], pos[seg == p]
        end = own[(own - own.mean(0)) @ (m - own.mean(0)) > 0]
        if len(end):
            origin, local = _move_joint(origin, local, skel.marker_segment, c, end.mean(0) - origin[c])
    return replace(skel, origin=origin, marker_local=local)


def within_markers(skel: Skeleton, ratio: float, skip: set[str]) -> Skeleton:
    """``skel`` with every joint (but those named in ``skip``) whose place along the axis it turns about most lies
    beyond all of its two segments' markers along that axis brought back to the nearest of them, or to one limb
    half-width beyond it where the two limbs measure one (:func:`~mocapskel.solvers.priors.deepen._half_width`: a knee
    whose markers are all lateral lies that far inside them), each segment's markers kept where they are; the prior's
    mean there.

    Along the axis a joint turns about the markers hardly place it, and an estimator's answer there is anywhere (a
    generated walk's knee, its shank and foot grouped as one segment, 430 mm out along its flexion axis). Wherever
    a joint is along that axis, it lies within the limb: not beyond every marker of the two segments it joins.
    ``ratio``: the hinge test of :func:`_hinge_direction` (1: every joint, about the axis it turns about most)."""
    if skel.pose_rot is None or skel.pose_frames is None:
        return skel
    seen = segments_seen(skel.marker_segment, len(skel.names), skel.joints.topology.segments.markers.points[skel.pose_frames])
    pos, seg, _ = _rest_groups(skel)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    moved: dict[str, float] = {}
    kids = set()
    for c in np.flatnonzero(skel.parent >= 0):
        c = int(c)
        p = int(skel.parent[c])
        if skel.names[c] in skip:
            continue
        m = pos[(seg == p) | (seg == c)]
        rel = _relative_rotations(skel.pose_rot, p, c, seen)
        if len(m) < 2 or rel is None:
            continue
        line = _bone_line(skel, c)
        ax = _hinge_direction(rel, ratio, None if line is None else line[1])
        if ax is None:
            continue
        t = (m - origin[c]) @ ax
        shift = float(t.min()) if t.min() > 0 else float(t.max()) if t.max() < 0 else 0.0
        if shift:  # up to a limb half-width beyond them, where the two limbs measure one (a knee marked laterally)
            hw = _half_width(skel, origin, c, origin[c] + shift * ax, pos, set())
            shift = float(np.sign(shift)) * max(abs(shift) - (hw[0] if hw else 0.0), 0.0)
        if shift:
            origin, local = _move_joint(origin, local, skel.marker_segment, c, shift * ax)
            moved[skel.names[c]] = round(abs(shift), 1)
            kids.add(c)
    return _with_moves(skel, origin, local, kids, "within_markers", moved) if moved else skel


#: A limb swings about one axis where its turns about the second axis spread at most this fraction of those about
#: the first (the joints stage's hinge test, ``stages.joints.Params.hinge_ratio``): generated walks' and runs' arms
#: 0.04-0.07, kicks' 0.17-0.27; a two-marker range of motion on 100 frames, whose shoulders the markers place,
#: 0.52-0.59.
SWING_RATIO = 0.4


def square_first_joints(skel: Skeleton, ratio: float, placed: set[str]) -> Skeleton:
    """``skel`` with every limb's first joint on a trunk (a shoulder: its parent not the root and carrying other
    children; its own segment of two markers, with one child) that swings about one axis (it turns
    :data:`~mocapskel.solvers.joints.centres.MIN_TURN_DEG` or more, and passes the hinge test ``ratio`` of
    :func:`_hinge_direction` with the segment's twist about its two markers' line left out) moved along that axis to
    where its bone is square to it, level with its child's joint (an elbow), each segment's markers kept where they
    are; the prior's mean there. Joints named in ``placed`` (put by a marker over their axis) stay.

    An arm swings across its bone. Along the axis of the swing the markers do not place the shoulder (a walk, a run),
    and two markers on the upper arm leave the joints stage to guess there (no SCoRE: the segment's own twist is the
    joints'); its guesses fall towards the middle of the two segments' markers, the thorax's seven pulling a shoulder
    towards the body's midline (a generated run's shoulders 150-200 mm in from the truth), while the elbow, which the
    forearm's markers turn about, is placed. Where the arm turns every way (a range of motion) the markers place the
    shoulder and it hardly moves; a segment of three or more markers has its own twist, and SCoRE's answer stays
    (moved, a sliding cluster set's shoulders went 27 -> 78 mm from the truth). A hip hangs from the root: squared to
    its knee, a real walk's (cmu_16_07) hips went 17 and 35 -> 88 mm from the reference, its knees' means lying
    lateral, where the generated gait set's hips gained (BENCHMARKS, "A shoulder level with its elbow")."""
    if skel.pose_rot is None or skel.pose_frames is None or skel.joints is None:
        return skel
    parent = np.asarray(skel.parent)
    seen = segments_seen(skel.marker_segment, len(skel.names), skel.joints.topology.segments.markers.points[skel.pose_frames])
    pos, seg, _ = _rest_groups(skel)
    origin, local = skel.origin.copy(), skel.marker_local.copy()
    moved: dict[str, float] = {}
    done = set()
    for c in np.flatnonzero(parent >= 0):
        c, p = int(c), int(parent[c])
        kids = np.flatnonzero(parent == c)
        own = pos[seg == c]
        if (skel.names[c] in placed or len(kids) != 1 or len(own) != 2
                or parent[p] < 0 or (parent == p).sum() < 2):
            continue
        rel = _relative_rotations(skel.pose_rot, p, c, seen)
        if rel is None or not relative_turn_deg(skel.pose_rot[:, p], skel.pose_rot[:, c]) >= MIN_TURN_DEG:
            continue  # (a limb that barely turns has no axis to speak of: a reach's still legs)
        # its twist, which two markers hardly fix, left out about their line (the joint's own bone line is in doubt)
        ax = _hinge_direction(rel, ratio, (own[1] - own[0]) / np.linalg.norm(own[1] - own[0]))
        if ax is None:
            continue
        shift = float((origin[int(kids[0])] - origin[c]) @ ax)
        if shift:
            origin, local = _move_joint(origin, local, skel.marker_segment, c, shift * ax)
            moved[skel.names[c]] = round(abs(shift), 1)
            done.add(c)
    return _with_moves(skel, origin, local, done, "squared", moved) if moved else skel


#: A limb's middle joint lies between its neighbours, at least this fraction of the way from either: a limb's two
#: long bones are within a factor of 3 of each other's length (thigh and shank, upper arm and forearm: 0.45-0.55 of
#: the way). A found tree whose "limb" is a head carrying an arm put its shoulder 0.07 of the way from the neck.
LIMB_MIDDLE = 0.25


def limb_lines(skel: Skeleton, rot: np.ndarray, pts: np.ndarray) -> list[tuple[int, int, np.ndarray, float, float]]:
    """[(k, j, u, t, length)]: every limb's middle joint k (a knee, an elbow: its parent segment, of two markers or
    more, carries no other limb; its own segment one child, j) that lies ``LIMB_MIDDLE`` or more of the way from
    either neighbour (its parent's joint, a hip; j's, an ankle); u the axis its relative rotations ``rot`` turn about
    most (:func:`_hinge_direction`, the child's twist about its bone left out; rest axes), t the fraction of the way
    from the one neighbour to the other at which it lies at rest, ``length`` their distance. A limb's middle joint
    lies along its axis in line with its neighbours, to within how far a limb is from straight (a knee's varus or
    valgus, an elbow's carrying angle). Every start of a take gets the same joints, hinges or not."""
    parent = np.asarray(skel.parent)
    seen = segments_seen(skel.marker_segment, len(skel.names), pts)
    out = []
    for k in range(len(parent)):
        p = int(parent[k])
        kids = np.flatnonzero(parent == k)
        if (p < 0 or parent[p] < 0 or len(kids) != 1 or (parent == p).sum() != 1
                or (skel.marker_segment == p).sum() < 2):
            continue  # a limb's middle joint: one segment of the limb above it (not a trunk), one below
        j = int(kids[0])
        rel = _relative_rotations(rot, p, k, seen)
        if rel is None:
            continue
        line = _bone_line(skel, k)
        # the axis it turns about most, hinge or not: the same joints for every start of a take, so that their
        # scores compare (with the hinges alone, one start of a generated walk had both knees tied, the other one)
        u = _hinge_direction(rel, 1.0, None if line is None else line[1])
        if u is None:
            continue
        h, a = skel.origin[p], skel.origin[j]
        v = a - h
        length = float(np.linalg.norm(v))
        if not length > 0:
            continue
        t = float((skel.origin[k] - h) @ v / length**2)
        if LIMB_MIDDLE <= t <= 1.0 - LIMB_MIDDLE:
            out.append((k, j, u, t, length))
    return out


def soft_joints(skel: Skeleton, sigma: float) -> dict[int, float]:
    """{child segment: ``sigma``} for the joints that may be soft: both segments carry three markers or more, so
    that each has a pose of its own (a segment of one or two markers is posed through its joints)."""
    n = np.bincount(skel.marker_segment[skel.marker_segment >= 0], minlength=len(skel.names))
    return {c: sigma for c in range(len(skel.names)) if skel.parent[c] >= 0 and min(n[c], n[skel.parent[c]]) >= 3}


def _without_gross(start: Skeleton, origin: np.ndarray, marker_local: np.ndarray, rot: np.ndarray,
                   root_pos: np.ndarray, obs: np.ndarray) -> tuple[np.ndarray, int, float]:
    """(``obs`` with the markers of its gross residuals (:func:`~mocapskel.solvers.model.skin.gross_mask`) unseen, how
    many, the squared length beyond which they are), the residuals of ``start``'s tree with offsets ``origin``,
    ``marker_local`` posed by ``rot``, ``root_pos``: each costs the posterior that much, as if at the bound (a truncated
    quadratic: a swapped or jumping marker is no draw of the noise)."""
    pr = _Problem(start.parent, start.marker_segment, obs)
    _, _, x = pr.fk(root_pos, rot, pr.offsets(origin), marker_local)
    mask, t2 = gross_mask(obs[:, pr.used] - x)
    if not mask.any():
        return obs, 0, t2
    out = obs.copy()
    f, i = np.nonzero(mask)
    out[f, pr.used[i]] = np.nan
    return out, int(mask.sum()), t2


@dataclass(frozen=True, eq=False)
class MapSetup:
    """What every fit of one start shares (:func:`map_setup`): the refinement's frames ``use``, the start's pose on
    them (``rot``, ``root_pos``: its IK) and ``centre``, the start with its joints' prior means (deepened, leaf-centred,
    within the limb), without the take (``joints`` None: small enough to send between processes)."""

    use: np.ndarray
    rot: np.ndarray
    root_pos: np.ndarray
    centre: Skeleton


def map_setup(start: Skeleton, centres: np.ndarray, *, frames: int, mean: str = "deepened", hinge_ratio: float = 0.6,
              mean_ratio: float | None = None, like_widths: bool = True, within: bool = False,
              square: bool = False) -> MapSetup | None:
    """The refinement's frames, ``start`` posed on them from ``centres`` (F, E, 3), and the prior's centre: ``start``'s
    joints, deepened (``mean`` "deepened"), then leaf-centred ("deepened+leaf"), by the hinge test ``mean_ratio`` (None:
    ``hinge_ratio``), with ``within`` brought within their limb, and with ``square`` limbs' first joints square to
    the axis they swing about (:func:`square_first_joints`) (the keywords as :func:`map_refine`'s). None where the
    take is too short to refine (under 10 frames)."""
    ratio = hinge_ratio if mean_ratio is None else mean_ratio
    pts = start.joints.topology.segments.markers.points
    use = refinement_frames(start, frames)
    if use.size < 10:
        return None
    pose = solve(start, pts[use], _centres_by_edges(start, centres)[use])
    centre = start
    if mean in ("deepened", "deepened+leaf"):
        centre = deepen_joints(replace(start, pose_frames=use, pose_rot=pose.rot, pose_root=pose.root_pos), ratio,
                               like=like_bone_pairs(start) if like_widths else None)
    if mean == "deepened+leaf":
        centre = one_marker_ends(centre_leaf_hinges(centre, ratio))
    if within:  # joints the estimators left beyond their markers along their axis
        centre = within_markers(centre, ratio, set(centre.info.get("deepened", {})) | set(centre.info.get("leaf_centred", {})))
    if square:  # limbs' first joints level with their next joints along the axis they swing about
        centre = square_first_joints(replace(centre, joints=start.joints, pose_frames=use, pose_rot=pose.rot,
                                             pose_root=pose.root_pos), SWING_RATIO, set(centre.info.get("deepened", {})))
    return MapSetup(use, pose.rot, pose.root_pos, replace(centre, joints=None))


def map_refine(start: Skeleton, centres: np.ndarray, *, frames: int, iterations: int, scale: float, noise: float,
               mean: str = "deepened", hinge_ratio: float = 0.6, rho: np.ndarray | None = None,
               bone_sigma: float = 0.0, hinge_scale: float = 0.0, hinge_placed: bool = True,
               soft_sigma: float = 0.0, mirror: bool = False, fitted: Skeleton | None = None, more: int = 0,
               gross: bool = True, line_sigma: float = 0.0, data_inflate: float = 1.0, skin: float | None = None,
               soft_fit: bool = True, mean_ratio: float | None = None, like_widths: bool = True,
               retest: bool = True, pose_trust: float = 0.0, within: bool = False, square: bool = False,
               setup: MapSetup | None = None) -> Skeleton:
    """``start`` refined to the MAP of the model (see the module), the prior centred on ``start``'s
    joints; ``centres`` (F, E, 3) (topology's edge order) start the poses. The skeleton's
    ``info["refined"]`` holds the negative log posterior (``neg_log_posterior``, up to a constant common to
    every start of a take) and the prior's sigmas. With ``rho`` (:func:`residual_correlation`), the
    refinement's n frames count as :func:`effective_frames` n_eff independent ones: the data term is
    scaled by n_eff / n (the prior's weights by n / n_eff). With ``bone_sigma`` > 0, like limbs' bones
    (:func:`like_bone_pairs`) differ in length by N(0, sigma_b^2), sigma_b = ``bone_sigma`` x their mean
    length at the start: one more factor each. With ``mirror``, like limbs' first joints (and a child on the middle
    line) lie in their parent's plane of symmetry (:func:`~mocapskel.solvers.priors.mirror.mirror_planes`), their mean's
    distance from it N(0, sigma_m^2), sigma_m how far the parent's markers are from mirror-symmetric about it.
    With ``fitted`` (this function's rigid output for ``start`` and ``frames``), the same posterior, its prior set up
    as before, is refined from ``fitted`` on :func:`refinement_frames` of ``more`` frames (of a short take, every frame),
    the joints that may be soft wandering by :func:`~mocapskel.solvers.model.slack.slack_sigma` measured there on
    ``frames`` of them (with ``soft_sigma`` > 0; rigid where it is below :data:`NOISE_FLOOR_MM`). With ``gross``, a
    fit whose joints stay rigid (the skin test passed) is made again without its gross residuals (:func:`_without_gross`);
    with ``fitted``, they are those of ``fitted`` posed on the new frames, left out before the one fit. With
    ``line_sigma`` > 0, each limb's middle joint (:func:`limb_lines`) lies along its axis in line with its neighbours,
    N(0, sigma_l^2) off it, sigma_l = ``line_sigma`` x their distance. The data term is divided by ``data_inflate``
    on top of that (the noise variance it assumes times it: frames worth less than independent ones,
    :func:`~mocapskel.solvers.model.worth.joint_overdispersion`). ``skin``: the skin test's z already
    measured for this start at a near posterior's MAP (the same take with the data weighed otherwise); above
    :data:`SKIN_Z` the rigid fit it would be measured at is skipped and the soft fit made alone (where no joint could be
    soft, the rigid fit is the one that counts and the test is made at it); at or below it, with ``retest=False``, the
    rigid fit is made and kept without a test of its own. ``pose_trust``: each frame's own damping
    (``refine_skeleton``'s). ``soft_fit=False``: the
    skin test made (``info["refined"]["skin_z"]``) but no soft fit. ``mean_ratio``: the hinge test of the prior's mean
    (the deepening and the leaves' centring) instead of ``hinge_ratio``, which the hinge prior along the axis keeps.
    ``square``: a shoulder's mean level with its elbow along the axis the arm swings about
    (:func:`square_first_joints`). ``like_widths``: the mean's deepening gives like limbs' joints the mean of their two half-widths
    (:func:`~mocapskel.solvers.priors.deepen.like_half_widths`). ``setup``: :func:`map_setup`'s answer for these
    ``start``, ``centres``, ``frames``, ``mean``, hinge test, ``like_widths`` and ``within`` (made here when None)."""
    pts = start.joints.topology.segments.markers.points
    if setup is None:
        setup = map_setup(start, centres, frames=frames, mean=mean, hinge_ratio=hinge_ratio, mean_ratio=mean_ratio,
                          like_widths=like_widths, within=within, square=square)
    if setup is None:
        return start
    use, pose = setup.use, setup
    ref = int(np.searchsorted(use, start.rest_frame))
    centre = replace(setup.centre, joints=start.joints)
    sn = noise
    sig = prior_sigmas(centre, scale)
    n_eff = float(use.size) if rho is None else min(float(use.size), max(1.0, effective_frames(rho, use)))
    inflate = data_inflate * use.size / n_eff  # the noise variance per frame, as seen by the data term, times this
    w = np.where(np.isfinite(sig), inflate * sn**2 / np.where(np.isfinite(sig), sig, 1.0) ** 2, 0.0)
    ties, tie_sig = [], []
    if bone_sigma > 0:
        for x, y in like_bone_pairs(start):
            lx, ly = (float(np.linalg.norm(start.origin[k] - start.origin[start.parent[k]])) for k in (x, y))
            sb = bone_sigma * 0.5 * (lx + ly)
            if sb > 0:
                ties.append((x, y, inflate * sn**2 / sb**2))
                tie_sig.append(sb)
    planes = []
    if mirror:  # the plane is known to within how far its markers are from mirror-symmetric
        for kids, _, n, miss in mirror_planes(start):
            sm = max(miss, sn)
            planes.append((kids, n, inflate * sn**2 / sm**2))
            tie_sig.append(sm)
    lines = []
    if line_sigma > 0:  # a limb's middle joint in line with its neighbours, as straight as a limb is
        for k, j, u, t, length in limb_lines(start, pose.rot, pts[use]):
            sl = max(line_sigma * length, sn)
            lines.append((k, j, u, t, inflate * sn**2 / sl**2))
            tie_sig.append(sl)
    hold, hold_w = {}, {}
    if hinge_scale > 0:
        placed = {start.names.index(n) for k in ("deepened", "leaf_centred") for n in centre.info.get(k, {})}
        per = start.joints.info.get("per_joint") or []  # hinges the joints stage placed on their axis
        for e, (a_, b_) in enumerate(start.joints.topology.edges):
            if hinge_placed and e < len(per) and per[e].get("hinge"):
                placed.add(int(b_) if start.parent[int(b_)] == int(a_) else int(a_))
        hold, hold_w = _hinge_priors(start, centre, pose.rot, pts[use], hinge_ratio, hinge_scale, inflate * sn**2, placed)
    kw = dict(ref_frame=ref, iterations=iterations, prior_weights=w, anchor=(centre.origin, centre.marker_local),
              like_bones=ties, hold_along=hold, hold_weights=hold_w, planes=planes, lines=lines, pose_trust=pose_trust)
    obs, n_gross, t2 = None, 0, 0.0
    skin_z, soft, slack = float("nan"), {}, None
    if fitted is not None:  # the prior as set up above; the data on the frames asked for, from the fitted joints
        use = refinement_frames(start, more, stride=1)  # noise alone: every frame of a short take adds to the data
        pose = solve(fitted, pts[use], _centres_by_edges(start, centres)[use])
        kw["ref_frame"] = int(np.searchsorted(use, start.rest_frame))
        if gross:  # the fitted skeleton's residual on these frames says which are gross: one fit instead of two
            obs, n_gross, t2 = _without_gross(start, fitted.origin, fitted.marker_local, pose.rot, pose.root_pos,
                                              pts[use])
        data = pts[use] if obs is None else obs
        skin_z = fitted.info["refined"]["skin_z"]
        if soft_sigma > 0:  # how far the joints wander, measured at the fitted skeleton
            soft_kids = sorted(soft_joints(start, 1.0))
            # on as many frames as the fits that chose the start (all 1800 cost 0.8 s more on a 48-marker take)
            sub = np.unique(np.linspace(0, use.size - 1, min(use.size, frames)).round().astype(int))
            slack = slack_sigma(start.parent, fitted.origin, start.marker_segment, fitted.marker_local, data[sub],
                                pose.rot[sub], pose.root_pos[sub], soft_kids, sn)
            if slack > NOISE_FLOOR_MM:
                soft = {c: slack for c in soft_kids}
        # from the fitted skeleton, its joints rigid or wandering as much as they were measured to
        res = refine_skeleton(start.parent, fitted.origin, start.marker_segment, fitted.marker_local, data, pose.rot,
                              pose.root_pos, soft={c: inflate * sn**2 / s**2 for c, s in soft.items()}, **kw)
    else:
        res = None
        carried = skin is not None and soft_sigma > 0 and skin > SKIN_Z
        if carried:
            # the skin test made already, on a near posterior's MAP (the same take, the data weighed otherwise): the
            # soft fit alone
            skin_z, soft = skin, soft_joints(start, soft_sigma)
        if not soft:
            res = refine_skeleton(start.parent, start.origin, start.marker_segment, start.marker_local, pts[use],
                                  pose.rot, pose.root_pos, **kw)
        # the carried test says skin motion, but no joint here could be soft: this rigid fit is the one that counts,
        # and the test is made at it (the carried one was made at a MAP of 20 iterations)
        rigid_anyway = carried and not soft
        if skin is not None and not retest and res is not None and not rigid_anyway:
            skin_z = skin
        elif soft_sigma > 0 and res is not None:
            # soft joints model skin motion: only where the rigid fit's residual follows the joint angles (the start's
            # would, wherever its joints are off: a rigid take's walk scored z = 52 there)
            skin_z = skin_motion(start.parent, start.marker_segment, res.origin, res.marker_local, pts[use], res.rot,
                                 res.root_pos, noise=NOISE_FLOOR_MM).z
            soft = soft_joints(start, soft_sigma) if skin_z > SKIN_Z and soft_fit else {}
        if soft:  # from the start, as the rigid fit was (from the rigid fit's joints a generated reach lost 32 mm)
            res = refine_skeleton(start.parent, start.origin, start.marker_segment, start.marker_local, pts[use],
                                  pose.rot, pose.root_pos, soft={c: inflate * sn**2 / s**2 for c, s in soft.items()},
                                  **kw)
    before = res.rms[0]
    # the residual is the noise: what lies far beyond it is no draw of it (on more frames, left out before the fit)
    if gross and not soft and skin_z <= SKIN_Z and fitted is None:
        obs, n_gross, t2 = _without_gross(start, res.origin, res.marker_local, res.rot, res.root_pos, pts[use])
        if n_gross:  # again without them, from where the fit ended
            res = refine_skeleton(start.parent, res.origin, start.marker_segment, res.marker_local, obs, res.rot,
                                  res.root_pos, **kw)
    # -log posterior: the objective over 2 sigma_n^2, plus the priors' normalisers (3 axes each)
    nlp = ((res.objective + n_gross * t2) / (2.0 * inflate * sn**2) + 3.0 * float(np.sum(np.log(sig[np.isfinite(sig)])))
           + float(np.sum(np.log(tie_sig))) + 0.5 * float(sum(np.log(inflate * sn**2 / x) for v in hold_w.values() for x in v if x > 0)))
    info = dict(start.info)
    info["refined"] = {"frames": int(use.size), "iterations": res.n_iter, "marker_rms_mm_before": before,
                       "marker_rms_mm_after": res.rms[1], "joint_model": "map", "noise_sigma_mm": sn, "effective_frames": n_eff, "like_bones": len(ties),
                       "prior_scale": scale, "neg_log_posterior": nlp, "mean_within_mm": dict(centre.info.get("within_markers", {})),
                       "mean_squared_mm": dict(centre.info.get("squared", {})), "skin_z": skin_z, "gross_residuals": n_gross,
                       "soft_sigma_mm": {start.names[c]: s for c, s in soft.items()}, "soft_noise_mm": float(np.sqrt(inflate) * sn),
                       "slack_sigma_mm": slack,
                       "prior_sigma_mm": {start.names[k]: [float(x) if np.isfinite(x) else None for x in sig[k]] for k in range(len(start.names))
                                          if start.parent[k] >= 0}}
    return replace(start, origin=res.origin, marker_local=res.marker_local, info=info,
                   pose_frames=use, pose_rot=res.rot, pose_root=res.root_pos)
