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

__all__ = ["hang_chain", "kirk_linkage"]

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


def _place_chain_markers(rng: np.random.Generator, n: int, ll: float, joints: np.ndarray) -> np.ndarray:
    """(n, 3) marker positions in a segment frame (bone along +x from 0 to ll).

    Around the bone: 15-85 % along it, 0.15-0.45 ll off its axis; pairwise at
    least 0.1 ll apart; 3+ markers not collinear, 4+ not coplanar (spread
    ratios >= 0.15); 2 markers not in line with a joint of the segment.
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
        if n == 2:
            axis = (p[1] - p[0]) / np.linalg.norm(p[1] - p[0])
            off = joints - p[0]
            perp = off - np.outer(off @ axis, axis)
            if np.linalg.norm(perp, axis=1).min() < 0.1 * ll:
                continue
        return p
    raise RuntimeError("could not place markers")  # pragma: no cover


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


def _markers_of(R: list[np.ndarray], O: list[np.ndarray], local: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([O[i][:, None, :] + np.einsum("fij,mj->fmi", R[i], local[i])
                           for i in range(len(local))], axis=1)


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
    about a radian), the root rotates and translates too.

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
        ``parent = [-1, 0, 1, ...]``, joints ``(F, L-1, 3)`` and bone lengths.
    """
    counts = [int(c) for c in counts]
    if not counts or min(counts) < 1:
        raise ValueError(f"counts must be a non-empty sequence of positive ints, got {counts}")
    if n_frames < 1:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    L = len(counts)
    F = int(n_frames)
    ll = float(link_length)
    t = np.arange(F) / CHAIN_RATE
    joints_local = np.array([[0.0, 0.0, 0.0], [ll, 0.0, 0.0]])
    local = [_place_chain_markers(rng, n, ll, joints_local) for n in counts]

    R0 = _rotations(_smooth(rng, t, 3, amp=1.0, freq=(0.2, 1.0))) @ Rotation.random(random_state=rng).as_matrix()
    T0 = _smooth(rng, t, 3, amp=ll, freq=(0.2, 1.0)) + rng.uniform(-ll, ll, 3)
    R_rel = [
        _rotations(_smooth(rng, t, 3, amp=1.0, freq=(0.5, 2.0)) + rng.uniform(-0.5, 0.5, 3))
        for _ in range(L - 1)
    ]
    R, O = _pose_chain(R0, T0, R_rel, [ll] * L)
    pts = _markers_of(R, O, local)
    if noise > 0:
        pts = pts + rng.normal(0.0, noise, pts.shape)
    joints = np.stack(O[1:], axis=1) if L > 1 else np.zeros((F, 0, 3))
    E = L - 1
    bone = np.array([ll if e + 1 < E else np.nan for e in range(E)])
    seg = np.repeat(np.arange(L), counts)
    labels = tuple(f"S{s}M{k}" for s, n in enumerate(counts) for k in range(n))
    name = "hang_chain<" + "-".join(map(str, counts)) + ">"
    info = {"kind": "hang_chain", "counts": counts, "link_length": ll, "noise": float(noise), "rate": CHAIN_RATE}
    markers = Markers(points=pts, labels=labels, rate=CHAIN_RATE, units="mm", source=name, info=dict(info))
    truth = Truth(
        segment_names=tuple(f"seg{i}" for i in range(L)),
        parent=np.arange(L) - 1,
        marker_segment=seg,
        marker_id=np.arange(seg.size),
        joint_child=np.arange(1, L),
        joints=joints,
        bone_length=bone,
        info=info,
    )
    return SynthTake(markers, truth)


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
