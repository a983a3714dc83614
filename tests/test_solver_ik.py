"""Tests of the batched skeleton IK solver, on seeded synthetic skeletons with known motion."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from mocapskel.solvers.ik import planes as ik_planes
from mocapskel.solvers.ik import problem as ik_model
from mocapskel.solvers.ik import segment_poses as ik_segment_poses
from mocapskel.solvers.ik import solve as ik_solve
from mocapskel.solvers.ik.solve import solve_ik

# --------------------------------------------------------------------------- synthetic skeletons


def make_tree(rng: np.random.Generator, S: int, chain: bool, n_markers) -> tuple[np.ndarray, ...]:
    """A random tree: parent (S,), origin (S, 3), marker_segment (M,), marker_local (M, 3).

    ``n_markers(s, is_leaf, parent_count)`` gives the number of markers on
    segment s (``parent_count``: markers on its parent, 0 for the root).
    Markers sit along the bone towards a child (or a random direction for
    leaves) and 30-60 mm off its axis.
    """
    parent = np.full(S, -1)
    for s in range(1, S):
        parent[s] = s - 1 if chain else rng.integers(0, s)
    origin = np.zeros((S, 3))
    for s in range(1, S):
        d = rng.normal(size=3)
        origin[s] = origin[parent[s]] + d / np.linalg.norm(d) * rng.uniform(150, 400)
    seg, loc = [], []
    counts = np.zeros(S, dtype=int)
    for s in range(S):
        kids = np.flatnonzero(parent == s)
        axis = origin[rng.choice(kids)] - origin[s] if kids.size else rng.normal(0, 150, 3)
        counts[s] = n_markers(s, kids.size == 0, counts[parent[s]] if s else 0)
        for _ in range(counts[s]):
            off = rng.normal(size=3)
            off -= off @ axis / (axis @ axis) * axis
            off *= rng.uniform(30, 60) / np.linalg.norm(off)
            seg.append(s)
            loc.append(rng.uniform(0.2, 0.8) * axis + off)
    return parent, origin, np.array(seg), np.array(loc)


def make_motion(rng: np.random.Generator, F: int, S: int, amp: float = 0.7) -> tuple[np.ndarray, np.ndarray]:
    """Smooth global rotations (F, S, 3, 3) from smoothly varying rotation vectors, and a root path."""
    t = np.linspace(0, 1, F)[:, None, None]
    freq = rng.uniform(0.3, 1.5, size=(1, S, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(1, S, 3))
    rv = rng.normal(0, amp, size=(1, S, 3)) + amp * np.sin(2 * np.pi * freq * t + phase)
    R = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(F, S, 3, 3)
    tt = t[:, 0, 0]
    root = np.stack([400 * np.sin(2 * np.pi * 0.7 * tt), 300 * np.cos(2 * np.pi * tt), 1000 + 200 * tt], -1)
    return R, root


def forward(parent, origin, seg, loc, R, root) -> tuple[np.ndarray, np.ndarray]:
    """Segment origins (F, S, 3) and markers (F, M, 3) of a pose sequence."""
    F, S = R.shape[:2]
    P = np.zeros((F, S, 3))
    order = [int(np.flatnonzero(parent < 0)[0])]
    for s in order:
        order.extend(np.flatnonzero(parent == s).tolist())
    P[:, order[0]] = root
    for s in order[1:]:
        P[:, s] = P[:, parent[s]] + R[:, parent[s]] @ (origin[s] - origin[parent[s]])
    x = P[:, seg] + np.einsum("fmij,mj->fmi", R[:, seg], loc)
    return P, x


def angle(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    c = (np.einsum("...ij,...ij->...", Ra, Rb) - 1) / 2
    return np.arccos(np.clip(c, -1, 1))


def perturb(rng: np.random.Generator, R: np.ndarray, deg_lo: float, deg_hi: float) -> np.ndarray:
    axis = rng.normal(size=R.shape[:-2] + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    ang = np.radians(rng.uniform(deg_lo, deg_hi, size=R.shape[:-2]))
    return Rotation.from_rotvec((axis * ang[..., None]).reshape(-1, 3)).as_matrix().reshape(R.shape) @ R


# --------------------------------------------------------------------------- the linear algebra


def test_structured_step_matches_dense_normal_equations():
    rng = np.random.default_rng(0)
    S, F = 9, 15
    parent, origin, seg, loc = make_tree(rng, S, chain=False, n_markers=lambda s, leaf, pc: int(rng.integers(1, 5)))
    R, root = make_motion(rng, F, S)
    _, x = forward(parent, origin, seg, loc, R, root)
    tree = ik_model._Tree(parent)
    inv = np.argsort(tree.perm)
    model = ik_model._Model(tree, origin[tree.perm], inv[seg], loc)
    # kernels' layout: component planes, frames last
    Rs = np.ascontiguousarray(perturb(rng, R[:, tree.perm], 5, 30).transpose(2, 3, 1, 0))
    p = (root + rng.normal(0, 20, (F, 3))).T.copy()
    y, w = model.planes(x + rng.normal(0, 5, x.shape), rng.uniform(0.2, 2.0, x.shape[:2]) * (rng.random(x.shape[:2]) > 0.2))
    e = rng.normal(0, 0.1, (3, S, F))
    st = model.stats(y, w)
    c = model.cost(p, Rs, y, w)
    r = model.markers(p, Rs) - y
    np.testing.assert_allclose(c, np.einsum("ksf,kisf->f", w, r * r), rtol=1e-12)
    G, P = model.fk(p, Rs)
    a = ik_planes._c_mv(Rs, st["lbar"])
    d = P + a - st["ybar"]
    # the cost from the sums
    c_st = (st["c0"] + st["W"] * ik_planes._c_dot(d, d) - 2 * np.einsum("ijsf,ijsf->sf", Rs, st["Cc"])).sum(0)
    np.testing.assert_allclose(c_st, c, rtol=1e-10)
    H, g = ik_model._dense_system(model, p, Rs, y, w, e, 7.0)
    want = -np.linalg.solve(H, g[..., None])[..., 0]
    dp, dr, pred = model.step(Rs, G, a, d, st, e, 7.0, np.zeros(F), 0.0)
    got = np.concatenate([dp.T[:, None], dr.transpose(2, 1, 0)], 1).reshape(F, -1)
    np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(want).max())
    # the predicted decrease is that of the quadratic model
    np.testing.assert_allclose(pred, -(2 * np.einsum("fi,fi->f", g, got) + np.einsum("fi,fij,fj->f", got, H, got)))
    # also for a damped step (the model is the undamped one)
    dp, dr, pred = model.step(Rs, G, a, d, st, e, 7.0, rng.uniform(0, 3, F), 1e-3)
    got = np.concatenate([dp.T[:, None], dr.transpose(2, 1, 0)], 1).reshape(F, -1)
    np.testing.assert_allclose(pred, -(2 * np.einsum("fi,fi->f", g, got) + np.einsum("fi,fij,fj->f", got, H, got)))
    assert np.all(pred > 0)


def test_rotation_helpers():
    rng = np.random.default_rng(1)
    rv = rng.normal(size=(500, 3))
    rv *= (rng.uniform(0, np.pi - 1e-6, 500) / np.linalg.norm(rv, axis=1))[:, None]
    rv[:5] *= 1e-9  # tiny angles
    rv[5:10] *= (np.pi - 1e-9) / np.linalg.norm(rv[5:10], axis=1)[:, None]  # almost pi
    R = ik_planes._exp(rv)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(ik_planes._log(R), rv, atol=1e-7)
    np.testing.assert_allclose(ik_planes._log(R[10:]), rv[10:], atol=1e-10)
    np.testing.assert_allclose(ik_planes._quat_to_mat(ik_planes._mat_to_quat(R)), R, atol=1e-12)
    A = rng.normal(size=(50, 3, 3))
    np.testing.assert_allclose(ik_planes._inv3(A) @ A, np.broadcast_to(np.eye(3), A.shape), atol=1e-9)


# --------------------------------------------------------------------------- noise-free recovery


@pytest.mark.parametrize("seed", range(8))
def test_noise_free_recovery(seed):
    rng = np.random.default_rng(100 + seed)
    S = int(rng.integers(3, 16))
    chain = seed % 2 == 0

    def n_markers(s, leaf, parent_count):
        # the root needs 3 markers and leaves 2 to fix their twist; a segment with
        # fewer than 3 markers hangs between well-marked ones
        if s == 0:
            return int(rng.integers(3, 5))
        n = int(rng.integers(2 if leaf else 1, 5))
        return 3 if n < 3 and parent_count < 3 else n

    parent, origin, seg, loc = make_tree(rng, S, chain, n_markers)
    F = 60
    R, root = make_motion(rng, F, S)
    P, x = forward(parent, origin, seg, loc, R, root)
    for init in (None, perturb(rng, R, 10, 20)):
        res = solve_ik(parent, origin, seg, loc, x, init_rot=init, iterations=30)
        np.testing.assert_allclose(res.rot, R, atol=1e-6)
        np.testing.assert_allclose(res.root_pos, root, atol=1e-6)
        assert np.nanmax(res.residual) < 1e-6
        assert res.converged.all()


def test_one_and_two_marker_segments_between_well_marked_ones():
    rng = np.random.default_rng(7)
    parent = np.array([-1, 0, 1, 2, 3, 4])
    counts = [4, 1, 4, 2, 3, 1]
    _, origin, _, _ = make_tree(rng, 6, chain=True, n_markers=lambda s, leaf, pc: 0)
    seg = np.repeat(np.arange(6), counts)
    _, _, _, loc = make_tree(np.random.default_rng(7), 6, chain=True, n_markers=lambda s, leaf, pc: counts[s])
    # regenerate markers on the same origins
    loc = np.zeros((len(seg), 3))
    for s in range(6):
        axis = origin[s + 1] - origin[s] if s < 5 else np.array([0.0, 0, 120])
        for m in np.flatnonzero(seg == s):
            off = rng.normal(size=3)
            off -= off @ axis / (axis @ axis) * axis
            loc[m] = rng.uniform(0.2, 0.8) * axis + off / np.linalg.norm(off) * 40
    F = 80
    R, root = make_motion(rng, F, 6)
    P, x = forward(parent, origin, seg, loc, R, root)
    res = solve_ik(parent, origin, seg, loc, x, init_rot=perturb(rng, R, 10, 20), iterations=30)
    # segments 0-4 are determined (the 1-marker segment 1 by its two joints and its marker)
    np.testing.assert_allclose(res.rot[:, :5], R[:, :5], atol=1e-6)
    np.testing.assert_allclose(res.root_pos, root, atol=1e-6)
    # the 1-marker leaf: its marker fits, its twist about the marker direction is the prior's
    assert np.nanmax(res.residual) < 1e-6
    assert np.isfinite(res.rot).all()
    # from the data-driven start as well
    res2 = solve_ik(parent, origin, seg, loc, x, iterations=30)
    np.testing.assert_allclose(res2.rot[:, :5], R[:, :5], atol=1e-6)
    assert np.nanmax(res2.residual) < 1e-6


def test_parents_in_any_order():
    rng = np.random.default_rng(8)
    S = 7
    parent, origin, seg, loc = make_tree(rng, S, chain=False, n_markers=lambda s, leaf, pc: 3)
    F = 30
    R, root = make_motion(rng, F, S)
    _, x = forward(parent, origin, seg, loc, R, root)
    # relabel the segments so that children come before parents
    new = rng.permutation(S)  # old -> new
    parent2 = np.full(S, -1)
    parent2[new] = np.where(parent >= 0, new[np.maximum(parent, 0)], -1)
    origin2 = np.empty_like(origin)
    origin2[new] = origin
    res = solve_ik(parent2, origin2, new[seg], loc, x)
    np.testing.assert_allclose(res.rot[:, new], R, atol=1e-6)
    np.testing.assert_allclose(res.root_pos, root, atol=1e-6)


# --------------------------------------------------------------------------- noise and gaps


def humanoid(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """15 segments, 48 markers: pelvis, legs, torso, head, arms."""
    parent = np.array([-1, 0, 1, 2, 0, 4, 5, 0, 7, 7, 9, 10, 7, 12, 13])
    origin = np.array(
        [[0, 0, 1000], [100, 0, 950], [100, 0, 520], [100, 30, 80], [-100, 0, 950], [-100, 0, 520],
         [-100, 30, 80], [0, 0, 1100], [0, 0, 1500], [180, 0, 1450], [450, 0, 1450], [700, 0, 1450],
         [-180, 0, 1450], [-450, 0, 1450], [-700, 0, 1450]],
        dtype=float,
    )  # fmt: skip
    counts = [4, 3, 3, 3, 3, 3, 3, 4, 4, 3, 3, 3, 3, 3, 3]
    seg = np.repeat(np.arange(15), counts)
    loc = np.zeros((len(seg), 3))
    for s in range(15):
        kids = np.flatnonzero(parent == s)
        axis = origin[kids].mean(0) - origin[s] if kids.size else np.array([0.0, 120, -40])
        if np.linalg.norm(axis) < 1:  # the pelvis: children all around
            axis = np.array([0.0, 0, 100])
        for m in np.flatnonzero(seg == s):
            off = rng.normal(size=3)
            off -= off @ axis / (axis @ axis) * axis
            loc[m] = rng.uniform(0.1, 0.9) * axis + off / np.linalg.norm(off) * rng.uniform(40, 80)
    return parent, origin, seg, loc


def joint_error(res, parent, origin, seg, loc, P_true) -> np.ndarray:
    P, _ = forward(parent, origin, seg, loc, res.rot, res.root_pos)
    return np.linalg.norm(P - P_true, axis=-1)


def test_one_mm_noise_gives_joints_within_a_few_mm():
    rng = np.random.default_rng(9)
    parent, origin, seg, loc = humanoid(rng)
    F = 300
    R, root = make_motion(rng, F, 15, amp=0.5)
    P, x = forward(parent, origin, seg, loc, R, root)
    res = solve_ik(parent, origin, seg, loc, x + rng.normal(0, 1.0, x.shape))
    err = joint_error(res, parent, origin, seg, loc, P)
    assert np.sqrt(np.mean(err**2)) < 1.5
    assert err.max() < 6.0
    # residuals are about the noise (3 coordinates, a few dof fitted per marker)
    assert 0.8 < np.sqrt(np.nanmean(res.residual**2)) < 1.7
    assert res.converged.mean() > 0.95


def test_gaps_are_filled_smoothly_by_the_skeleton():
    rng = np.random.default_rng(10)
    parent, origin, seg, loc = humanoid(rng)
    F = 240
    R, root = make_motion(rng, F, 15, amp=0.5)
    P, x = forward(parent, origin, seg, loc, R, root)
    obs = x.copy()
    obs[rng.random(obs.shape[:2]) < 0.3] = np.nan
    gone = {2: (40, 60), 11: (100, 120), 7: (150, 170), 3: (200, 220)}  # shank, hand, torso, foot
    for s, (a, b) in gone.items():
        obs[a:b, seg == s] = np.nan
    res = solve_ik(parent, origin, seg, loc, obs, iterations=20)
    assert np.isfinite(res.rot).all() and np.isfinite(res.root_pos).all()
    err = joint_error(res, parent, origin, seg, loc, P)
    # noise-free: where the data determine the pose it is all but exact (the prior,
    # interpolated over the gaps, pulls a little where it is not the data's pose)
    assert np.median(err) < 1e-4
    assert np.percentile(err, 90) < 1e-2
    assert err.max() < 20.0
    # markers of the missing segments are predicted close to where they were
    xm = forward(parent, origin, seg, loc, res.rot, res.root_pos)[1]
    for s, (a, b) in gone.items():
        d = np.linalg.norm(xm[a:b, seg == s] - x[a:b, seg == s], axis=-1)
        assert d.max() < 20.0, (s, d.max())
    # smooth: no frame-to-frame jump much above the true motion's
    step = np.degrees(angle(res.rot[1:], res.rot[:-1]))
    true_step = np.degrees(angle(R[1:], R[:-1]))
    assert step.max() < 2 * true_step.max() + 1.0
    # residual is NaN exactly where a marker is unseen
    assert np.array_equal(np.isnan(res.residual), np.isnan(obs).any(-1))


def test_a_limb_hidden_while_the_body_turns_keeps_its_joint_angles():
    # the body turns by 150 degrees; the left arm's and the right foot's joints hold still, and these
    # limbs are hidden at the take's start and end: the solver carries them round with the body, so
    # their markers are predicted where they were (held in the lab, they would be 100s of mm off)
    rng = np.random.default_rng(13)
    parent, origin, seg, loc = humanoid(rng)
    F, S = 200, 15
    turn = Rotation.from_rotvec(np.outer(np.linspace(0, np.radians(150), F), [0, 0, 1])).as_matrix()
    t = np.linspace(0, 1, F)[:, None]
    still = {3, 10, 11}  # right foot; left forearm and hand
    rel = np.empty((F, S, 3, 3))
    for k in range(S):
        rv = rng.normal(0, 0.3, 3) + (0 if k in still else 0.3 * np.sin(2 * np.pi * rng.uniform(0.5, 1.5, 3) * t))
        rel[:, k] = Rotation.from_rotvec(np.broadcast_to(rv, (F, 3)).copy()).as_matrix()
    R = np.empty_like(rel)
    for k in range(S):  # parents come first in this tree's numbering
        R[:, k] = turn @ rel[:, k] if parent[k] < 0 else R[:, parent[k]] @ rel[:, k]
    root = np.stack([np.linspace(0, 800, F), np.zeros(F), np.full(F, 1000.0)], -1)
    P, x = forward(parent, origin, seg, loc, R, root)
    obs = x.copy()
    hidden = np.zeros(obs.shape[:2], dtype=bool)
    hidden[:60, np.isin(seg, [10, 11])] = True
    hidden[140:, seg == 3] = True
    obs[hidden] = np.nan
    res = solve_ik(parent, origin, seg, loc, obs, iterations=20)
    xm = forward(parent, origin, seg, loc, res.rot, res.root_pos)[1]
    err = np.linalg.norm(xm - x, axis=-1)
    assert err[hidden].max() < 1.0, err[hidden].max()
    assert err[~hidden].max() < 1e-3
    held = forward(parent, origin, seg, loc, np.where(hidden.any(1)[:, None, None, None], R[[60]], R), root)[1]
    assert np.linalg.norm(held - x, axis=-1)[hidden].max() > 100.0  # what holding them in the lab would miss by


def test_noise_and_gaps_together():
    rng = np.random.default_rng(11)
    parent, origin, seg, loc = humanoid(rng)
    F = 200
    R, root = make_motion(rng, F, 15, amp=0.5)
    P, x = forward(parent, origin, seg, loc, R, root)
    obs = x + rng.normal(0, 1.0, x.shape)
    obs[rng.random(obs.shape[:2]) < 0.3] = np.nan
    obs[50:70, seg == 10] = np.nan  # a forearm
    res = solve_ik(parent, origin, seg, loc, obs)
    err = joint_error(res, parent, origin, seg, loc, P)
    assert np.isfinite(err).all()
    assert np.sqrt(np.mean(err**2)) < 3.0
    assert err.max() < 30.0


def test_frames_without_any_marker_are_interpolated():
    rng = np.random.default_rng(12)
    parent, origin, seg, loc = make_tree(rng, 5, chain=False, n_markers=lambda s, leaf, pc: 3)
    F = 50
    R, root = make_motion(rng, F, 5, amp=0.3)
    P, x = forward(parent, origin, seg, loc, R, root)
    obs = x.copy()
    obs[:5] = np.nan  # at the start
    obs[20:25] = np.nan  # in the middle
    obs[-3:] = np.nan  # at the end
    res = solve_ik(parent, origin, seg, loc, obs)
    assert np.isfinite(res.rot).all() and np.isfinite(res.root_pos).all()
    np.testing.assert_allclose(res.root_pos[:5], np.broadcast_to(root[5], (5, 3)), atol=1e-6)
    np.testing.assert_allclose(res.root_pos[-3:], np.broadcast_to(root[-4], (3, 3)), atol=1e-6)
    lin = root[19] + (root[25] - root[19]) * (np.arange(20, 25) - 19)[:, None] / 6
    np.testing.assert_allclose(res.root_pos[20:25], lin, atol=1e-6)
    np.testing.assert_allclose(res.rot[6:19], R[6:19], atol=1e-6)
    assert np.isnan(res.residual[20:25]).all()


def test_nothing_seen_raises():
    parent, origin = np.array([-1, 0]), np.array([[0.0, 0, 0], [0, 0, 100]])
    seg, loc = np.array([0, 0, 1]), np.array([[10.0, 0, 0], [0, 10, 0], [0, 10, 50]])
    with pytest.raises(ValueError, match="nothing to solve"):
        solve_ik(parent, origin, seg, loc, np.full((4, 3, 3), np.nan))
    obs = np.zeros((4, 3, 3))
    with pytest.raises(ValueError, match="nothing to solve"):  # markers on no segment only
        solve_ik(parent, origin, np.array([-1, -1, -1]), loc, obs)


def test_unassigned_markers_are_ignored_and_unreported():
    rng = np.random.default_rng(13)
    parent, origin, seg, loc = make_tree(rng, 4, chain=True, n_markers=lambda s, leaf, pc: 3)
    F = 20
    R, root = make_motion(rng, F, 4)
    _, x = forward(parent, origin, seg, loc, R, root)
    junk = rng.normal(0, 1e4, (F, 2, 3))
    res = solve_ik(
        parent, origin, np.concatenate([seg, [-1, -1]]), np.concatenate([loc, np.zeros((2, 3))]),
        np.concatenate([x, junk], axis=1),
    )  # fmt: skip
    np.testing.assert_allclose(res.rot, R, atol=1e-6)
    assert res.residual.shape == (F, len(seg) + 2)
    assert np.isnan(res.residual[:, -2:]).all()


def test_weights_downweight_an_outlier_marker():
    rng = np.random.default_rng(14)
    parent, origin, seg, loc = make_tree(rng, 4, chain=True, n_markers=lambda s, leaf, pc: 4)
    F = 20
    R, root = make_motion(rng, F, 4)
    _, x = forward(parent, origin, seg, loc, R, root)
    obs = x.copy()
    obs[:, 5, 0] += 200.0
    w = np.ones(len(seg))
    w[5] = 0.0
    res = solve_ik(parent, origin, seg, loc, obs, weights=w)
    np.testing.assert_allclose(res.rot, R, atol=1e-6)
    np.testing.assert_allclose(res.residual[:, 5], 200.0, atol=1e-6)


def test_deterministic():
    rng = np.random.default_rng(15)
    parent, origin, seg, loc = humanoid(rng)
    R, root = make_motion(rng, 50, 15)
    _, x = forward(parent, origin, seg, loc, R, root)
    x = x + rng.normal(0, 1, x.shape)
    x[rng.random(x.shape[:2]) < 0.3] = np.nan
    a = solve_ik(parent, origin, seg, loc, x)
    b = solve_ik(parent, origin, seg, loc, x)
    assert np.array_equal(a.rot, b.rot) and np.array_equal(a.root_pos, b.root_pos)
    assert np.array_equal(a.residual, b.residual, equal_nan=True)


@pytest.mark.parametrize(
    "parent, message",
    [
        (np.array([-1, 0, -1]), "exactly one root"),
        (np.array([-1, 2, 1]), "not describe a tree"),
        (np.array([-1, 0, 5]), "parent indices"),
    ],
)
def test_bad_trees_are_rejected(parent, message):
    origin = np.zeros((3, 3))
    with pytest.raises(ValueError, match=message):
        solve_ik(parent, origin, np.array([0]), np.zeros((1, 3)), np.zeros((2, 1, 3)))


def test_bad_shapes_are_rejected():
    parent, origin = np.array([-1, 0]), np.array([[0.0, 0, 0], [0, 0, 100]])
    seg, loc = np.array([0, 1]), np.array([[10.0, 0, 0], [0, 10, 50]])
    with pytest.raises(ValueError, match="observed"):
        solve_ik(parent, origin, seg, loc, np.zeros((5, 3, 3)))
    with pytest.raises(ValueError, match="init_rot"):
        solve_ik(parent, origin, seg, loc, np.zeros((5, 2, 3)), init_rot=np.zeros((5, 3, 3, 3)))
    with pytest.raises(ValueError, match="marker_segment"):
        solve_ik(parent, origin, np.array([0, 2]), loc, np.zeros((5, 2, 3)))


def test_single_segment_single_frame_and_markerless_segment():
    rng = np.random.default_rng(16)
    parent, origin = np.array([-1]), np.zeros((1, 3))
    seg, loc = np.zeros(4, int), rng.normal(0, 50, (4, 3))
    R, root = make_motion(rng, 10, 1)
    _, x = forward(parent, origin, seg, loc, R, root)
    res = solve_ik(parent, origin, seg, loc, x)
    np.testing.assert_allclose(res.rot, R, atol=1e-9)
    np.testing.assert_allclose(res.root_pos, root, atol=1e-9)
    res = solve_ik(parent, origin, seg, loc, x[:1])
    np.testing.assert_allclose(res.rot, R[:1], atol=1e-9)
    # a segment without markers, placed by its parent and its two children
    parent = np.array([-1, 0, 1, 1])
    origin = np.array([[0.0, 0, 0], [0, 0, 200], [100, 0, 400], [-100, 50, 380]])
    seg, loc = np.array([0, 0, 0, 2, 2, 2, 3, 3, 3]), rng.normal(0, 50, (9, 3))
    R, root = make_motion(rng, 30, 4)
    _, x = forward(parent, origin, seg, loc, R, root)
    res = solve_ik(parent, origin, seg, loc, x)
    np.testing.assert_allclose(res.rot, R, atol=1e-6)


# --------------------------------------------------------------------------- active set, blocks, output


def test_frames_leave_when_converged_with_the_answer_of_running_them_all():
    rng = np.random.default_rng(17)
    parent, origin, seg, loc = humanoid(rng)
    F = 400
    R, root = make_motion(rng, F, 15, amp=0.5)
    P, x = forward(parent, origin, seg, loc, R, root)
    obs = x + rng.normal(0, 1.0, x.shape)
    obs[rng.random(obs.shape[:2]) < 0.2] = np.nan
    # tol 0: every frame iterates until the linear model can no longer lower its cost
    full = solve_ik(parent, origin, seg, loc, obs, iterations=20, tol=0.0)
    assert full.converged.all() and full.n_iter >= 8
    early = solve_ik(parent, origin, seg, loc, obs, iterations=20, tol=0.1)
    assert early.converged.all() and early.n_iter <= 5
    # the frames that left early are where running them all puts them
    d = joint_error(early, parent, origin, seg, loc, forward(parent, origin, seg, loc, full.rot, full.root_pos)[0])
    assert d.max() < 0.05 and np.sqrt(np.mean(d**2)) < 5e-3
    # and as good against the truth
    e_full = joint_error(full, parent, origin, seg, loc, P)
    e_early = joint_error(early, parent, origin, seg, loc, P)
    assert abs(np.sqrt(np.mean(e_early**2)) - np.sqrt(np.mean(e_full**2))) < 1e-3
    np.testing.assert_allclose(np.nanmax(np.abs(early.residual - full.residual)), 0.0, atol=0.05)
    # a tight tolerance converges to the same solution
    tight = solve_ik(parent, origin, seg, loc, obs, iterations=30)
    np.testing.assert_allclose(tight.rot, full.rot, atol=1e-6)


def test_blocks_and_output_array_do_not_change_the_answer(monkeypatch):
    rng = np.random.default_rng(18)
    parent, origin, seg, loc = humanoid(rng)
    F = 300
    R, root = make_motion(rng, F, 15, amp=0.5)
    _, x = forward(parent, origin, seg, loc, R, root)
    obs = x + rng.normal(0, 1.0, x.shape)
    prior = perturb(rng, R, 0.5, 2)
    one = solve_ik(parent, origin, seg, loc, obs, prior_rot=prior, init_root=root)
    monkeypatch.setattr(ik_solve, "_BLOCK", 64)  # several blocks, the last one short
    many = solve_ik(parent, origin, seg, loc, obs, prior_rot=prior, init_root=root)
    np.testing.assert_array_equal(many.rot, one.rot)
    np.testing.assert_array_equal(many.root_pos, one.root_pos)
    # written over the prior itself, which is read before it is overwritten
    out = prior.copy()
    res = solve_ik(parent, origin, seg, loc, obs, prior_rot=out, init_root=root, out=out)
    assert res.rot is out
    np.testing.assert_array_equal(res.rot, one.rot)
    with pytest.raises(ValueError, match="out"):
        solve_ik(parent, origin, seg, loc, obs, out=np.empty((F, 14, 3, 3)))
    # blocks solved on several threads: the same answer, bit for bit
    monkeypatch.setenv("MOCAPSKEL_THREADS", "3")
    threaded = solve_ik(parent, origin, seg, loc, obs, prior_rot=prior, init_root=root)
    np.testing.assert_array_equal(threaded.rot, one.rot)
    np.testing.assert_array_equal(threaded.residual, one.residual)
    np.testing.assert_array_equal(threaded.converged, one.converged)
    monkeypatch.setattr(ik_segment_poses, "_POSE_BLOCK", 64)
    shapes = [origin[s] + loc[seg == s] for s in range(len(parent))]
    cols = [np.flatnonzero(seg == s) for s in range(len(parent))]
    Rt, tt = ik_segment_poses.segment_poses(shapes, cols, [obs])
    monkeypatch.setenv("MOCAPSKEL_THREADS", "1")
    Rs, ts = ik_segment_poses.segment_poses(shapes, cols, [obs])
    np.testing.assert_array_equal(Rt, Rs)
    np.testing.assert_array_equal(tt, ts)


# --------------------------------------------------------------------------- per-segment rigid poses


def test_segment_poses_match_kabsch():
    from mocapskel.solvers.rigid import kabsch

    rng = np.random.default_rng(19)
    F, Q = 500, 40
    shapes, columns = [], []
    for P in (3, 4, 7, 5, 60):  # the last one is handed to kabsch whole
        cols = rng.choice(Q, size=min(P, Q), replace=False)
        shapes.append(rng.normal(0, 80, (len(cols), 3)))
        columns.append(cols)
    shapes[1][3] = shapes[1][0] + 2 * (shapes[1][1] - shapes[1][0])  # collinear with points 0 and 1
    shapes[2][2] = np.nan  # a reference point left out
    rot = Rotation.random(F, random_state=rng).as_matrix()  # turns of any size
    pts = np.full((F, Q, 3), np.nan)
    for ref, cols in zip(shapes, columns):
        seen = np.isfinite(ref).all(1)
        pts[:, cols[seen]] = np.einsum("fij,pj->fpi", rot, ref[seen]) + rng.normal(0, 500, (F, 1, 3))
    pts += rng.normal(0, 1.0, pts.shape)
    pts[rng.random((F, Q)) < 0.3] = np.nan
    pts[:5, columns[1][2]] = np.nan  # only collinear points (0, 1, 3) of shape 1 left in some frames
    pts[:5, columns[1][1:3]] = np.nan
    R, t = ik_segment_poses.segment_poses(shapes, columns, [pts[:, :25], pts[:, 25:]])  # two arrays side by side
    for b, (ref, cols) in enumerate(zip(shapes, columns)):
        Rk, tk, _ = kabsch(ref, pts[:, cols])
        np.testing.assert_array_equal(np.isnan(R[:, b, 0, 0]), np.isnan(Rk[:, 0, 0]))
        np.testing.assert_allclose(R[:, b], Rk, atol=1e-10)
        np.testing.assert_allclose(t[:, b], tk, atol=1e-7)
    assert np.isnan(R[:5, 1]).all() and np.isfinite(R[:, 0]).any()




@pytest.mark.parametrize("seed", range(4))
def test_tolerance_bounds_what_the_pose_still_moves(seed):
    """With tol = 0.1 mm (the IK stage's), every marker and joint of the solved poses lies within 0.1 mm
    of where the fully converged solution puts it, from a start a few degrees off, with 1 mm noise."""
    rng = np.random.default_rng(300 + seed)
    S = int(rng.integers(6, 16))

    def n_markers(s, leaf, parent_count):
        return int(rng.integers(3, 5)) if s == 0 else int(rng.integers(2, 5))

    parent, origin, seg, loc = make_tree(rng, S, seed % 2 == 0, n_markers)
    F = 400
    R, root = make_motion(rng, F, S)
    _, x = forward(parent, origin, seg, loc, R, root)
    x = x + rng.normal(0.0, 1.0, x.shape)
    start = perturb(rng, R, 2, 6)
    loose = solve_ik(parent, origin, seg, loc, x, init_rot=start, tol=0.1)
    tight = solve_ik(parent, origin, seg, loc, x, init_rot=start, tol=1e-9, iterations=50)
    assert tight.converged.all() and loose.converged.all()
    Pa, xa = forward(parent, origin, seg, loc, loose.rot, loose.root_pos)
    Pb, xb = forward(parent, origin, seg, loc, tight.rot, tight.root_pos)
    assert np.linalg.norm(xa - xb, axis=-1).max() < 0.1
    assert np.linalg.norm(Pa - Pb, axis=-1).max() < 0.1
    assert loose.n_iter < tight.n_iter
