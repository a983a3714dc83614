"""Tests of the batched Kabsch and generalised Procrustes solvers."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mocapskel.solvers import rigid, rigid_shape
from mocapskel.solvers.rigid import kabsch
from mocapskel.solvers.rigid_shape import procrustes_shape


def _motion(rng: np.random.Generator, F: int) -> tuple[np.ndarray, np.ndarray]:
    R = Rotation.random(F, random_state=rng).as_matrix()
    t = rng.uniform(-2000, 2000, size=(F, 3))
    return R, t


def _apply(R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    if pts.ndim == 2:
        return np.einsum("fij,pj->fpi", R, pts) + t[:, None, :]
    return np.einsum("fij,fpj->fpi", R, pts) + t[:, None, :]


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between batches of rotations."""
    c = (np.einsum("fij,fij->f", Ra, Rb) - 1) / 2
    return np.arccos(np.clip(c, -1, 1))


def test_kabsch_noise_free_exact():
    rng = np.random.default_rng(0)
    F, P = 500, 6
    ref = rng.normal(0, 100, size=(P, 3)) + 500
    R, t = _motion(rng, F)
    obs = _apply(R, t, ref)
    Rh, th, rms = kabsch(ref, obs)
    np.testing.assert_allclose(Rh, R, atol=1e-9)
    np.testing.assert_allclose(th, t, atol=1e-9 * 1e3)
    assert np.all(rms < 1e-9)
    np.testing.assert_allclose(np.linalg.det(Rh), 1, atol=1e-12)


def test_kabsch_three_points_and_coplanar_are_proper_rotations():
    rng = np.random.default_rng(1)
    F = 200
    ref = np.array([[0.0, 0, 0], [100, 0, 0], [0, 50, 0], [70, 80, 0]])  # coplanar
    R, t = _motion(rng, F)
    for pts in (ref[:3], ref):
        Rh, th, rms = kabsch(pts, _apply(R, t, pts))
        np.testing.assert_allclose(Rh, R, atol=1e-9)
        np.testing.assert_allclose(th, t, atol=1e-6)
        np.testing.assert_allclose(np.linalg.det(Rh), 1, atol=1e-12)


def test_kabsch_reflection_is_not_returned():
    # observations are a mirror image: the best proper rotation must still have det +1
    rng = np.random.default_rng(2)
    ref = rng.normal(0, 100, size=(8, 3))
    obs = (ref * np.array([1, 1, -1]))[None]
    Rh, _, rms = kabsch(ref, obs)
    np.testing.assert_allclose(np.linalg.det(Rh), 1, atol=1e-12)
    assert rms[0] > 1.0


