"""Joints: a joint-centre trajectory for every edge of the tree.

Methods (``Params.method``):

- ``score``: SCoRE (Ehrig et al. 2006), the joint fixed in both segments'
  frames by linear least squares; hinge-like joints (small axis ratio) get
  their centre on the axis, in the plane of the neighbouring joints;
- ``mtb``: Hang et al. 2015 — marker-trajectory bases with solvability
  propagation, JMV only where nothing else can (the hybrid framework);
- ``jmv``: Kirk et al. 2005 — joint-marker-variance optimisation, every joint;
- ``sphere``: Knight & Semwal 2009 — the unbiased multi-radius sphere fit
  (MGDK) of one segment's markers in the other's frame;
- ``auto``: per joint, SCoRE when both segments carry 3+ markers (the best in
  ``bench/joints.py``: realistic noise and soft tissue, 10 seeds); otherwise every
  other estimator's candidate (JMV; the sphere fit where one segment carries 3+
  markers and the other one or two; Hang's framework) scored by one criterion, the
  joint cost with the distance penalty of the candidate held fixed in the frame of
  the segment of 3+ markers (see :func:`held_cost`), and the lowest kept.

Long takes: every segment's pose in every frame comes from one batched rigid
fit (:func:`~mocapskel.solvers.rigid_shape.shape_poses`), SCoRE's constant offsets
from sums over all frames (a spread subsample measurably changes them: 2000
to 8000 of the 60,000 frames of an active ROM take moved its joint RMS error
by 0.04 to 0.07 mm, 600 of 7200 frames by up to 0.3 mm), and every frame's
centre from its segments' poses. The diagnostics (turn check, residual) use
``Params.diag_frames`` frames spread over the take.
"""
from __future__ import annotations

import warnings as pywarnings
from dataclasses import dataclass, replace

import numpy as np

from ..artifacts import Joints, Topology
from ..model.measures import marker_extent
from ..errors import DataError
from ..model.leave_out import leave_out
from ..model.naming import segment_names
from ..solvers.parallel import run_blocks, run_forked
from ..solvers.joints.simplex import nelder_mead
from ..solvers.joints.hybrid import solve_tree
from ..solvers.joints.jmv import edge_alpha, jmv_joint_long
from ..solvers.joints.centres import (
    MIN_TURN_DEG, _rotate, along_axis_sigma, centre_from_either_side, loose_along_axis, place_on_hinge, relative_turn_deg,
    sphere_centre, spread_frames,
)
from ..solvers.joints.cost import distance_penalty, joint_cost
from ..solvers.rigid_shape import shape_poses
from ..solvers.joints.score import group_pose, score

VERSION = 22

#: Default ``Params.diag_frames``: takes up to 80 s at 120 Hz in full.
DIAG_FRAMES = 10_000

METHODS = ("auto", "jmv", "mtb", "sphere", "score")

#: A leaf is left out as riding on nothing of the subject (see :func:`stray_leaves`) only when its joint's
#: residual exceeds this many times the take's rigid tolerance: one marker (the variation of its distance to
#: the joint: at most 0.9 times on the real takes of the shared folders, a sync marker 2.1 times) ...
STRAY_RESIDUAL_ONE = 1.0
#: ... two or more (SCoRE's residual, the skin motion of both bodies in it: at most 1.6 times, a carried box 12).
STRAY_RESIDUAL = 4.0


