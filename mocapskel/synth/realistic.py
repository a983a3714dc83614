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
    The 48 (or ``markers_per_segment``) markers of :func:`human_take`.

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
reaches 6-10 m/s), ``rom`` (the range-of-motion take of :func:`human_take`).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..artifacts import Markers
from .human import (
    _check_take_args,
    _HINGE,
    HINGES,
    JOINT_NAMES,
    PARENT,
    SEGMENTS,
    _band_noise,
    _floor_lift,
    _forward,
    _hinge_frame,
    _make_subject,
    _marker_counts,
    _matmul33,
    _mirror,
    _mirror_axial,
    _rom_motion,
    _rot_z,
    _smooth,
    _soft_tissue,
    _Subject,
    rotvec_to_matrix,
)
from .truth import SynthTake, Truth

__all__ = ["MARKERSETS", "REALISTIC_MOTIONS", "SKINS", "realistic_take", "restrict_truth"]

MARKERSETS: tuple[str, ...] = ("default", "cmu41", "gait", "cluster")
REALISTIC_MOTIONS: tuple[str, ...] = ("walk", "run", "climb", "reach", "kick", "rom")
SKINS: tuple[str, ...] = ("none", "realistic")

_S = len(SEGMENTS)
_SEG = {n: i for i, n in enumerate(SEGMENTS)}
_JNT = {n: i for i, n in enumerate(JOINT_NAMES)}  # joint e has child segment e + 1
_WOBBLE = 0.05  # rms of the band-limited wobble, as a fraction of the amplitude
_WOBBLE_BAND_HZ = (2.0, 8.0)
_NORMAL_DAMP = 0.6  # skin motion along the skin normal is reduced by this fraction
_ACROMION_RHYTHM = 0.2  # the clavicle rises about the SC joint by this fraction of the arm's elevation
_PROTRACTION = 0.25  # and turns forward by this fraction of the arm's forward flexion
_WAND_MM = 60.0
_WAND_GAIN = 1.3

# ------------------------------------------------------------------ marker tables
# (label, host segment, anchor segment (its proximal joint is the origin of the offset),
#  offset mm (left side, body axes, scaled with the host), kind, amplitude range mm p2p, jitter mm)
# kind: skin | muscle | bony | belt | joint | band | wand | acromion | plate:<name>
# label "L..." gives a left and a mirrored right marker; other labels are single.

_JOINT_AXIS = object()  # offset placeholder: along the joint's flexion axis


@dataclass(frozen=True)
class _Spec:
    label: str
    host: str
    anchor: str
    offset: tuple
    kind: str
    amp: tuple[float, float]
    jitter: float = 8.0
    axis_mm: float = 0.0  # for joint markers on a flexion axis: distance along it


_HEAD_BAND = [
    _Spec("LFHD", "Head", "Head", (95, 70, 110), "band", (2, 5), 6),
    _Spec("LBHD", "Head", "Head", (-50, 62, 100), "band", (2, 5), 6),
]
_THORAX = [
    _Spec("C7", "Torso", "Head", (-65, 0, 5), "bony", (3, 6), 5),
    _Spec("T10", "Torso", "Torso", (-95, 0, 240), "bony", (5, 12), 10),  # the thoracic spine bends
    _Spec("CLAV", "Torso", "Head", (95, 0, -50), "bony", (3, 8), 5),
    _Spec("STRN", "Torso", "Torso", (130, 0, 240), "bony", (4, 10), 10),
]
_ARM_JOINTS = [
    _Spec("LSHO", "Torso", "LUpperArm", (-5, 15, 45), "acromion", (3, 8), 5),
    _Spec("LELB", "LUpperArm", "LForearm", (), "joint", (4, 12), 3, axis_mm=42.0),
    _Spec("LWRA", "LForearm", "LHand", (), "joint", (2, 6), 3, axis_mm=62.0),
    _Spec("LWRB", "LForearm", "LHand", (), "joint", (2, 6), 3, axis_mm=-62.0),
    _Spec("LFIN", "LHand", "LHand", (15, 25, -75), "bony", (2, 5), 8),
]
_LEG_JOINTS = [
    _Spec("LKNE", "LThigh", "LShank", (), "joint", (5, 15), 3, axis_mm=52.0),  # skin folds over the knee
    _Spec("LANK", "LShank", "LFoot", (), "joint", (3, 8), 3, axis_mm=45.0),
    _Spec("LHEE", "LFoot", "LFoot", (-65, 0, -40), "bony", (3, 8), 6),  # heel pad
    _Spec("LTOE", "LFoot", "LFoot", (150, 10, -42), "bony", (4, 10), 8),  # slides with the toes' extension
]
_LMT5 = _Spec("LMT5", "LFoot", "LFoot", (125, 45, -50), "bony", (3, 8), 8)
_PIG_PELVIS = [
    _Spec("LASI", "Pelvis", "Pelvis", (85, 125, 35), "bony", (4, 12), 8),
    _Spec("LPSI", "Pelvis", "Pelvis", (-105, 45, 55), "bony", (3, 8), 8),
]