def test_kabsch_matches_scipy_with_noise_and_weights():
    rng = np.random.default_rng(3)
    F, P = 50, 7
    ref = rng.normal(0, 80, size=(P, 3))
    R, t = _motion(rng, F)
    obs = _apply(R, t, ref) + rng.normal(0, 2.0, size=(F, P, 3))
    w = rng.uniform(0.2, 3.0, size=(F, P))
    Rh, th, rms = kabsch(ref, obs, w)
    for f in range(F):
        ww = w[f]
        ca = (ww[:, None] * ref).sum(0) / ww.sum()
        cb = (ww[:, None] * obs[f]).sum(0) / ww.sum()
        rot, _ = Rotation.align_vectors(obs[f] - cb, ref - ca, weights=ww)
        np.testing.assert_allclose(Rh[f], rot.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(th[f], cb - rot.as_matrix() @ ca, atol=1e-7)
        res = obs[f] - (ref @ Rh[f].T + th[f])
        np.testing.assert_allclose(rms[f], np.sqrt((ww * (res**2).sum(1)).sum() / ww.sum()))
    # noise of 2 mm per coordinate on a ~100 mm body: rotation within ~2 deg
    assert np.degrees(_angle(Rh, R)).max() < 3


def test_kabsch_gaps_and_zero_weights_are_ignored():
    rng = np.random.default_rng(4)
    F, P = 300, 6
    ref = rng.normal(0, 100, size=(P, 3))
    R, t = _motion(rng, F)
    obs = _apply(R, t, ref)
    # up to 3 gaps per frame: at least 3 points (random, so not collinear) remain
    for f in range(F):
        obs[f, rng.choice(P, size=rng.integers(0, 4), replace=False)] = np.nan
    # a wild outlier with zero weight
    w = np.ones((F, P))
    obs[:, 0] = np.where(np.isnan(obs[:, 0]), np.nan, obs[:, 0] + 1e4)
    w[:, 0] = 0
    Rh, th, rms = kabsch(ref, obs, w)
    ok = np.isfinite(obs[:, 1:]).all(-1).sum(1) >= 3
    np.testing.assert_allclose(Rh[ok], R[ok], atol=1e-9)
    np.testing.assert_allclose(th[ok], t[ok], atol=1e-6)
    assert np.all(rms[ok] < 1e-9)
    assert np.isnan(Rh[~ok]).all() and np.isnan(th[~ok]).all() and np.isnan(rms[~ok]).all()


def test_kabsch_degenerate_frames_give_nan():
    rng = np.random.default_rng(5)
    F = 6
    ref = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 0], [0, 0, 100], [200, 0, 0]])
    R, t = _motion(rng, F)
    obs = _apply(R, t, ref)
    obs[0] = np.nan  # nothing seen
    obs[1, 2:] = np.nan  # 2 points
    obs[2, [2, 3]] = np.nan  # 3 collinear points (0, 1, 4 on the x axis)
    obs[3, [1, 4]] = np.nan  # 3 good points
    Rh, th, rms = kabsch(ref, obs)
    bad = np.array([True, True, True, False, False, False])
    assert np.isnan(Rh[bad]).all() and np.isnan(th[bad]).all() and np.isnan(rms[bad]).all()
    np.testing.assert_allclose(Rh[~bad], R[~bad], atol=1e-9)


def test_kabsch_nearly_collinear_tolerance():
    ref = np.array([[0.0, 0, 0], [100, 0, 0], [200, 1e-3, 0]])
    obs = ref[None] + 10.0
    assert np.isfinite(kabsch(ref, obs)[0]).all()
    assert np.isnan(kabsch(ref, obs, collinear_tol=1e-4)[0]).all()


def test_kabsch_per_frame_reference():
    rng = np.random.default_rng(6)
    F, P = 40, 5
    ref = rng.normal(0, 100, size=(F, P, 3))
    R, t = _motion(rng, F)
    obs = _apply(R, t, ref)
    ref[3, 0] = np.nan  # a missing reference point is left out
    Rh, th, rms = kabsch(ref, obs)
    np.testing.assert_allclose(Rh, R, atol=1e-9)
    np.testing.assert_allclose(th, t, atol=1e-6)


def test_kabsch_bad_shapes_and_weights():
    with pytest.raises(ValueError):
        kabsch(np.zeros((4, 3)), np.zeros((2, 5, 3)))
    with pytest.raises(ValueError):
        kabsch(np.zeros((4, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError):
        kabsch(np.zeros((4, 3)), np.zeros((2, 4, 3)), -np.ones((2, 4)))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), P=st.integers(3, 12), scale=st.floats(1e-2, 1e4))
def test_kabsch_property_recovers_any_rigid_motion(seed, P, scale):
    rng = np.random.default_rng(seed)
    ref = rng.normal(0, scale, size=(P, 3))
    R, t = _motion(rng, 4)
    Rh, th, rms = kabsch(ref, _apply(R, t, ref))
    np.testing.assert_allclose(Rh, R, atol=1e-7)
    assert np.all(rms <= 1e-9 * max(scale, 2000))