@dataclass(frozen=True)
class Params:
    method: str = "auto"
    alpha: float | None = None
    """Kirk's distance penalty in the final fit; None: scaled to the take (``alpha_k`` skin
    variances per median marker distance, see :func:`~mocapskel.solvers.joints.cost.distance_penalty`).
    Kirk drops it in the final pass but notes it helps where the motion does not exercise
    every degree of freedom — on real takes, most joints: a hinge's centre, or a joint
    between two-marker segments, otherwise slides off along what the markers do not fix."""
    alpha_k: float = 2.0
    min_turn_deg: float = MIN_TURN_DEG
    """Joints whose segments turn less than this relative to each other (95th
    percentile over frames) are reported as poorly determined."""
    hinge_ratio: float = 0.4
    """SCoRE's smallest-to-next singular value ratio below which a joint is hinge-like:
    its centre is then fixed along the axis by the plane of the neighbouring joints..."""
    hinge_plane: bool = True
    """Move a hinge's centre along its axis into the plane of its neighbours along the chain
    that SCoRE fixed in full (a knee between a hip and an ankle that the motion fixes);
    with no such neighbour the centre stays on the axis nearest the two segments' markers."""
    hinge_min_sigma_mm: float = 0.1
    """...and only when SCoRE's standard error along the axis exceeds this (noise-free
    data fix even a near-hinge exactly)."""
    jmv_frames: int = 1200
    """JMV joints of longer takes are fitted on this many frames spread over the take,
    every frame then placed from the fitted radii (``jmv_joint_long``); Hang's framework's JMV
    joints likewise."""
    stray_far: float = 0.5
    """A leaf of the tree whose joint lies farther than this fraction of the subject's marker extent from
    its markers and from every marker of its neighbour, that moves, and (two or more markers) fits no
    joint, rides on nothing of the subject (a sync light, a ball, a carried box): it is left out of the
    skeleton (see :func:`stray_leaves`); 0: kept. The bar of the output check ``joint_far``; a joint that still
    lies that far from every marker of its two segments is held near them (see :func:`hold_far_joints`)."""
    hold_refine: bool = True
    """``auto``: the candidate kept among JMV, the sphere fit and Hang's framework (see :func:`held_cost`) is
    moved, held fixed in the segment of 3+ markers, to the least joint cost there (:func:`held_refined`).
    Without it the generated bench gains 1-4 mm and a real walk's hip stays where the sphere fit put it,
    120 mm from the reference's (BENCHMARKS, "The joints stage's gross failures")."""
    diag_frames: int = DIAG_FRAMES
    """Longer takes: frames (spread over the take) on which the diagnostics are
    computed, the turn check and the joint residual (the residual came within 1 %
    of the whole take's on a 60,000-frame take). The centres use every frame."""