_CMU41 = [
    *_HEAD_BAND, *_THORAX,
    _Spec("RBAK", "Torso", "Torso", (-100, -90, 330), "muscle", (6, 15), 15),
    *_ARM_JOINTS,
    _Spec("LUPA", "LUpperArm", "LUpperArm", (-15, 45, -150), "muscle", (5, 20), 20),
    _Spec("LFRM", "LForearm", "LForearm", (-20, 25, -120), "muscle", (4, 12), 20),
    _Spec("LFWT", "Pelvis", "Pelvis", (80, 130, 40), "belt", (5, 15), 8),  # on a waist belt, which slides
    _Spec("LBWT", "Pelvis", "Pelvis", (-110, 55, 50), "belt", (4, 12), 8),
    _Spec("LTHI", "LThigh", "LThigh", (15, 85, -240), "muscle", (10, 30), 30),
    _Spec("LSHN", "LShank", "LShank", (45, 35, -190), "muscle", (5, 15), 25),
    *_LEG_JOINTS, _LMT5,
]  # fmt: skip

_GAIT = [
    *_PIG_PELVIS,
    _Spec("LTHI", "LThigh", "LThigh", (10, 85, -260), "wand", (10, 30), 25),
    _Spec("LTIB", "LShank", "LShank", (15, 50, -220), "wand", (5, 15), 25),
    *_LEG_JOINTS,
]

# plates: name -> (host, centre offset from the host's joint, plate axes (u, v) in body axes,
#                  translation amplitude mm p2p, rotation amplitude deg p2p)
_PLATES = {
    "LUA": ("LUpperArm", (-10, 62, -160), ((1, 0, 0), (0, 0, 1)), (5, 15), 6.0),
    "LFA": ("LForearm", (-15, 42, -130), ((1, 0, 0), (0, 0, 1)), (3, 8), 5.0),
    "LTH": ("LThigh", (25, 100, -230), ((1, 0, 0), (0, 0, 1)), (8, 20), 6.0),
    "LSK": ("LShank", (35, 68, -210), ((1, 0, 0), (0, 0, 1)), (4, 10), 5.0),
}
_PLATE_CORNERS = ((35, 30), (-35, 30), (-30, -35), (38, -28))  # (u, v) mm, deliberately not symmetric
_CLUSTER = [
    *_HEAD_BAND, *_THORAX, *_PIG_PELVIS, *_ARM_JOINTS, *_LEG_JOINTS, _LMT5,
    *[_Spec(f"{p}{k + 1}", _PLATES[p][0], _PLATES[p][0], (), f"plate:{p}", _PLATES[p][3], 0.0) for p in _PLATES
      for k in range(4)],
]  # fmt: skip

_SETS = {"cmu41": _CMU41, "gait": _GAIT, "cluster": _CLUSTER}

# skin amplitude (mm p2p) of the default marker set, per body part
_DEFAULT_AMP = {"Pelvis": (3, 12), "Torso": (4, 10), "Head": (2, 5), "UpperArm": (5, 20), "Forearm": (4, 12),
                "Hand": (2, 5), "Thigh": (10, 30), "Shank": (5, 15), "Foot": (2, 6)}  # fmt: skip

# everyday range (deg) of each degree of freedom (rotation-vector components X, Y, Z of a ball joint,
# left side; flexion of a hinge): the skin reaches its amplitude over these ranges
_EVERYDAY = {
    "Lumbar": ((-10, 10), (-10, 30), (-15, 15)), "Neck": ((-15, 15), (-20, 30), (-30, 30)),
    "LShoulder": ((0, 60), (-90, 20), (-30, 30)), "LWrist": ((-15, 15), (-30, 30), (-20, 20)),
    "LHip": ((-10, 20), (-60, 15), (-15, 15)), "LAnkle": ((-10, 10), (-20, 25), (-10, 10)),
    "LKnee": ((0, 90),), "LElbow": ((-120, -10),),
}  # fmt: skip
_LIMIT = 0.75  # a marker's skin displacement stays within this fraction of its amplitude from the mean
_CAL_QUANTILE = 0.5  # the amplitude is the p2p displacement of a typical everyday pose (median)

# joints whose angles drive the skin of each segment (the joints at its ends)
_DRIVERS = {
    "Pelvis": ("LHip", "RHip", "Lumbar"), "Torso": ("Lumbar", "Neck", "LShoulder", "RShoulder"), "Head": ("Neck",),
    "LUpperArm": ("LShoulder", "LElbow"), "LForearm": ("LElbow", "LWrist"), "LHand": ("LWrist",),
    "LThigh": ("LHip", "LKnee"), "LShank": ("LKnee", "LAnkle"), "LFoot": ("LAnkle",),
}  # fmt: skip


def _left(name: str) -> str:
    return "L" + name[1:] if name.startswith("R") else name


def _part(seg: str) -> str:
    """Body part of a segment name (no side)."""
    return seg[1:] if seg[0] in "LR" and seg[1:2].isupper() else seg


def _side_name(name: str, right: bool) -> str:
    return ("R" + name[1:]) if right and name.startswith("L") and name != "Lumbar" else name


def _drivers(seg: str) -> tuple[str, ...]:
    right = seg.startswith("R")
    return tuple(_side_name(j, right) for j in _DRIVERS[_left(seg)])


# ------------------------------------------------------------------ the subject's markers


@dataclass(frozen=True)
class _Placed:
    subj: _Subject
    host: np.ndarray  # (M,) host segment
    kind: tuple[str, ...]
    amp: np.ndarray  # (M,) skin amplitude mm p2p
    joint: tuple[str | None, ...]  # joint a marker sits on
    plate: tuple[str | None, ...]
    plate_centre: dict  # plate name -> (3,) rest position (body frame)


