"""A seeded synthetic human: 15 rigid segments, 48 skin markers, exact truth.

Lab frame
---------
Right-handed, **Z up**, millimetres. In the rest pose (standing, arms hanging
at the sides, palms forward) the subject faces **+X** and **+Y** is the
subject's **left**. The floor is the plane ``z = 0``. Every segment's rest
orientation is the lab axes (the convention of :mod:`mocapskel.artifacts`), so
a joint rotation is a rotation of the child relative to the parent, expressed
in lab axes at rest.

Body
----
Segments (parent first)::

    0 Pelvis (root)  1 Torso  2 Head
    3 LUpperArm  4 LForearm  5 LHand     6 RUpperArm  7 RForearm  8 RHand
    9 LThigh    10 LShank   11 LFoot    12 RThigh    13 RShank   14 RFoot

14 joints, one per non-root segment (named in ``truth.info["joint_names"]``):
Lumbar, Neck, L/RShoulder, L/RWrist, L/RHip, L/RAnkle are ball joints (3 DoF);
L/RElbow and L/RKnee are hinges: one large rotation about an anatomical axis
plus a little varus/valgus and axial rotation (±5° and ±12° by default, the
``hinge_slack_deg`` of :func:`human_take`), so that the joint centre along the
hinge axis stays observable, as on a real knee.

Adult proportions for a ~1.75 m subject (hip joints 925 mm above the floor,
thigh 430, shank 420, upper arm 300, forearm 255 mm, lumbar joint to C7
~470 mm); each body part varies by up to ±3 % between subjects, and ``scale``
multiplies everything.

Markers sit on the skin around each segment, 25–85 mm from a limb's bone
axis (85–135 mm around the torso and pelvis, ~95 mm around the head), spread
along it, at least ~45 mm from any joint; the first three of a segment always
make a well-shaped triangle (never nearly collinear). The default is 48 markers: pelvis, torso and
head 4 each, every limb segment 3. Labels are ``<code><k>`` with codes
``PELV TRSO HEAD LUPA LFRM LHND RUPA RFRM RHND LTHI LSHN LFOT RTHI RSHN RFOT``
(e.g. ``LTHI1``). The first ``n`` markers of a segment do not depend on how
many are asked for, so a 2-marker subject is a subset of the 3-marker one.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..artifacts import Markers
from .truth import SynthTake, Truth

__all__ = [
    "SEGMENTS",
    "PARENT",
    "JOINT_NAMES",
    "LABEL_CODES",
    "DEFAULT_MARKERS_PER_SEGMENT",
    "HINGES",
    "MOTIONS",
    "human_take",
    "rotvec_to_matrix",
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
MOTIONS: tuple[str, ...] = ("rom", "walk")

_S = len(SEGMENTS)
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

# Joint motion. Ball joints: range (deg) of each rotation-vector component
# about the lab/rest axes X (forward), Y (left), Z (up), left side; the right
# side is the mirror image (X and Z components negated).
_ROM_BALL = {
    "Lumbar": ((-25, 25), (-20, 45), (-35, 35)),
    "Neck": ((-30, 30), (-40, 50), (-60, 60)),
    "LShoulder": ((-10, 90), (-120, 40), (-50, 50)),
    "LWrist": ((-25, 20), (-70, 60), (-60, 60)),
    "LHip": ((-20, 45), (-100, 25), (-35, 35)),
    "LAnkle": ((-20, 20), (-25, 45), (-20, 20)),
}
# Hinges: axis (left side) and flexion range (deg). The off-axis motion (slack)
# is a parameter of human_take.
_HINGE = {
    "LElbow": ((0.05, 1.0, 0.08), (-140.0, -5.0)),
    "LKnee": ((0.03, 1.0, -0.03), (0.0, 120.0)),
}
_SOFT_TISSUE_BAND_HZ = (1.0, 5.0)
#: The first three markers of a segment are redrawn until their second principal
#: spread is at least this fraction of the first (no near-collinear clusters).
_MIN_TRIANGLE = 0.4
_SOFT_TISSUE_SHARED = 0.3  # fraction of soft-tissue variance shared by a segment's markers


# --------------------------------------------------------------------------- rotations


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation matrices from rotation vectors (Rodrigues), batched.

    Parameters
    ----------
    v : (..., 3) ndarray
        Rotation vectors (axis times angle, radians).

    Returns
    -------
    R : (..., 3, 3) ndarray
    """
    v = np.asarray(v, dtype=float)
    th2 = np.einsum("...i,...i->...", v, v)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / np.where(small, 1.0, th2))
    # R = I + a K + b K^2 with K = [v]x and K^2 = v v^T - |v|^2 I
    R = (b[..., None, None] * v[..., :, None]) * v[..., None, :]
    diag = 1.0 - b * th2
    R[..., 0, 0] += diag
    R[..., 1, 1] += diag
    R[..., 2, 2] += diag
    av = a[..., None] * v
    R[..., 0, 1] -= av[..., 2]
    R[..., 1, 0] += av[..., 2]
    R[..., 0, 2] += av[..., 1]
    R[..., 2, 0] -= av[..., 1]
    R[..., 1, 2] -= av[..., 0]
    R[..., 2, 1] += av[..., 0]
    return R