def run(topology: Topology, params: Params = Params()) -> Joints:
    """Estimate every joint centre over all frames."""
    if params.method not in METHODS:
        raise ValueError(f"unknown joint method {params.method!r}")
    seg = topology.segments
    pts = seg.markers.points
    S = seg.n_segments
    groups = [_columns(pts, seg.members(s)) for s in range(S)]
    edges = topology.edges
    E = edges.shape[0]
    F = pts.shape[0]
    per_joint: list[dict] = [{} for _ in range(E)]
    alpha = params.alpha if params.alpha is not None else distance_penalty(seg.info, params.alpha_k, 0.0)
    diag = spread_frames(F, params.diag_frames)
    warnings: list[str] = []
    centres = np.full((F, E, 3), np.nan)
    methods = ["none"] * E
    done = np.zeros(E, dtype=bool)
    hinges: dict[int, tuple] = {}
    if params.method in ("score", "auto"):
        # (R, t, reference shape) or a reason, every segment (independent: side by side on the cores)
        poses = run_blocks(lambda sg: group_pose(sg[1], str(sg[0])), list(enumerate(groups)))

        def score_edge(e: int):
            a, b = edges[e]
            if isinstance(poses[a], str) or isinstance(poses[b], str):
                return None
            (R1, t1, ref1), (R2, t2, ref2) = poses[a], poses[b]
            fit = score(R1, t1, R2, t2, markers1=ref1, markers2=ref2, hinge_threshold=0.0)
            along_chain = False  # hinge-like, but the data's centre kept (see loose_along_axis)
            if fit.ok and fit.axis_ratio < params.hinge_ratio and along_axis_sigma(fit) > params.hinge_min_sigma_mm:
                # hinge-like: placed on the axis by the markers when the data leave the centre looser
                # along the axis than that placement does
                on_axis = score(R1, t1, R2, t2, markers1=ref1, markers2=ref2, hinge_threshold=1.0)
                if loose_along_axis(fit, on_axis):
                    fit = on_axis
                else:
                    along_chain = True
            if not fit.ok:
                return None
            return fit, centre_from_either_side(fit, poses[a], poses[b]), along_chain

        for e, got in enumerate(run_blocks(score_edge, range(E))):
            if got is None:
                continue
            fit, centres[:, e], along_chain = got
            if fit.hinge:
                hinges[e] = (fit, poses[edges[e][0]][0])
            methods[e] = "score-hinge" if fit.hinge else "score"
            per_joint[e]["why"] = (
                "both segments have 3+ markers: SCoRE linear least squares"
                + ("; hinge-like motion, centre on the axis nearest the markers" if fit.hinge else "")
                + ("; hinge-like motion about an axis along the chain (the two segments' markers lie one after"
                   " the other on it): the centre the data give" if along_chain else "")
            )
            per_joint[e]["hinge"] = bool(fit.hinge)
            done[e] = True
    tree = None
    alt_from_tree: list[int] = []  # JMV joints that the framework also placed
    if params.method == "auto":  # the rules measured in bench/joints.py (see the module docstring)
        # the JMV fits of the joints left and Hang's framework are independent of each other and of
        # the rules below that choose among them: fitted first, side by side on the cores
        todo = [e for e in range(E) if not done[e]]

        def fit_job(e: int):
            if e < 0:
                return solve_tree(groups, edges, alpha=alpha, max_frames=params.jmv_frames)
            return jmv_joint_long(groups[edges[e][0]], groups[edges[e][1]], alpha=alpha, max_frames=params.jmv_frames)

        fitted = dict(zip([-1] + todo, run_forked(fit_job, [-1] + todo))) if todo else {}
        if todo:
            tree = fitted[-1]
        refine = []  # (edge, kept candidate, both segments' markers, alpha, pose) for held_refined
        for e in todo:
            a, b = edges[e]
            na, nb = groups[a].shape[1], groups[b].shape[1]
            fit = fitted[e]
            both = np.concatenate([groups[a][diag], groups[b][diag]], axis=1)
            # every estimator's candidate, scored alike (see held_cost): JMV; Knight's sphere fit where one
            # segment has 3+ markers and the other one or two; Hang's framework
            cands = [("jmv", fit.centre, f"segments of {na} and {nb} markers: joint-marker-variance optimisation")]
            if max(na, nb) >= 3 and min(na, nb) <= 2:
                c, side = sphere_centre(groups[a], groups[b])
                if side is not None:
                    cands.append(("sphere", c, f"segments of {na} and {nb} markers: the {'marker' if min(na, nb) == 1 else 'two markers'}"
                                               " on spheres about the joint in the other segment's frame (MGDK)"))
            if np.isfinite(tree.centres[:, e]).any():
                alt_from_tree.append(e)
            if np.isfinite(tree.centres[:, e]).any() and np.isfinite(fit.centre).any():
                # (as before: a joint JMV cannot place in any frame stays unplaced and its leaf is left out)
                cands.append((tree.method[e], tree.centres[:, e], _why(tree.method[e], tree.category, edges[e])))
            frame = a if na >= nb else b
            pose = poses[frame] if not isinstance(poses[frame], str) else None
            w = edge_alpha(alpha, groups[a][diag], groups[b][diag])  # the penalty JMV minimises: each segment's share half
            costs = [held_cost(c, both, w, pose, diag) for _, c, _ in cands]
            k = int(np.argmin(costs)) if np.isfinite(costs).any() else 0
            name, centres[:, e], why = cands[k]
            if params.hold_refine and pose is not None and np.isfinite(costs[k]):
                refine.append((e, centres[:, e], both, w, pose))
            methods[e], done[e] = name, True
            if len(cands) > 1:
                why += f"; the lowest joint cost of {', '.join(n for n, _, _ in cands)}"
                if pose is not None:
                    why += f", each held fixed in the frame of the segment of {max(na, nb)} markers"
            per_joint[e]["why"] = why
            if name == "jmv" and not fit.ok:
                per_joint[e]["note"] = fit.reason
        # each kept candidate moved to its least held cost: independent searches, side by side
        for (e, *_), c in zip(refine, run_forked(lambda job: held_refined(*job[1:], diag), refine)):
            centres[:, e] = c
    if params.method == "jmv":
        for e, (a, b) in enumerate(edges):
            fit = jmv_joint_long(groups[a], groups[b], alpha=alpha, max_frames=params.jmv_frames)
            centres[:, e] = fit.centre
            methods[e] = "jmv"
            if not fit.ok:
                per_joint[e]["note"] = fit.reason
        done[:] = True
    if not done.all():  # the hybrid framework (MTB, propagation, JMV) for the rest
        tree = solve_tree(groups, edges, alpha=alpha, max_frames=params.jmv_frames)
        for e in np.flatnonzero(~done):
            centres[:, e] = tree.centres[:, e]
            methods[e] = tree.method[e]
            per_joint[e]["why"] = _why(tree.method[e], tree.category, edges[e])
            if not tree.ok[e]:
                per_joint[e]["note"] = tree.reason[e]
            if params.method == "score":
                per_joint[e]["note"] = f"SCoRE needs 3+ markers on both segments; {tree.method[e]} used"
    for e, (fit, R1) in (hinges.items() if params.hinge_plane else ()):
        # only neighbours that SCoRE fixed in full: a hinge is as loose along its own axis, and a
        # joint of a one- or two-marker segment is held only by the distance prior
        loose = {k for k in range(E) if k in hinges or methods[k] != "score"}
        centres[:, e], shift = place_on_hinge(fit, R1, centres, edges, e, skip=loose)
        if shift is not None:
            per_joint[e]["why"] += "; moved along the axis into the plane of the neighbouring joints"
    if params.method == "sphere":
        for e, (a, b) in enumerate(edges):
            c, side = sphere_centre(groups[a], groups[b])
            if side is not None:
                centres[:, e] = c
                methods[e] = "sphere"
                per_joint[e]["why"] = f"UGDK/MGDK sphere fit of the {'child' if side == 0 else 'parent'} markers in the {'parent' if side == 0 else 'child'} frame"
            else:
                per_joint[e]["note"] = f"sphere fit not possible (no side with 3+ markers); {methods[e]} used"
    if params.method in ("score", "auto"):
        names = _segment_labels(seg)
        for e, (a, b) in enumerate(edges):
            if isinstance(poses[a], str) or isinstance(poses[b], str):
                continue
            turn = relative_turn_deg(poses[a][0][diag], poses[b][0][diag])
            per_joint[e]["turn_deg"] = turn
            if np.isfinite(turn) and turn < params.min_turn_deg:
                warnings.append(
                    f"joint {names[a]}–{names[b]}: centre poorly determined — the segments turn only {turn:.1f}° relative"
                    " to each other; record a range-of-motion take that exercises this joint"
                )
    if not np.isfinite(centres).any():
        raise DataError("no joint centre could be estimated", seg.markers.source or None)
    unplaced = unplaced_leaves(edges, [e for e in range(E) if not np.isfinite(centres[:, e]).any()], S)
    residual = np.full(E, np.nan)
    for e, (a, b) in enumerate(edges):
        c = centres[diag, e]
        if np.isfinite(c).any():
            both = np.concatenate([groups[a][diag], groups[b][diag]], axis=1)
            residual[e] = np.sqrt(joint_cost(c, both, alpha=0.0))
        elif e not in {e_ for _, e_ in unplaced}:
            warnings.append(f"joint {a}-{b} could not be placed in any frame")
    info = {"version": VERSION, "method": params.method, "per_joint": per_joint, "warnings": warnings}
    alt = None
    not_framework = [e for e in alt_from_tree if not np.array_equal(centres[:, e], tree.centres[:, e], equal_nan=True)]
    if not_framework:
        # the joints placed by JMV or the sphere fit (or moved to the least held cost) against the
        # framework's, which, propagated through rigid bodies, keep every segment's markers and joints
        # rigid together: the better start for the skeleton's fit on many takes. The rigid stage tries both.
        alt = centres.copy()
        alt[:, not_framework] = tree.centres[:, not_framework]
        info["alt_start"] = [int(e) for e in not_framework]
    out = Joints(topology=topology, centres=centres, method=tuple(methods), residual=residual, info=info,
                 alt_centres=alt)
    if unplaced:
        out = leave_out(out, unplaced, [_unplaced_note(out, s_, e) for s_, e in unplaced])
    if not params.stray_far:
        return out
    return hold_far(leave_out_strays(out, params.stray_far), params.stray_far, diag)