def test_fast_rotation_matches_svd_on_hard_cases():
    """The quaternion/Newton rotation equals the SVD one, including special configurations."""
    rng = np.random.default_rng(7)
    cases = []
    a = rng.normal(0, 100, (5, 3))
    for R in [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, -1, 1]), Rotation.from_rotvec([0, 0, np.pi - 1e-9]).as_matrix()]:
        cases.append((a, a @ R.T))  # identity and half turns
    tet = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) * 50  # isotropic scatter
    Rr = Rotation.random(random_state=rng).as_matrix()
    cases.append((tet, tet @ Rr.T))
    tri = np.array([[0.0, 0, 0], [100, 0, 0], [50, 50 * np.sqrt(3), 0]])  # equilateral, planar
    cases.append((tri, tri @ Rr.T))
    cases.append((a, a * np.array([1, 1, -1])))  # mirror image
    cases.append((a, rng.normal(0, 100, (5, 3))))  # unrelated points
    H = []
    for ref, obs in cases:
        ref = ref - ref.mean(0)
        obs = obs - obs.mean(0)
        H.append(ref.T @ obs)
    H = np.array(H)
    R_fast = rigid._best_rotation(H)
    R_svd = rigid._svd_rotation(H)
    obj_fast = np.einsum("nij,nji->n", R_fast, H)
    obj_svd = np.einsum("nij,nji->n", R_svd, H)
    assert np.all(obj_fast >= obj_svd - 1e-9 * np.abs(H).max())
    np.testing.assert_allclose(np.linalg.det(R_fast), 1, atol=1e-12)
    np.testing.assert_allclose(R_fast @ np.swapaxes(R_fast, 1, 2), np.broadcast_to(np.eye(3), H.shape), atol=1e-12)
    unique = [0, 1, 2, 3, 4, 5, 7]  # the mirror case has a non-unique optimum
    np.testing.assert_allclose(R_fast[unique], R_svd[unique], atol=1e-9)
    # rank-1 H: no unique rotation; the fallback still returns a rotation
    R1 = rigid._best_rotation(np.outer([1.0, 2, 3], [3.0, 1, 0])[None])
    np.testing.assert_allclose(np.linalg.det(R1), 1, atol=1e-12)


# --------------------------------------------------------------------------- Procrustes


def test_procrustes_noise_free_with_gaps():
    rng = np.random.default_rng(10)
    F, P = 400, 7
    shape = rng.normal(0, 100, size=(P, 3))
    R, t = _motion(rng, F)
    obs = _apply(R, t, shape)
    gap = rng.random((F, P)) < 0.3
    obs[gap] = np.nan
    ref_frame = int(np.flatnonzero(~gap.any(1))[0])
    est, Rh, th, rms = procrustes_shape(obs, ref_frame=ref_frame)
    # the shape is the ref frame's pose of the body
    np.testing.assert_allclose(est, obs[ref_frame], atol=1e-8)
    ok = np.isfinite(Rh[:, 0, 0])
    assert ok.sum() > 0.8 * F
    recon = _apply(Rh[ok], th[ok], est)
    np.testing.assert_allclose(np.where(gap[ok, :, None], 0, recon), np.where(gap[ok, :, None], 0, obs[ok]), atol=1e-8)
    assert np.all(rms[ok] < 1e-8)


def test_procrustes_fills_points_missing_at_the_reference_frame():
    rng = np.random.default_rng(11)
    F, P = 100, 6
    shape = rng.normal(0, 100, size=(P, 3))
    R, t = _motion(rng, F)
    obs = _apply(R, t, shape)
    obs[0, 5] = np.nan  # point 5 not seen at the reference frame
    obs[:50, 4] = np.nan  # point 4 only seen late
    obs[:, 3] = np.nan  # point 3 never seen
    est, Rh, th, rms = procrustes_shape(obs, ref_frame=0)
    truth = shape @ R[0].T + t[0]  # the body in frame 0's pose
    np.testing.assert_allclose(est[[0, 1, 2, 4, 5]], truth[[0, 1, 2, 4, 5]], atol=1e-8)
    assert np.isnan(est[3]).all()


