"""Tests of the functional joint solvers: SCoRE, SARA, the hinge centre, poses from markers."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapskel.solvers.joints.score import (
    SaraFit,
    ScoreFit,
    sara,
    score,
    score_from_markers,
    score_hinge,
)

C1 = np.array([80.0, -60.0, -90.0])  # joint in segment 1 (e.g. hip in the pelvis frame), mm
C2 = np.array([0.0, 15.0, 210.0])  # joint in segment 2 (e.g. hip in the thigh frame)
M1 = np.array([[0, 0, 0], [120, 0, 0], [0, 110, 10], [60, 50, 80.0]]) - [40, 40, 20]  # segment-1 markers
M2 = np.array([[40, 0, 0], [-40, 10, 30], [0, 45, 120], [10, -40, 60.0]])  # segment-2 markers
HINGE_AXIS2 = np.array([1.0, 0.2, -0.1]) / np.linalg.norm([1.0, 0.2, -0.1])  # in segment 2


def _smooth_rotvec(rng: np.random.Generator, F: int, amp: float) -> np.ndarray:
    """(F, 3) smooth random rotation vectors, a few harmonics per axis, ~amp rad."""
    t = np.linspace(0, 1, F)
    rv = np.zeros((F, 3))
    for k in range(3):
        for h in range(1, 4):
            rv[:, k] += amp / h * np.sin(2 * np.pi * h * t * rng.uniform(1, 3) + rng.uniform(0, 2 * np.pi))
    return rv


def _poses(rng: np.random.Generator, F: int, hinge: bool = False, amp: float = 0.5):
    """Two segments joined at C1 (in 1) = C2 (in 2): ball (3-DoF) or hinge motion.

    Returns R1, t1, R2, t2 and the lab joint J (F, 3)."""
    R1 = Rotation.from_rotvec(_smooth_rotvec(rng, F, 0.3)).as_matrix()
    t1 = np.array([0.0, 0.0, 900.0]) + np.cumsum(rng.normal(0, 2, (F, 3)), 0)
    if hinge:
        angle = amp * np.sin(np.linspace(0, 8 * np.pi, F)) + 0.6
        Rrel = Rotation.from_rotvec(angle[:, None] * HINGE_AXIS2).as_matrix()
    else:
        Rrel = Rotation.from_rotvec(_smooth_rotvec(rng, F, amp)).as_matrix()
    R2 = R1 @ Rrel
    J = np.einsum("fij,j->fi", R1, C1) + t1
    t2 = J - np.einsum("fij,j->fi", R2, C2)
    return R1, t1, R2, t2, J


def _markers(R, t, local):
    return np.einsum("fij,pj->fpi", R, local) + t[:, None, :]


def _point_line_distance(p: np.ndarray, q: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance of points p (F, 3) to the lines through q (F, 3) with unit directions d (F, 3)."""
    v = p - q
    return np.linalg.norm(v - np.einsum("fi,fi->f", v, d)[:, None] * d, axis=1)


# ---------------------------------------------------------------- ball joint


def test_ball_joint_noise_free_exact():
    rng = np.random.default_rng(0)
    R1, t1, R2, t2, J = _poses(rng, 500)
    fit = score(R1, t1, R2, t2)
    assert isinstance(fit, ScoreFit)
    assert fit.ok and fit and not fit.hinge, fit.reason
    np.testing.assert_allclose(fit.c1, C1, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fit.c2, C2, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fit.centre, J, rtol=0, atol=1e-9)
    assert fit.rms < 1e-9 and np.all(fit.residual < 1e-9)
    assert fit.n_frames == 500
    assert fit.axis_ratio > 0.1 and 0 < fit.cond <= 1
    assert np.all(np.diff(fit.singular_values) <= 0)  # largest first
    assert np.isnan(fit.axis1).all()