def _held_point(c: np.ndarray, pose: tuple, diag) -> np.ndarray:
    """(3,) a joint trajectory ``c`` (F, 3) held fixed in the segment of ``pose`` (its (R, t, shape)): its median
    place in that segment's frame over the diagnostic frames ``diag``; NaN where it is never seen with it."""
    R, t, _ = pose
    with pywarnings.catch_warnings():  # frames where the segment or the candidate is not seen: NaN
        pywarnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.einsum("fji,fj->fi", R[diag], c[diag] - t[diag]), axis=0)


def held_refined(c: np.ndarray, both: np.ndarray, alpha, pose: tuple, diag) -> np.ndarray:
    """The candidate ``c`` held fixed in the segment of ``pose`` and moved there to the least joint cost
    (Kirk's, with the distance penalty ``alpha``): three unknowns, the joint's place in that segment."""
    R, t, _ = pose
    Rd, td = R[diag], t[diag]
    p0 = _held_point(c, pose, diag)
    if not np.isfinite(p0).all():
        return c
    x = nelder_mead(lambda p: joint_cost(_rotate(Rd, p) + td, both, alpha=alpha),
                    p0 + np.vstack([np.zeros(3), 10.0 * np.eye(3)]), xatol=0.05, fatol=1e-9)
    out = _rotate(R, x) + t
    return np.where(np.isfinite(out[:, :1]), out, c)


