"""The realistic generator's marker sets (CMU 41, Plug-in-Gait, clusters) and their placement on a subject."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .body import _S, _SEG, HINGES, JOINT_NAMES, SEGMENTS, _hinge_frame, _left, _part, _side_name, _Subject
from .rotations import _mirror

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