def test_nan_frames_and_zero_weights_are_skipped():
    rng = np.random.default_rng(1)
    R1, t1, R2, t2, J = _poses(rng, 400)
    # corrupt some frames: wrong poses, then hide them by NaN or by zero weight
    bad = rng.random(400) < 0.2
    t2c = t2.copy()
    t2c[bad] += 500.0
    R1n = R1.copy()
    R1n[bad, 0, 0] = np.nan
    fit_nan = score(R1n, t1, R2, t2c)
    w = np.where(bad, 0.0, 1.0)
    fit_w = score(R1, t1, R2, t2c, weights=w)
    for fit in (fit_nan, fit_w):
        assert fit.ok, fit.reason
        assert fit.n_frames == int((~bad).sum())
        np.testing.assert_allclose(fit.c1, C1, atol=1e-9)
        np.testing.assert_allclose(fit.c2, C2, atol=1e-9)
        assert np.isnan(fit.centre[bad]).all() and np.isnan(fit.residual[bad]).all()
        np.testing.assert_allclose(fit.centre[~bad], J[~bad], atol=1e-9)


def test_weights_scale_free():
    rng = np.random.default_rng(2)
    R1, t1, R2, t2, _ = _poses(rng, 300)
    t2 = t2 + rng.normal(0, 1.0, t2.shape)
    w = rng.uniform(0.5, 2.0, 300)
    a, b = score(R1, t1, R2, t2, weights=w), score(R1, t1, R2, t2, weights=7 * w)
    np.testing.assert_allclose(a.c1, b.c1, atol=1e-9)
    assert a.rms == pytest.approx(b.rms)


def test_score_from_markers_noise_free_exact_with_gaps():
    rng = np.random.default_rng(3)
    R1, t1, R2, t2, J = _poses(rng, 400)
    A, B = _markers(R1, t1, M1), _markers(R2, t2, M2)
    A[5:40, 1] = np.nan  # a marker gap: 3 markers remain
    B[100:110, :2] = np.nan  # only 2 markers: those frames cannot be solved
    fit = score_from_markers(A, B)
    assert fit.ok, fit.reason
    ok = np.ones(400, bool)
    ok[100:110] = False
    assert fit.n_frames == ok.sum()
    np.testing.assert_allclose(fit.centre[ok], J[ok], rtol=0, atol=1e-8)
    assert np.isnan(fit.centre[~ok]).all()
    assert fit.markers1.shape == (4, 3) and fit.markers2.shape == (4, 3)


def test_score_from_markers_three_planar_markers():
    rng = np.random.default_rng(4)
    R1, t1, R2, t2, J = _poses(rng, 300)
    fit = score_from_markers(_markers(R1, t1, M1[:3]), _markers(R2, t2, M2[:3]))
    assert fit.ok, fit.reason
    np.testing.assert_allclose(fit.centre, J, rtol=0, atol=1e-8)


def test_score_from_markers_1mm_noise_centre_error():
    # 4 markers per segment, clusters ~100 mm, joint ~200 mm from segment 2's
    # markers, 1 mm isotropic marker noise: the per-frame lab centre error is
    # dominated by the segment pose noise (lever arm); the fitted local centre
    # is within a fraction of a millimetre
    per_frame, systematic = [], []
    for seed in range(4):
        rng = np.random.default_rng([seed, 5])
        R1, t1, R2, t2, J = _poses(rng, 1000)
        A = _markers(R1, t1, M1) + rng.normal(0, 1.0, (1000, 4, 3))
        B = _markers(R2, t2, M2) + rng.normal(0, 1.0, (1000, 4, 3))
        fit = score_from_markers(A, B)
        assert fit.ok and not fit.hinge, fit.reason
        err = fit.centre - J
        per_frame.append(np.sqrt(np.mean(np.sum(err**2, 1))))
        # the error expressed in segment 1's true frame: its mean is the fit's systematic error
        systematic.append(np.linalg.norm(np.einsum("fji,fj->fi", R1, err).mean(0)))
    assert np.mean(per_frame) < 2.0  # measured ~1.4 mm
    assert np.mean(systematic) < 0.5  # measured ~0.1-0.2 mm


# ---------------------------------------------------------------- hinge


def _expected_hinge_centre(R1, t1, R2, t2):
    """The point of the true hinge axis closest to the centroid of all markers, in the lab per frame.

    A hinge preserves the axial coordinate in segment 1 of segment 2's markers,
    so that point is the axial projection of the centroid of all markers."""
    a1 = R1[0].T @ R2[0] @ HINGE_AXIS2  # the axis in segment 1
    m2_in_1 = R1[0].T @ (R2[0] @ M2.mean(0) + t2[0] - t1[0])
    g = (len(M1) * M1.mean(0) + len(M2) * m2_in_1) / (len(M1) + len(M2))
    c1 = C1 + a1 * (a1 @ (g - C1))
    return np.einsum("fij,j->fi", R1, c1) + t1, a1


