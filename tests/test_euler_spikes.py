"""Euler spikes: BVH rotation channels that step by more than the joint turns plus 5 degrees."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.io.bvh import write_bvh
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.markers import write_markers
from mocapskel.errors import DataError
from mocapskel.solvers.bvh_pose import (BvhSkeleton, bvh_to_lab, choose_rest_and_order, choose_rotation_order,
                                        forward_kinematics, local_to_global_rot, rerest_local)
from mocapskel.solvers.euler_continuity import (RestSteps, channel_steps, euler_spikes, order_spike_counts,
                                                rotation_steps, step_spike_counts)
from mocapskel.solvers.rotations import ORDERS, euler_to_matrix, matrix_to_quat, rotvec_to_matrix
from mocapskel.stages import export
from mocapskel.synth.presets import active_rom, make, passive_rom


def _channels(path: Path) -> np.ndarray:
    """(F, S, 3) rotation channel values of a BVH file, joints in file order."""
    text = path.read_text().splitlines()
    k = next(i for i, l in enumerate(text) if l.startswith("Frame Time"))
    vals = np.loadtxt(text[k + 1 :], ndmin=2)
    cols, c = [], 0
    for l in text[:k]:
        t = l.split()
        if t[:1] == ["CHANNELS"]:
            cols.append([c + i for i, n in enumerate(t[2:]) if n.endswith("rotation")])
            c += len(t) - 2
    return np.stack([vals[:, r] for r in cols], axis=1)


def _file_spikes(path: Path) -> int:
    """Spikes of a BVH file, from its own channels and the rotations they mean."""
    _, _, local, _ = read_bvh(path)
    return int(euler_spikes(_channels(path), local).sum())


def _chain(S: int, order: str) -> BvhSkeleton:
    parent = np.arange(S) - 1
    off = np.tile([0.0, 10.0, 0.0], (S, 1))
    off[0] = 0.0
    return BvhSkeleton(tuple(f"j{s}" for s in range(S)), parent, off, np.tile([0.0, 5.0, 0.0], (S, 1)), order)


def _write(path: Path, R: np.ndarray, order: str) -> Path:
    write_bvh(path, _chain(R.shape[1], order), np.zeros((R.shape[0], 3)), R, 1 / 120)
    return path


# --------------------------------------------------------------------------- the measure


def test_rotation_steps_are_the_turn_between_frames() -> None:
    rng = np.random.default_rng(3)
    F = 400
    theta = np.degrees(np.exp(rng.uniform(np.log(1e-5), np.log(3.0), F - 1)))  # 1e-5 .. 170 degrees
    axis = rng.normal(size=(F - 1, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    R = np.empty((F, 3, 3))
    R[0] = rotvec_to_matrix(rng.normal(size=3))
    step = rotvec_to_matrix(np.radians(theta)[:, None] * axis)
    for f in range(F - 1):
        R[f + 1] = R[f] @ step[f]
    np.testing.assert_allclose(rotation_steps(R), theta, atol=1e-6)
    # against the quaternion angle, 2 acos |<q0, q1>|
    q = matrix_to_quat(R)
    ref = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(q[1:] * q[:-1], axis=1)), 0, 1)))
    np.testing.assert_allclose(rotation_steps(R)[theta > 1.0], ref[theta > 1.0], atol=1e-6)


def test_channel_steps_count_no_whole_turn() -> None:
    a = np.array([[10.0, 0.0, 0.0], [370.0, 5.0, 0.0], [20.0, 5.0, -350.0], [20.0, 5.0, 190.0]])
    np.testing.assert_allclose(channel_steps(a), [5.0, 10.0, 180.0])


def test_a_sweep_around_zxy_lock_spikes_in_zxy_and_not_in_the_chosen_order(tmp_path: Path) -> None:
    """Rz(p) Rx(89.8) Ry(-p): p sweeps 60 degrees in 4 frames while the joint turns under 0.1 degree a frame."""
    F = 300
    f = np.arange(F)
    p = 60.0 * np.clip((f - 100) / 4.0, 0.0, 1.0)
    R = euler_to_matrix(np.stack([p, np.full(F, 89.8), -p], axis=1), "ZXY")[:, None]
    assert _file_spikes(_write(tmp_path / "zxy.bvh", R, "ZXY")) == 4
    order = choose_rotation_order(R)
    assert order != "ZXY" and _file_spikes(_write(tmp_path / "auto.bvh", R, order)) == 0


# --------------------------------------------------------------------------- through gimbal lock


def _through_lock(F: int = 240) -> np.ndarray:
    """(F, 3, 3, 3) in ZXY, joints: (0) the middle angle crosses 90 degrees (80 -> 100) while the outer ones
    drift; (1) held at the lock while it twists about the locked axis (a + c changes, a - c does not
    matter); (2) the middle angle comes to 90 and goes back (80 -> 90 -> 80) with the outer angles
    turning."""
    t = np.linspace(0.0, 1.0, F)
    drift = 20.0 * np.sin(2 * np.pi * t)
    ang = np.empty((F, 3, 3))
    ang[:, 0] = np.stack([drift, 80.0 + 20.0 * t, 0.5 * drift], axis=1)
    ang[:, 1] = np.stack([40.0 * t, np.full(F, 90.0), 30.0 * t], axis=1)
    ang[:, 2] = np.stack([drift, 90.0 - 10.0 * np.abs(2 * t - 1), -drift], axis=1)
    return euler_to_matrix(ang, "ZXY")


def test_sequences_through_gimbal_lock_are_written_without_spikes(tmp_path: Path) -> None:
    R = _through_lock()
    path = _write(tmp_path / "lock.bvh", R, "ZXY")
    ang = _channels(path)
    _, _, back, _ = read_bvh(path)
    assert not euler_spikes(ang, back).any()
    np.testing.assert_allclose(back, R, atol=1e-7)  # the same rotations, to the file's 6 decimals
    assert np.abs(channel_steps(ang)).max() < rotation_steps(R).max() + 1.0


def test_predicted_spikes_are_those_of_the_written_file(tmp_path: Path) -> None:
    """order_spike_counts (which decomposes only the steps its Euler-rate bound cannot clear) against
    every order's file, read back and measured step by step."""
    rng = np.random.default_rng(11)
    F, S = 600, 5
    w = np.cumsum(rng.normal(scale=0.04, size=(F, S, 3)), axis=0)  # a random walk of rotation vectors
    R = rotvec_to_matrix(w)
    # joints near lock in three orders, moving about it
    for s, order in ((1, "ZXY"), (2, "YXZ"), (3, "XZY")):
        p = 30.0 * np.sin(np.linspace(0, 6 * np.pi, F)) + rng.normal(scale=1.0, size=F)
        R[:, s] = euler_to_matrix(np.stack([p, 86.0 + 2.0 * np.sin(np.linspace(0, 9, F)), -p], axis=1), order)
    pred = order_spike_counts(R)
    got = [_file_spikes(_write(tmp_path / f"{o}.bvh", R, o)) for o in ORDERS]
    assert pred.tolist() == got
    assert min(got) < max(got)  # the orders differ: the choice matters
    assert pred[ORDERS.index(choose_rotation_order(R))] == min(got)