def _place(subj: _Subject, markerset: str, seed: int, wands: bool) -> _Placed:
    """Rest positions (body frame), hosts, kinds and skin amplitudes of a marker set's markers."""
    fac = subj.seg_factor
    if markerset == "default":
        host = subj.marker_segment.copy()
        arng = np.random.default_rng([seed, 7])
        amp = np.array([arng.uniform(*_DEFAULT_AMP[_part(SEGMENTS[s])]) for s in host])
        n = host.size
        return _Placed(subj, host, ("skin",) * n, amp, (None,) * n, (None,) * n, {})
    specs = _SETS[markerset]
    rest, host, kinds, amps, joints, plates, labels, centres = [], [], [], [], [], [], [], {}
    for spec in specs:
        sides = (False, True) if spec.label.startswith("L") else (False,)
        for right in sides:
            label = _side_name(spec.label, right)
            h = _SEG[_side_name(spec.host, right)]
            a = _SEG[_side_name(spec.anchor, right)]
            mrng = np.random.default_rng([seed, 11, sum(map(ord, label)) * 131 + len(label)])
            jit = mrng.normal(0.0, 1.0, 3)
            joint = None
            if spec.kind == "joint":
                jname = JOINT_NAMES[a - 1]
                joint = jname
                ax = _flexion_axis(jname)
                perp = jit - (jit @ ax) * ax
                # on the flexion axis, laterally (axis_mm > 0) or medially, a few mm off it
                pos = subj.joint_rest[a] + fac[h] * (abs(spec.axis_mm) * _lateral(ax, right, spec.axis_mm > 0))
                pos = pos + spec.jitter * perp / max(np.linalg.norm(perp), 1e-9) * mrng.uniform(0.3, 1.0)
            elif spec.kind.startswith("plate:"):
                p = _side_name(spec.kind.split(":")[1], right)
                pl = _PLATES[_left(p) if p.startswith("R") else p]
                k = int(label[-1]) - 1
                centre = np.array(pl[1], float)
                u, v = np.array(pl[2][0], float), np.array(pl[2][1], float)
                cu, cv = _PLATE_CORNERS[k]
                off = centre + cu * u + cv * v + mrng.normal(0.0, 4.0, 3)
                off, c_off = (_mirror(off), _mirror(centre)) if right else (off, centre)
                pos = subj.joint_rest[a] + fac[h] * off
                centres[p] = subj.joint_rest[a] + fac[h] * c_off
                plates.append(p)
            else:
                off = np.array(spec.offset, float)
                if spec.kind == "wand" and wands:
                    off = off + np.array([0.0, _WAND_MM, 0.0])
                off = off + spec.jitter * np.clip(jit, -2, 2) * np.array([1.0, 0.4, 1.0])
                pos = subj.joint_rest[a] + fac[h] * (_mirror(off) if right else off)
            if not spec.kind.startswith("plate:"):
                plates.append(None)
            lo, hi = spec.amp
            if spec.kind == "muscle" and _left(SEGMENTS[h]) == "LThigh":
                # largest near the hip
                frac = np.clip((subj.joint_rest[h, 2] - pos[2]) / (fac[h] * 430.0), 0.0, 1.0)
                amp = hi - (hi - lo) * (0.3 + 0.7 * frac) * mrng.uniform(0.6, 1.0)
            else:
                amp = mrng.uniform(lo, hi)
            if spec.kind == "wand" and wands:
                amp *= _WAND_GAIN
            rest.append(pos)
            host.append(h)
            kinds.append(spec.kind)
            amps.append(amp)
            joints.append(joint)
            labels.append(label)
    rest_a = np.array(rest)
    host_a = np.array(host, dtype=int)
    subj2 = replace(subj, marker_rest=rest_a, marker_segment=host_a, labels=tuple(labels),
                    counts=tuple(int((host_a == s).sum()) for s in range(_S)))
    return _Placed(subj2, host_a, tuple(kinds), np.array(amps), tuple(joints), tuple(plates), centres)


def _flexion_axis(joint: str) -> np.ndarray:
    """Unit flexion axis of a joint at rest (hinges: their axis; ankle and wrist: the lateral axis)."""
    if joint in HINGES:
        return _hinge_frame(joint)[0]
    return np.array([0.0, 1.0, 0.0])


def _lateral(ax: np.ndarray, right: bool, outward: bool) -> np.ndarray:
    """The flexion axis pointed laterally (outward) or medially for the side's marker."""
    lat = np.array([0.0, -1.0 if right else 1.0, 0.0])
    a = ax if ax @ lat > 0 else -ax
    return a if outward else -a


# ------------------------------------------------------------------ skin motion


def _joint_features(rv: np.ndarray, joint: str) -> np.ndarray:
    """(F, K) smooth features of a joint's angles: ~[-1, 1] over its everyday range, saturating beyond."""
    s = _JNT[joint] + 1
    v = rv[:, s] if not joint.startswith("R") else _mirror_axial(rv[:, s])
    left = "L" + joint[1:] if joint.startswith("R") else joint
    box = np.deg2rad(np.array(_EVERYDAY[left], float)).reshape(-1, 2)
    if left in _HINGE:
        v = (v @ _hinge_frame(left)[0])[:, None]
    u = (v - box.mean(1)) / (0.5 * (box[:, 1] - box[:, 0]))
    return _features(u)


