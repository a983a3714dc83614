"""A fast run through the whole capture volume, far from the lab's origin, with two markers seen as one
at its far end: the take fits (it used to end in ``LinAlgError: SVD did not converge``), and the kernels
that pick one frame as their reference pick one that can be solved.

The cause: the frame test of the segment stage (``partition.frame_scatters``) takes a group's shape by
generalised Procrustes started at the first sampled frame, and ``procrustes_shape`` gave up (an all-NaN
shape) when that one frame's points lay in one line or on one spot, although every other frame saw
them well apart. Two markers a few centimetres apart that the cameras see as one point for a few frames
(both labels carrying it) do that to a three-marker forefoot.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from mocapskel import evaluate, pipeline
from mocapskel.solvers.grouping.partition import frame_scatters
from mocapskel.solvers.rigid_shape import procrustes_shape
from mocapskel.solvers.rotations import rotvec_to_matrix
from mocapskel.solvers.joints.score import group_pose, score_from_markers
from mocapskel.synth.body import SEGMENTS
from mocapskel.synth.realistic import realistic_take


def _fuse_first_frames(points: np.ndarray, members: np.ndarray, frames: int) -> tuple[int, int]:
    """The two nearest of ``members`` seen as one point (their midpoint) on the first ``frames`` frames."""
    P0 = points[0, members]
    D = np.linalg.norm(P0[:, None] - P0[None], axis=-1) + np.diag(np.full(members.size, np.inf))
    i, j = np.unravel_index(int(np.argmin(D)), D.shape)
    a, b = members[i], members[j]
    mid = 0.5 * (points[:frames, a] + points[:frames, b])
    points[:frames, a] = mid
    points[:frames, b] = mid
    return int(a), int(b)


def _body(seed: int, K: int = 60, n: int = 3, offset: float = 6700.0, noise: float = 0.3) -> np.ndarray:
    """(K, n, 3) a rigid body of n markers turning and travelling 12 m along x, from ``offset``."""
    rng = np.random.default_rng(seed)
    shape = rng.normal(0.0, 40.0, (n, 3))
    R = rotvec_to_matrix(rng.normal(0.0, 0.8, (K, 3)))
    path = np.column_stack([offset + np.linspace(0.0, 12000.0, K), np.zeros(K), np.full(K, 900.0)])
    return path[:, None] + np.einsum("kij,nj->kni", R, shape) + rng.normal(0.0, noise, (K, n, 3))


def test_a_shape_starts_from_a_frame_that_can_be_aligned() -> None:
    """The first frame has two of three markers on one point (it was an all-NaN shape): the shape is the
    body's, from the other frames (the spoilt frame, aligned like any other, moves it by at most its
    marker's displacement over the number of frames)."""
    P = _body(1, noise=0.0)
    true = np.linalg.norm(P[1] - P[1].mean(0), axis=1)  # pose-free: distances from the centroid
    moved = np.linalg.norm(P[0, 1] - P[0, 0])
    P[0, 1] = P[0, 0]
    shape = procrustes_shape(P, ref_frame=0)[0]
    assert np.isfinite(shape).all()
    np.testing.assert_allclose(np.linalg.norm(shape - shape.mean(0), axis=1), true, atol=2 * moved / len(P))
    # no frame of three points out of line: no shape, as documented
    P[:, 1] = P[:, 0]
    assert np.isnan(procrustes_shape(P, ref_frame=0)[0]).all()


def test_the_frame_test_measures_a_group_whose_first_frame_is_in_line() -> None:
    """A three-marker group, a marker riding on it and one on another body, far from the origin, the group's
    first frame with two markers on one point: every marker's scatter in the group's frame is measured (it
    was NaN, and before that a LinAlgError), the rider's well under the other body's marker's."""
    P = np.concatenate([_body(2, n=4), _body(102, n=1)], axis=1)
    P[0, 1] = P[0, 0]
    got = frame_scatters(P, np.arange(3), 150, 20)[0]
    assert np.isfinite(got).all()
    assert got[0, 3] < 0.25 * got[0, 4]


def test_score_takes_its_reference_from_a_frame_out_of_line() -> None:
    P = _body(3)
    P[0, 2] = P[0, 0] + 0.5 * (P[0, 1] - P[0, 0])  # first frame: three markers in one line
    pose = group_pose(P, "A")
    assert not isinstance(pose, str), pose
    R, t, ref = pose
    assert np.isfinite(R[1:]).all()
    fit = score_from_markers(P, _body(4))
    assert "collinear" not in fit.reason


def test_a_far_fast_run_with_two_markers_seen_as_one_fits() -> None:
    """A generated run through the volume as a real sprint take that failed: CMU-style 41 markers with
    realistic skin motion, 836 frames at 250 Hz (generated at 240 Hz: the generator's run a little
    quicker), the markers along x from -5.5 m to about +6.7 m, with the forefoot's two nearest markers
    (LTOE, LMT5, 45 mm apart) seen as one point for the first 40 ms, where the subject is farthest from
    the cameras. The code before 096bf88 ended in ``LinAlgError: SVD did not converge`` (exit 1); the
    joints after IK now lie within the bound of the realistic runs (measured 24.6 mm rms)."""
    take = realistic_take(rng=np.random.default_rng(1), n_frames=836, rate=240.0, markerset="cmu41", motion="run")
    pts = take.markers.points.copy()
    d = pts[-1].mean(0)[:2] - pts[0].mean(0)[:2]
    c, s = d / np.linalg.norm(d)
    Rz = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # the run along +x
    pts = pts @ Rz.T
    shift = np.array([-5500.0 - pts[..., 0].min(), 0.0, 0.0])
    pts += shift
    assert 11500.0 < np.ptp(pts[..., 0]) < 13000.0
    fused = _fuse_first_frames(pts, np.flatnonzero(take.truth.marker_segment == SEGMENTS.index("LFoot")), 10)
    assert {take.markers.labels[m] for m in fused} == {"LTOE", "LMT5"}

    res = pipeline.fit(replace(take.markers, points=pts, rate=250.0), pipeline.make_params())
    sc = evaluate.score_motion(res.motion, replace(take.truth, joints=take.truth.joints @ Rz.T + shift))
    assert len(sc.joint_rms_each) >= 10 and sc.joint_rms_mm < 55.0, sc.joint_rms_each
