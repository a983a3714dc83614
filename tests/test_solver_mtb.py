"""Marker-trajectory bases and the MTB joint (Hang 2015, §II-A)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapskel.solvers.joints.jmv import jmv_joint
from mocapskel.solvers.joints.cost import JointFit, balanced_alpha, joint_cost
from mocapskel.solvers.joints.mtb import Basis, mtb_basis, mtb_joint
from mocapskel.synth.chains import hang_chain, kirk_linkage


def groups(take):
    P, seg = take.markers.points, take.truth.marker_segment
    return [P[:, seg == s] for s in range(seg.max() + 1)]


def _rigid_dists(basis: np.ndarray, pts: np.ndarray) -> np.ndarray:
    both = np.concatenate([basis, pts], axis=1)
    return np.linalg.norm(both[:, :, None] - both[:, None], axis=-1)


@pytest.mark.parametrize("n", [3, 4, 5])
def test_basis_is_rigid_with_its_group(n):
    rng = np.random.default_rng(n)
    local = rng.normal(size=(n, 3)) * 0.3
    R = Rotation.random(100, random_state=rng).as_matrix()
    T = rng.normal(size=(100, 3))
    P = T[:, None] + np.einsum("fij,mj->fmi", R, local)
    b = mtb_basis(P)
    assert isinstance(b, Basis) and b and b.reason == "" and b.coverage == 1.0
    assert b.points.shape == (100, 4, 3)
    dd = _rigid_dists(b.points, P)
    np.testing.assert_allclose(dd, dd[:1].repeat(100, 0), atol=1e-12)
    # well conditioned: the three axes are orthogonal and of the group's size
    E = b.points[0, 1:] - b.points[0, 0]
    sv = np.linalg.svd(E, compute_uv=False)
    assert sv[2] / sv[0] > 0.99
    assert b.coplanar == (n == 3)


def test_basis_failures():
    rng = np.random.default_rng(0)
    F = 30
    two = rng.normal(size=(F, 2, 3))
    b = mtb_basis(two)
    assert not b and "2 point" in b.reason and not b.special and np.isnan(b.points).all()
    # collinear 4-marker group: Hang's special group, with its two characteristic markers
    t = np.array([0.0, 0.3, 1.0, 0.55])
    p0, p1 = rng.normal(size=(F, 3)), rng.normal(size=(F, 3))
    line = p0[:, None] + t[None, :, None] * (p1 - p0)[:, None]
    b = mtb_basis(line)
    assert not b and b.special and "collinear" in b.reason
    np.testing.assert_array_equal(b.pair, [0, 2])
    # never seen together
    g = rng.normal(size=(F, 3, 3))
    g[::2, 0] = np.nan
    g[1::2, 1] = np.nan
    assert not mtb_basis(g)


def test_basis_with_gaps_reproduces_the_full_basis():
    take = hang_chain([5, 3], 90, rng=np.random.default_rng(3))
    a = groups(take)[0]
    full = mtb_basis(a).points
    gappy = a.copy()
    gappy[10:20, 0] = np.nan
    gappy[30:40, 1:3] = np.nan
    gappy[50:55, 1:] = np.nan  # one marker left: no basis
    b = mtb_basis(gappy)
    assert b and b.coverage == pytest.approx(85 / 90)
    ok = np.isfinite(b.points).all((1, 2))
    assert not ok[50:55].any() and ok.sum() == 85
    np.testing.assert_allclose(b.points[ok], full[ok], atol=1e-12)


@pytest.mark.parametrize("counts", [[4, 3], [3, 3], [3, 1], [5, 2]])
def test_mtb_joint_exact_on_noise_free_data(counts):
    for seed in range(3):
        take = hang_chain(counts, 100, rng=np.random.default_rng(seed))
        a, b = groups(take)
        truth = take.truth.joints[:, 0]
        fit = mtb_joint(mtb_basis(a), a, b)
        assert isinstance(fit, JointFit) and fit.ok and fit.reason == ""
        assert np.abs(fit.centre - truth).max() < 1e-12
        assert fit.cost < 1e-25
        # the lambdas reproduce the joint from the basis
        B = mtb_basis(a).points
        lam = fit.params
        c = B[:, 0] + np.einsum("fki,k->fi", B[:, 1:] - B[:, :1], lam)
        np.testing.assert_allclose(c, fit.centre, atol=1e-12)
        if counts[1] >= 3:  # the other side's basis works as well
            fb = mtb_joint(mtb_basis(b), a, b)
            assert np.abs(fb.centre - truth).max() < 1e-12


def test_mtb_joint_minimises_q_with_noise():
    take = hang_chain([4, 3], 300, rng=np.random.default_rng(1), noise=0.003)
    a, b = groups(take)
    both = np.concatenate([a, b], 1)
    truth = take.truth.joints[:, 0]
    fit = mtb_joint(mtb_basis(a), a, b)
    assert fit.ok and fit.n_iter >= 1
    assert fit.cost == pytest.approx(joint_cost(fit.centre, both), rel=1e-10)
    B = mtb_basis(a).points
    # the lambdas closest to the true joint give a higher Q than the fit's
    E = np.swapaxes(B[:, 1:] - B[:, :1], 1, 2)  # (F, 3, 3)
    lam_true = np.linalg.lstsq(E.reshape(-1, 3), (truth - B[:, 0]).reshape(-1), rcond=None)[0]
    assert fit.cost <= joint_cost(B[:, 0] + E @ lam_true, both)
    err = np.sqrt(np.mean(np.sum((fit.centre - truth) ** 2, -1)))
    assert err < 0.02
    # a stationary point in lambda: nudging any lambda raises Q
    for k in range(3):
        for h in (-1e-4, 1e-4):
            lam = fit.params.copy()
            lam[k] += h
            c = B[:, 0] + np.einsum("fki,k->fi", B[:, 1:] - B[:, :1], lam)
            assert joint_cost(c, both) >= fit.cost - 1e-15
    # JMV's free per-frame positions can only reach a lower Q
    assert jmv_joint(a, b, init=fit.centre).cost <= fit.cost


def test_mtb_joint_hinge_is_reported_undetermined():
    rng = np.random.default_rng(2)
    F = 100
    la, lb = rng.normal(size=(3, 3)), rng.normal(size=(3, 3)) + [2.0, 0, 0]
    Ra = Rotation.random(F, random_state=rng).as_matrix()
    hinge = Rotation.from_rotvec(np.outer(np.sin(np.linspace(0, 6, F)), [0, 0, 1.2])).as_matrix()
    T = rng.normal(size=(F, 3))
    a = T[:, None] + np.einsum("fij,mj->fmi", Ra, la)
    b = T[:, None] + np.einsum("fij,mj->fmi", np.matmul(Ra, hinge), lb)
    fit = mtb_joint(mtb_basis(a), a, b)
    assert not fit and "hinge" in fit.reason
    # what comes back is still a point of the hinge axis (through T, along Ra z)
    rel = np.einsum("fji,fj->fi", Ra, fit.centre - T)
    np.testing.assert_allclose(rel[:, :2], 0.0, atol=1e-8)


def test_mtb_joint_alpha_and_nan_frames():
    take = hang_chain([4, 3], 100, rng=np.random.default_rng(6))
    a, b = groups(take)
    a = a.copy()
    a[5:8] = np.nan
    basis = mtb_basis(a)
    fit = mtb_joint(basis, a, b, alpha=0.02)
    assert fit.ok
    assert np.isnan(fit.centre[5:8]).all() and np.isfinite(fit.centre[8:]).all()
    both = np.concatenate([a, b], 1)
    alpha = balanced_alpha(0.02, a.shape[1], b.shape[1])  # each segment's share of the penalty half
    assert alpha[: a.shape[1]].sum() == pytest.approx(alpha[a.shape[1]:].sum())
    assert fit.cost == pytest.approx(joint_cost(fit.centre, both, alpha), rel=1e-10)
    assert fit.cost <= joint_cost(take.truth.joints[:, 0], both, alpha) + 1e-12
    with pytest.raises(ValueError):
        mtb_joint(basis.points[:, :3], a, b)


def test_kirk_linkage_middle_rod_from_mtb():
    take = kirk_linkage(1200, rng=np.random.default_rng(0), noise_mm=0.5)
    g = groups(take)
    j1 = mtb_joint(mtb_basis(g[1]), g[0], g[1]).centre
    j2 = mtb_joint(mtb_basis(g[1]), g[1], g[2]).centre
    length = np.linalg.norm(j2 - j1, axis=1).mean()
    assert abs(length / 341.0 - 1) < 0.003


def test_long_take_basis_is_rigid_and_joint_exact():
    """Thousands of frames (the basis points are built in pieces): still exact on noise-free data."""
    take = hang_chain((4, 3), 9000, rng=np.random.default_rng(11))
    A, B = groups(take)
    b = mtb_basis(A)
    assert b and b.coverage == 1.0
    dd = _rigid_dists(b.points, A)
    np.testing.assert_allclose(dd, dd[:1].repeat(len(A), 0), atol=1e-11)
    fit = mtb_joint(b, A, B, basis_side="a")
    assert fit.ok, fit.reason
    np.testing.assert_allclose(fit.centre, take.truth.joints[:, 0], atol=1e-9)


def test_unmasked_fast_paths_equal_the_masked_computation():
    """Every point seen: the unmasked sums give what the masked ones give (a never-seen point added)."""
    from mocapskel.solvers.joints import cost as jcost, mtb

    rng = np.random.default_rng(12)
    F = 400
    o = rng.normal(0, 100, (F, 3))
    E = Rotation.random(F, random_state=rng).as_matrix() * 50
    pts = o[:, None] + rng.normal(0, 300, (F, 5, 3)) + rng.normal(0, 1, (F, 5, 3))
    valid = np.ones((F, 5), bool)
    ghost = np.concatenate([pts, np.full((F, 1, 3), np.nan)], axis=1)
    gvalid = np.concatenate([valid, np.zeros((F, 1), bool)], axis=1)
    fast = mtb._linear_start(o, E, pts, valid)
    masked = mtb._linear_start(o, E, ghost, gvalid)
    for x, y in zip(fast, masked):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)
    c = o + rng.normal(0, 10, (F, 3))
    q, d, diff, n, dbar, used = jcost._cost_terms(c, pts, valid, 3.0)
    qm, dm, diffm, nm, dbarm, usedm = jcost._cost_terms(c, ghost, gvalid, 3.0)
    assert q == pytest.approx(qm, rel=1e-12)
    np.testing.assert_allclose(d, dm[:, :5], rtol=1e-14)
    np.testing.assert_allclose(dbar, dbarm[:5], rtol=1e-14)
    np.testing.assert_array_equal(n, nm[:5])
    assert used.all() and not usedm[5]