def _features(u: np.ndarray) -> np.ndarray:
    """Linear and quadratic terms of angles normalised to their everyday range; skin stretches only
    so far, so each saturates (tanh) beyond that range (at most ~1.3 times its in-range value)."""
    s = np.tanh(u) / np.tanh(1.0)
    return np.concatenate([s, s**2 - 0.4], axis=1)


def _joint_dim(joint: str) -> int:
    left = "L" + joint[1:] if joint.startswith("R") else joint
    return 1 if left in _HINGE else 3


def _skin(placed: _Placed, rv: np.ndarray, rate: float, seed: int, nrng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(F, M, 3) skin displacements in the host segments' frames, and the (M,) amplitudes used."""
    subj = placed.subj
    F, M = rv.shape[0], placed.host.size
    out = np.zeros((F, M, 3))
    crng = np.random.default_rng([seed, 21])  # the subject's skin: fixed by the subject seed
    n_cal = 512
    feats: dict[str, np.ndarray] = {}
    cal: dict[str, np.ndarray] = {}
    for s in np.unique(placed.host):
        for j in _drivers(SEGMENTS[s]):
            if j not in feats:
                feats[j] = _joint_features(rv, j)
                d = _joint_dim(j)
                u = np.random.default_rng([seed, 22, _JNT[j]]).uniform(-1.0, 1.0, (n_cal, d))
                cal[j] = _features(u)
    done_plates: dict[str, np.ndarray] = {}
    for m in range(M):
        h = int(placed.host[m])
        drv = _drivers(SEGMENTS[h])
        phi = np.concatenate([feats[j] for j in drv], axis=1)
        phic = np.concatenate([cal[j] for j in drv], axis=1)
        plate = placed.plate[m]
        if plate is not None:
            if plate not in done_plates:
                done_plates[plate] = _plate_motion(crng, phi, phic, placed, plate, h)
            T, W = done_plates[plate]  # (F, 3), (F, 3) rad
            local = subj.marker_rest[m] - placed.plate_centre[plate]
            R = rotvec_to_matrix(W)
            out[:, m] = T + np.einsum("fij,j->fi", R, local) - local
            continue
        C = crng.normal(0.0, 1.0, (3, phi.shape[1]))
        # mostly along the skin: damp the component along the outward normal
        n = _outward_normal(subj, h, subj.marker_rest[m])
        C = C - _NORMAL_DAMP * np.outer(n, n @ C)
        dc = phic @ C.T
        dc -= dc.mean(0)
        scale = placed.amp[m] / (2.0 * np.quantile(np.linalg.norm(dc, axis=1), _CAL_QUANTILE))
        out[:, m] = _soft_limit((phi - phic.mean(0)) @ C.T * scale, _LIMIT * placed.amp[m])
    if placed.kind.count("acromion"):
        for m in (i for i, k in enumerate(placed.kind) if k == "acromion"):
            out[:, m] += _acromion(subj, rv, m)
    # band-limited wobble (inertia), independent per marker, rigid per plate
    wob = _band_noise(nrng, F, M * 3, rate, _WOBBLE_BAND_HZ).reshape(F, M, 3)
    for plate in set(p for p in placed.plate if p is not None):
        idx = [i for i, p in enumerate(placed.plate) if p == plate]
        wob[:, idx] = wob[:, idx[:1]]
    out += wob * (_WOBBLE * placed.amp / np.sqrt(3.0))[None, :, None]
    return out, placed.amp


def _plate_motion(crng, phi, phic, placed: _Placed, plate: str, h: int):
    """(F, 3) translation (mm) and (F, 3) rotation vector (rad) of a sliding plate."""
    left = plate if not plate.startswith("R") else "L" + plate[1:]
    _, _, _, tr_amp, rot_deg = _PLATES[left]
    C = crng.normal(0.0, 1.0, (6, phi.shape[1]))
    dc = phic @ C.T
    dc -= dc.mean(0)
    a_tr = crng.uniform(*tr_amp)
    C[:3] *= a_tr / (2.0 * np.quantile(np.linalg.norm(dc[:, :3], axis=1), _CAL_QUANTILE))
    C[3:] *= np.deg2rad(rot_deg) / (2.0 * np.quantile(np.linalg.norm(dc[:, 3:], axis=1), _CAL_QUANTILE))
    idx = [i for i, p in enumerate(placed.plate) if p == plate]
    placed.amp[idx] = a_tr  # a plate's markers share its translation amplitude
    d = (phi - phic.mean(0)) @ C.T
    return _soft_limit(d[:, :3], _LIMIT * a_tr), _soft_limit(d[:, 3:], _LIMIT * np.deg2rad(rot_deg))


def _soft_limit(d: np.ndarray, limit: float) -> np.ndarray:
    """(F, 3) displacements shrunk smoothly so that their length stays under ``limit`` (skin stretches
    only so far): nearly unchanged below ~60 % of it."""
    n = np.linalg.norm(d, axis=1, keepdims=True) / max(limit, 1e-9)
    return d / (1.0 + n**4) ** 0.25


def _outward_normal(subj: _Subject, h: int, p: np.ndarray) -> np.ndarray:
    kids = np.flatnonzero(PARENT == h)
    o = subj.joint_rest[h]
    leaf_axis = {"Foot": (1.0, 0.0, 0.0), "Hand": (0.0, 0.0, -1.0)}.get(_part(SEGMENTS[h]), (0.0, 0.0, 1.0))
    axis = (subj.joint_rest[kids].mean(0) - o) if kids.size else np.array(leaf_axis)
    axis = axis / np.linalg.norm(axis)
    r = (p - o) - ((p - o) @ axis) * axis
    nr = np.linalg.norm(r)
    return r / nr if nr > 1e-6 else np.zeros(3)


def _girdle(subj: _Subject, rv: np.ndarray, right: bool) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3, 3) rotation of a shoulder girdle in the thorax frame and (3,) its pivot (the
    sterno-clavicular joint, body frame at rest): the scapulohumeral rhythm. About the pivot the girdle
    rises by a fifth of the arm's elevation and turns forward (protraction) by a quarter of its forward
    flexion; it carries the acromion and the shoulder joint centre."""
    sh = _SEG["RUpperArm" if right else "LUpperArm"]
    R = rotvec_to_matrix(rv[:, sh])  # upper arm relative to the thorax (thorax axes)
    v = -R[:, :, 2]  # the arm's long axis (rest: straight down)
    elev = np.arccos(np.clip(-v[:, 2], -1.0, 1.0))
    fwd = np.clip(np.arctan2(v[:, 0], -v[:, 2]), 0.0, None)
    sign = -1.0 if right else 1.0
    zero = np.zeros_like(elev)
    up = rotvec_to_matrix(np.column_stack([sign * _ACROMION_RHYTHM * elev, zero, zero]))
    forward = rotvec_to_matrix(np.column_stack([zero, zero, -sign * _PROTRACTION * fwd]))
    sc = subj.joint_rest[_SEG["Head"]] + np.array([60.0, 20.0 * sign, -50.0]) * subj.seg_factor[1]
    return _matmul33(forward, up), sc


def _girdle_shift(subj: _Subject, rv: np.ndarray, right: bool, p: np.ndarray) -> np.ndarray:
    """(F, 3) displacement (thorax frame) of a point ``p`` (body frame at rest) carried by a shoulder girdle."""
    Rc, sc = _girdle(subj, rv, right)
    arm = p - sc
    return np.einsum("fij,j->fi", Rc, arm) - arm


def _acromion(subj: _Subject, rv: np.ndarray, m: int) -> np.ndarray:
    """(F, 3) displacement of an acromion marker in the thorax frame (it rides the shoulder girdle)."""
    p = subj.marker_rest[m]
    return _girdle_shift(subj, rv, bool(p[1] < 0), p)


# ------------------------------------------------------------------ motions


def _minjerk_keys(t: np.ndarray, times: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(F, C) minimum-jerk interpolation through keyframes ``values`` (K, C) at ``times`` (K,)."""
    times = np.asarray(times, float)
    values = np.asarray(values, float)
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
    span = times[k + 1] - times[k]
    s = np.clip((t - times[k]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    w = s**3 * (10.0 - 15.0 * s + 6.0 * s * s)
    return values[k] + w[:, None] * (values[k + 1] - values[k])


def _put_ball(rv: np.ndarray, joint: str, v_deg: np.ndarray) -> None:
    """Set a ball joint from left-side-convention angles (deg, rotation vector components X, Y, Z)."""
    v = np.asarray(v_deg, float)
    rv[:, _JNT[joint] + 1] = np.deg2rad(_mirror_axial(v) if joint.startswith("R") else v)


def _put_hinge(rv: np.ndarray, joint: str, flex_deg: np.ndarray, slack_deg: np.ndarray) -> None:
    a, e1, e2 = _hinge_frame(joint)
    rv[:, _JNT[joint] + 1] = np.deg2rad(flex_deg[:, None] * a + slack_deg[:, :1] * e1 + slack_deg[:, 1:] * e2)


def _bumpc(phase_cycles: np.ndarray, centre: float, width: float) -> np.ndarray:
    d = (phase_cycles - centre + 0.5) % 1.0 - 0.5
    return np.exp(-0.5 * (d / width) ** 2)


_GAITS = {
    # f strides/s, stride (m, for a 995 mm pelvis), hip mean/amp, knee base, stance bump (h, c, w),
    # swing bump (h, c, w), ankle dorsi/plantar bumps, arm swing, elbow mean/amp, lumbar rot, lean, rise per stride
    # (walking elbows 30 +- 15 deg: in CMU's walks 07_01 and 07_12 the LUPA-LWRA distance varies by 6-7 mm (std)
    # and RUPA-RWRA by 11-12 mm; 22 +- 8 gave 2-4 mm, an arm stiffer than any real walk's)
    "walk": dict(f=(0.85, 0.95), stride=1.45, hip=(10, 20), knee0=4, kst=(15, 0.12, 0.07), ksw=(56, 0.72, 0.1),
                 dor=(10, 0.42, 0.1), pla=(20, 0.62, 0.06), arm=15, elb=(30, 15), rot=5, lean=3, rise=0.0, bob=12),
    "run": dict(f=(1.3, 1.4), stride=2.2, hip=(15, 27), knee0=15, kst=(25, 0.15, 0.07), ksw=(80, 0.64, 0.14),
                dor=(15, 0.18, 0.07), pla=(25, 0.42, 0.06), arm=35, elb=(85, 12), rot=10, lean=10, rise=0.0, bob=35),
    "climb": dict(f=(0.7, 0.8), stride=0.56, hip=(32, 28), knee0=10, kst=(55, 0.02, 0.12), ksw=(85, 0.72, 0.12),
                  dor=(12, 0.35, 0.1), pla=(15, 0.6, 0.07), arm=10, elb=(20, 6), rot=4, lean=10, rise=0.34, bob=15),
}


def _locomotion(kind: str, rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Walking, running or climbing stairs along a straight line."""
    g = _GAITS[kind]
    F = t.size
    size = subj.pelvis_height / 995.0
    f = rng.uniform(*g["f"])
    stride = g["stride"] * size * rng.uniform(0.93, 1.07) * 1000.0  # mm
    speed = stride * f
    cyc0 = rng.uniform()
    rv = np.zeros((F, _S, 3))
    zero = np.zeros(F)
    for side, off in (("L", 0.0), ("R", 0.5)):
        c = f * t + cyc0 + off  # gait cycle of this leg (0 = heel strike)
        ph = 2.0 * np.pi * c
        opp = ph + np.pi
        hip_flex = g["hip"][0] + g["hip"][1] * np.cos(ph)
        knee = g["knee0"] + g["kst"][0] * _bumpc(c, *g["kst"][1:]) + g["ksw"][0] * _bumpc(c, *g["ksw"][1:])
        dorsi = g["dor"][0] * _bumpc(c, *g["dor"][1:]) - g["pla"][0] * _bumpc(c, *g["pla"][1:])
        arm = g["arm"] * np.cos(opp)
        elbow = g["elb"][0] + g["elb"][1] * np.cos(opp)
        var = _smooth(rng, t, 3, 0.1, 0.6, k=3)  # stride-to-stride variability, ~±2 deg
        _put_ball(rv, side + "Hip", np.column_stack([2.0 + 3.0 * np.cos(ph), -hip_flex, 3.0 * np.sin(ph)]) + var)
        _put_ball(rv, side + "Ankle", np.column_stack([2.0 * np.sin(ph), -dorsi, 2.0 * np.sin(ph)]) + 0.5 * var)
        _put_ball(rv, side + "Shoulder", np.column_stack([8.0 + zero, -arm, 4.0 + zero]) + var)
        _put_ball(rv, side + "Wrist", np.column_stack([zero, -5.0 + 2.0 * np.sin(ph), zero]) + 0.5 * var)
        sl = _smooth(rng, t, 2, 0.2, 1.0, k=3) * 0.2 * slack
        _put_hinge(rv, side + "Knee", knee, sl)
        _put_hinge(rv, side + "Elbow", -elbow, sl)
    c = f * t + cyc0
    phL = 2.0 * np.pi * c
    _put_ball(rv, "Lumbar", np.column_stack([2.0 * np.cos(phL), g["lean"] + zero, -g["rot"] * np.sin(phL)])
              + _smooth(rng, t, 3, 0.1, 0.5, k=3))
    _put_ball(rv, "Neck", np.column_stack([zero, -0.6 * g["lean"] + zero, g["rot"] * np.sin(phL)])
              + _smooth(rng, t, 3, 0.05, 0.3) * np.array([2.0, 3.0, 6.0]))
    heading = rng.uniform(0.0, 2.0 * np.pi)
    d = np.array([np.cos(heading), np.sin(heading)])
    s = speed * (t - t.mean())
    lateral = 20.0 * size * np.sin(phL)
    xy = s[:, None] * d + lateral[:, None] * np.array([-d[1], d[0]])
    z = subj.pelvis_height - 15.0 * size + g["bob"] * size * np.cos(2.0 * phL) + g["rise"] * 1000.0 * size * f * t
    root_pos = np.column_stack([xy, z])
    tilt = np.deg2rad(np.column_stack([4.0 * np.cos(phL), 4.0 + 0.5 * g["lean"] + 2.0 * np.sin(2.0 * phL), zero]))
    root_rot = _matmul33(_rot_z(heading + np.deg2rad(g["rot"] * np.sin(phL))), rotvec_to_matrix(tilt))
    return root_pos, root_rot, rv


def _standing_root(rng: np.random.Generator, t: np.ndarray, subj: _Subject):
    F = t.size
    yaw = rng.uniform(0.0, 2.0 * np.pi) + np.deg2rad(2.0) * _smooth(rng, t, 1, 0.05, 0.2)[:, 0] / 2.0
    xy = rng.uniform(-500.0, 500.0, 2) + 10.0 * _smooth(rng, t, 2, 0.05, 0.3) / 2.0
    root_pos = np.column_stack([xy, np.full(F, subj.pelvis_height)])
    return root_pos, yaw


def _reach(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Standing; one or both arms reach to random targets and come back; the trunk leans and turns."""
    F, T = t.size, float(t[-1])
    # channels: per arm shoulder (x, y, z), elbow flex, wrist (x, y, z); lumbar (x, y, z); neck (x, y, z); hips flex
    rest = {"sh": [8.0, 0.0, 0.0], "el": 15.0, "wr": [0.0, 0.0, 0.0]}
    times, keys = [0.0], []
    el_times, el_keys = [0.0], [[rest["el"], rest["el"]]]  # elbows: they flex on the way out and back

    def pose(reach_l, reach_r, trunk, neck):
        row = []
        for r in (reach_l, reach_r):
            row += (r["sh"] + [r["el"]] + r["wr"]) if r else (rest["sh"] + [rest["el"]] + rest["wr"])
        return row + trunk + neck

    base = pose(None, None, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    keys.append(base)
    tk = rng.uniform(0.2, 0.6)
    while tk < T + 3.0:
        which = rng.choice(["L", "R", "LR"], p=[0.4, 0.4, 0.2])
        flex = rng.uniform(30.0, 160.0)
        abd = rng.uniform(0.0, 70.0)
        r = {"sh": [abd, -flex, rng.uniform(-30.0, 30.0)], "el": rng.uniform(5.0, 30.0),
             "wr": list(rng.uniform(-20.0, 20.0, 3))}
        lean = rng.uniform(0.0, 30.0) if flex < 90 else rng.uniform(-5.0, 10.0)
        turn = rng.uniform(-20.0, 20.0)
        trunk = [rng.uniform(-8.0, 8.0), lean, turn]
        neck = [0.0, rng.uniform(-20.0, 25.0), rng.uniform(-30.0, 30.0)]
        target = pose(r if "L" in which else None, r if "R" in which else None, trunk, neck)
        d_out, hold, d_back, pause = rng.uniform(0.7, 1.1), rng.uniform(0.2, 0.5), rng.uniform(0.5, 0.8), rng.uniform(0.2, 0.6)
        times += [tk, tk + d_out, tk + d_out + hold, tk + d_out + hold + d_back]
        keys += [base, target, target, base]
        bent = rng.uniform(60.0, 100.0)
        el_mid = [bent if "L" in which else rest["el"], bent if "R" in which else rest["el"]]
        el_end = [r["el"] if "L" in which else rest["el"], r["el"] if "R" in which else rest["el"]]
        el_times += [tk, tk + 0.45 * d_out, tk + d_out, tk + d_out + hold, tk + d_out + hold + 0.5 * d_back,
                     tk + d_out + hold + d_back]
        el_keys += [[rest["el"]] * 2, el_mid, el_end, el_end, el_mid, [rest["el"]] * 2]
        tk += d_out + hold + d_back + pause
    V = _minjerk_keys(t, np.array(times), np.array(keys))
    V[:, [3, 10]] = _minjerk_keys(t, np.array(el_times), np.array(el_keys))
    rv = np.zeros((F, _S, 3))
    for i, side in enumerate("LR"):
        o = 7 * i
        _put_ball(rv, side + "Shoulder", V[:, o:o + 3])
        _put_hinge(rv, side + "Elbow", -V[:, o + 3], _smooth(rng, t, 2, 0.1, 0.5, k=3) * 0.2 * slack)
        _put_ball(rv, side + "Wrist", V[:, o + 4:o + 7])
        # the legs stand still (the trunk leans at the lumbar joint)
        _put_ball(rv, side + "Hip", np.column_stack([np.full(F, 3.0), np.full(F, -5.0), np.zeros(F)])
                  + 0.5 * _smooth(rng, t, 3, 0.05, 0.3, k=3))
        _put_hinge(rv, side + "Knee", 6.0 + _smooth(rng, t, 1, 0.05, 0.3, k=3)[:, 0], np.zeros((F, 2)))
    _put_ball(rv, "Lumbar", V[:, 14:17])
    _put_ball(rv, "Neck", V[:, 17:20])
    root_pos, yaw = _standing_root(rng, t, subj)
    root_rot = _rot_z(yaw)
    return root_pos, root_rot, rv


def _kick(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Fighting guard with front and roundhouse kicks of either leg (fast: the foot reaches 6-10 m/s) and punches."""
    F, T = t.size, float(t[-1])
    # channels per leg: hip (x, y, z), knee; shared: lumbar (x, y, z)
    guard = [0.0, -15.0, 0.0, 20.0]
    times, keys = [0.0], [guard + guard + [0.0, 5.0, 0.0]]
    tk = rng.uniform(0.3, 0.7)
    while tk < T + 3.0:
        side = int(rng.integers(2))
        round_ = rng.uniform() < 0.4
        hi = rng.uniform(80.0, 100.0)
        if round_:
            chamber = [rng.uniform(40, 60), -rng.uniform(50, 70), rng.uniform(-30, -15), rng.uniform(110, 130)]
            extend = [rng.uniform(60, 75), -rng.uniform(55, 75), rng.uniform(-35, -20), rng.uniform(5, 15)]
            lean = [rng.uniform(15, 30), rng.uniform(0, 10), 0.0]  # away from the kicking (left) leg
        else:
            chamber = [rng.uniform(0, 10), -hi + 10.0, 0.0, rng.uniform(110, 130)]
            extend = [rng.uniform(0, 10), -hi, 0.0, rng.uniform(3, 12)]
            lean = [0.0, -rng.uniform(10, 20), 0.0]
        support = [0.0, -25.0, 0.0, 25.0]
        if side == 1:  # the right leg kicks: lateral lean the other way
            lean[0] = -lean[0]

        def row(kick, sup, trunk):
            legs = (kick + sup) if side == 0 else (sup + kick)
            return legs + trunk

        d_ch, d_ex, d_re, d_dn = rng.uniform(0.25, 0.35), rng.uniform(0.22, 0.3), rng.uniform(0.2, 0.25), rng.uniform(0.3, 0.4)
        times += [tk, tk + d_ch, tk + d_ch + d_ex, tk + d_ch + d_ex + 0.05, tk + d_ch + d_ex + 0.05 + d_re,
                  tk + d_ch + d_ex + 0.05 + d_re + d_dn]
        g_trunk = [0.0, 5.0, 0.0]
        keys += [row(guard, guard, g_trunk), row(chamber, support, [0.5 * x for x in lean]), row(extend, support, lean),
                 row(extend, support, lean), row(chamber, support, [0.5 * x for x in lean]), row(guard, guard, g_trunk)]
        tk = times[-1] + rng.uniform(0.6, 1.2)
    V = _minjerk_keys(t, np.array(times), np.array(keys))
    # arms: guard, with punches (shoulder forward, elbow straight) in between
    guard_arm = [20.0, -45.0, -20.0, 110.0]
    a_times, a_keys = [0.0], [guard_arm * 2]
    tp = rng.uniform(0.2, 0.8)
    while tp < T + 1.0:
        punch = [rng.uniform(0.0, 20.0), -rng.uniform(75.0, 95.0), rng.uniform(-10.0, 15.0), rng.uniform(5.0, 20.0)]
        row = punch + guard_arm if rng.uniform() < 0.5 else guard_arm + punch
        d_out, d_back = rng.uniform(0.15, 0.22), rng.uniform(0.2, 0.3)
        a_times += [tp, tp + d_out, tp + d_out + 0.04, tp + d_out + 0.04 + d_back]
        a_keys += [guard_arm * 2, row, row, guard_arm * 2]
        tp = a_times[-1] + rng.uniform(0.4, 1.2)
    A = _minjerk_keys(t, np.array(a_times), np.array(a_keys))
    rv = np.zeros((F, _S, 3))
    for i, side in enumerate("LR"):
        o = 4 * i
        var = _smooth(rng, t, 3, 0.1, 0.5, k=3)
        sl = _smooth(rng, t, 2, 0.1, 0.5, k=3) * 0.3 * slack
        _put_ball(rv, side + "Hip", V[:, o:o + 3] + var)
        _put_hinge(rv, side + "Knee", V[:, o + 3], sl)
        _put_ball(rv, side + "Ankle", np.column_stack([np.zeros(F), 0.25 * V[:, o + 3] - 5.0, np.zeros(F)]) + 0.5 * var)
        _put_ball(rv, side + "Shoulder", A[:, 4 * i:4 * i + 3] + 3.0 * var)
        _put_hinge(rv, side + "Elbow", -A[:, 4 * i + 3] + 8.0 * _smooth(rng, t, 1, 0.2, 0.8, k=3)[:, 0], sl)
        _put_ball(rv, side + "Wrist", 2.0 * var)
    _put_ball(rv, "Lumbar", V[:, 8:11])
    _put_ball(rv, "Neck", -0.6 * V[:, 8:11] + _smooth(rng, t, 3, 0.05, 0.3) * 2.0)
    root_pos, yaw = _standing_root(rng, t, subj)
    root_rot = _rot_z(yaw)
    return root_pos, root_rot, rv


def _motion(motion: str, rng, t, subj, slack):
    if motion in _GAITS:
        return _locomotion(motion, rng, t, subj, slack)
    if motion == "reach":
        return _reach(rng, t, subj, slack)
    if motion == "kick":
        return _kick(rng, t, subj, slack)
    return _rom_motion(rng, t, subj, slack)


# ------------------------------------------------------------------ truth


def restrict_truth(truth: Truth, keep: Sequence[int]) -> Truth:
    """The truth of a take whose markers sit on ``keep`` segments only (a subtree holding the root).

    Segments are renumbered in their old order; joints between kept segments
    stay, with their bone lengths recomputed over the kept tree."""
    keep = sorted(int(s) for s in keep)
    new = {s: i for i, s in enumerate(keep)}
    if truth.parent[keep[0]] != -1 or any(truth.parent[s] not in new for s in keep[1:]):
        raise ValueError("the kept segments must form a subtree holding the root")
    parent = np.array([-1 if truth.parent[s] < 0 else new[int(truth.parent[s])] for s in keep])
    cols = [e for e, c in enumerate(truth.joint_child) if int(c) in new]
    joint_child = np.array([new[int(truth.joint_child[e])] for e in cols], dtype=int)
    joints = truth.joints[:, cols]
    bone = np.full(len(cols), np.nan)
    for k, e in enumerate(cols):
        c = new[int(truth.joint_child[e])]
        kid_cols = [i for i, cc in enumerate(joint_child) if parent[cc] == c]
        if kid_cols:
            bone[k] = float(np.mean(np.linalg.norm(joints[:, kid_cols].mean(1) - joints[:, k], axis=-1)))
    ms = np.array([new[int(s)] if s >= 0 else -1 for s in truth.marker_segment])
    info = dict(truth.info)
    info["joint_names"] = [truth.info["joint_names"][e] for e in cols] if "joint_names" in truth.info else None
    if "rest_joints_mm" in info:
        info["rest_joints_mm"] = [truth.info["rest_joints_mm"][e] for e in cols]
    for key in ("hinges", "ball_joints"):
        if key in info:
            info[key] = [j for j in info[key] if j in info["joint_names"]]
    return Truth(segment_names=tuple(truth.segment_names[s] for s in keep), parent=parent, marker_segment=ms,
                 marker_id=truth.marker_id.copy(), joint_child=joint_child, joints=joints, bone_length=bone, info=info)


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
        ``"default"`` set only, as in :func:`human_take`.
    soft_tissue_mm : float
        Extra pose-independent skin wobble of :func:`human_take` (RMS mm).
    hinge_slack_deg : (2,) floats
        Half-ranges of the knees' and elbows' off-axis rotation (the ``rom``
        motion uses them whole; everyday motions 20-30 % of them).

    Returns
    -------
    SynthTake
        The truth has the format of :func:`human_take`'s (15 segments; the 7
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