def held_cost(c: np.ndarray, both: np.ndarray, alpha: float | np.ndarray, pose: tuple | None, diag: np.ndarray | slice) -> float:
    """Kirk's joint cost (with the distance penalty ``alpha``) of a candidate joint trajectory ``c`` (F, 3)
    against both segments' markers ``both`` (per point where ``alpha`` is an array) on the diagnostic frames ``diag``, the candidate first held fixed
    in the frame of a segment of 3+ markers (``pose``: its (R, t, shape); None: the trajectory as it is).

    A joint is one point fixed in both segments. The estimators differ in how free their joint is: the
    sphere fit and Hang's framework fix it in a segment, JMV places it anew in every frame and so absorbs
    skin motion and noise into the joint, reaching a cost below the true joint's (on generated takes with
    skin motion, in every joint it put more than 100 mm off). Held fixed, every candidate has the same three
    unknowns (its place in that segment, here the median over frames), and the costs compare what the
    candidates say about the joint rather than how freely each could follow the noise."""
    if not np.isfinite(c).any():
        return np.inf
    if pose is not None:
        p = _held_point(c, pose, diag)
        if np.isfinite(p).all():
            R, t, _ = pose
            return float(joint_cost(_rotate(R[diag], p) + t[diag], both, alpha=alpha))
    return float(joint_cost(c[diag], both, alpha=alpha))


def hold_far(joints: Joints, far: float, diag: np.ndarray | slice) -> Joints:
    """``joints`` with the joints that ran off along a free line held near their markers
    (:func:`hold_far_joints`), their residuals measured again and a warning each."""
    seg = joints.topology.segments
    pts = seg.markers.points
    groups = _Groups(pts, [seg.members(s) for s in range(seg.n_segments)], diag)
    edges = joints.topology.edges
    centres = joints.centres.copy()
    # the subject's extent on the frames it reads (of the segments' markers, in segment order)
    extent = marker_extent(pts, columns=np.concatenate(groups.members))
    held = hold_far_joints(centres, groups, edges, far, diag, extent)
    alt = None
    if joints.alt_centres is not None:  # the rigid stage's other start: its joints ran off as far
        alt = joints.alt_centres.copy()
        hold_far_joints(alt, groups, edges, far, diag, extent)
    if not held and (alt is None or np.array_equal(alt, joints.alt_centres, equal_nan=True)):
        return joints
    names = _segment_labels(seg)
    per_joint = [dict(p) for p in joints.info["per_joint"]]
    warnings = list(joints.info.get("warnings", []))
    residual = joints.residual.copy()
    for e, (dist, step) in held.items():
        a, b = edges[e]
        both = np.concatenate([groups.at_diag(a), groups.at_diag(b)], axis=1)
        residual[e] = np.sqrt(joint_cost(centres[diag, e], both, alpha=0.0))
        per_joint[e]["why"] = per_joint[e].get("why", "") + (
            f"; ran {dist:.0f} mm from its markers along a line they hardly fix: held where that line passes nearest them")
        per_joint[e]["held_mm"] = round(step, 1)
        warnings.append(f"joint {names[a]}–{names[b]}: the markers leave its centre free along a line (a hinge in a"
                        f" planar motion, or two joints with no markers between them): it ran {dist:.0f} mm from them"
                        f" and is held where the line passes nearest them, {step:.0f} mm back")
    return replace(joints, centres=centres, residual=residual, alt_centres=alt,
                   info=dict(joints.info, per_joint=per_joint, warnings=warnings))