def test_hinge_detected_and_centre_placed_by_markers_noise_free():
    rng = np.random.default_rng(6)
    R1, t1, R2, t2, J = _poses(rng, 400, hinge=True)
    bare = score(R1, t1, R2, t2)
    assert not bare.ok and bare.hinge and "hinge" in bare.reason
    assert bare.axis_ratio < 1e-6
    fit = score(R1, t1, R2, t2, markers1=M1, markers2=M2)
    assert fit.ok and fit.hinge, fit.reason
    expected, a1 = _expected_hinge_centre(R1, t1, R2, t2)
    axis_lab = np.einsum("fij,j->fi", R1, a1)
    assert np.all(_point_line_distance(fit.centre, J, axis_lab) < 1e-9)  # on the true axis
    np.testing.assert_allclose(fit.centre, expected, rtol=0, atol=1e-8)  # closest to the markers
    assert abs(abs(fit.axis1 @ a1) - 1) < 1e-12
    assert abs(abs(fit.axis2 @ HINGE_AXIS2) - 1) < 1e-12
    np.testing.assert_allclose(np.einsum("fij,j->fi", R1, fit.axis1), np.einsum("fij,j->fi", R2, fit.axis2), atol=1e-12)
    assert fit.rms < 1e-9
    # score_hinge gives the same answer
    h = score_hinge(R1, t1, R2, t2, M1, M2)
    np.testing.assert_allclose(h.c1, fit.c1, atol=1e-9)
    np.testing.assert_allclose(h.c2, fit.c2, atol=1e-9)


def test_hinge_from_noisy_markers():
    rng = np.random.default_rng(7)
    R1, t1, R2, t2, J = _poses(rng, 1000, hinge=True)
    A = _markers(R1, t1, M1) + rng.normal(0, 1.0, (1000, 4, 3))
    B = _markers(R2, t2, M2) + rng.normal(0, 1.0, (1000, 4, 3))
    fit = score_from_markers(A, B)
    assert fit.ok and fit.hinge, fit.reason
    assert fit.axis_ratio < 0.1
    expected, a1 = _expected_hinge_centre(R1, t1, R2, t2)
    axis_lab = np.einsum("fij,j->fi", R1, a1)
    assert np.sqrt(np.mean(_point_line_distance(fit.centre, J, axis_lab) ** 2)) < 2.0
    assert np.sqrt(np.mean(np.sum((fit.centre - expected) ** 2, 1))) < 3.0


@pytest.mark.parametrize("wobble, hinge", [(0.1, False), (0.02, True)])
def test_hinge_threshold_on_a_wobbling_hinge(wobble, hinge):
    # a hinge plus a 3-DoF wobble of the given RMS angle (rad): axis_ratio is
    # about twice the wobble here, so 0.1 rad stays a (well-determined) ball
    # joint while 0.02 rad is treated as a hinge
    rng = np.random.default_rng(8)
    R1, t1, R2, t2, J = _poses(rng, 500, hinge=True)
    rv = _smooth_rotvec(rng, 500, 1.0)
    rv *= wobble / np.sqrt(np.mean(np.sum(rv**2, 1)))
    R2 = R2 @ Rotation.from_rotvec(rv).as_matrix()
    t2 = J - np.einsum("fij,j->fi", R2, C2)
    fit = score(R1, t1, R2, t2, markers1=M1, markers2=M2)
    assert fit.ok and fit.hinge == hinge, fit.reason
    if not hinge:
        np.testing.assert_allclose(fit.c1, C1, atol=1e-9)
    else:  # on the hinge axis, within the wobble's reach
        assert fit.axis_ratio < 0.1
        assert np.all(np.linalg.norm(fit.centre - J, axis=1) < 60)


# ---------------------------------------------------------------- SARA