def test_procrustes_with_noise_beats_any_single_frame():
    rng = np.random.default_rng(12)
    F, P, sigma = 600, 5, 1.0
    shape = rng.normal(0, 100, size=(P, 3))
    R, t = _motion(rng, F)
    obs = _apply(R, t, shape) + rng.normal(0, sigma, size=(F, P, 3))
    obs[rng.random((F, P)) < 0.2] = np.nan
    est, Rh, th, rms = procrustes_shape(obs)
    # compare intrinsic geometry (pairwise distances) with the truth
    d_true = np.linalg.norm(shape[:, None] - shape[None], axis=-1)
    d_est = np.linalg.norm(est[:, None] - est[None], axis=-1)
    assert np.abs(d_est - d_true).max() < 0.3  # single frame: ~1.4 mm
    # and the rotation estimates are close to the truth
    ok = np.isfinite(Rh[:, 0, 0])
    # est lives in the pose of the best frame: Rh = R @ R_best^T
    best = int(np.argmax(np.isfinite(obs).all(-1).sum(1)))
    Rrel = np.einsum("fij,kj->fik", R[ok], R[best])
    assert np.degrees(_angle(Rh[ok], Rrel)).max() < 3
    # per frame, E[rms^2] ~ sigma^2 (3 - 6 / n) for n visible points (6 dof fitted)
    n = np.isfinite(obs).all(-1).sum(1)[ok]
    expect = sigma * np.sqrt(np.mean(3 - 6 / n))
    np.testing.assert_allclose(np.sqrt(np.mean(rms[ok] ** 2)), expect, rtol=0.1)


def test_procrustes_degenerate_input_is_nan_not_an_error():
    obs = np.full((5, 4, 3), np.nan)
    obs[:, :2] = 1.0
    shape, R, t, rms = procrustes_shape(obs)
    assert np.isnan(shape).all() and np.isnan(R).all() and np.isnan(t).all() and np.isnan(rms).all()


def test_procrustes_unsolvable_ref_frame_falls_back():
    rng = np.random.default_rng(13)
    F, P = 30, 5
    shape = rng.normal(0, 100, size=(P, 3))
    R, t = _motion(rng, F)
    obs = _apply(R, t, shape)
    obs[4, 2:] = np.nan
    est, Rh, _, _ = procrustes_shape(obs, ref_frame=4)
    np.testing.assert_allclose(est, obs[0], atol=1e-8)  # pose of the best (first full) frame
    assert np.isnan(Rh[4]).all()


# --------------------------------------------------------------------------- shape_poses (one shape, many frames)


def _noisy_take(rng, F, shape, noise=1.5, gap=0.05):
    R, t = _motion(rng, F)
    obs = _apply(R, t, shape) + rng.normal(0, noise, (F, len(shape), 3))
    obs[rng.random((F, len(shape))) < gap] = np.nan
    return R, t, obs


@pytest.mark.parametrize("P", [3, 4, 6])
@pytest.mark.parametrize("F", [7, 300, 20_000])  # one block, and several (rigid_shape._BLOCK frames each)
def test_shape_poses_equals_kabsch(P, F):
    """Noise, gaps, any rotation (half turns included): kabsch's R and t to rounding, NaN in the same frames."""
    rng = np.random.default_rng(P * 100 + F)
    shape = rng.normal(0, 80, (P, 3)) + [300.0, -200, 1000]  # not centred
    _, _, obs = _noisy_take(rng, F, shape)
    R0, t0, _ = kabsch(shape, obs)
    R1, t1 = rigid_shape.shape_poses(shape, obs)
    same = np.isfinite(R0[:, 0, 0])
    np.testing.assert_array_equal(np.isfinite(R1[:, 0, 0]), same)
    np.testing.assert_array_equal(np.isfinite(t1[:, 0]), same)
    np.testing.assert_allclose(R1[same], R0[same], rtol=0, atol=1e-11)
    np.testing.assert_allclose(t1[same], t0[same], rtol=0, atol=1e-8)


