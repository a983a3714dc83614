"""Checks of a solved take before it is written: is this a skeleton a subject can have?

A fit can explain its markers well and still be nonsense (a joint free to slide
along a direction the markers do not fix), and a take in the wrong units or a
skeleton of another subject can be solved without an error. These checks judge
the result against the take itself, with no template:

- ``units``         a subject larger than any optical capture volume (marker
                    extent above 20 m) or smaller than 5 mm: a take in other
                    units than it says (micrometres labelled mm fit as well as
                    millimetres: the fit alone cannot tell);
- ``residual``      a segment's IK marker residual far above the noise its rigid
                    fit measured (more than 3 times that noise plus 10 mm): a take
                    in other units than it says, another subject's skeleton, a
                    segment the skeleton cannot follow;
- ``bone_length``   a bone (joint to joint, or to the End Site) longer than the
                    subject's marker extent (the median over frames of the
                    largest distance between two markers seen at once);
- ``joint_far``     a joint farther than half that extent from every marker of
                    its two segments;
- ``joint_step``    frames where a joint moves more than the take's fastest
                    marker plus 20 mm (a pop the markers do not show; not the
                    fastest marker of the joint's own segments: a well placed
                    joint beyond its segments' markers moves faster than they do,
                    108 against 71 mm in one frame of a noise-free generated chain);
- ``rotation_flip`` frames where a joint's rotation relative to its parent turns
                    by more than 90 degrees while the fastest marker of its two
                    segments moves less than a tenth of its segment's extent
                    (two equivalent solutions swapped, not a fast turn);
- ``limb_asymmetry`` in a skeleton recognised as a person (see
                    :mod:`mocapskel.model.naming`), the same bone of the left and the
                    right limb (thigh, shank, foot, upper arm, forearm, shoulder)
                    longer on one side by more than a fifth: people's left and
                    right long bones differ by a few per cent, so one side has a
                    joint the markers did not fix (a hip a walk moves too little
                    to place along the thigh); in a skeleton not recognised as a
                    person (a lower-body gait set), the same for like limbs: two
                    children of one segment that are chains of the same length,
                    two segments or more, compared segment for segment; and in a
                    tree that would be a person's but for its two legs (arms),
                    those two when their lengths differ by more than half or their
                    numbers of segments differ (a stair descent's foot split in two);
- ``limb_mirror``   in a skeleton recognised as a person, a joint on the midline
                    (the lumbar or neck joint of the segment both hips or both
                    shoulders hang from) farther from the mid-plane of the two
                    hips (shoulders) than a fifth of their spacing: a person's
                    left and right limbs hang mirrored about the midline, so one
                    of the three joints sits where no person's does (a shoulder
                    the walk hardly moves, put in the neck; a segment holding
                    the other side's markers). Mirrored errors (both shoulders
                    too medial) keep the symmetry and are not seen;
- ``limb_cross``    two like limbs (two children of one segment whose subtrees have the same
                    shape and marker counts: two legs, two arms, in any tree) whose
                    first joints lie in the opposite order to their own markers
                    (rest pose): the right hip left of the left hip while the right
                    thigh's markers lie right of the left thigh's. No body crosses
                    its limbs at their roots; a joint slid along the axis the take
                    hardly turns about (a walk's hip along its flexion axis) does;
- ``not_converged`` joints whose centre fit stopped before converging.

Every failing check is one :class:`Finding`: which check, the joint or segment
it names, the frames (empty when it holds for the whole take) and a sentence.
The pipeline adds them to the report's ``checks`` and ``warnings``; ``--strict``
turns any of them into exit code 4. Vectorised over frames.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .artifacts import Motion
from .model.kinematics import segment_origins
from .model.measures import frames_text, marker_extent
from .model.tree import like_limb_pairs, like_subtrees, unlike_bones
from .solvers.bvh_pose import _transpose_blocks

__all__ = ["Finding", "Limits", "run_checks"]


@dataclass(frozen=True)
class Limits:
    residual_factor: float = 3.0
    """A segment's IK rms may be this many times its rigid-fit noise..."""
    residual_margin_mm: float = 10.0
    """...plus this (soft tissue the rigid fit averages away)."""
    bone_extent: float = 1.0
    """A bone may be at most this fraction of the marker extent."""
    joint_extent: float = 0.5
    """A joint may be at most this fraction of the extent from its segments' markers."""
    step_margin_mm: float = 20.0
    """A joint may move this much more in one frame than the fastest marker."""
    flip_deg: float = 90.0
    """A joint's rotation step (deg, one frame) above this is a flip when the markers hardly move."""
    extent_frames: int = 400
    """Frames sampled to measure the marker extent."""
    largest_mm: float = 20_000.0
    """No optical capture volume holds a subject larger than this."""
    smallest_mm: float = 5.0
    """...nor one smaller than this."""
    asymmetry: float = 0.2
    """The same bone of a left and a right limb may be at most this fraction longer on one side."""
    mirror: float = 0.2
    """A person's midline joint may lie at most this fraction of the hips' (shoulders') spacing off their
    mid-plane. On generated takes with their truth, the fits it flags had a hip or shoulder 78-174 mm off
    (a mid-plane 0.21-1.75 of the spacing off a midline joint), fits within 70 mm of the truth at most 0.14."""