def test_sara_recovers_the_axis_noise_free():
    rng = np.random.default_rng(9)
    R1, t1, R2, t2, J = _poses(rng, 400, hinge=True)
    fit = sara(R1, t1, R2, t2)
    assert isinstance(fit, SaraFit) and fit.ok, fit.reason
    _, a1 = _expected_hinge_centre(R1, t1, R2, t2)
    assert np.linalg.norm(np.cross(fit.axis1, a1)) < 1e-12
    assert np.linalg.norm(np.cross(fit.axis2, HINGE_AXIS2)) < 1e-12
    assert np.max(fit.angle) < 1e-9
    assert fit.axis1[np.argmax(np.abs(fit.axis1))] > 0  # documented sign convention
    # the point lies on the axis in both segments, in the lab every frame
    axis_lab = np.einsum("fij,j->fi", R1, a1)
    assert np.all(_point_line_distance(fit.point, J, axis_lab) < 1e-9)
    assert np.all(np.linalg.norm(np.cross(fit.axis, axis_lab), axis=1) < 1e-12)
    assert fit.rms < 1e-9 and fit.axis_ratio < 1e-6


def test_sara_axis_from_noisy_markers():
    from mocapskel.solvers.joints.score import group_pose

    rng = np.random.default_rng(10)
    R1, t1, R2, t2, J = _poses(rng, 1000, hinge=True)
    A = _markers(R1, t1, M1) + rng.normal(0, 1.0, (1000, 4, 3))
    B = _markers(R2, t2, M2) + rng.normal(0, 1.0, (1000, 4, 3))
    P1, P2 = group_pose(A, "A"), group_pose(B, "B")
    fit = sara(P1[0], P1[1], P2[0], P2[1])
    assert fit.ok
    # compare in the lab: the estimated lab axis against the true one
    _, a1 = _expected_hinge_centre(R1, t1, R2, t2)
    axis_lab = np.einsum("fij,j->fi", R1, a1)
    ang = np.degrees(np.arcsin(np.clip(np.linalg.norm(np.cross(fit.axis, axis_lab), axis=1), 0, 1)))
    assert np.mean(ang) < 1.0  # degrees; measured ~0.3
    assert np.sqrt(np.mean(_point_line_distance(fit.point, J, axis_lab) ** 2)) < 2.0


# ---------------------------------------------------------------- failures


def test_no_relative_motion_fails():
    rng = np.random.default_rng(11)
    R1, t1, _, _, J = _poses(rng, 200)
    R2 = R1 @ Rotation.from_rotvec([0.3, 0.1, -0.2]).as_matrix()  # rigidly attached
    t2 = J - np.einsum("fij,j->fi", R2, C2)
    for fit in (score(R1, t1, R2, t2), sara(R1, t1, R2, t2), score_hinge(R1, t1, R2, t2, M1, M2)):
        assert not fit.ok and "relative rotation" in fit.reason
        assert not fit