def test_shape_poses_noise_free_exact_and_rounding_level():
    rng = np.random.default_rng(3)
    shape = rng.normal(0, 60, (4, 3))
    R, t = _motion(rng, 5000)
    axes = rng.normal(size=(10, 3))
    R[:10] = Rotation.from_rotvec(np.pi * axes / np.linalg.norm(axes, axis=1, keepdims=True)).as_matrix()  # half turns
    obs = _apply(R, t, shape)
    Rh, th = rigid_shape.shape_poses(shape, obs)
    np.testing.assert_allclose(Rh, R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(th, t, rtol=0, atol=1e-9)


def test_shape_poses_unsolvable_frames_and_shapes():
    rng = np.random.default_rng(4)
    shape = np.array([[0.0, 0, 0], [100, 0, 0], [0, 80, 0], [30, 30, 90]])
    R, t = _motion(rng, 50)
    obs = _apply(R, t, shape)
    obs[5, :2] = np.nan  # 2 points left: unsolvable
    obs[6, 3] = np.nan  # 3 left: solvable
    obs[7, 1:3] = np.nan  # 2 left
    obs[8, [1, 3]] = np.inf  # non-finite counts as missing
    Rh, th = rigid_shape.shape_poses(shape, obs)
    bad = np.zeros(50, bool)
    bad[[5, 7, 8]] = True
    assert np.isnan(Rh[bad]).all() and np.isnan(th[bad]).all()
    np.testing.assert_allclose(Rh[~bad], R[~bad], atol=1e-12)
    # a NaN row in the shape is left out, as kabsch does
    shape_nan = shape.copy()
    shape_nan[3] = np.nan
    Rn, tn = rigid_shape.shape_poses(shape_nan, obs)
    R0, t0, _ = kabsch(shape_nan, obs)
    np.testing.assert_array_equal(np.isnan(Rn[:, 0, 0]), np.isnan(R0[:, 0, 0]))
    np.testing.assert_allclose(Rn, R0, atol=1e-12)
    np.testing.assert_allclose(tn, t0, atol=1e-9)
    # collinear shape: no frame can be solved
    line = np.array([[0.0, 0, 0], [1, 2, 3], [2, 4, 6], [5, 10, 15]])
    Rl, tl = rigid_shape.shape_poses(line, _apply(R, t, line))
    assert np.isnan(Rl).all() and np.isnan(tl).all()
    with pytest.raises(ValueError):
        rigid_shape.shape_poses(shape[:3], obs)


def test_shape_poses_nearly_collinear_frames_fall_back_to_the_exact_solver():
    """A thin triangle: its largest eigenvalue is not well apart, kabsch's solver is used; same result."""
    rng = np.random.default_rng(5)
    shape = np.array([[0.0, 0, 0], [200, 0, 0], [100, 0.5, 0]])
    R, t = _motion(rng, 400)
    obs = _apply(R, t, shape) + rng.normal(0, 0.05, (400, 3, 3))
    R0, t0, _ = kabsch(shape, obs)
    R1, t1 = rigid_shape.shape_poses(shape, obs)
    np.testing.assert_allclose(R1, R0, atol=1e-9)
    np.testing.assert_allclose(t1, t0, atol=1e-7)


def test_qcp_columns_agree_with_the_eigenvector():
    """The adjugate column used (first, second or the largest) is the top eigenvector of Horn's matrix."""
    rng = np.random.default_rng(6)
    H = rng.normal(0, 1, (2000, 3, 3)) + 5 * Rotation.random(2000, random_state=rng).as_matrix()
    Ht = np.ascontiguousarray(H.reshape(-1, 9).T)
    q, lam, apart, col0 = rigid_shape._qcp(Ht, np.linalg.svd(H, compute_uv=False).sum(1) * (1 + 1e-9))  # a tight upper bound
    R = rigid_shape._quat_to_matrix(q)
    R_svd = rigid._svd_rotation(H)
    ok = apart & col0
    assert ok.mean() > 0.8
    np.testing.assert_allclose(R[ok], R_svd[ok], atol=1e-10)
    redo = np.flatnonzero(apart & ~col0)
    if redo.size:
        np.testing.assert_allclose(rigid_shape._redo_rotations(Ht[:, redo], lam[redo]), R_svd[redo], atol=1e-10)


