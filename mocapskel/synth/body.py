"""The synthetic human's body: its segments, joints and hinge axes, and a seeded subject (proportions and
markers at rest)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .rotations import _mirror, _mirror_axial

__all__ = [
    "SEGMENTS",
    "PARENT",
    "JOINT_NAMES",
    "LABEL_CODES",
    "DEFAULT_MARKERS_PER_SEGMENT",
    "HINGES",
]

SEGMENTS: tuple[str, ...] = (
    "Pelvis", "Torso", "Head",
    "LUpperArm", "LForearm", "LHand", "RUpperArm", "RForearm", "RHand",
    "LThigh", "LShank", "LFoot", "RThigh", "RShank", "RFoot",
)  # fmt: skip
#: The humanoid name (``--names humanoid``) of each segment, its trunk of two: the truth the naming
#: tests and benchmarks compare with.
HUMANOID_NAMES: dict[str, str] = {
    "Pelvis": "Hips", "Torso": "Spine", "Head": "Head",
    "LUpperArm": "LeftArm", "LForearm": "LeftForeArm", "LHand": "LeftHand",
    "RUpperArm": "RightArm", "RForearm": "RightForeArm", "RHand": "RightHand",
    "LThigh": "LeftUpLeg", "LShank": "LeftLeg", "LFoot": "LeftFoot",
    "RThigh": "RightUpLeg", "RShank": "RightLeg", "RFoot": "RightFoot",
}  # fmt: skip
#: (S,) parent segment of each segment, -1 for the root.
PARENT = np.array([-1, 0, 1, 1, 3, 4, 1, 6, 7, 0, 9, 10, 0, 12, 13])
#: Joint ``e`` connects segment ``e + 1`` to its parent.
JOINT_NAMES: tuple[str, ...] = (
    "Lumbar", "Neck", "LShoulder", "LElbow", "LWrist", "RShoulder", "RElbow", "RWrist",
    "LHip", "LKnee", "LAnkle", "RHip", "RKnee", "RAnkle",
)  # fmt: skip
LABEL_CODES: tuple[str, ...] = (
    "PELV", "TRSO", "HEAD", "LUPA", "LFRM", "LHND", "RUPA", "RFRM", "RHND",
    "LTHI", "LSHN", "LFOT", "RTHI", "RSHN", "RFOT",
)  # fmt: skip
#: Default marker count per segment (48 in all).
DEFAULT_MARKERS_PER_SEGMENT: dict[str, int] = {
    name: (4 if name in ("Pelvis", "Torso", "Head") else 3) for name in SEGMENTS
}
HINGES: tuple[str, ...] = ("LElbow", "RElbow", "LKnee", "RKnee")

_S = len(SEGMENTS)
_SEG = {n: i for i, n in enumerate(SEGMENTS)}
_JNT = {n: i for i, n in enumerate(JOINT_NAMES)}  # joint e has child segment e + 1
_RIGHT = frozenset(i for i, n in enumerate(SEGMENTS) if n.startswith("R"))
#: Body part of each segment (lengths jitter per part, the same on both sides).
_PART = ("pelvis", "torso", "head", "uarm", "farm", "hand", "uarm", "farm", "hand",
         "thigh", "shank", "foot", "thigh", "shank", "foot")  # fmt: skip
_PARTS = ("pelvis", "torso", "head", "uarm", "farm", "hand", "thigh", "shank", "foot")
_ANKLE_HEIGHT = 75.0  # mm, ankle joint centre above the floor at rest

# Nominal offsets (mm, left side) of each segment's proximal joint from its
# parent's origin (the parent's proximal joint; the pelvis centre for the root).
_JOINT_OFFSET = {
    "Torso": (-20.0, 0.0, 90.0),  # L5/S1 above and behind the pelvis centre
    "Head": (-20.0, 0.0, 470.0),  # C7/T1 above the lumbar joint
    "LUpperArm": (-10.0, 175.0, 410.0),  # gleno-humeral centre
    "LForearm": (0.0, 5.0, -300.0),
    "LHand": (10.0, 0.0, -255.0),
    "LThigh": (0.0, 85.0, -70.0),  # hip joint centre
    "LShank": (0.0, 5.0, -430.0),
    "LFoot": (-10.0, 0.0, -420.0),
}


@dataclass(frozen=True)
class _MarkerSpec:
    """Where a segment's markers go, in its local rest frame (origin at its joint).

    Markers lie at ``p0 + t (p1 - p0) + r (cos a d + sin a (u x d))`` with
    ``u`` the axis direction, ``d`` the sector centre made perpendicular to it.
    """

    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    r: tuple[float, float]
    t: tuple[float, float]
    sector: tuple[float, float, float]
    half_deg: float


_MARKER_SPEC = {
    "Pelvis": _MarkerSpec((0, 0, -10), (0, 0, 60), (105, 135), (0.0, 1.0), (1, 0, 0), 180),
    "Torso": _MarkerSpec((55, 0, 40), (45, 0, 400), (85, 130), (0.1, 0.9), (1, 0, 0), 180),
    "Head": _MarkerSpec((20, 0, 60), (30, 0, 250), (88, 102), (0.35, 0.95), (1, 0, 0), 180),
    "LUpperArm": _MarkerSpec((0, 0, 0), (0, 5, -300), (35, 55), (0.2, 0.85), (0, 1, 0), 120),
    "LForearm": _MarkerSpec((0, 0, 0), (10, 0, -255), (28, 42), (0.2, 0.85), (-0.5, 1, 0), 110),
    "LHand": _MarkerSpec((0, 3, -20), (0, 5, -180), (30, 45), (0.2, 0.9), (-1, 0, 0), 70),
    "LThigh": _MarkerSpec((0, 0, 0), (0, 5, -430), (60, 85), (0.2, 0.8), (0.6, 1, 0), 120),
    "LShank": _MarkerSpec((0, 0, 0), (-10, 0, -420), (40, 60), (0.15, 0.8), (0.5, 1, 0), 120),
    "LFoot": _MarkerSpec((-20, 0, -55), (175, 5, -60), (25, 45), (0.3, 1.0), (0, 0, 1), 100),
}

# Hinges: axis (left side) and flexion range (deg). The off-axis motion (slack)
# is a parameter of human_take.
_HINGE = {
    "LElbow": ((0.05, 1.0, 0.08), (-140.0, -5.0)),
    "LKnee": ((0.03, 1.0, -0.03), (0.0, 120.0)),
}
#: The first three markers of a segment are redrawn until their second principal
#: spread is at least this fraction of the first (no near-collinear clusters).
_MIN_TRIANGLE = 0.4


# --------------------------------------------------------------------------- names and hinge axes


def _left(name: str) -> str:
    return "L" + name[1:] if name.startswith("R") else name


def _part(seg: str) -> str:
    """Body part of a segment name (no side)."""
    return seg[1:] if seg[0] in "LR" and seg[1:2].isupper() else seg


def _side_name(name: str, right: bool) -> str:
    return ("R" + name[1:]) if right and name.startswith("L") and name != "Lumbar" else name


def _hinge_frame(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit hinge axis ``a`` and two unit axes perpendicular to it, for a joint name."""
    left = "L" + name[1:]
    a = np.array(_HINGE[left][0], float)
    if name.startswith("R"):
        a = _mirror_axial(a)
    a /= np.linalg.norm(a)
    e1 = np.array([1.0, 0.0, 0.0]) - a[0] * a
    e1 /= np.linalg.norm(e1)
    return a, e1, np.cross(a, e1)