@dataclass(frozen=True)
class Finding:
    """One failing check."""

    check: str
    name: str
    message: str
    frames: tuple[int, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict:
        return {"check": self.check, "name": self.name, "frames": frames_text(self.frames), "n_frames": len(self.frames),
                "message": self.message}


def _joint_name(names: tuple[str, ...], parent: np.ndarray, s: int) -> str:
    return f"{names[parent[s]]}-{names[s]}" if parent[s] >= 0 else names[s]


def run_checks(motion: Motion, points: np.ndarray, limits: Limits = Limits(), *, joint_notes: dict[int, str] | None = None) -> list[Finding]:
    """Check a solved take; returns the failing checks (empty when everything holds).

    Parameters
    ----------
    motion : Motion
        The IK result (its skeleton's markers ordered as ``points``' columns).
    points : (F, M, 3) ndarray
        The markers the motion was solved from (mm, NaN where unseen).
    limits : Limits
    joint_notes : {child segment: note}
        Joints whose centre fit did not converge, with the solver's reason.
    """
    sk = motion.skeleton
    names, parent = sk.names, np.asarray(sk.parent)
    S = len(names)
    F = motion.root_pos.shape[0]
    seg = np.asarray(sk.marker_segment)
    out: list[Finding] = []
    extent = marker_extent(points, limits.extent_frames)

    if np.isfinite(extent) and not limits.smallest_mm <= extent <= limits.largest_mm:
        out.append(Finding("units", "take",
                           f"the subject's marker extent is {extent:.4g} mm, "
                           f"{'more' if extent > limits.largest_mm else 'less'} than a capture volume can hold — "
                           "is the take in other units than it says (mm)?"))

    # residual against the rigid fit's noise
    res = np.asarray(motion.residual, dtype=np.float64)
    noise = np.asarray(sk.noise, dtype=np.float64)
    typical = float(np.nanmedian(noise)) if np.isfinite(noise).any() else 0.0
    for s in range(S):
        cols = np.flatnonzero(seg == s)
        if not cols.size:
            continue
        r = res[:, cols]
        seen = np.isfinite(r)
        if not seen.any():
            continue
        r2 = np.where(seen, r, 0.0) ** 2
        rms = float(np.sqrt(r2.sum() / seen.sum()))
        nz = noise[s] if np.isfinite(noise[s]) else typical
        thr = limits.residual_factor * nz + limits.residual_margin_mm
        if rms > thr:
            with np.errstate(invalid="ignore", divide="ignore"):
                per = np.sqrt(r2.sum(1) / seen.sum(1))
            bad = np.flatnonzero(per > thr)
            out.append(Finding("residual", names[s],
                               f"segment {names[s]}: IK marker rms {rms:.1f} mm against a rigid-fit noise of {nz:.1f} mm "
                               f"(limit {thr:.1f} mm) — a take in other units than it says, or a skeleton of another subject?",
                               tuple(bad.tolist())))

    # bone lengths against the subject's extent
    if np.isfinite(extent):
        lim = limits.bone_extent * extent
        off = np.linalg.norm(sk.offset, axis=1)
        end = np.linalg.norm(sk.end_site, axis=1)
        for s in range(S):
            for what, L in (("bone", off[s] if parent[s] >= 0 else 0.0), ("end site", end[s])):
                if np.isfinite(L) and L > lim:
                    out.append(Finding("bone_length", _joint_name(names, parent, s),
                                       f"{what} of {names[s]} is {L:.0f} mm long, more than the subject's marker extent "
                                       f"({extent:.0f} mm)"))
        # every joint's distance to the markers of its two segments (rest pose; rigid, so every frame)
        lim_j = limits.joint_extent * extent
        for s in np.flatnonzero(parent >= 0):
            cols = np.flatnonzero((seg == s) | (seg == parent[s]))
            if not cols.size:
                continue
            at_rest = sk.origin[seg[cols]] + sk.marker_local[cols]
            d = float(np.linalg.norm(at_rest - sk.origin[s], axis=1).min())
            if d > lim_j:
                out.append(Finding("joint_far", _joint_name(names, parent, s),
                                   f"joint {_joint_name(names, parent, s)} is {d:.0f} mm from the nearest marker of its two "
                                   f"segments, more than half the subject's marker extent ({extent:.0f} mm)"))

    if F >= 2:
        jstep = _steps(segment_origins(motion))  # (F-1, S)
        mstep = _steps(points)  # (F-1, M), NaN unless seen in both frames
        np.copyto(mstep, -np.inf, where=~np.isfinite(mstep))
        any_m = mstep.max(1) if mstep.size else np.full(F - 1, -np.inf)
        seg_max = np.full((F - 1, S), -np.inf)
        for s in range(S):
            cols = np.flatnonzero(seg == s)
            if cols.size:
                seg_max[:, s] = mstep[:, cols].max(1)
        del mstep
        rel = _joint_turns(motion.rot, parent)  # (F-1, S) degrees
        for s in range(S):
            both = seg_max[:, s] if parent[s] < 0 else np.maximum(seg_max[:, s], seg_max[:, parent[s]])
            fastest = np.where(np.isfinite(both), both, any_m)  # the joint's own segments (for flips)
            judged = np.isfinite(any_m) & np.isfinite(jstep[:, s])
            bad = np.flatnonzero(judged & (jstep[:, s] > any_m + limits.step_margin_mm)) + 1
            jn = _joint_name(names, parent, s)
            if bad.size:
                k = bad[np.argmax(jstep[bad - 1, s])] - 1
                out.append(Finding("joint_step", jn,
                                   f"joint {jn} moves more in one frame than the fastest marker plus "
                                   f"{limits.step_margin_mm:g} mm in {bad.size} frames (worst: {jstep[k, s]:.0f} mm at frame "
                                   f"{k + 1}, fastest marker {any_m[k]:.0f} mm, its segments' {fastest[k]:.0f} mm)",
                                   tuple(bad.tolist())))
            # a flip: a large turn in one frame that the markers do not show
            cols = np.flatnonzero((seg == s) | ((seg == parent[s]) if parent[s] >= 0 else False))
            size = 0.0
            if cols.size:
                loc = sk.origin[seg[cols]] + sk.marker_local[cols]
                size = float(np.linalg.norm(loc - sk.origin[s], axis=1).max())
            flip = (rel[:, s] > limits.flip_deg) & ~(np.isfinite(fastest) & (fastest > 0.1 * max(size, 1.0)))
            bad = np.flatnonzero(flip) + 1
            if bad.size:
                out.append(Finding("rotation_flip", jn,
                                   f"joint {jn} turns by more than {limits.flip_deg:g} degrees in one frame in {bad.size} "
                                   f"frames (up to {rel[:, s].max():.0f} degrees) while its markers hardly move",
                                   tuple(bad.tolist())))

    from .model.naming import recognise

    naming = recognise(sk, motion)  # a person's, or why not (see mocapskel.model.naming)
    out.extend(_limb_asymmetry(motion, limits.asymmetry, naming))
    out.extend(_limb_mirror(motion, limits.mirror, naming))
    out.extend(_limb_cross(motion))

    for s, note in (joint_notes or {}).items():
        jn = _joint_name(names, parent, s)
        out.append(Finding("not_converged", jn, f"joint {jn}: the centre fit did not converge ({note})"))
    return out


def _joint_turns(R: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """(F-1, S) angle (degrees) by which every joint's rotation relative to its parent (a root's: to the
    lab) turns from one frame to the next, from ``R`` (F, S, 3, 3) global rotations.

    On component planes, frames innermost: the products ``P^T G`` written out entry by entry (a
    batched ``@`` of 3x3 matrices over a long take is several times slower)."""
    F, S = R.shape[:2]
    rel = np.empty((max(F - 1, 0), S))
    # (S, 3, 3, F), copied a few hundred frames at a time (one transposing copy of a long take is twice as slow)
    Rt = _transpose_blocks(np.ascontiguousarray(R, dtype=np.float64).reshape(F, -1)).reshape(S, 3, 3, F)
    L = np.empty((3, 3, F))
    tmp = np.empty(F)
    for s in range(S):
        G = Rt[s]
        if parent[s] < 0:
            L[:] = G
        else:
            P = Rt[parent[s]]
            for i in range(3):
                for j in range(3):
                    o = L[i, j]
                    np.multiply(P[0, i], G[0, j], out=o)
                    o += np.multiply(P[1, i], G[1, j], out=tmp)
                    o += np.multiply(P[2, i], G[2, j], out=tmp)
        Lf = L.reshape(9, F)
        c = np.einsum("kf,kf->f", Lf[:, 1:], Lf[:, :-1])  # trace(L[f+1]^T L[f])
        c -= 1.0
        c /= 2.0
        rel[:, s] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return rel


def _steps(x: np.ndarray, block: int = 8192) -> np.ndarray:
    """(F-1, K) length of every frame-to-frame step of ``x`` (F, K, 3), NaN where either end is NaN:
    ``np.linalg.norm(np.diff(x, axis=0), axis=-1)`` to the bit (its sum order, (dx² + dy²) + dz²),
    a block of frames at a time (the differences of a whole long take are large)."""
    F, K = x.shape[:2]
    out = np.empty((max(F - 1, 0), K))
    for lo in range(1, F, block):
        hi = min(F, lo + block)
        with np.errstate(invalid="ignore"):
            d = np.subtract(x[lo:hi], x[lo - 1 : hi - 1])
        d *= d
        o = out[lo - 1 : hi - 1]
        np.add(d[..., 0], d[..., 1], out=o)
        o += d[..., 2]
    return np.sqrt(out, out=out)


def _limb_asymmetry(motion: Motion, tol: float, naming) -> list[Finding]:
    """The bones of a person's left and right limbs that differ by more than ``tol`` (a fraction); in a
    skeleton not recognised as a person (a lower-body gait set), those of like limbs: two children of
    one segment whose subtrees have the same shape, each a chain of two segments or more (two legs on
    a pelvis), compared segment for segment down the chain; and in a tree that would be a person's but for its
    two legs or its two arms, those two when their lengths from the trunk differ by more than half or their
    numbers of segments differ (a real stair descent's right foot split in two, a 487 mm rear-foot bone,
    the legs 1087 and 1644 mm)."""
    sk = motion.skeleton
    parent = np.asarray(sk.parent)
    what = {}  # (left segment, right segment) -> (what they are, kind)
    if isinstance(naming, str):  # not a person: like limbs by the tree's shape alone
        for s_a, s_b, k in like_limb_pairs(parent):
            nth = ("first", "second", "third", "fourth")[k] if k < 4 else f"{k + 1}th"
            what[s_a, s_b] = (f"like limbs' {nth} segments", "like")
    else:
        role = {n: s for s, n in enumerate(naming.names)}
        for left, s_l in role.items():
            if left.startswith("Left") and "Right" + left[4:] in role:
                what[s_l, role["Right" + left[4:]]] = (f"left and right {left[4:]}", "person")
    out = []
    for s_l, s_r, la, lb in unlike_bones(sk, list(what), tol):
        part, kind = what[s_l, s_r]
        who = "a person's differ by a few per cent" if kind == "person" else (
            "two legs or two arms differ by a few per cent; another machine's like limbs may not")
        out.append(Finding("limb_asymmetry", f"{sk.names[s_l]}/{sk.names[s_r]}",
                           f"the {part} ({sk.names[s_l]}, {sk.names[s_r]}) are {la:.0f} and {lb:.0f} mm long "
                           f"({100 * (max(la, lb) / min(la, lb) - 1):.0f} % apart; {who}) — a "
                           "joint of the longer or the shorter is poorly determined (the take hardly moves it)"))
    limbs = getattr(naming, "limbs", None) if isinstance(naming, str) else None
    if limbs is not None:
        # a person's tree but for this pair: their lengths, or their numbers of segments, differ
        what, ca, cb, la, lb = limbs
        pair = f"{sk.names[ca[0]]}/{sk.names[cb[0]]}"
        if not (min(la, lb) > 0 and max(la, lb) <= 1.5 * min(la, lb)):
            how = (f"are {la:.0f} and {lb:.0f} mm long from the trunk ({100 * (max(la, lb) / max(min(la, lb), 1e-9) - 1):.0f} % "
                   "apart; a person's differ by a few per cent)")
        else:
            how = (f"have {len(ca)} and {len(cb)} segments (a person's are alike: a joint the take hardly moves was not "
                   "found on one side, or a group of its markers made a segment of its own)")
        if not any(set(f.name.split("/")) == {sk.names[ca[0]], sk.names[cb[0]]} for f in out):
            out.append(Finding("limb_asymmetry", pair,
                               f"the two {what} of this otherwise person-shaped tree ({sk.names[ca[0]]}..., {sk.names[cb[0]]}...) "
                               f"{how} — so it is not named as a person"))
    return out


def _limb_cross(motion: Motion) -> list[Finding]:
    """Like limbs (:func:`~mocapskel.model.tree.like_subtrees`) whose first joints, along the line between their
    first segments' marker centroids, lie in the opposite order to those centroids (rest pose)."""
    sk = motion.skeleton
    parent = np.asarray(sk.parent)
    seg = np.asarray(sk.marker_segment)
    count = np.bincount(seg[seg >= 0], minlength=len(parent))
    pos = sk.origin[seg] + sk.marker_local
    out = []
    for _, a, b in like_subtrees(parent, count):
        ca, cb = (np.nanmean(pos[seg == x], axis=0) for x in (a, b))
        d = ca - cb
        if not (np.isfinite(d).all() and np.linalg.norm(d) > 0):
            continue
        u = d / np.linalg.norm(d)
        along = float((sk.origin[a] - sk.origin[b]) @ u)
        if along < 0:
            ja, jb = _joint_name(sk.names, parent, a), _joint_name(sk.names, parent, b)
            out.append(Finding("limb_cross", f"{sk.names[a]}/{sk.names[b]}",
                               f"like limbs cross at their roots: joints {ja} and {jb} lie {-along:.0f} mm in the opposite "
                               f"order to their segments' markers ({np.linalg.norm(d):.0f} mm apart); no body has that — "
                               "one of the two joints slid along a direction the take hardly moves"))
    return out


def _limb_mirror(motion: Motion, tol: float, naming) -> list[Finding]:
    """The hips and the shoulders of a person whose mid-plane misses a midline joint of the segment they hang
    from by more than ``tol`` of their spacing (rest pose; rigid, so every frame).

    The pair: the first segments of the two legs (``UpLeg``) and of the two arms (``Shoulder``, else ``Arm``),
    when they hang from one segment. Its midline joints: that segment's own joint with its parent (none for the
    root, whose origin the fit may put anywhere) and its other children but limbs (the spine on the pelvis; the
    neck or head on the chest)."""
    sk = motion.skeleton
    if isinstance(naming, str):
        return []
    parent = np.asarray(sk.parent)
    names = sk.names
    role = {n: s for s, n in enumerate(naming.names)}
    sided = {s for n, s in role.items() if n.startswith(("Left", "Right"))}
    out = []
    for part, firsts in (("hips", ("UpLeg",)), ("shoulders", ("Shoulder", "Arm"))):
        a, b = (next((role[side + f] for f in firsts if side + f in role), None) for side in ("Left", "Right"))
        if a is None or b is None or parent[a] != parent[b] or parent[a] < 0:
            continue
        p = int(parent[a])
        mids = ([p] if parent[p] >= 0 else []) + [int(k) for k in np.flatnonzero(parent == p) if int(k) not in sided]
        w = sk.origin[a] - sk.origin[b]
        width = float(np.linalg.norm(w))
        if not mids or not width > 0:
            continue
        u = w / width
        mid = 0.5 * (sk.origin[a] + sk.origin[b])
        off = {q: float((sk.origin[q] - mid) @ u) for q in mids}
        q = max(off, key=lambda k: abs(off[k]))
        if abs(off[q]) > tol * width:
            jn = _joint_name(names, parent, q)
            # how far each of the two lies from the midline (the line through two midline joints, or the one)
            if len(mids) >= 2:
                i, j = max(((i, j) for i in mids for j in mids if i < j),
                           key=lambda ij: float(np.linalg.norm(sk.origin[ij[0]] - sk.origin[ij[1]])))
                d = sk.origin[j] - sk.origin[i]
                d = d / max(float(np.linalg.norm(d)), 1e-12)
                from_mid = [float(np.linalg.norm((sk.origin[x] - sk.origin[i]) - ((sk.origin[x] - sk.origin[i]) @ d) * d))
                            for x in (a, b)]
            else:
                from_mid = [float(np.linalg.norm(sk.origin[x] - sk.origin[q])) for x in (a, b)]
            out.append(Finding("limb_mirror", f"{names[a]}/{names[b]}",
                               f"the {part} (left {names[a]}, right {names[b]}) are not mirrored about the midline: joint {jn} lies "
                               f"{abs(off[q]):.0f} mm off their mid-plane ({abs(off[q]) / width:.2f} of their {width:.0f} mm "
                               f"spacing; a person's lie on it), the left {from_mid[0]:.0f} mm and the right {from_mid[1]:.0f} mm from the "
                               "midline — one of the three joints is poorly determined (the take hardly moves it) or a segment "
                               "holds markers of its neighbour"))
    return out


def joint_notes(motion: Motion) -> dict[int, str]:
    """Joints (by child segment) whose centre fit did not converge, with the solver's reason."""
    joints = motion.skeleton.joints
    if joints is None or joints.topology is None:
        return {}
    per = joints.info.get("per_joint") or []
    out = {}
    for e, (a, b) in enumerate(joints.topology.edges.tolist()):
        note = str(per[e].get("note", "")) if e < len(per) else ""
        if "converge" in note:
            out[int(b)] = note
    return out


def add_to_report(report: dict, findings: list[Finding]) -> None:
    """Record the findings in a report: ``report["checks"]`` (one dict each) and one warning each."""
    report["checks"] = [f.as_dict() for f in findings]
    ws = report.setdefault("warnings", [])
    for f in findings:
        fr = frames_text(f.frames)
        ws.append(f"check {f.check}: {f.message}" + (f"; frames {fr}" if fr else ""))


def strict_error(findings: list[Finding], source: str | None):
    """The DataError (exit code 4) that ``--strict`` raises when checks failed (None when none did)."""
    from .errors import DataError

    if not findings:
        return None
    by: dict[str, list[str]] = {}
    for f in findings:
        by.setdefault(f.check, []).append(f.name)
    what = "; ".join(f"{c}: {', '.join(n[:6])}{' …' if len(n) > 6 else ''}" for c, n in by.items())
    return DataError(f"{len(findings)} output checks failed ({what}) — nothing written (--strict); "
                     "run without --strict to write the result and read the report's checks", source)