class _Groups:
    """Each segment's markers (F, m, 3) of ``pts``, gathered when first asked for (``groups[s]``), and on
    the diagnostic frames ``diag`` alone (``at_diag(s)``, the same values as ``groups[s][diag]``): a long
    take's joints are judged on those frames, and a segment's every frame is gathered only for a joint
    that is moved."""

    def __init__(self, pts: np.ndarray, members: list[np.ndarray], diag: np.ndarray | slice):
        self.pts, self.members, self.diag = pts, members, diag
        self._full: dict[int, np.ndarray] = {}
        self._at: dict[int, np.ndarray] = {}
        self._pts_diag: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.members)

    def __getitem__(self, s: int) -> np.ndarray:
        if s not in self._full:
            self._full[s] = _columns(self.pts, self.members[s])
        return self._full[s]

    def __iter__(self):
        return (self[s] for s in range(len(self)))

    def at_diag(self, s: int) -> np.ndarray:
        if s not in self._at:
            if self._pts_diag is None:
                self._pts_diag = self.pts[self.diag]
            self._at[s] = _columns(self._pts_diag, self.members[s])
        return self._at[s]


def hold_far_joints(centres: np.ndarray, groups: list | _Groups, edges: np.ndarray, far: float,
                    diag: np.ndarray | slice, extent: float | None = None) -> dict[int, tuple[float, float]]:
    """Bring back, in place, joints that ran off along a line the markers hardly fix.

    A joint farther than ``far`` times the subject's marker extent from every marker of its two segments
    (the output check ``joint_far``) where one segment has three or more markers: taken as fixed in that
    segment (its median place in the segment's frame), it is moved along the direction its joint cost
    changes least (the weakest of the cost's Gauss-Newton curvature, 3 x 3) to where that line passes
    nearest the two segments' markers. ``extent``: the subject's marker extent, when the caller has it.
    Returns {edge: (distance it ran, mm; the step back, mm)}."""
    out: dict[int, tuple[float, float]] = {}
    if extent is None:
        extent = marker_extent(np.concatenate(groups, axis=1))
    if not np.isfinite(extent):
        return out
    for e, (a, b) in enumerate(edges):
        c = centres[:, e]
        # the distance on the diagnostic frames: those frames of the two segments' markers alone
        if isinstance(groups, _Groups):
            near = np.concatenate([groups.at_diag(a), groups.at_diag(b)], axis=1)
        else:
            near = np.concatenate([groups[a], groups[b]], axis=1)[diag]
        with pywarnings.catch_warnings():
            pywarnings.simplefilter("ignore", RuntimeWarning)
            dist = float(np.nanmedian(np.nanmin(np.linalg.norm(near - c[diag][:, None], axis=-1), axis=1)))
        if not dist > far * extent:
            continue
        A, B = groups[a], groups[b]
        both = np.concatenate([A, B], axis=1)
        frame = A if A.shape[1] >= B.shape[1] else B
        full = np.flatnonzero(np.isfinite(frame).all(axis=(1, 2)))
        if frame.shape[1] < 3 or not full.size:
            continue
        R, t = shape_poses(frame[full[0]], frame)
        loc = np.einsum("fji,fkj->fki", R, both - t[:, None, :])  # every marker in the frame
        local_c = np.einsum("fji,fj->fi", R, c - t)
        ok = np.isfinite(local_c).all(1)
        if not ok.any():
            continue
        p = np.median(local_c[ok], axis=0)
        diff = p - loc[diag]  # (f, m, 3)
        u = diff / np.linalg.norm(diff, axis=-1, keepdims=True)
        with pywarnings.catch_warnings():  # markers never seen: NaN means, left out
            pywarnings.simplefilter("ignore", RuntimeWarning)
            dev = u - np.nanmean(u, axis=0)
            m = np.nanmean(loc.reshape(-1, 3), axis=0)
        dev = np.where(np.isfinite(dev), dev, 0.0)
        v = np.linalg.eigh(np.einsum("fmi,fmj->ij", dev, dev))[1][:, 0]
        step = float(v @ (m - p))
        q = p + step * v
        centres[:, e] = np.where(np.isfinite(R[:, 0, 0])[:, None], _rotate(R, q) + t, c)
        out[e] = (dist, abs(step))
    return out