def test_all_frames_unknown_fails():
    R = np.full((10, 3, 3), np.nan)
    t = np.zeros((10, 3))
    fit = score(R, t, R, t)
    assert not fit.ok and "no frame" in fit.reason
    assert fit.centre.shape == (10, 3) and np.isnan(fit.centre).all()


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda A, B: (A[:, :2], B), "at least 3"),
        (lambda A, B: (A, B[:, :1]), "at least 3"),
        (lambda A, B: (np.stack([A[:, 0], A[:, 0] + [10, 0, 0], A[:, 0] + [25, 0, 0]], 1), B), "collinear"),
        (lambda A, B: (np.where(np.arange(A.shape[1])[None, :, None] == np.arange(A.shape[0])[:, None, None] % 4, np.nan, A), B), "no frame"),
    ],
)
def test_score_from_markers_reports_unusable_groups(make, words):
    rng = np.random.default_rng(12)
    R1, t1, R2, t2, _ = _poses(rng, 100)
    A, B = make(_markers(R1, t1, M1), _markers(R2, t2, M2))
    fit = score_from_markers(A, B)
    assert not fit.ok and words in fit.reason
    assert fit.centre.shape == (100, 3) and np.isnan(fit.centre).all()


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        score(np.zeros((5, 3, 3)), np.zeros((4, 3)), np.zeros((5, 3, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError):
        score_from_markers(np.zeros((5, 4, 3)), np.zeros((6, 4, 3)))
    with pytest.raises(ValueError):
        score(np.zeros((5, 3, 3)), np.zeros((5, 3)), np.zeros((5, 3, 3)), np.zeros((5, 3)), weights=-np.ones(5))


# ---------------------------------------------------------------- long takes, sums over frames


def test_long_take_with_gaps_and_weights_equals_the_stacked_least_squares():
    """Sums taken in pieces (long takes), NaN frames and weights: the stacked system's solution."""
    rng = np.random.default_rng(21)
    F = 30_000
    R1, t1, R2, t2, _ = _poses(rng, F)
    t2 = t2 + rng.normal(0, 2.0, (F, 3))
    R1[rng.random(F) < 0.03] = np.nan
    t2[rng.random(F) < 0.03, 1] = np.nan
    w = rng.uniform(0.2, 2.0, F)
    for weights in (None, w):
        fit = score(R1, t1, R2, t2, weights)
        ok = np.isfinite(R1).all((1, 2)) & np.isfinite(t2).all(1)
        sw = np.sqrt(np.ones(F) if weights is None else weights)[ok]
        A = np.concatenate([R1[ok], -R2[ok]], axis=2) * sw[:, None, None]  # (n, 3, 6)
        b = (t2[ok] - t1[ok]) * sw[:, None]
        x = np.linalg.lstsq(A.reshape(-1, 6), b.reshape(-1), rcond=None)[0]
        assert fit.ok and fit.n_frames == ok.sum()
        np.testing.assert_allclose(fit.c1, x[:3], rtol=0, atol=1e-8)
        np.testing.assert_allclose(fit.c2, x[3:], rtol=0, atol=1e-8)
        assert np.isnan(fit.centre[~ok]).all() and np.isfinite(fit.centre[ok]).all()
        q1 = np.einsum("fij,j->fi", R1[ok], x[:3]) + t1[ok]
        q2 = np.einsum("fij,j->fi", R2[ok], x[3:]) + t2[ok]
        np.testing.assert_allclose(fit.centre[ok], 0.5 * (q1 + q2), atol=1e-8)
        r2 = np.sum((q1 - q2) ** 2, 1)
        wn = (np.ones(F) if weights is None else weights)[ok]
        assert fit.rms == pytest.approx(np.sqrt(np.sum(wn * r2) / wn.sum()), rel=1e-9)


def test_hinge_centre_from_the_sums_equals_the_per_frame_formula():
    """The hinge placement uses the system's sums (R^T R = I); the same as summing over frames."""
    from mocapskel.solvers.joints import score as S

    rng = np.random.default_rng(22)
    F = 2000
    R1, t1, R2, t2, _ = _poses(rng, F, hinge=True)
    R2 = R2 @ Rotation.from_rotvec(rng.normal(0, 0.01, (F, 3))).as_matrix()  # a wobbling hinge
    t2 = t2 + rng.normal(0, 1.0, (F, 3))
    t1[::50] = np.nan
    w = rng.uniform(0.5, 1.5, F)
    sy = S._system(R1, t1, R2, t2, w)
    x, v = S._hinge_solution(sy, M1, M2)
    # the per-frame formula: alpha = sum w u.(g - p0) / sum w |u|^2
    x0 = S._truncated(sy, 1)
    g1, g2 = S._images(sy, M1.mean(0), M2.mean(0))
    g = (len(M1) * g1 + len(M2) * g2) / (len(M1) + len(M2))
    p1, p2 = S._images(sy, x0[:3], x0[3:])
    u = 0.5 * (np.einsum("fij,j->fi", R1, v[:3]) + np.einsum("fij,j->fi", R2, v[3:]))
    ok = sy.valid
    alpha = np.sum(sy.w[ok] * np.einsum("fi,fi->f", u[ok], (g - 0.5 * (p1 + p2))[ok])) / np.sum(
        sy.w[ok] * np.einsum("fi,fi->f", u[ok], u[ok]))
    np.testing.assert_allclose(x, x0 + alpha * v, rtol=0, atol=1e-9)


def test_group_pose_reference_is_the_first_complete_frame():
    from mocapskel.solvers.joints.score import group_pose

    rng = np.random.default_rng(23)
    R1, t1, *_ = _poses(rng, 3000)
    A = _markers(R1, t1, M1) + rng.normal(0, 0.5, (3000, 4, 3))
    A[:2500, 1] = np.nan  # the first complete frame is 2500
    R, t, ref = group_pose(A, "A")
    np.testing.assert_allclose(ref, A[2500] - A[2500].mean(0))
    np.testing.assert_allclose(R[2500], np.eye(3), atol=1e-12)
    assert np.isfinite(R[:2500]).all()  # three markers are enough
