"""Generated takes that look like real captures: real marker sets, real skin, everyday motion.

The body is the 15-segment human of :mod:`mocapskel.synth.human` (same lab
frame, proportions, joints and truth format). What differs from its default
take:

Marker sets (``markerset``)
---------------------------
``"cmu41"``
    The CMU / Vicon 41-marker full body: head band LFHD RFHD LBHD RBHD; C7
    T10 CLAV STRN RBAK on the thorax; LSHO RSHO on the acromion (above the
    shoulder joint); LUPA; LELB on the elbow's flexion axis; LFRM; LWRA LWRB on
    the wrist's flexion axis (ends of a wrist bar, ~60 mm each side); LFIN on
    the hand; LFWT RFWT LBWT RBWT on the pelvis; LTHI; LKNE on the knee's
    flexion axis; LSHN; LANK on the ankle's flexion axis; LHEE LTOE LMT5.
    Hands carry 1 marker, upper arm, thigh and shank 2 (one of them on a joint),
    forearm 3 (two on the wrist axis).
``"gait"``
    The lower-body Plug-in-Gait set: LASI RASI LPSI RPSI, and per side LTHI
    LKNE LTIB LANK LHEE LTOE (16 markers); LTHI and LTIB stand on ~60 mm wands
    unless ``wands=False``. The truth then covers only the 7 lower-body
    segments (pelvis, thighs, shanks, feet).
``"cluster"``
    A cluster set: a rigid 4-marker plate on each thigh, shank, upper arm and
    forearm (labels ``LTH1..4``, ``LSK1..4``, ``LUA1..4``, ``LFA1..4``), plus
    anatomical markers (head band, C7 T10 CLAV STRN, LASI RASI LPSI RPSI,
    LSHO LELB LWRA LWRB LFIN LKNE LANK LHEE LTOE LMT5; 64 markers). A plate
    slides on the skin as a whole (its markers stay rigid among themselves).
``"default"``
    The 48 (or ``markers_per_segment``) markers of :func:`~mocapskel.synth.human.human_take`.

Markers on a joint
------------------
LELB, LKNE, LANK, LWRA and LWRB sit on the flexion axis of their joint
(within ~10 mm of the axis line, 40-65 mm from the centre); LSHO sits ~45 mm
above the shoulder centre. In the truth (``marker_segment``) such a marker
belongs to the **bone it sits on**: the lateral epicondyles to the thigh /
upper arm, the malleolus to the shank, the styloids to the forearm, the
acromion to the thorax. Because it sits on the axis, its distance to the
markers of the other neighbour stays nearly constant too: a grouping that puts
it with that neighbour is as defensible, and ``truth.info["marker_segments_ok"]``
lists both segments for it (``info["joint_markers"]`` names its joint; the
acromion, above the joint rather than on an axis, is listed with the thorax
and the upper arm for the reason below, but has no joint named). The
shoulder girdle moves with the arm (the scapulohumeral rhythm: about the
sterno-clavicular joint it rises by 20 % of the arm's elevation and turns
forward by 25 % of its forward flexion), carrying the acromion (LSHO) and the
shoulder joint centre: the shoulder centre moves on the thorax by up to
~50 mm in a take that lifts the arms (no clavicle segment in the truth).

Skin motion (``skin="realistic"``)
----------------------------------
Each marker moves on its bone by a smooth function of the angles of the
joints at both ends of its segment (linear and quadratic terms of every degree
of freedom, each normalised to the joint's everyday range and saturating
beyond it; random coefficients per marker, so markers of one segment do not
move together), mostly along the skin (the normal component is damped by 60 %).
A marker's amplitude (peak-to-peak) is twice the median distance of its
displacement from the mean over poses drawn uniformly in the joints' everyday
ranges; it is drawn per marker from the
ranges of the literature (Leardini et al. 2005, Peters et al. 2010): thigh
10-30 mm (largest near the hip), shank 5-15, upper arm 5-20, forearm 4-12,
knee marker 5-15 (the skin folds over the knee), elbow marker 4-12, other
bony landmarks 2-12 (malleoli 3-8, pelvis 3-12, heel and toes 3-10), waist belt
4-15, head band
2-5; wand markers 1.3 times their skin's. Walking moves a thigh marker by about
its amplitude, a range-of-motion take by up to about three times it. A plate
moves as a whole (a translation of that amplitude plus a rotation of a few
degrees). However large the motion, a marker's displacement stays within
0.75 times its amplitude of the mean (a smooth limit: skin stretches only so
far), so its peak-to-peak never exceeds 1.5 times the amplitude. On top, a small band-limited (2-8 Hz) wobble of rms 5 % of the
amplitude. ``truth.info["skin_p2p_mm"]`` holds each marker's amplitude. The
feet are rigid (no toe joint, no arch): real heel-to-toe distances vary more.

Motions
-------
``walk`` (straight line, ~1.3 m/s, hip ~40 deg flexion range, knee ~60),
``run`` (~3 m/s, hip ~55 deg, knee ~90; feet past 5 m/s), ``climb`` (stairs up,
170 mm rise, 280 mm going), ``reach`` (standing, arms reach to random targets,
trunk leans), ``kick`` (fighting guard, front and roundhouse kicks; the foot
reaches 6-10 m/s), ``rom`` (the range-of-motion take of :func:`~mocapskel.synth.human.human_take`).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..artifacts import Markers
from .body import (
    _check_take_args,
    _JNT,
    _S,
    _SEG,
    HINGES,
    JOINT_NAMES,
    PARENT,
    SEGMENTS,
    _hinge_frame,
    _make_subject,
    _marker_counts,
    _side_name,
)
from .forward import _acromion, _floor_lift, _forward, _girdle_shift
from .markersets import _place
from .motions import _motion
from .skin import _WOBBLE, _skin
from .soft_tissue import _soft_tissue
from .truth import SynthTake, Truth, restrict_truth

__all__ = ["MARKERSETS", "REALISTIC_MOTIONS", "SKINS", "realistic_take"]

MARKERSETS: tuple[str, ...] = ("default", "cmu41", "gait", "cluster")
REALISTIC_MOTIONS: tuple[str, ...] = ("walk", "run", "climb", "reach", "kick", "rom")
SKINS: tuple[str, ...] = ("none", "realistic")


# ------------------------------------------------------------------ public


def realistic_take(
    *,
    rng: np.random.Generator,
    n_frames: int = 1200,
    rate: float = 120.0,
    markerset: str = "cmu41",
    motion: str = "walk",
    skin: str = "realistic",
    noise_mm: float = 1.0,
    scale: float = 1.0,
    subject_seed: int | None = None,
    wands: bool = True,
    markers_per_segment: int | Sequence[int] | Mapping[str, int] | None = None,
    soft_tissue_mm: float = 0.0,
    hinge_slack_deg: tuple[float, float] = (5.0, 12.0),
) -> SynthTake:
    """A seeded take with a real marker set, skin motion driven by the joint angles, and its truth.

    Parameters
    ----------
    rng : numpy.random.Generator
        The only source of randomness; three seeds are drawn from it (subject
        with its marker placement and skin, motion, noise), so the same state
        gives the same subject for every motion and skin setting.
    n_frames, rate : int, float
        Frames (at least 2) and frames per second.
    markerset : {"cmu41", "gait", "cluster", "default"}
    motion : {"walk", "run", "climb", "reach", "kick", "rom"}
    skin : {"realistic", "none"}
        ``"none"``: every marker rigid on its bone (the acromion still follows
        the arm's elevation).
    noise_mm : float
        Standard deviation of white noise per coordinate.
    scale : float
        Multiplies every length of the subject.
    subject_seed : int, optional
        Fix the subject regardless of ``rng``.
    wands : bool
        ``"gait"``: LTHI and LTIB on ~60 mm wands.
    markers_per_segment :
        ``"default"`` set only, as in :func:`~mocapskel.synth.human.human_take`.
    soft_tissue_mm : float
        Extra pose-independent skin wobble of :func:`~mocapskel.synth.human.human_take` (RMS mm).
    hinge_slack_deg : (2,) floats
        Half-ranges of the knees' and elbows' off-axis rotation (the ``rom``
        motion uses them whole; everyday motions 20-30 % of them).

    Returns
    -------
    SynthTake
        The truth has the format of :func:`~mocapskel.synth.human.human_take`'s (15 segments; the 7
        lower-body ones for ``"gait"``); ``marker_segment`` is the bone each
        marker sits on. ``info`` adds ``markerset``, ``skin``, ``marker_kind``,
        ``joint_markers`` {label: joint}, ``marker_segments_ok`` (per label the
        segments a grouping may rightly give it), ``skin_p2p_mm``,
        ``skin_wobble_rms_mm``, ``plates`` {plate: labels}.
    """
    if markerset not in MARKERSETS:
        raise ValueError(f"markerset must be one of {MARKERSETS}, got {markerset!r}")
    if motion not in REALISTIC_MOTIONS:
        raise ValueError(f"motion must be one of {REALISTIC_MOTIONS}, got {motion!r}")
    if skin not in SKINS:
        raise ValueError(f"skin must be one of {SKINS}, got {skin!r}")
    n_frames = _check_take_args(n_frames, rate, scale, noise_mm, soft_tissue_mm)
    if markers_per_segment is not None and markerset != "default":
        raise ValueError("markers_per_segment applies to the default marker set only")
    slack = np.array(hinge_slack_deg, dtype=float)
    if slack.shape != (2,) or (slack < 0).any():
        raise ValueError(f"hinge_slack_deg must be two non-negative angles, got {hinge_slack_deg}")
    seeds = rng.integers(0, 2**63 - 1, size=3)
    sseed = int(seeds[0]) if subject_seed is None else int(subject_seed)
    mseed, nseed = int(seeds[1]), int(seeds[2])

    subj0 = _make_subject(sseed, _marker_counts(markers_per_segment), float(scale))
    placed = _place(subj0, markerset, sseed, wands)
    subj = placed.subj
    t = np.arange(n_frames) / float(rate)
    root_pos, root_rot, rv = _motion(motion, np.random.default_rng(mseed), t, subj, slack)
    G, O, pts = _forward(subj, root_pos, root_rot, rv)
    # the shoulder girdles carry the arms: the shoulder centres move on the thorax
    for side in "LR":
        ua = _SEG[side + "UpperArm"]
        shift = np.einsum("fij,fj->fi", G[:, _SEG["Torso"]], _girdle_shift(subj, rv, side == "R", subj.joint_rest[ua]))
        for s in (ua, _SEG[side + "Forearm"], _SEG[side + "Hand"]):
            O[:, s] += shift
    if motion in ("walk", "run", "reach", "kick"):  # the lower foot touches the floor
        lift = _floor_lift(subj, G, O)
        O[..., 2] += lift[:, None]
        pts[..., 2] += lift[:, None]

    nrng = np.random.default_rng(nseed)
    host = placed.host
    local = subj.marker_rest - subj.joint_rest[host]  # (M, 3) bone-fixed offsets
    amp = placed.amp
    if skin == "realistic":
        d, amp = _skin(placed, rv, float(rate), sseed, nrng)
        local = local[None] + d
    else:
        local = np.broadcast_to(local, (n_frames,) + local.shape).copy()
        for m in (i for i, k in enumerate(placed.kind) if k == "acromion"):
            local[:, m] += _acromion(subj, rv, m)
    pts = O[:, host] + np.einsum("fmij,fmj->fmi", G[:, host], local)
    del G
    if soft_tissue_mm > 0:
        pts += _soft_tissue(nrng, n_frames, host, float(rate), float(soft_tissue_mm))
    if noise_mm > 0:
        pts += nrng.normal(0.0, float(noise_mm), pts.shape)

    joint_child = np.arange(1, _S)
    bone = np.full(_S - 1, np.nan)
    for e, c in enumerate(joint_child):
        kids = np.flatnonzero(PARENT == c)
        if kids.size:
            bone[e] = np.linalg.norm(subj.joint_rest[kids].mean(0) - subj.joint_rest[c])
    labels = subj.labels
    M = len(labels)
    ok = []
    for m in range(M):
        segs = [int(host[m])]
        if placed.joint[m] is not None:
            child = _JNT[placed.joint[m]] + 1
            segs.append(child if child != host[m] else int(PARENT[child]))
        elif placed.kind[m] == "acromion":
            # on the shoulder girdle, which has no segment here: it moves with the thorax and, by the
            # scapulohumeral rhythm, with the arm, and its distances vary as little to the one as to
            # the other (generated walks: 1.5-1.6 mm; CMU 16_07's RSHO: 3.3 to the upper arm's markers,
            # 5.5-11 to the thorax's)
            segs.append(_SEG[_side_name("LUpperArm", labels[m].startswith("R"))])
        ok.append(segs)
    plates: dict[str, list[str]] = {}
    for m, p in enumerate(placed.plate):
        if p is not None:
            plates.setdefault(p, []).append(labels[m])
    info = {
        "kind": "human",
        "generator": "realistic",
        "motion": motion,
        "markerset": markerset,
        "skin": skin,
        "wands": bool(wands) if markerset == "gait" else None,
        "subject_seed": sseed,
        "motion_seed": mseed,
        "noise_seed": nseed,
        "n_frames": n_frames,
        "rate": float(rate),
        "scale": float(scale),
        "noise_mm": float(noise_mm),
        "noise_mm_is": "standard deviation per coordinate",
        "soft_tissue_mm": float(soft_tissue_mm),
        "skin_p2p_mm": {labels[m]: float(amp[m]) for m in range(M)} if skin == "realistic" else {},
        "skin_p2p_mm_is": "peak-to-peak skin displacement of each marker over its joints' full ranges",
        "skin_wobble_rms_mm": {labels[m]: float(_WOBBLE * amp[m]) for m in range(M)} if skin == "realistic" else {},
        "marker_kind": {labels[m]: placed.kind[m] for m in range(M)},
        "joint_markers": {labels[m]: placed.joint[m] for m in range(M) if placed.joint[m] is not None},
        "marker_segments_ok": [[SEGMENTS[s] for s in segs] for segs in ok],
        "marker_segment_is": "the bone the marker sits on; a marker on a joint also fits the joint's other segment",
        "plates": plates,
        "lab_up": "z",
        "lab_frame": "right-handed, Z up, mm; subject faces +X at rest, +Y is its left, floor z=0",
        "joint_names": list(JOINT_NAMES),
        "ball_joints": [j for j in JOINT_NAMES if j not in HINGES],
        "hinges": list(HINGES),
        "hinge_axes": {h: _hinge_frame(h)[0].tolist() for h in HINGES},
        "bone_length_is": "distance from the joint to the mean of the child segment's child joints",
        "part_factor": subj.part_factor,
        "pelvis_height_mm": subj.pelvis_height,
        "rest_joints_mm": subj.joint_rest[1:].tolist(),
        "rest_markers_mm": subj.marker_rest.tolist(),
        "physical_labels": list(labels),
    }
    markers = Markers(points=pts, labels=labels, rate=float(rate), units="mm",
                      source=f"synth-human-{markerset}-{motion}", stage="read", info={})
    truth = Truth(segment_names=SEGMENTS, parent=PARENT.copy(), marker_segment=host.copy(), marker_id=np.arange(M),
                  joint_child=joint_child, joints=O[:, 1:].copy(), bone_length=bone, info=info)
    used = sorted(set(int(s) for s in host))
    if len(used) < _S:
        truth = restrict_truth(truth, used)
    return SynthTake(markers=markers, truth=truth)