# --------------------------------------------------------------------------- subject


@dataclass(frozen=True)
class _Subject:
    joint_rest: np.ndarray  # (S, 3) origin of each segment at rest (body frame)
    marker_rest: np.ndarray  # (M, 3) markers at rest (body frame)
    marker_segment: np.ndarray  # (M,)
    labels: tuple[str, ...]
    counts: tuple[int, ...]
    pelvis_height: float  # pelvis centre above the floor at rest
    part_factor: dict[str, float]
    seg_factor: np.ndarray  # (S,) length factor of each segment (part factor times scale)


def _check_take_args(n_frames, rate: float, scale: float, noise_mm: float, soft_tissue_mm: float) -> int:
    """The frame count as an int, after checking a generated take's arguments (ValueError if wrong)."""
    n_frames = int(n_frames)
    if n_frames < 2:
        raise ValueError(f"n_frames must be at least 2, got {n_frames}")
    if not rate > 0 or not scale > 0:
        raise ValueError(f"rate and scale must be positive, got rate={rate}, scale={scale}")
    if noise_mm < 0 or soft_tissue_mm < 0:
        raise ValueError("noise_mm and soft_tissue_mm must be non-negative")
    return n_frames


def _marker_counts(markers_per_segment: int | Sequence[int] | Mapping[str, int] | None) -> tuple[int, ...]:
    if markers_per_segment is None:
        counts = [DEFAULT_MARKERS_PER_SEGMENT[n] for n in SEGMENTS]
    elif isinstance(markers_per_segment, (int, np.integer)):
        counts = [int(markers_per_segment)] * _S
    elif isinstance(markers_per_segment, Mapping):
        unknown = set(markers_per_segment) - set(SEGMENTS)
        if unknown:
            raise ValueError(f"unknown segment names {sorted(unknown)}; segments are {list(SEGMENTS)}")
        counts = [int(markers_per_segment.get(n, DEFAULT_MARKERS_PER_SEGMENT[n])) for n in SEGMENTS]
    else:
        counts = [int(c) for c in markers_per_segment]
        if len(counts) != _S:
            raise ValueError(f"markers_per_segment needs {_S} counts (one per segment), got {len(counts)}")
    if min(counts) < 1:
        raise ValueError(f"every segment needs at least 1 marker, got {counts}")
    return tuple(counts)


