"""Joint centres from segment poses: a hinge's centre placed along its axis, the sphere fit of one
segment's markers in the other's frame, how far two segments turn, frames spread over a take."""
from __future__ import annotations

import numpy as np

from ..rigid_shape import shape_poses
from ..spheres.sphere import mgdk


def place_on_hinge(fit, R1: np.ndarray, centres: np.ndarray, edges: np.ndarray, e: int,
                   skip: set | frozenset = frozenset()) -> tuple[np.ndarray, float | None]:
    """Move a hinge centre along its axis into the plane (normal to the axis) of the neighbouring joints along the chain.

    A hinge's centre is undetermined along its axis. Anatomically (a knee
    between hip and ankle, an elbow between shoulder and wrist) the centre lies
    where the axis meets the plane of the adjacent joint centres; those are
    fixed in one of the two segments, so their distance along the axis is
    constant. fit : a hinge ScoreFit; R1 : (F, 3, 3) rotations of the fit's
    first segment; centres : (F, E, 3) all joint centres so far; ``skip``: joints
    not to use (the other hinges: on real takes a walk makes hip, knee and ankle
    all hinge-like, and each would carry the others' freedom along their axes).
    Returns (centre (F, 3), shift or None).
    """
    a, b = edges[e]
    # the neighbours along a chain: the other joint of a segment with two joints (a thigh's hip for
    # its knee); a segment with more (a pelvis: both hips and the lumbar joint) says nothing about
    # where along the axis this one sits, a leaf has no other joint
    nb = []
    for s in (a, b):
        ks = [k for k in range(edges.shape[0]) if k != e and s in edges[k]]
        if len(ks) == 1 and ks[0] not in skip:  # a hinge neighbour is as loose along its own axis
            nb.extend(ks)
    base = centres[:, e].copy()
    if not nb:
        return base, None
    u = _rotate(R1, fit.axis1)
    s = np.stack([np.einsum("fi,fi->f", centres[:, k] - base, u) for k in nb], axis=1)
    ok = np.isfinite(s)
    if not ok.any():
        return base, None
    per_frame = np.where(ok, s, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    shift = float(np.median(per_frame[ok.any(axis=1)]))
    return base + shift * u, shift


def centre_from_either_side(fit, pose1: tuple, pose2: tuple) -> np.ndarray:
    """Joint centre per frame from a SCoRE fit, using whichever segment is seen.

    ``fit.centre`` needs both segments' poses; where only one is known the
    centre is still fixed in that one. pose1, pose2 : (R (F, 3, 3), t (F, 3),
    reference shape) of the fit's two segments. Returns (F, 3), NaN where
    neither is seen.
    """
    out = fit.centre.copy()  # both segments seen: the mean of the two images
    one = np.flatnonzero(~np.isfinite(out[:, 0]))
    if one.size:
        (R1, t1, _), (R2, t2, _) = pose1, pose2
        p1 = _rotate(R1[one], fit.c1) + t1[one]
        p2 = _rotate(R2[one], fit.c2) + t2[one]
        out[one] = np.where(np.isfinite(p1[:, :1]), p1, p2)  # NaN where neither is seen
    return out


def _rotate(R: np.ndarray, x: np.ndarray) -> np.ndarray:
    """R[f] @ x for all frames (F, 3), by columns (faster than einsum for 3x3)."""
    return R[:, :, 0] * x[0] + R[:, :, 1] * x[1] + R[:, :, 2] * x[2]


def spread_frames(F: int, n: int) -> np.ndarray | slice:
    """Up to ``n`` frame indices spread evenly over a take of ``F`` frames (all of them, as a slice, when F <= n)."""
    if F <= n:
        return slice(None)
    return np.unique(np.linspace(0, F - 1, max(int(n), 1)).round().astype(int))


def sphere_centre(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, int | None]:
    """Joint centre by Knight's unbiased multi-radius sphere fit (MGDK with estimated noise).

    The markers of one segment, expressed in the frame of the other (which
    needs 3+ markers), move on spheres about the joint. The parent side
    (``A`` as the frame) is tried first. Returns (centre (F, 3), side used:
    0 = A's frame, 1 = B's frame, None = failed).
    """
    for side, (P, C) in enumerate(((A, B), (B, A))):
        if P.shape[1] < 3 or C.shape[1] < 1:
            continue
        full = np.flatnonzero(np.isfinite(P).all(axis=(1, 2)))
        if not full.size:
            continue
        R, t = shape_poses(P[full[0]], P)
        local = np.einsum("fji,fkj->fki", R, C - t[:, None, :])  # R^T (C - t)
        fit = mgdk(local, sigma=None)
        if not fit.ok:
            fit = mgdk(local, sigma=0.0)
        if fit.ok:
            return np.einsum("fij,j->fi", R, fit.centre) + t, side
    return np.full((A.shape[0], 3), np.nan), None


#: Two segments that turn less than this relative to each other (:func:`relative_turn_deg`) leave their joint poorly
#: determined: the joints stage says so, and no axis of their turns is taken for one.
MIN_TURN_DEG = 5.0


def relative_turn_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """How far two segments turn relative to each other (95th percentile over frames, degrees).

    R1, R2 : (F, 3, 3) segment rotations (NaN where unknown). The relative
    rotation of every frame is compared with the typical one, their chordal
    mean (the rotation nearest the mean of the relative rotation matrices; it
    depends continuously on the data, unlike a frame picked as typical).
    """
    ok = np.isfinite(np.einsum("fij->f", R1) + np.einsum("fij->f", R2))
    if ok.sum() < 2:
        return float("nan")
    if not ok.all():
        R1, R2 = R1[ok], R2[ok]
    A, B = R1.reshape(-1, 3), R2.reshape(-1, 3)
    S = np.zeros((3, 3))
    for lo in range(0, len(A), 8192):  # sum of R1^T R2; products small enough for BLAS to stay on one thread
        S += A[lo : lo + 8192].T @ B[lo : lo + 8192]
    U, _, Vt = np.linalg.svd(S)
    Q = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt
    return float(np.percentile(_angle_to(R1, R2, Q), 95))


def _angle_to(R1: np.ndarray, R2: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Angle (degrees) between R1[f]^T R2[f] and Q for every frame.

    cos = (tr(Q^T R1^T R2) - 1) / 2, and tr(Q^T R1^T R2) is the sum of the entries of (R1 Q) * R2.
    """
    A = R1.reshape(-1, 3)
    R1Q = np.empty_like(A)
    for lo in range(0, len(A), 8192):  # products small enough for BLAS to stay on one thread
        np.matmul(A[lo : lo + 8192], Q, out=R1Q[lo : lo + 8192])
    cos = (np.einsum("fi,fi->f", R1Q.reshape(-1, 9), R2.reshape(-1, 9)) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def loose_along_axis(fit, on_axis) -> bool:
    """Whether a hinge-like SCoRE centre is better placed on its axis by the markers (``on_axis``, the
    hinge fit of the same poses, which puts it where the axis passes nearest the two segments' markers)
    than left where the data put it (``fit``).

    Across a limb (a knee, an elbow, a hip swinging forwards and back) the two segments' markers lie
    beside each other along the axis, and the placement puts the centre among them: it stays. Along a
    chain (a trunk twisting on the pelvis, a head turning on the neck) they lie one after the other on
    the axis: the two segments' marker centroids are farther apart along it than their distances from
    it summed, and the placement puts the centre anywhere between them, wherever the markers' counts
    weigh it. There the data decide unless they leave the centre looser still: ``rms / s_min``, the
    shift along the weakest direction that a residual of the fit's own size could make if it moved
    with the pose as skin does, against half the centroids' distance along the axis (realistic
    generated runs: a lumbar joint that twisted more than it bent went 170-220 mm up the axis by the
    placement, 16-53 mm from the truth by the data; a hip in a real walk, its axis across the chain,
    keeps the placement, 21-28 mm from the lab's hip centre, 56-60 mm by the data)."""
    m1, m2 = (None if m is None else m[np.isfinite(m).all(1)] for m in (fit.markers1, fit.markers2))
    if not on_axis.ok or m1 is None or m2 is None or not (len(m1) and len(m2)):
        return True  # (a failed placement fails the joint, as before the comparison)
    v1, v2 = m1.mean(0) - on_axis.c1, m2.mean(0) - on_axis.c2
    a1, a2 = float(v1 @ on_axis.axis1), float(v2 @ on_axis.axis2)
    along = abs(a2 - a1)
    radial = float(np.linalg.norm(v1 - a1 * on_axis.axis1) + np.linalg.norm(v2 - a2 * on_axis.axis2))
    if not along > radial:
        return True  # the axis runs across the chain
    s_min = float(fit.singular_values[-1])
    data = float(fit.rms) / s_min if s_min > 0 else float("inf")
    return not data <= 0.5 * along


def along_axis_sigma(fit) -> float:
    """Standard error of a SCoRE centre along its weakest direction (mm): rms / (s_min sqrt(n))."""
    s_min = float(fit.singular_values[-1])
    if not (s_min > 0) or fit.n_frames < 1:
        return float("inf")
    return float(fit.rms) / (s_min * np.sqrt(fit.n_frames))
