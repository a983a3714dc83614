"""Seeded articulated chains with ground truth: Hang's marker chains, Kirk's rod linkage.

Both generators are vectorised over frames: every rotation is the exponential
of a smooth random rotation vector (a sum of a few sinusoids per component), so
angular velocities are random and smooth, and poses are composed down the
chain segment by segment.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ..artifacts import Markers
from .truth import SynthTake, Truth

__all__ = ["hang_chain", "hang_tree", "hinge_chain", "kirk_linkage"]

#: Nominal frame rate of Hang chains (Hz); Hang gives none.
CHAIN_RATE = 100.0


def _smooth(rng: np.random.Generator, t: np.ndarray, n_dims: int, *, amp: float,
            freq: tuple[float, float], n_waves: int = 3) -> np.ndarray:
    """(F, n_dims) smooth random signal: per dimension a sum of sinusoids, peak ~ amp."""
    f = rng.uniform(*freq, size=(n_waves, n_dims))
    ph = rng.uniform(0.0, 2.0 * np.pi, size=(n_waves, n_dims))
    a = rng.uniform(0.5, 1.0, size=(n_waves, n_dims)) * amp / np.sqrt(n_waves)
    return np.einsum("wd,fwd->fd", a, np.sin(2.0 * np.pi * f * t[:, None, None] + ph))


def _rotations(rotvec: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotation matrices of (F, 3) rotation vectors."""
    return Rotation.from_rotvec(rotvec).as_matrix()


def _spread_ok(p: np.ndarray, min_ratio: float) -> bool:
    X = p - p.mean(0)
    s = np.linalg.svd(X, compute_uv=False)
    if p.shape[0] >= 3 and s[1] < min_ratio * s[0]:
        return False
    if p.shape[0] >= 4 and s[2] < min_ratio * s[0]:
        return False
    return True


def _line_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance of point p from the line through a and b."""
    ax = (b - a) / np.linalg.norm(b - a)
    off = p - a
    return float(np.linalg.norm(off - (off @ ax) * ax))


def _place_chain_markers(rng: np.random.Generator, n: int, ll: float, joints: np.ndarray) -> np.ndarray:
    """(n, 3) marker positions in a segment frame (bone along +x from 0 to ll).

    Around the bone: 15-85 % along it, 0.15-0.45 ll off its axis; pairwise at
    least 0.1 ll apart; 3+ markers not collinear, 4+ not coplanar (spread
    ratios >= 0.15); 2 markers not in line with a joint of the segment, 1
    marker not in line with two joints of the segment (so that solvability
    propagation is possible).
    """
    for _ in range(10_000):
        x = rng.uniform(0.15, 0.85, n) * ll
        r = rng.uniform(0.15, 0.45, n) * ll
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        p = np.stack([x, r * np.cos(phi), r * np.sin(phi)], axis=1)
        if n >= 2:
            dd = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(n) * ll
            if dd.min() < 0.1 * ll:
                continue
        if not _spread_ok(p, 0.15):
            continue
        if n == 2 and min(_line_dist(j, p[0], p[1]) for j in joints) < 0.1 * ll:
            continue
        if n == 1 and any(_line_dist(p[0], joints[i], joints[k]) < 0.1 * ll
                          for i in range(len(joints)) for k in range(i + 1, len(joints))):
            continue
        return p
    raise RuntimeError("could not place markers")  # pragma: no cover


def _child_directions(rng: np.random.Generator, k: int) -> np.ndarray:
    """(k, 3) unit directions of a segment's child joints: +x first, others forward-ish, 40+ degrees apart."""
    dirs = [np.array([1.0, 0.0, 0.0])]
    while len(dirs) < k:
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        if v[0] < 0.2 or any(v @ d > np.cos(np.radians(40.0)) for d in dirs):
            continue
        dirs.append(v)
    return np.array(dirs[:k]).reshape(k, 3)


