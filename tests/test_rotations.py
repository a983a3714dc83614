"""Tests of the rotation kernels: BVH Euler angles, continuity, slerp, SO(3) projection."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mocapskel.solvers.rotations import (
    ORDERS,
    euler_to_matrix,
    hold_unobserved,
    matrix_to_euler,
    matrix_to_quat,
    matrix_to_rotvec,
    project_to_so3,
    quat_to_matrix,
    rotvec_to_matrix,
    slerp_fill,
    slerp_fill_joints,
    unwrap_euler,
)


def _elementary(axis: str, deg: float) -> np.ndarray:
    """Right-handed rotation about one coordinate axis, written out by hand."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {
        "X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def _angle_between(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Geodesic angle (degrees) between batches of rotations."""
    c = (np.einsum("...ij,...ij->...", Ra, Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def _slerp_path(keys: np.ndarray, steps: int) -> np.ndarray:
    """(K-1)*steps+1 rotations through K keyframes at constant speed per segment."""
    out = [keys[0][None]]
    t = np.arange(1, steps + 1) / steps
    for a, b in zip(keys[:-1], keys[1:]):
        rel = matrix_to_rotvec(a.T @ b)
        out.append(a @ rotvec_to_matrix(t[:, None] * rel))
    return np.concatenate(out)


# --------------------------------------------------------------------------- Euler


@pytest.mark.parametrize("order", ORDERS)
def test_euler_to_matrix_is_intrinsic_product_in_channel_order(order: str) -> None:
    rng = np.random.default_rng(1)
    for a, b, c in rng.uniform(-180, 180, (20, 3)):
        want = _elementary(order[0], a) @ _elementary(order[1], b) @ _elementary(order[2], c)
        np.testing.assert_allclose(euler_to_matrix([a, b, c], order), want, atol=1e-14)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_round_trip_random_rotations(order: str) -> None:
    R = Rotation.random(2000, random_state=np.random.default_rng(2)).as_matrix().reshape(40, 50, 3, 3)
    ang = matrix_to_euler(R, order)
    assert ang.shape == (40, 50, 3)
    np.testing.assert_allclose(euler_to_matrix(ang, order), R, atol=1e-13)
    assert np.all(np.abs(ang[..., 1]) <= 90) and np.all(np.abs(ang) <= 180)
    # the same as scipy's intrinsic (upper-case) convention
    np.testing.assert_allclose(Rotation.from_euler(order, ang.reshape(-1, 3), degrees=True).as_matrix(),
                               R.reshape(-1, 3, 3), atol=1e-13)


@pytest.mark.parametrize("order", ORDERS)
def test_second_euler_solution_is_the_same_rotation(order: str) -> None:
    ang = np.random.default_rng(3).uniform(-180, 180, (500, 3))
    other = ang + [180.0, 0.0, 180.0]
    other[:, 1] = 180.0 - ang[:, 1]
    np.testing.assert_allclose(euler_to_matrix(other, order), euler_to_matrix(ang, order), atol=1e-13)


@pytest.mark.parametrize("order", ORDERS)
def test_gimbal_lock_gives_no_nan_and_the_same_rotation(order: str) -> None:
    rng = np.random.default_rng(4)
    ang = rng.uniform(-180, 180, (400, 3))
    ang[:, 1] = rng.choice([90.0, -90.0], 400) + rng.choice([0.0, 1e-12, 1e-9, 1e-7, 1e-4], 400)
    R = euler_to_matrix(ang, order)
    back = matrix_to_euler(R, order)
    assert np.isfinite(back).all()
    np.testing.assert_allclose(euler_to_matrix(back, order), R, atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(ORDERS),
    st.floats(-720, 720),
    st.one_of(st.floats(-720, 720), st.sampled_from([90.0, -90.0, 270.0, 89.99999999])),
    st.floats(-720, 720),
)
def test_euler_round_trip_any_angles(order: str, a: float, b: float, c: float) -> None:
    R = euler_to_matrix([a, b, c], order)
    back = matrix_to_euler(R, order)
    assert np.isfinite(back).all()
    np.testing.assert_allclose(euler_to_matrix(back, order), R, atol=1e-12)


def test_bad_order_is_refused() -> None:
    with pytest.raises(ValueError, match="permutation"):
        euler_to_matrix([0, 0, 0], "XXY")
    with pytest.raises(ValueError, match="permutation"):
        matrix_to_euler(np.eye(3), "ZX")


# --------------------------------------------------------------------------- continuity


def _max_jump_ok(ang: np.ndarray, R: np.ndarray, slack: float = 1.5) -> None:
    """Frame-to-frame Euler jumps bounded by the angular step (and 1/cos b for a, c)."""
    step = _angle_between(R[:-1], R[1:])
    cos_b = np.minimum(np.abs(np.cos(np.radians(ang[:-1, ..., 1]))), np.abs(np.cos(np.radians(ang[1:, ..., 1]))))
    jump = np.abs(np.diff(ang, axis=0))
    assert np.all(jump[..., 1] <= slack * step + 1e-6)
    bound = slack * step / np.maximum(cos_b, 1e-300) + 1e-6
    assert np.all(jump[..., 0] <= bound) and np.all(jump[..., 2] <= bound)


@pytest.mark.parametrize("order", ORDERS)
def test_unwrap_smooth_random_path_is_continuous(order: str) -> None:
    rng = np.random.default_rng(5)
    keys = Rotation.random(30, random_state=rng).as_matrix()
    R = _slerp_path(keys, 25)  # about 7 degrees per frame at most
    ang = unwrap_euler(matrix_to_euler(R, order), order)
    np.testing.assert_allclose(euler_to_matrix(ang, order), R, atol=1e-12)
    _max_jump_ok(ang, R)
    # where the path is far from gimbal lock, no jump is large
    far = np.abs(np.cos(np.radians(ang[:, 1]))) > 0.5
    both = far[1:] & far[:-1]
    assert np.abs(np.diff(ang, axis=0))[both].max() < 30


@pytest.mark.parametrize("order", ORDERS)
def test_unwrap_full_turns_keep_counting(order: str) -> None:
    # two and a half turns about the first axis, a slow wobble on the others
    F = 400
    truth = np.stack([np.linspace(-170, 730, F), 20 * np.sin(np.linspace(0, 6, F)), np.linspace(0, -500, F)], axis=1)
    R = euler_to_matrix(truth, order)
    ang = unwrap_euler(matrix_to_euler(R, order), order)
    np.testing.assert_allclose(ang, truth, atol=1e-9)


@pytest.mark.parametrize("order", ORDERS)
def test_unwrap_recovers_a_smooth_path_from_scrambled_representations(order: str) -> None:
    rng = np.random.default_rng(6)
    F = 300
    t = np.linspace(0, 1, F)[:, None]
    truth = np.concatenate(
        [-150 + 600 * t, 80 * np.sin(9 * t), 120 * np.cos(5 * t) - 300 * t], axis=1
    )
    scrambled = truth.copy()
    alt = rng.random(F) < 0.5
    scrambled[alt] += [180.0, 0.0, 180.0]
    scrambled[alt, 1] = 180.0 - truth[alt, 1]
    scrambled += 360.0 * rng.integers(-3, 4, (F, 3))
    np.testing.assert_allclose(unwrap_euler(scrambled, order), truth, atol=1e-9)


@pytest.mark.parametrize("order", ORDERS)
def test_unwrap_through_gimbal_lock(order: str) -> None:
    # the middle angle sweeps through +90 exactly at frame 30 and on to 110
    F = 51
    b = np.linspace(60, 110, F)
    a = np.linspace(-40, 80, F)
    c = 30 * np.sin(np.linspace(0, 3, F))
    truth = np.stack([a, b, c], axis=1)
    R = euler_to_matrix(truth, order)
    ang = unwrap_euler(matrix_to_euler(R, order), order)
    assert np.isfinite(ang).all()
    np.testing.assert_allclose(euler_to_matrix(ang, order), R, atol=1e-12)
    lock = 30
    off = np.arange(F) != lock
    np.testing.assert_allclose(ang[off], truth[off], atol=1e-6)
    # at the locked frame a is held from the frame before and c carries the rest
    np.testing.assert_allclose(ang[lock, 0], truth[lock - 1, 0], atol=1e-6)
    assert np.abs(ang[lock] - truth[lock]).max() <= np.abs(np.diff(a)).max() + 1e-6


@pytest.mark.parametrize("order", ORDERS)
def test_unwrap_near_gimbal_lock_and_locked_start(order: str) -> None:
    rng = np.random.default_rng(7)
    F = 200
    # a pass that grazes the lock (b peaks at 89.9) while a and c turn
    b = 89.9 - 400 * np.linspace(-1, 1, F) ** 2
    truth = np.stack([np.linspace(0, 200, F), b, np.linspace(50, -100, F)], axis=1)
    truth[:5, 1] = 90.0  # locked for the first frames
    R = euler_to_matrix(truth, order)
    ang = unwrap_euler(matrix_to_euler(R, order), order)
    assert np.isfinite(ang).all()
    np.testing.assert_allclose(euler_to_matrix(ang, order), R, atol=1e-10)
    _max_jump_ok(ang[5:], R[5:])
    # random rotations per frame: no NaN, same matrices
    Rr = Rotation.random(100, random_state=rng).as_matrix()
    np.testing.assert_allclose(euler_to_matrix(unwrap_euler(matrix_to_euler(Rr, order), order), order), Rr, atol=1e-12)


def test_unwrap_trailing_axes_are_independent_and_idempotent() -> None:
    rng = np.random.default_rng(8)
    R = np.stack([_slerp_path(Rotation.random(6, random_state=rng).as_matrix(), 20) for _ in range(4)], axis=1)
    ang = matrix_to_euler(R, "ZXY")
    both = unwrap_euler(ang, "ZXY")
    assert both.shape == ang.shape
    for s in range(4):
        np.testing.assert_array_equal(both[:, s], unwrap_euler(ang[:, s], "ZXY"))
    np.testing.assert_allclose(unwrap_euler(both, "ZXY"), both, atol=1e-9)


def test_unwrap_refuses_nan_and_handles_empty() -> None:
    ang = np.zeros((5, 3))
    ang[2, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        unwrap_euler(ang)
    assert unwrap_euler(np.zeros((0, 2, 3))).shape == (0, 2, 3)
    np.testing.assert_allclose(unwrap_euler([[[370.0, 100.0, -190.0]]]), [[[-170.0, 80.0, -10.0]]])


# --------------------------------------------------------------------------- other helpers


def test_rotvec_and_quaternion_round_trips_keep_shape() -> None:
    R = Rotation.random(60, random_state=np.random.default_rng(9)).as_matrix().reshape(3, 4, 5, 3, 3)
    v = matrix_to_rotvec(R)
    assert v.shape == (3, 4, 5, 3) and np.all(np.linalg.norm(v, axis=-1) <= np.pi + 1e-12)
    np.testing.assert_allclose(rotvec_to_matrix(v), R, atol=1e-12)
    q = matrix_to_quat(R)
    assert q.shape == (3, 4, 5, 4) and np.all(q[..., 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(3 * q), R, atol=1e-12)  # need not be unit
    theta = 0.7  # scalar first: (cos t/2, 0, 0, sin t/2) turns about +z
    np.testing.assert_allclose(quat_to_matrix([np.cos(theta / 2), 0, 0, np.sin(theta / 2)]),
                               _elementary("Z", np.degrees(theta)), atol=1e-15)
    assert rotvec_to_matrix(np.zeros((0, 3))).shape == (0, 3, 3)


def test_slerp_fill_recovers_constant_speed_rotation() -> None:
    F = 50
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    truth = rotvec_to_matrix(np.radians(3.0) * np.arange(F)[:, None] * axis)
    valid = np.ones(F, dtype=bool)
    valid[[0, 1, 2, 10, 20, 21, 22, 23, 24, 25, 26, 27, 48, 49]] = False
    R = truth.copy()
    R[~valid] = np.nan
    filled = slerp_fill(R, valid)
    np.testing.assert_array_equal(filled[valid], truth[valid])
    inner = ~valid & (np.arange(F) > 2) & (np.arange(F) < 48)
    np.testing.assert_allclose(filled[inner], truth[inner], atol=1e-12)
    np.testing.assert_allclose(filled[:3], np.broadcast_to(truth[3], (3, 3, 3)), atol=0)  # held
    np.testing.assert_allclose(filled[48:], np.broadcast_to(truth[47], (2, 3, 3)), atol=0)
    assert np.isnan(R[~valid]).all()  # the input is not modified
    with pytest.raises(ValueError, match="no valid frame"):
        slerp_fill(R, np.zeros(F, dtype=bool))


def test_slerp_fill_takes_the_short_way_round() -> None:
    a, b = np.eye(3), _elementary("Z", 300.0)  # 300 deg one way = 60 deg the other
    R = np.stack([a, np.full((3, 3), np.nan), b])
    mid = slerp_fill(R, np.array([True, False, True]))[1]
    np.testing.assert_allclose(mid, _elementary("Z", -30.0), atol=1e-12)


def _random_tracks(seed: int, F: int, S: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, F)[:, None, None]
    rv = rng.normal(0, 0.8, (1, S, 3)) + 0.8 * np.sin(2 * np.pi * rng.uniform(0.3, 1.5, (1, S, 3)) * t
                                                     + rng.uniform(0, 6.3, (1, S, 3)))
    return rotvec_to_matrix(rv)


def test_slerp_fill_joints_slerps_joint_angles_and_holds_them_at_the_ends() -> None:
    from scipy.spatial.transform import Slerp

    F, parent = 80, np.array([2, 0, -1, 1])  # a chain 2 -> 0 -> 1 -> 3, listed children first
    R = _random_tracks(3, F, 4)
    valid = np.ones((F, 4), dtype=bool)
    valid[:12, 1] = False  # the start
    valid[30:45, 1] = False  # the middle
    valid[:12, 3] = valid[25:50, 3] = False  # the child, over its parent's gaps
    valid[70:, 3] = False  # the end
    valid[5:9, 2] = False  # the root: slerped in the lab
    R_in = np.where(valid[..., None, None], R, np.nan)
    out = slerp_fill_joints(parent, R_in, valid)
    np.testing.assert_array_equal(out[valid], R[valid])
    assert np.isnan(R_in[~valid]).all()  # the input is not modified
    np.testing.assert_allclose(out[5:9, 2], slerp_fill(R_in[:, 2], valid[:, 2])[5:9], atol=1e-12)
    for s in (1, 3):  # the joint's rotation, as scipy slerps it between the valid frames, held at the ends
        p = parent[s]
        rel_true = np.swapaxes(R[:, p], -1, -2) @ R[:, s]  # parents are valid where s is
        key = np.flatnonzero(valid[:, s])
        want = Slerp(key, Rotation.from_matrix(rel_true[key]))(np.clip(np.arange(F), key[0], key[-1])).as_matrix()
        np.testing.assert_allclose(np.swapaxes(out[:, p], -1, -2) @ out[:, s], want, atol=1e-9)
    never = valid.copy()
    never[:, 3] = False
    o = slerp_fill_joints(parent, R, never)
    np.testing.assert_array_equal(o[:, 3], o[:, 1])  # its parent's
    with pytest.raises(ValueError, match="not a tree"):
        slerp_fill_joints(np.array([1, 0]), R[:, :2], valid[:, :2])


def test_hold_unobserved_fills_only_limbs_with_nothing_seen_below() -> None:
    F, parent = 60, np.array([-1, 0, 1, 0, 3])  # root; a chain 1 -> 2; a chain 3 -> 4
    R = _random_tracks(4, F, 5)
    seen = np.ones((F, 5), dtype=bool)
    seen[10:30, 1] = False  # held by its seen child: left as it is
    seen[20:40, 3:5] = False  # a whole limb: its joints keep their angles
    seen[:, 0] = False  # a root with no markers of its own: left as it is
    out = hold_unobserved(parent, R, seen)
    np.testing.assert_array_equal(out[:, :3], R[:, :3])
    np.testing.assert_array_equal(out[:20], R[:20])
    np.testing.assert_array_equal(out[40:], R[40:])
    gap = np.arange(20, 40)
    for s in (3, 4):
        rel = np.swapaxes(R[:, parent[s]], -1, -2) @ R[:, s]
        got = np.swapaxes(out[gap, parent[s]], -1, -2) @ out[gap, s]
        np.testing.assert_allclose(got, slerp_fill(np.where(seen[:, 3:4, None], rel, np.nan), seen[:, 3])[gap],
                                   atol=1e-12)
        assert not np.allclose(got, rel[gap], atol=1e-3)  # the track's own rotations there were not joint slerps


def test_project_to_so3() -> None:
    rng = np.random.default_rng(10)
    R = Rotation.random(100, random_state=rng).as_matrix()
    np.testing.assert_allclose(project_to_so3(R), R, atol=1e-12)
    noisy = R + 0.01 * rng.normal(size=R.shape)
    P = project_to_so3(noisy)
    np.testing.assert_allclose(np.swapaxes(P, -1, -2) @ P, np.broadcast_to(np.eye(3), P.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(P), 1, atol=1e-12)
    assert _angle_between(P, R).max() < 3.0
    # the polar factor: a rotation times a positive diagonal stretch gives the rotation back
    stretched = R @ np.diag([1.5, 0.7, 2.0])
    np.testing.assert_allclose(project_to_so3(stretched), R, atol=1e-12)
    # a reflection becomes a proper rotation; NaN stays NaN, shape kept
    refl = project_to_so3(np.diag([1.0, 1.0, -1.0]))
    np.testing.assert_allclose(np.linalg.det(refl), 1, atol=1e-12)
    batch = np.stack([R[:2], np.full((2, 3, 3), np.nan)])
    out = project_to_so3(batch)
    assert out.shape == (2, 2, 3, 3) and np.isnan(out[1]).all()
    np.testing.assert_allclose(out[0], R[:2], atol=1e-12)


def test_rotvec_and_quaternion_conversions_match_scipy() -> None:
    """Against an independent implementation (scipy's Rotation), small angles, half-turns and nearly orthonormal input included."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(21)
    axes = rng.normal(size=(400, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, 300), [0.0, 1e-12, 1e-7, 1e-4, 1e-3, 2e-3],
                             np.pi - np.array([0.0, 1e-12, 1e-8, 1e-5]), rng.uniform(0, 1e-2, 90)])
    v = axes * angles[:, None]
    ref = Rotation.from_rotvec(v)
    R = rotvec_to_matrix(v)
    np.testing.assert_allclose(R, ref.as_matrix(), atol=1e-14)
    q = matrix_to_quat(R)
    np.testing.assert_allclose(q, ref.as_quat(canonical=True, scalar_first=True), atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-14)
    back = matrix_to_rotvec(R)
    away = angles < np.pi - 1e-6  # at a half-turn v and -v are the same rotation
    np.testing.assert_allclose(back[away], v[away], atol=1e-12)
    np.testing.assert_allclose(rotvec_to_matrix(back), R, atol=1e-12)
    noisy = R + rng.normal(0, 1e-7, R.shape)  # nearly orthonormal
    np.testing.assert_allclose(matrix_to_rotvec(noisy)[away], Rotation.from_matrix(noisy).as_rotvec()[away], atol=1e-6)
    np.testing.assert_allclose(rotvec_to_matrix(matrix_to_rotvec(noisy)), Rotation.from_matrix(noisy).as_matrix(), atol=1e-6)


def test_fill_joint_slerps_the_joint_angle_of_the_whole_track():
    """A segment's gaps filled from the joint's rotation at the gaps' ends only are what slerping the joint's
    rotation over the whole track gives (the parent's rotation composed with it), and valid frames are kept."""
    from mocapskel.solvers.rotations import fill_joint, rotvec_to_matrix, slerp_fill

    rng = np.random.default_rng(8)
    F = 400
    parent = rotvec_to_matrix(np.cumsum(rng.normal(0, 0.05, (F, 3)), axis=0))
    rot = rotvec_to_matrix(np.cumsum(rng.normal(0, 0.05, (F, 3)), axis=0))
    valid = rng.random(F) > 0.3
    valid[:5] = False  # a leading gap, held
    valid[-3:] = False  # a trailing gap, held
    rel = slerp_fill(np.swapaxes(parent, -1, -2) @ rot, valid)
    expected = np.where(valid[:, None, None], rot, parent @ rel)
    got = fill_joint(parent, np.where(valid[:, None, None], rot, np.nan), valid)
    np.testing.assert_allclose(got, expected, atol=1e-12)
    np.testing.assert_array_equal(got[valid], rot[valid])