def _matmul33(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(..., 3, 3) @ (..., 3, 3) as three broadcast products (faster than batched matmul)."""
    return (
        A[..., :, 0, None] * B[..., None, 0, :]
        + A[..., :, 1, None] * B[..., None, 1, :]
        + A[..., :, 2, None] * B[..., None, 2, :]
    )


def _apply33(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations applied to (P, 3) points -> (F, P, 3)."""
    return (
        A[:, None, :, 0] * x[None, :, 0, None]
        + A[:, None, :, 1] * x[None, :, 1, None]
        + A[:, None, :, 2] * x[None, :, 2, None]
    )


def _rot_z(angle: np.ndarray) -> np.ndarray:
    """(F,) radians -> (F, 3, 3) rotations about Z."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    R[..., 2, 2] = 1.0
    return R


def _mirror(v: np.ndarray) -> np.ndarray:
    """Mirror through the sagittal (XZ) plane: points negate y, axial vectors x and z."""
    return np.asarray(v, dtype=float) * np.array([1.0, -1.0, 1.0])


def _mirror_axial(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, dtype=float) * np.array([-1.0, 1.0, -1.0])


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


# --------------------------------------------------------------------------- motion


def _smooth(rng: np.random.Generator, t: np.ndarray, n: int, fmin: float, fmax: float, k: int = 4) -> np.ndarray:
    """(F, n) sums of ``k`` random sinusoids per column, frequencies in [fmin, fmax] Hz."""
    out = np.zeros((t.size, n))
    for _ in range(k):
        f = rng.uniform(fmin, fmax, n)
        ph = rng.uniform(0.0, 2.0 * np.pi, n)
        amp = rng.uniform(0.5, 1.0, n)
        out += amp * np.sin(2.0 * np.pi * np.outer(t, f) + ph)
    return out


def _rescale(x: np.ndarray, lo: np.ndarray | float, hi: np.ndarray | float) -> np.ndarray:
    """Map every column of ``x`` affinely onto exactly [lo, hi] (its min to lo, max to hi)."""
    mn, mx = x.min(0), x.max(0)
    span = np.where(mx > mn, mx - mn, 1.0)
    return lo + (np.asarray(hi) - lo) * (x - mn) / span


def _bump(phase: np.ndarray, centre: float, width: float) -> np.ndarray:
    """Periodic Gaussian bump over the gait cycle (phase in radians, centre/width in cycles)."""
    d = (phase / (2.0 * np.pi) - centre + 0.5) % 1.0 - 0.5
    return np.exp(-0.5 * (d / width) ** 2)


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


def _phase_envelope(rng: np.random.Generator, t: np.ndarray, n_groups: int, base: float) -> np.ndarray:
    """(F, G) smooth weights in [base, 1]: the groups take turns being exercised fully."""
    T = t[-1] + (t[1] - t[0] if t.size > 1 else 1.0)
    phase_len = min(8.0, T / n_groups)
    n_phase = int(np.ceil(T / phase_len))
    order = np.concatenate([rng.permutation(n_groups) for _ in range(n_phase // n_groups + 1)])[:n_phase]
    idx = np.minimum((t / phase_len).astype(int), n_phase - 1)
    ind = np.zeros((t.size, n_groups))
    ind[np.arange(t.size), order[idx]] = 1.0
    # smooth the switching: three moving averages over a ninth of a phase (C2, no jerks)
    dt = t[1] - t[0] if t.size > 1 else 1.0
    w = max(1, int(round(phase_len / 9.0 / dt)))
    for _ in range(3 if w > 1 else 0):
        c = np.cumsum(np.pad(ind, ((w // 2 + 1, w - 1 - w // 2), (0, 0)), mode="edge"), axis=0)
        ind = (c[w:] - c[:-w]) / w
    return base + (1.0 - base) * ind


def _rom_motion(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Range-of-motion take: every DoF covers its full range; joints take turns."""
    F = t.size
    groups = {"Lumbar": 0, "Neck": 0, "LShoulder": 1, "LElbow": 1, "LWrist": 1, "RShoulder": 2,
              "RElbow": 2, "RWrist": 2, "LHip": 3, "LKnee": 3, "LAnkle": 3, "RHip": 4, "RKnee": 4,
              "RAnkle": 4}  # fmt: skip
    env = _phase_envelope(rng, t, 5, base=0.25)
    rv = np.zeros((F, _S, 3))
    for e, name in enumerate(JOINT_NAMES):
        s = e + 1
        g = env[:, groups[name]][:, None]
        left = "L" + name[1:] if name[0] in "LR" else name
        if left in _HINGE:
            a, e1, e2 = _hinge_frame(name)
            lo, hi = _HINGE[left][1]
            x = _rescale(g * _smooth(rng, t, 1, 0.08, 0.5), lo, hi)[:, 0]
            y = _rescale(g * _smooth(rng, t, 2, 0.08, 0.5), -slack, slack)
            rv[:, s] = np.deg2rad(x[:, None] * a + y[:, :1] * e1 + y[:, 1:] * e2)
        else:
            rng_lohi = np.array(_ROM_BALL[left], float)
            if name.startswith("R"):
                rng_lohi[[0, 2]] = -rng_lohi[[0, 2], ::-1]
            x = _rescale(g * _smooth(rng, t, 3, 0.08, 0.5), rng_lohi[:, 0], rng_lohi[:, 1])
            rv[:, s] = np.deg2rad(x)
    # root: wander over the capture volume, turn around, tilt a little
    xy = _rescale(_smooth(rng, t, 2, 0.01, 0.08), -800.0, 800.0)
    z = subj.pelvis_height + _rescale(_smooth(rng, t, 1, 0.05, 0.3), 0.0, 50.0 * subj.pelvis_height / 995.0)[:, 0]
    yaw = np.deg2rad(_rescale(_smooth(rng, t, 1, 0.02, 0.08), -150.0, 150.0)[:, 0])
    tilt = np.deg2rad(_rescale(_smooth(rng, t, 2, 0.05, 0.3), np.array([-10.0, -10.0]), np.array([10.0, 20.0])))
    root_pos = np.column_stack([xy, z])
    root_rot = _matmul33(_rot_z(yaw), rotvec_to_matrix(np.column_stack([tilt, np.zeros(F)])))
    return root_pos, root_rot, rv


def _walk_motion(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Walking round a wobbly circle (~1.5 m radius) with random small extra motion."""
    F = t.size
    fc = rng.uniform(0.85, 0.95)  # strides per second
    phi0 = rng.uniform(0.0, 2.0 * np.pi)
    size = subj.pelvis_height / 995.0
    speed = 1100.0 * size * rng.uniform(0.9, 1.1)  # mm/s
    direction = rng.choice([-1.0, 1.0])
    radius = 1500.0 + 300.0 * _rescale(_smooth(rng, t, 1, 0.01, 0.05), -1.0, 1.0)[:, 0]
    alpha = rng.uniform(0.0, 2.0 * np.pi) + direction * speed / 1500.0 * t
    deg = np.deg2rad
    rv = np.zeros((F, _S, 3))
    for side, ph in (("L", 2.0 * np.pi * fc * t + phi0), ("R", 2.0 * np.pi * fc * t + phi0 + np.pi)):
        opp = ph + np.pi
        hip_flex = 10.0 + 20.0 * np.cos(ph - 0.85 * 2.0 * np.pi)
        arm_flex = 18.0 * np.cos(opp - 0.85 * 2.0 * np.pi)
        knee = 5.0 + 15.0 * _bump(ph, 0.12, 0.07) + 55.0 * _bump(ph, 0.72, 0.1)
        elbow = 25.0 + 10.0 * np.cos(opp - 0.85 * 2.0 * np.pi)
        ball = {
            "Hip": np.column_stack([3.0 + 4.0 * np.cos(ph), -hip_flex, 4.0 * np.sin(ph)]),
            "Ankle": np.column_stack([3.0 * np.sin(ph), 5.0 + 12.0 * np.sin(ph - 1.0), 2.0 * np.sin(ph)]),
            "Shoulder": np.column_stack([8.0 + 0 * ph, -arm_flex, 5.0 + 0 * ph]),
            "Wrist": np.column_stack([0 * ph, -10.0 + 3.0 * np.sin(ph), 0 * ph]),
        }
        for joint, v in ball.items():
            v = v + _smooth(rng, t, 3, 0.1, 0.6, k=3) * 1.0
            rv[:, JOINT_NAMES.index(side + joint) + 1] = deg(_mirror_axial(v) if side == "R" else v)
        for joint, ang in (("Knee", knee), ("Elbow", -elbow)):
            name = side + joint
            a, e1, e2 = _hinge_frame(name)
            y = _rescale(_smooth(rng, t, 2, 0.2, 1.0, k=3), -0.3 * slack, 0.3 * slack)
            rv[:, JOINT_NAMES.index(name) + 1] = deg(ang[:, None] * a + y[:, :1] * e1 + y[:, 1:] * e2)
    phL = 2.0 * np.pi * fc * t + phi0
    zero = np.zeros(F)
    lumbar = np.column_stack([2.0 * np.cos(phL), 5.0 + zero, -5.0 * np.sin(phL)])  # counter-rotation
    rv[:, 1] = deg(lumbar + _smooth(rng, t, 3, 0.1, 0.5, k=3))
    neck = np.column_stack([zero, zero, 5.0 * np.sin(phL)])  # keeps looking ahead, looks around
    rv[:, 2] = deg(neck + _smooth(rng, t, 3, 0.05, 0.3) * np.array([3.0, 4.0, 8.0]))
    pos = radius[:, None] * np.column_stack([np.cos(alpha), np.sin(alpha)])
    if F > 1:
        vel = np.gradient(pos, t, axis=0)
        heading = np.unwrap(np.arctan2(vel[:, 1], vel[:, 0]))
    else:
        heading = alpha + direction * np.pi / 2.0
    z = subj.pelvis_height - 15.0 * size + 12.0 * size * np.cos(2.0 * phL)
    root_pos = np.column_stack([pos, z])
    tilt = deg(np.column_stack([4.0 * np.cos(phL), 3.0 + 2.0 * np.sin(2.0 * phL), np.zeros(F)]))
    root_rot = _matmul33(_rot_z(heading + deg(5.0 * np.sin(phL))), rotvec_to_matrix(tilt))
    return root_pos, root_rot, rv


# --------------------------------------------------------------------------- kinematics & skin


def _forward(subj: _Subject, root_pos: np.ndarray, root_rot: np.ndarray, rv: np.ndarray):
    """Global rotations (F, S, 3, 3), segment origins (F, S, 3) and clean markers (F, M, 3)."""
    F = root_pos.shape[0]
    G = np.empty((F, _S, 3, 3))
    O = np.empty((F, _S, 3))
    G[:, 0], O[:, 0] = root_rot, root_pos
    rel = rotvec_to_matrix(rv[:, 1:])  # (F, S-1, 3, 3)
    for s in range(1, _S):
        p = PARENT[s]
        G[:, s] = _matmul33(G[:, p], rel[:, s - 1])
        O[:, s] = O[:, p] + _apply33(G[:, p], (subj.joint_rest[s] - subj.joint_rest[p])[None])[:, 0]
    pts = np.empty((F, subj.marker_rest.shape[0], 3))
    for s in range(_S):
        idx = np.flatnonzero(subj.marker_segment == s)
        local = subj.marker_rest[idx] - subj.joint_rest[s]
        pts[:, idx] = O[:, s, None, :] + _apply33(G[:, s], local)
    return G, O, pts


def _floor_lift(subj: _Subject, G: np.ndarray, O: np.ndarray) -> np.ndarray:
    """(F,) vertical shift that puts the lowest heel or toe point (a smooth minimum) at its rest height."""
    spec = _MARKER_SPEC["LFoot"]
    tau = 8.0 * subj.seg_factor[SEGMENTS.index("LFoot")]  # mm
    lows, rest_low = [], np.inf
    for name in ("LFoot", "RFoot"):
        s = SEGMENTS.index(name)
        pts = np.array([spec.p0, spec.p1], float) * subj.seg_factor[s]
        if name.startswith("R"):
            pts = _mirror(pts)
        lows.append(O[:, s, None, 2] + np.einsum("fj,pj->fp", G[:, s, 2], pts))
        rest_low = min(rest_low, subj.pelvis_height + subj.joint_rest[s, 2] + pts[:, 2].min())
    z = np.concatenate(lows, axis=1)  # (F, 4)
    # smooth minimum (no kink when the supporting foot changes)
    zmin = z.min(1, keepdims=True)
    soft = zmin[:, 0] - tau * np.log(np.exp(-(z - zmin) / tau).sum(1))
    return rest_low - soft


def _band_noise(rng: np.random.Generator, n: int, channels: int, rate: float, band: tuple[float, float]) -> np.ndarray:
    """(n, channels) Gaussian noise limited to ``band`` Hz, unit variance per channel."""
    f = np.fft.rfftfreq(n, 1.0 / rate)
    keep = np.flatnonzero((f >= band[0]) & (f <= band[1]))
    if keep.size == 0:  # too short a take for the band: use its lowest frequencies
        keep = np.arange(1, min(4, f.size))
    # random Fourier coefficients in the band only (white noise, filtered, without the forward FFT)
    W = np.zeros((f.size, channels), dtype=complex)
    W[keep] = rng.standard_normal((keep.size, channels)) + 1j * rng.standard_normal((keep.size, channels))
    x = np.fft.irfft(W, n=n, axis=0)
    sd = x.std(axis=0)
    return x / np.where(sd > 0, sd, 1.0)


def _soft_tissue(rng: np.random.Generator, n: int, marker_segment: np.ndarray, rate: float, rms: float) -> np.ndarray:
    """(n, M, 3) smooth skin motion, RMS displacement length exactly ``rms`` per marker."""
    M = marker_segment.size
    own = _band_noise(rng, n, M * 3, rate, _SOFT_TISSUE_BAND_HZ).reshape(n, M, 3)
    shared = _band_noise(rng, n, _S * 3, rate, _SOFT_TISSUE_BAND_HZ).reshape(n, _S, 3)
    c = _SOFT_TISSUE_SHARED
    d = np.sqrt(1.0 - c) * own + np.sqrt(c) * shared[:, marker_segment]
    d -= d.mean(axis=0)
    cur = np.sqrt(np.mean(np.einsum("fmi,fmi->fm", d, d), axis=0))
    return d * (rms / np.where(cur > 0, cur, 1.0))[:, None]


# --------------------------------------------------------------------------- public


def human_take(
    *,
    rng: np.random.Generator,
    n_frames: int = 7200,
    rate: float = 120.0,
    markers_per_segment: int | Sequence[int] | Mapping[str, int] | None = None,
    scale: float = 1.0,
    motion: str = "rom",
    noise_mm: float = 0.0,
    soft_tissue_mm: float = 0.0,
    subject_seed: int | None = None,
    hinge_slack_deg: tuple[float, float] = (5.0, 12.0),
) -> SynthTake:
    """A seeded take of a 15-segment human with 48 skin markers and its truth.

    Lab frame: Z up, mm; the subject faces +X at rest, +Y is its left, the
    floor is ``z = 0`` (see the module docstring for the body and markers).

    Parameters
    ----------
    rng : numpy.random.Generator
        The only source of randomness. Three seeds are drawn from it (subject,
        motion, noise), so the same generator state gives the same subject for
        every ``motion``, ``n_frames`` and noise setting.
    n_frames : int
        Number of frames F (at least 2).
    rate : float
        Frames per second.
    markers_per_segment : int, sequence of 15 ints or {segment name: int}, optional
        Markers on each segment (at least 1). Default (None): pelvis, torso
        and head 4, limb segments 3 — 48 markers. A mapping overrides the
        default for the segments it names.
    scale : float
        Multiplies every length of the subject (not the capture volume).
    motion : {"rom", "walk"}
        ``"rom"``: range of motion; the joint groups (spine+neck, each arm,
        each leg) take turns moving through their full ranges (every ball-joint
        DoF covers ≥ 20°, the hinges ≥ 115°) while the pelvis wanders
        ±800 mm over the floor, turns ±150° and tilts. ``"walk"``: walking at
        ~1.1 m/s round a wobbly circle of ~1.5 m radius, smaller joint
        amplitudes (feet are not pinned to the floor).
    noise_mm : float
        Standard deviation of white Gaussian noise added to every coordinate.
    soft_tissue_mm : float
        RMS length of the smooth (1–5 Hz) skin displacement of each marker,
        30 % of its variance shared by the markers of a segment.
    subject_seed : int, optional
        Fix the subject (proportions, marker placement) regardless of ``rng``,
        e.g. ``take.truth.info["subject_seed"]`` of another take, to make
        several takes of one subject.
    hinge_slack_deg : (2,) floats
        Half-ranges (deg) of the off-axis rotation of elbows and knees:
        varus/valgus and axial. They make the joint centre along the flexion
        axis observable (as on real knees); (0, 0) gives pure hinges. In
        ``"walk"`` the slack used is 30 % of this.

    Returns
    -------
    SynthTake
        ``markers.points`` : (F, M, 3) float64 mm, no gaps. ``truth.joints`` :
        (F, 14, 3) exact joint centres (joint ``e`` has child segment
        ``e + 1``); ``truth.bone_length`` : (14,) distance from the joint to the
        mean of the child segment's own child joints (NaN for Head, hands and
        feet). ``truth.info`` holds ``joint_names``, ``hinges``,
        ``hinge_axes``, ``rest_joints_mm`` (14, 3) and ``rest_markers_mm``
        (M, 3) in the body frame at rest (pelvis centre at the origin, lab
        axes), ``physical_labels``, the seeds and settings.
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
    n_frames = _check_take_args(n_frames, rate, scale, noise_mm, soft_tissue_mm)
    counts = _marker_counts(markers_per_segment)
    seeds = rng.integers(0, 2**63 - 1, size=3)
    sseed = int(seeds[0]) if subject_seed is None else int(subject_seed)
    mseed, nseed = int(seeds[1]), int(seeds[2])

    subj = _make_subject(sseed, counts, float(scale))
    t = np.arange(n_frames) / float(rate)
    mrng = np.random.default_rng(mseed)
    slack = np.array(hinge_slack_deg, dtype=float)
    if slack.shape != (2,) or (slack < 0).any():
        raise ValueError(f"hinge_slack_deg must be two non-negative angles, got {hinge_slack_deg}")
    root_pos, root_rot, rv = (_rom_motion if motion == "rom" else _walk_motion)(mrng, t, subj, slack)
    G, O, pts = _forward(subj, root_pos, root_rot, rv)
    if motion == "walk":  # lower or raise the body so that the lower foot touches the floor
        lift = _floor_lift(subj, G, O)
        O[..., 2] += lift[:, None]
        pts[..., 2] += lift[:, None]
    del G

    nrng = np.random.default_rng(nseed)
    if soft_tissue_mm > 0:
        pts += _soft_tissue(nrng, n_frames, subj.marker_segment, float(rate), float(soft_tissue_mm))
    if noise_mm > 0:
        pts += nrng.normal(0.0, float(noise_mm), pts.shape)

    joint_child = np.arange(1, _S)
    joints = O[:, 1:].copy()
    bone = np.full(_S - 1, np.nan)
    for e, c in enumerate(joint_child):
        kids = np.flatnonzero(PARENT == c)
        if kids.size:
            bone[e] = np.linalg.norm(subj.joint_rest[kids].mean(0) - subj.joint_rest[c])
    M = subj.marker_rest.shape[0]
    hinge_axes = {h: _hinge_frame(h)[0].tolist() for h in HINGES}
    info = {
        "kind": "human",
        "motion": motion,
        "subject_seed": sseed,
        "motion_seed": mseed,
        "noise_seed": nseed,
        "n_frames": n_frames,
        "rate": float(rate),
        "scale": float(scale),
        "markers_per_segment": list(counts),
        "noise_mm": float(noise_mm),
        "noise_mm_is": "standard deviation per coordinate",
        "soft_tissue_mm": float(soft_tissue_mm),
        "soft_tissue_mm_is": "RMS length of each marker's 3-D skin displacement",
        "soft_tissue_band_hz": list(_SOFT_TISSUE_BAND_HZ),
        "lab_up": "z",
        "lab_frame": "right-handed, Z up, mm; subject faces +X at rest, +Y is its left, floor z=0",
        "joint_names": list(JOINT_NAMES),
        "ball_joints": [j for j in JOINT_NAMES if j not in HINGES],
        "hinges": list(HINGES),
        "hinge_axes": hinge_axes,
        "hinge_off_axis_deg": {h: slack.tolist() for h in HINGES},
        "bone_length_is": "distance from the joint to the mean of the child segment's child joints",
        "part_factor": subj.part_factor,
        "pelvis_height_mm": subj.pelvis_height,
        "rest_joints_mm": subj.joint_rest[1:].tolist(),
        "rest_markers_mm": subj.marker_rest.tolist(),
        "physical_labels": list(subj.labels),
    }
    markers = Markers(
        points=pts,
        labels=subj.labels,
        rate=float(rate),
        units="mm",
        source=f"synth-human-{motion}",
        stage="read",
        info={},
    )
    truth = Truth(
        segment_names=SEGMENTS,
        parent=PARENT.copy(),
        marker_segment=subj.marker_segment.copy(),
        marker_id=np.arange(M),
        joint_child=joint_child,
        joints=joints,
        bone_length=bone,
        info=info,
    )
    return SynthTake(markers=markers, truth=truth)