def _van_der_corput(k: int) -> float:
    x, denom = 0.0, 1.0
    while k:
        k, r = divmod(k, 2)
        denom *= 2.0
        x += r / denom
    return x


def _make_subject(seed: int, counts: Sequence[int], scale: float) -> _Subject:
    srng = np.random.default_rng([seed, 0])
    part_factor = {p: float(srng.uniform(0.97, 1.03)) for p in _PARTS}
    fac = np.array([part_factor[_PART[s]] for s in range(_S)]) * scale

    joint_rest = np.zeros((_S, 3))
    for s in range(1, _S):
        name, p = SEGMENTS[s], PARENT[s]
        off = np.array(_JOINT_OFFSET["L" + name[1:] if s in _RIGHT else name])
        if s in _RIGHT:
            off = _mirror(off)
        joint_rest[s] = joint_rest[p] + fac[p] * off
    pelvis_height = -joint_rest[SEGMENTS.index("LFoot"), 2] + _ANKLE_HEIGHT * fac[SEGMENTS.index("LFoot")]

    golden = (np.sqrt(5.0) - 1.0) / 2.0
    rest, seg, labels = [], [], []
    for s, n in enumerate(counts):
        name = SEGMENTS[s]
        spec = _MARKER_SPEC["L" + name[1:] if s in _RIGHT else name]
        p0, p1 = np.array(spec.p0, float) * fac[s], np.array(spec.p1, float) * fac[s]
        d = np.array(spec.sector, float)
        if s in _RIGHT:
            p0, p1, d = _mirror(p0), _mirror(p1), _mirror(d)
        u = (p1 - p0) / np.linalg.norm(p1 - p0)
        d = d - (d @ u) * u
        d /= np.linalg.norm(d)
        e2 = np.cross(u, d)
        mrng = np.random.default_rng([seed, 1, s])  # per segment: counts elsewhere do not matter
        half = np.deg2rad(spec.half_deg)

        def place(k: int, u0: float, u1: float) -> np.ndarray:
            r_k, jt, ja = mrng.uniform(size=3)
            t = spec.t[0] + (spec.t[1] - spec.t[0]) * ((_van_der_corput(k + 1) + u1 + 0.05 * (jt - 0.5)) % 1.0)
            a = (2.0 * ((u0 + k * golden + 0.03 * (ja - 0.5)) % 1.0) - 1.0) * half
            r = (spec.r[0] + (spec.r[1] - spec.r[0]) * r_k) * fac[s]
            return joint_rest[s] + p0 + t * (p1 - p0) + r * (np.cos(a) * d + np.sin(a) * e2)

        for _ in range(100):  # the first three markers must make a fat triangle
            u0, u1 = mrng.uniform(size=2)
            first = np.array([place(k, u0, u1) for k in range(3)])
            sv = np.linalg.svd(first - first.mean(0), compute_uv=False)
            if sv[1] >= _MIN_TRIANGLE * sv[0]:
                break
        placed = list(first) + [place(k, u0, u1) for k in range(3, n)]
        for k in range(n):
            rest.append(placed[k])
            seg.append(s)
            labels.append(f"{LABEL_CODES[s]}{k + 1}")
    return _Subject(
        joint_rest=joint_rest,
        marker_rest=np.array(rest),
        marker_segment=np.array(seg, dtype=int),
        labels=tuple(labels),
        counts=tuple(int(c) for c in counts),
        pelvis_height=float(pelvis_height),
        part_factor=part_factor,
        seg_factor=fac,
    )