def _columns(pts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """pts[:, idx]: a view when idx is a run of consecutive markers, else a copy laid out by frames
    (fancy indexing would lay it out by markers, slow to read frame by frame)."""
    if idx.size and idx[-1] - idx[0] == idx.size - 1 and np.all(np.diff(idx) == 1):
        return pts[:, idx[0] : idx[-1] + 1]
    return np.take(pts, idx, axis=1)


def _why(method: str, category: tuple[str, ...], edge: np.ndarray) -> str:
    a, b = int(edge[0]), int(edge[1])
    cats = f"groups of {category[a]} and {category[b]} markers"
    return {
        "mtb": f"closed form: a group has 3+ non-collinear markers ({cats})",
        "mtb-propagated": f"closed form with solved joints as markers ({cats})",
        "jmv": f"no basis available, joint-marker-variance optimisation ({cats})",
    }.get(method, cats)


def _segment_labels(seg) -> list[str]:
    """Short names for segments in messages (their markers' common prefix, as the rigid stage names them)."""
    mk = seg.markers
    return segment_names([[mk.labels[i] for i in seg.members(s)] for s in range(seg.n_segments)])


def stray_leaves(joints: Joints, far: float, frames: int = 400) -> list[tuple[int, int, float]]:
    """Leaf segments that ride on nothing of the subject: (segment, its edge, the joint's distance from
    the nearest marker of its two segments, mm).

    Such a marker (a sync light, a ball, a marker knocked off and moving by itself) or object (a box the
    subject carries) still gets a joint: the point that keeps its distances least badly, but one that
    keeps them badly and lies far from everything (a real take's sync marker: 1.0 m from it and 1.4 m
    from the forearm it was hung on; a carried box: 0.6 m from it and 0.9 m from the scapula). A leaf is
    a stray when
    - its joint's residual exceeds the take's rigid tolerance (``STRAY_RESIDUAL_ONE`` times it for one
      marker, ``STRAY_RESIDUAL`` times for more): no point keeps its place in both bodies as a joint does;
    - the joint's median distance over the frames from the leaf's markers and from every marker of its
      neighbour exceeds ``far`` times the subject's marker extent without the leaf (the output checks'
      :func:`~mocapskel.model.measures.marker_extent` of the other markers, the bar of ``joint_far``);
    - it moves: a marker or object that stands still (a robot's base on its table) is the lab's own
      frame, not a stray.
    On 440 generated random trees of three to five links of 300 mm with one-marker leaves (a subject barely
    two links across, its markers up to a link's length from their joints), five leaves were strays, each
    one that the tree had hung on the wrong segment (no joint there: residual 3 to 400 times the
    tolerance); no leaf of a right tree.
    """
    topo = joints.topology
    seg = topo.segments
    S = seg.n_segments
    edges = topo.edges
    if S < 3 or not far:
        return []
    tau = float(seg.info.get("rigid_tolerance_mm", 0.0))
    pts = seg.markers.points
    use = spread_frames(pts.shape[0], frames)
    P = pts[use]
    deg = np.bincount(edges.ravel(), minlength=S)
    leaves = []
    for s_ in np.flatnonzero(deg == 1):
        e = int(np.flatnonzero((edges == s_).any(axis=1))[0])
        if joints.residual[e] > (STRAY_RESIDUAL_ONE if seg.members(s_).size == 1 else STRAY_RESIDUAL) * tau:
            leaves.append((int(s_), e))
    if not leaves:
        return []
    out = []
    for s_, e in leaves:
        others = np.flatnonzero((seg.group >= 0) & (seg.group != s_))
        if others.size < 2 or S - 1 - len(out) < 2:
            continue
        # the output checks' subject extent (joint_far's bar), without this leaf: a stray far away inflates it
        extent = marker_extent(pts[:, others], frames)
        if not np.isfinite(extent):
            continue
        lim = far * extent
        x = P[:, seg.members(s_)]  # (n, k, 3)
        with pywarnings.catch_warnings():
            pywarnings.simplefilter("ignore", RuntimeWarning)
            mid = np.nanmean(x, axis=1)
            seen = np.isfinite(mid).all(-1)
            if seen.sum() < 2:
                continue
            still = float(np.sqrt(np.mean(((mid[seen] - mid[seen].mean(axis=0)) ** 2).sum(-1))))
            if not still > tau:
                continue  # it stands still: the lab's frame
            other = int(edges[e][0] if edges[e][1] == s_ else edges[e][1])
            c = joints.centres[use, e]
            own = np.nanmedian(np.nanmin(np.linalg.norm(x - c[:, None], axis=-1), axis=1))
            nb = np.nanmedian(np.nanmin(np.linalg.norm(P[:, seg.members(other)] - c[:, None], axis=-1), axis=1))
        if np.isfinite(own) and np.isfinite(nb) and min(own, nb) > lim:
            out.append((s_, e, float(min(own, nb))))
    return out


def unplaced_leaves(edges: np.ndarray, unplaced: list[int], n_segments: int) -> list[tuple[int, int]]:
    """The leaf segments whose joint (an edge of ``unplaced``) could not be placed in any frame: [(segment,
    edge)]. A joint needs three or more markers of its two segments seen together (a one-marker segment at
    the end of a chain, hung on another one-marker segment, has two); without it the leaf cannot be fitted,
    and the rest of the skeleton still can. Two segments are always kept."""
    deg = np.bincount(np.asarray(edges).ravel(), minlength=n_segments)
    out: list[tuple[int, int]] = []
    for e in unplaced:
        a, b = (int(x) for x in edges[e])
        leaf = b if deg[b] == 1 else a if deg[a] == 1 else None
        if leaf is not None and leaf not in {s_ for s_, _ in out} and n_segments - 1 - len(out) >= 2:
            out.append((leaf, e))
    return out


def _leaf_words(joints: Joints, s_: int, e: int, names: list[str]) -> tuple[list[str], int, str]:
    """A leaf ``s_`` about to be left out: its markers' labels, the segment at the other end of its edge
    ``e``, and how a warning names it ("marker X", or "segment N (markers X, Y)")."""
    seg = joints.topology.segments
    ms = [seg.markers.labels[int(i)] for i in seg.members(s_)]
    a, b = (int(x) for x in joints.topology.edges[e])
    what = f"marker {ms[0]}" if len(ms) == 1 else f"segment {names[s_]} (markers {', '.join(ms)})"
    return ms, (a if b == s_ else b), what


def _unplaced_note(joints: Joints, s_: int, e: int) -> str:
    """The warning of a leaf left out because its joint could not be placed."""
    seg = joints.topology.segments
    names = _segment_labels(seg)
    ms, other, what = _leaf_words(joints, s_, e, names)
    n = len(ms) + int(seg.members(other).size)
    return (f"{what} left out of the skeleton: its joint with segment {names[other]} could not be placed in any frame —"
            f" a joint needs three or more markers on its two segments, seen together, and they have {n}")


def leave_out_strays(joints: Joints, far: float) -> Joints:
    """``joints`` without the stray leaves of :func:`stray_leaves` (see :func:`leave_out`)."""
    strays = stray_leaves(joints, far)
    if not strays or joints.topology.segments.n_segments - len(strays) < 2:
        return joints
    names = _segment_labels(joints.topology.segments)
    said = []
    for s_, e, dist in strays:
        ms, other, what = _leaf_words(joints, s_, e, names)
        fit = "" if len(ms) == 1 else f" fits its markers only to {joints.residual[e]:.0f} mm and"
        said.append(f"{what} left out of the skeleton: it rides on nothing of the subject — its best joint with"
                    f" segment {names[other]}{fit} lies {dist:.0f} mm from {'it' if len(ms) == 1 else 'them'} and"
                    f" from that segment's markers (more than {far:g} of the subject's marker extent): a marker on a"
                    " prop or a sync device, a loose marker, an object the subject handles")
    return leave_out(joints, [(s_, e) for s_, e, _ in strays], said)