def _markers_of(R: list[np.ndarray], O: list[np.ndarray], local: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([O[i][:, None, :] + np.einsum("fij,mj->fmi", R[i], local[i])
                           for i in range(len(local))], axis=1)


def hang_tree(
    parent: Sequence[int],
    counts: Sequence[int],
    n_frames: int = 100,
    *,
    rng: np.random.Generator,
    link_length: float = 1.0,
    noise: float = 0.0,
) -> SynthTake:
    """A tree of rigid segments with markers, generalising Hang's chains.

    Segment ``i`` hangs from its parent ``parent[i]`` (``parent[0] = -1``,
    parents listed before children) at a joint; a segment's first child joint
    lies ``link_length`` along its own x axis from its proximal joint, further
    child joints at the same distance in other forward directions (40+
    degrees apart). Markers and motion as in :func:`hang_chain`.

    Parameters
    ----------
    parent : sequence of int
        Parent of every segment, -1 for the root (segment 0 only).
    counts : sequence of int
        Markers per segment, each >= 1.
    n_frames, rng, link_length, noise
        As in :func:`hang_chain`.

    Returns
    -------
    SynthTake
        One joint per non-root segment ``c`` (edge ``(parent[c], c)``), in segment
        order; ``bone_length`` is ``link_length`` for a joint whose child has
        children, NaN otherwise.
    """
    parent = [int(p) for p in parent]
    counts = [int(c) for c in counts]
    S = len(parent)
    if S == 0 or len(counts) != S or min(counts) < 1:
        raise ValueError(f"need one positive marker count per segment, got {counts} for {S} segments")
    if parent[0] != -1 or any(not (0 <= parent[i] < i) for i in range(1, S)):
        raise ValueError(f"parent must be -1 for segment 0 and list parents before children, got {parent}")
    if n_frames < 1:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    F = int(n_frames)
    ll = float(link_length)
    t = np.arange(F) / CHAIN_RATE
    children = [[c for c in range(S) if parent[c] == i] for i in range(S)]
    tip = [ll * _child_directions(rng, max(len(ch), 1)) for ch in children]  # local child-joint positions
    local = [
        _place_chain_markers(rng, counts[i], ll, np.vstack([np.zeros((1, 3)), tip[i]]))
        for i in range(S)
    ]
    R = [_rotations(_smooth(rng, t, 3, amp=1.0, freq=(0.2, 1.0))) @ Rotation.random(random_state=rng).as_matrix()]
    O = [_smooth(rng, t, 3, amp=ll, freq=(0.2, 1.0)) + rng.uniform(-ll, ll, 3)]
    for c in range(1, S):
        p = parent[c]
        k = children[p].index(c)
        O.append(O[p] + R[p] @ tip[p][k])
        Rrel = _rotations(_smooth(rng, t, 3, amp=1.0, freq=(0.5, 2.0)) + rng.uniform(-0.5, 0.5, 3))
        R.append(R[p] @ Rrel)
    pts = _markers_of(R, O, local)
    if noise > 0:
        pts = pts + rng.normal(0.0, noise, pts.shape)
    joints = np.stack(O[1:], axis=1) if S > 1 else np.zeros((F, 0, 3))
    bone = np.array([ll if children[c] else np.nan for c in range(1, S)])
    seg = np.repeat(np.arange(S), counts)
    labels = tuple(f"S{s}M{k}" for s, n in enumerate(counts) for k in range(n))
    info = {"kind": "hang_tree", "parent": parent, "counts": counts, "link_length": ll,
            "noise": float(noise), "rate": CHAIN_RATE}
    markers = Markers(points=pts, labels=labels, rate=CHAIN_RATE, units="mm", source="hang_tree", info=dict(info))
    truth = Truth(
        segment_names=tuple(f"seg{i}" for i in range(S)),
        parent=np.array(parent),
        marker_segment=seg,
        marker_id=np.arange(seg.size),
        joint_child=np.arange(1, S),
        joints=joints,
        bone_length=bone,
        info=info,
    )
    return SynthTake(markers, truth)


def hang_chain(
    counts: Sequence[int],
    n_frames: int = 100,
    *,
    rng: np.random.Generator,
    link_length: float = 1.0,
    noise: float = 0.0,
) -> SynthTake:
    """A chain of rigid segments like Hang et al.'s ⟨N1-N2-...-NL⟩.

    Segment ``i`` carries ``counts[i]`` markers placed randomly around it; the
    joints between successive segments are ``link_length`` apart (segment ``i``
    runs from joint ``i-1`` to joint ``i`` along its own x axis; the end
    segments have the same length). Every segment rotates relative to its
    neighbour by a smooth random rotation (all three degrees of freedom, up to
    about a radian, frequencies 0.5-2 Hz), the root rotates and translates too.

    Parameters
    ----------
    counts : sequence of int
        Markers per segment, each >= 1; ``len(counts)`` segments.
    n_frames : int
        Frames (at a nominal 100 Hz).
    rng : numpy.random.Generator
        Source of all randomness.
    link_length : float
        Joint-to-joint distance (Hang uses 1). Marker values are in these units,
        labelled "mm".
    noise : float
        Standard deviation of isotropic Gaussian noise added to the markers.

    Returns
    -------
    SynthTake
        Markers labelled ``S{segment}M{k}`` in segment order; truth with
        ``parent = [-1, 0, 1, ...]``, joints ``(F, L-1, 3)`` (joint ``e`` between
        segments ``e`` and ``e+1``) and bone lengths (``link_length``, NaN for
        the last joint).
    """
    counts = [int(c) for c in counts]
    if not counts or min(counts) < 1:
        raise ValueError(f"counts must be a non-empty sequence of positive ints, got {counts}")
    take = hang_tree(list(range(-1, len(counts) - 1)), counts, n_frames, rng=rng,
                     link_length=link_length, noise=noise)
    name = "hang_chain<" + "-".join(map(str, counts)) + ">"
    info = {"kind": "hang_chain", "counts": counts, "link_length": float(link_length),
            "noise": float(noise), "rate": CHAIN_RATE}
    m, tr = take.markers, take.truth
    markers = Markers(points=m.points, labels=m.labels, rate=m.rate, units=m.units, source=name, info=dict(info))
    truth = Truth(tr.segment_names, tr.parent, tr.marker_segment, tr.marker_id, tr.joint_child,
                  tr.joints, tr.bone_length, info)
    return SynthTake(markers, truth)


def hinge_chain(
    counts: Sequence[int],
    n_frames: int = 100,
    *,
    rng: np.random.Generator,
    link_length: float = 300.0,
    noise: float = 0.0,
    amplitude: float = 1.0,
) -> SynthTake:
    """A chain of rigid segments joined by hinges (one degree of freedom each), like a robot arm.

    As :func:`hang_chain` (markers, root motion, ``link_length`` between joints), but segment ``i + 1``
    turns relative to segment ``i`` about one axis fixed in both: a random direction at least 30
    degrees off the bone, by a smooth random angle (peak about ``amplitude`` rad, 0.3-1.2 Hz).

    Returns
    -------
    SynthTake
        Truth as :func:`hang_chain`'s, and in ``info["hinge_axes_lab"]`` every hinge's unit axis in
        the lab per frame ((F, L-1, 3) as nested lists) and in ``info["hinge_axes_local"]`` in its
        parent segment's frame.
    """
    counts = [int(c) for c in counts]
    if not counts or min(counts) < 1:
        raise ValueError(f"counts must be a non-empty sequence of positive ints, got {counts}")
    if n_frames < 1:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    F, S, ll = int(n_frames), len(counts), float(link_length)
    t = np.arange(F) / CHAIN_RATE
    tip = np.array([ll, 0.0, 0.0])
    ends = np.vstack([np.zeros(3), tip])
    local = [_place_chain_markers(rng, counts[i], ll, ends) for i in range(S)]
    R = [_rotations(_smooth(rng, t, 3, amp=1.0, freq=(0.2, 1.0))) @ Rotation.random(random_state=rng).as_matrix()]
    O = [_smooth(rng, t, 3, amp=ll, freq=(0.2, 1.0)) + rng.uniform(-ll, ll, 3)]
    axes = []
    for _ in range(1, S):
        while True:
            a = rng.normal(size=3)
            a /= np.linalg.norm(a)
            if abs(a[0]) < np.cos(np.radians(30.0)):
                break
        ang = _smooth(rng, t, 1, amp=amplitude, freq=(0.3, 1.2))[:, 0]
        O.append(O[-1] + R[-1] @ tip)
        axes.append(a)
        R.append(R[-1] @ _rotations(ang[:, None] * a))
    pts = _markers_of(R, O, local)
    if noise > 0:
        pts = pts + rng.normal(0.0, noise, pts.shape)
    lab_axes = np.stack([R[i] @ axes[i] for i in range(S - 1)], axis=1) if S > 1 else np.zeros((F, 0, 3))
    name = "hinge_chain<" + "-".join(map(str, counts)) + ">"
    info = {"kind": "hinge_chain", "counts": counts, "link_length": ll, "noise": float(noise), "rate": CHAIN_RATE,
            "hinge_axes_local": [a.tolist() for a in axes], "hinge_axes_lab": lab_axes.round(9).tolist()}
    seg = np.repeat(np.arange(S), counts)
    markers = Markers(points=pts, labels=tuple(f"S{s}M{k}" for s, n in enumerate(counts) for k in range(n)),
                      rate=CHAIN_RATE, units="mm", source=name, info={k: v for k, v in info.items() if k != "hinge_axes_lab"})
    truth = Truth(
        segment_names=tuple(f"seg{i}" for i in range(S)),
        parent=np.arange(-1, S - 1),
        marker_segment=seg,
        marker_id=np.arange(seg.size),
        joint_child=np.arange(1, S),
        joints=np.stack(O[1:], axis=1) if S > 1 else np.zeros((F, 0, 3)),
        bone_length=np.array([ll] * (S - 2) + [np.nan]) if S > 1 else np.zeros(0),
        info=info,
    )
    return SynthTake(markers, truth)


def _pose_chain(R_root: np.ndarray, T_root: np.ndarray, R_rel: list[np.ndarray],
                lengths: Sequence[float]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Global rotations and origins of every segment (origin = proximal joint; root: T_root)."""
    R = [R_root]
    O = [T_root]
    for i, Rr in enumerate(R_rel):
        tip = O[-1] + R[-1] @ np.array([lengths[i], 0.0, 0.0])
        O.append(tip)
        R.append(R[-1] @ Rr)
    return R, O


#: Joint-to-joint length of the middle rod of Kirk's linkage (mm).
KIRK_MIDDLE_MM = 341.0


def kirk_linkage(
    n_frames: int,
    *,
    rng: np.random.Generator,
    noise_mm: float = 0.5,
    rate: float = 120.0,
) -> SynthTake:
    """Kirk et al.'s calibration linkage: three rods joined by two universal joints.

    The middle rod is 341 mm joint to joint, the outer rods 290-390 mm. Each
    universal joint turns about an axis across the first rod and then about a
    perpendicular axis across the second (two degrees of freedom, no twist
    about the rods). Three markers ride on each rod on short stand-offs
    (15-35 mm off the rod axis, spread along it). The first rod is held at its
    end and waved about (smooth random rotation and translation), the others
    swing in their joints by up to about 60 degrees.

    Parameters
    ----------
    n_frames : int
        Frames.
    rng : numpy.random.Generator
        Source of all randomness.
    noise_mm : float
        Standard deviation of Gaussian marker noise (mm).
    rate : float
        Frame rate (Hz).

    Returns
    -------
    SynthTake
        Nine markers ``rod{1,2,3}_{a,b,c}`` (mm); truth with joints ``(F, 2, 3)``
        and ``bone_length = [341, nan]``.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    F = int(n_frames)
    t = np.arange(F) / float(rate)
    lengths = [float(rng.uniform(290.0, 390.0)), KIRK_MIDDLE_MM, float(rng.uniform(290.0, 390.0))]
    local = []
    for ln in lengths:
        frac = np.array([rng.uniform(0.12, 0.30), rng.uniform(0.42, 0.58), rng.uniform(0.70, 0.88)])
        r = rng.uniform(15.0, 35.0, 3)
        phi = rng.uniform(0, 2 * np.pi) + np.arange(3) * 2 * np.pi / 3 + rng.uniform(-0.4, 0.4, 3)
        local.append(np.stack([frac * ln, r * np.cos(phi), r * np.sin(phi)], axis=1))

    R0 = _rotations(_smooth(rng, t, 3, amp=0.8, freq=(0.1, 0.6))) @ Rotation.random(random_state=rng).as_matrix()
    T0 = _smooth(rng, t, 3, amp=250.0, freq=(0.1, 0.6)) + np.array([0.0, 0.0, 1200.0])
    R_rel = []
    for _ in range(2):
        ang = _smooth(rng, t, 2, amp=1.0, freq=(0.2, 1.0)) + rng.uniform(-0.3, 0.3, 2)
        Ry = _rotations(np.stack([np.zeros(F), ang[:, 0], np.zeros(F)], axis=1))
        Rz = _rotations(np.stack([np.zeros(F), np.zeros(F), ang[:, 1]], axis=1))
        R_rel.append(Ry @ Rz)  # yoke axis across rod i, then across rod i+1: no twist
    R, O = _pose_chain(R0, T0, R_rel, lengths)
    pts = _markers_of(R, O, local)
    if noise_mm > 0:
        pts = pts + rng.normal(0.0, noise_mm, pts.shape)
    labels = tuple(f"rod{i + 1}_{c}" for i in range(3) for c in "abc")
    info = {"kind": "kirk_linkage", "rod_lengths_mm": lengths, "noise_mm": float(noise_mm), "rate": float(rate)}
    markers = Markers(points=pts, labels=labels, rate=float(rate), units="mm", source="kirk_linkage", info=dict(info))
    truth = Truth(
        segment_names=("rod1", "rod2", "rod3"),
        parent=np.array([-1, 0, 1]),
        marker_segment=np.repeat(np.arange(3), 3),
        marker_id=np.arange(9),
        joint_child=np.array([1, 2]),
        joints=np.stack(O[1:], axis=1),
        bone_length=np.array([KIRK_MIDDLE_MM, np.nan]),
        info=info,
    )
    return SynthTake(markers, truth)