# --------------------------------------------------------------------------- generated ROM takes


@pytest.fixture(scope="module")
def roms(tmp_path_factory) -> dict:
    """Short generated ROM takes (seed 2, 10 s) that spike in most orders, active and passive, fitted."""
    d = tmp_path_factory.mktemp("roms")
    out = {}
    for kind, recipe in (("active", active_rom), ("passive", passive_rom)):
        take = make(recipe(seed=2, frames=1200))
        p = d / f"{kind}.c3d"
        write_markers(p, replace(take.markers, source=p.name))
        out[kind] = pipeline.fit(p, pipeline.make_params())
    return out


@pytest.mark.parametrize("up", ["y", "z"])
@pytest.mark.parametrize("kind", ["active", "passive"])
def test_rom_bvh_has_the_fewest_spikes_of_any_order_and_keeps_the_motion(roms, tmp_path: Path, kind: str,
                                                                         up: str) -> None:
    res = roms[kind]
    b = export.run(res.motion, export.Params(up=up))
    counts = {}
    for order in ORDERS:
        p = tmp_path / f"{order}.bvh"
        write_bvh(p, replace(b.skeleton, order=order), b.root_pos, b.local_rot, b.frame_time)
        counts[order] = _file_spikes(p)
    assert max(counts.values()) > 0  # the take does spike somewhere: the check can fail
    assert counts[b.skeleton.order] == min(counts.values()), counts
    # the chosen order's file still puts every joint where the fit does
    path = tmp_path / "auto.bvh"
    write_bvh(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    skel, root, local, _ = read_bvh(path)
    got = bvh_to_lab(forward_kinematics(skel, root, local), up, b.units)
    np.testing.assert_allclose(got, export.joint_positions_lab(res.motion, b), atol=1e-3)  # mm


# --------------------------------------------------------------------------- the rest frame


def _random_take(locks: tuple[str, ...] = ("ZXY", "YXZ"), F: int = 500, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(local, parent): a chain whose joints random-walk, one more joint moving about each order's lock of
    ``locks`` (outer angles swinging +-40 degrees, the middle one at 82-88 degrees)."""
    rng = np.random.default_rng(seed)
    S = 3 + len(locks)
    R = rotvec_to_matrix(np.cumsum(rng.normal(scale=0.05, size=(F, S, 3)), axis=0))
    for s, order in enumerate(locks, 1):
        p = 40.0 * np.sin(np.linspace(0, 5 * np.pi, F) + s) + rng.normal(scale=1.0, size=F)
        R[:, s] = euler_to_matrix(np.stack([p, 85.0 + 3.0 * np.sin(np.linspace(0, 7, F)), -p], axis=1), order)
    return R, np.arange(S) - 1


def test_spikes_under_other_rests_are_those_of_the_re_posed_motion() -> None:
    """RestSteps counts from one matrix entry per order; against each rest's motion re-posed in full."""
    L, parent = _random_take()
    rests = np.array([0, 77, 250, 499])
    Q = local_to_global_rot(parent, L[rests])
    got, near = RestSteps(L, parent).count(Q)
    want = np.array([order_spike_counts(rerest_local(parent, L, q)) for q in Q])
    np.testing.assert_array_equal(got, want)
    assert want.min() < want.max() and want.max() > 0  # the rests differ: the choice matters
    assert (near >= got).all()
    # the re-posed motion: frame r's pose is the rest (every rotation the identity there), the turns unchanged
    for r, q in zip(rests, Q):
        Lr = rerest_local(parent, L, q)
        np.testing.assert_allclose(Lr[r], np.broadcast_to(np.eye(3), Lr[r].shape), atol=1e-12)
        np.testing.assert_allclose(rotation_steps(Lr), rotation_steps(L), atol=1e-6)
    # a subset of the steps: as the pairs counted on their own
    steps = np.arange(0, L.shape[0] - 1, 3)
    sub, _ = RestSteps(L, parent, steps).count(Q[1:2])
    Lr = rerest_local(parent, L, Q[1])
    np.testing.assert_array_equal(sub[0], step_spike_counts(Lr[steps], Lr[steps + 1]))


def test_the_rest_chosen_with_the_order_writes_no_spike(tmp_path: Path) -> None:
    L, parent = _random_take(ORDERS, seed=0)
    keep = 0
    assert order_spike_counts(L).min() > 0  # the motion's own rest spikes in every order
    r, order = choose_rest_and_order(L, parent, np.arange(L.shape[0]), keep)
    assert r != keep
    Lr = rerest_local(parent, L, local_to_global_rot(parent, L[r : r + 1])[0])
    assert _file_spikes(_write(tmp_path / "r.bvh", Lr, order)) == 0
    # without spikes at its own rest, the rest stays and the order is choose_rotation_order's
    calm = rotvec_to_matrix(np.cumsum(np.full((300, 3, 3), 0.002), axis=0))
    assert choose_rest_and_order(calm, np.arange(3) - 1, np.arange(300), 7) == (7, choose_rotation_order(calm))


def _rest_channels_zero(path: Path, frame: int) -> None:
    ang = _channels(path)
    assert np.abs(((ang[frame] + 180.0) % 360.0) - 180.0).max() < 1e-4


@pytest.mark.parametrize("up", ["y", "z"])
@pytest.mark.parametrize("kind", ["active", "passive"])
def test_rom_bvh_written_by_default_has_no_spike(roms, tmp_path: Path, kind: str, up: str) -> None:
    """The default BVH of a generated ROM take: no Euler spike, every joint where the fit puts it, all
    channels zero at the rest frame; with the skeleton's rest frame kept (the previous choice) it spikes."""
    res = roms[kind]
    b = export.run(res.motion, export.Params(up=up))
    path = write_bvh_of(tmp_path / "auto.bvh", b)
    assert _file_spikes(path) == 0
    skel, root, local, _ = read_bvh(path)
    got = bvh_to_lab(forward_kinematics(skel, root, local), up, b.units)
    np.testing.assert_allclose(got, export.joint_positions_lab(res.motion, b), atol=1e-3)  # mm
    assert b.rest_frame in export.rest_candidates(res.motion).tolist() + [res.motion.skeleton.rest_frame]
    _rest_channels_zero(path, b.rest_frame)
    assert res.report["rest_frame"] == res.bvh.rest_frame
    old = export.run(res.motion, export.Params(up=up, rest_frame="skeleton"))
    assert _file_spikes(write_bvh_of(tmp_path / "old.bvh", old)) > 0


def write_bvh_of(path: Path, b) -> Path:
    write_bvh(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    return path


def test_a_rest_frame_given_is_the_rest(roms, tmp_path: Path) -> None:
    motion = roms["active"].motion
    F = motion.rot.shape[0]
    keep = motion.skeleton.rest_frame
    base = export.run(motion, export.Params(rest_frame="skeleton"))
    same = export.run(motion, export.Params(rest_frame=keep))
    np.testing.assert_array_equal(same.skeleton.offset, base.skeleton.offset)
    np.testing.assert_array_equal(same.local_rot, base.local_rot)
    N = (keep + F // 2) % F
    b = export.run(motion, export.Params(rest_frame=N, order="ZXY"))
    assert b.rest_frame == N and b.skeleton.order == "ZXY" and b.report()["rest_frame"] == N
    path = write_bvh_of(tmp_path / "n.bvh", b)
    _rest_channels_zero(path, N)
    skel, root, local, _ = read_bvh(path)
    np.testing.assert_allclose(bvh_to_lab(forward_kinematics(skel, root, local), "y", b.units),
                               export.joint_positions_lab(motion, b), atol=1e-3)
    # bone lengths are the skeleton's whatever the rest
    np.testing.assert_allclose(np.linalg.norm(b.skeleton.offset, axis=1), np.linalg.norm(base.skeleton.offset, axis=1),
                               atol=1e-9)
    with pytest.raises(DataError, match="outside the take"):
        export.run(motion, export.Params(rest_frame=F))
