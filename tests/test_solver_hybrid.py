"""Hang's hybrid framework: MTB, solvability propagation, reduced JMV (Hang 2015, §II-B, §III)."""
from __future__ import annotations

import numpy as np
import pytest

from mocapskel.solvers.joints.hybrid import TreeJoints, solve_tree
from mocapskel.synth.chains import hang_chain, hang_tree, kirk_linkage


def rse(est: np.ndarray, truth: np.ndarray) -> float:
    """Hang (10): sqrt(sum of squared joint errors) / (joints x frames)."""
    F, M, _ = truth.shape
    return float(np.sqrt(np.sum((est - truth) ** 2)) / (M * F))


def solve(take, **kw) -> TreeJoints:
    P, t = take.markers.points, take.truth
    gs = [P[:, t.marker_segment == s] for s in range(len(t.segment_names))]
    edges = np.stack([t.parent[t.joint_child], t.joint_child], axis=1)
    return solve_tree(gs, edges, **kw)


def mean_rse(counts, seeds=range(3), n_frames=100, **kw) -> tuple[float, TreeJoints]:
    out = []
    for seed in seeds:
        take = hang_chain(counts, n_frames, rng=np.random.default_rng(seed))
        tj = solve(take, **kw)
        out.append(rse(tj.centres, take.truth.joints))
    return float(np.mean(out)), tj


@pytest.mark.parametrize("counts,hang", [([4, 3, 3], 3.9e-7), ([4, 3, 3, 4, 3], 2.9e-7)])
def test_noise_free_chains_by_mtb(counts, hang):
    err, tj = mean_rse(counts)
    assert err < 1e-12 and err < hang
    assert set(tj.method) == {"mtb"}
    assert tj.ok.all() and np.isfinite(tj.cost).all()
    assert tj.log[0]["stage"] == "pre"


def test_chain4_by_propagation():
    err, tj = mean_rse([3, 2, 2, 2, 2])
    assert err < 1e-9  # Hang: 1.5e-6
    assert tj.method == ("mtb", "mtb-propagated", "mtb-propagated", "mtb-propagated")
    np.testing.assert_array_equal(tj.order, [0, 1, 2, 3])
    assert tj.category == ("3", "2", "2", "2", "2")
    assert [e["stage"] for e in tj.log] == ["pre", "propagate", "propagate", "propagate"]
    assert tj.log[-1]["joint_state"] == "1111" and tj.log[-1]["waiting"] == []


def test_chain5_hybrid_with_one_jmv():
    err, tj = mean_rse([3, 1, 2, 2, 2, 2])
    assert err < 1e-9  # brief: 1e-3; Hang: 2.8e-2
    assert tj.method == ("mtb", "jmv", "mtb-propagated", "mtb-propagated", "mtb-propagated")
    stages = [e["stage"] for e in tj.log]
    assert stages[:2] == ["pre", "jmv"] and set(stages[2:]) == {"propagate"}
    assert tj.log[1]["joint_state"] == "11000"
    np.testing.assert_array_equal(tj.basis_group[1], -1)


def test_two_marker_chain_needs_one_jmv_only():
    err, tj = mean_rse([1, 2, 2, 1], n_frames=150)
    assert err < 1e-9
    assert tj.method.count("jmv") == 1


def test_special_group_is_solved_through_a_joint():
    # <3 - S3 - 2>: the middle group's three markers are collinear; with the
    # joint solved from the first group it gets a basis and solves the last joint.
    take = hang_chain([3, 4, 2], 100, rng=np.random.default_rng(5))
    P, t = take.markers.points.copy(), take.truth
    mid = np.flatnonzero(t.marker_segment == 1)
    p, q = P[:, mid[0]].copy(), P[:, mid[1]].copy()
    for k, s in zip(mid[1:], (0.5, 1.0, 1.7)):
        P[:, k] = p + s * (q - p)  # rigid with the segment, all on one line
    gs = [P[:, t.marker_segment == s] for s in range(3)]
    tj = solve_tree(gs, [[0, 1], [1, 2]])
    assert tj.special.tolist() == [False, True, False]
    assert tj.category == ("3", "special-4", "2")
    assert tj.method == ("mtb", "mtb-propagated")
    assert np.abs(tj.centres - t.joints).max() < 1e-9


def test_one_marker_group_with_two_solved_joints():
    # segment 1 has one marker and joints to segments 0, 2 (3 markers each) and 3 (2 markers)
    take = hang_tree([-1, 0, 1, 1], [3, 1, 3, 2], 100, rng=np.random.default_rng(4))
    tj = solve(take)
    assert tj.method == ("mtb", "mtb", "mtb-propagated")
    assert tj.category == ("3", "1", "3", "2")
    assert np.abs(tj.centres - take.truth.joints).max() < 1e-9


def test_underdetermined_joint_is_reported():
    # <1-1>: two points in all can never place a joint
    take = hang_chain([1, 1], 50, rng=np.random.default_rng(0))
    tj = solve(take)
    assert tj.method == ("jmv",) and not tj.ok[0] and tj.reason[0]
    assert np.isnan(tj.centres).all()


@pytest.mark.parametrize("combine", ["weighted", "average", "best"])
def test_kirk_linkage_middle_rod_length(combine):
    errs = []
    for seed in range(3):
        take = kirk_linkage(1200, rng=np.random.default_rng(seed), noise_mm=0.5)
        tj = solve(take, combine=combine)
        length = np.linalg.norm(tj.centres[:, 1] - tj.centres[:, 0], axis=1)
        errs.append(abs(np.mean(length) / 341.0 - 1))
        if combine == "best":
            assert set(tj.basis_group.tolist()) <= {0, 1, 2}
        else:
            np.testing.assert_array_equal(tj.basis_group, -1)
    assert max(errs) < 0.003  # Kirk: 1.7 % on average


def test_gaps_and_validation():
    take = hang_chain([4, 4, 3], 100, rng=np.random.default_rng(9))
    P, t = take.markers.points.copy(), take.truth
    P[20:40, 0] = np.nan  # one of group 0's four markers
    gs = [P[:, t.marker_segment == s] for s in range(3)]
    tj = solve_tree(gs, [[0, 1], [1, 2]])
    assert np.abs(tj.centres - t.joints).max() < 1e-9
    with pytest.raises(ValueError):
        solve_tree(gs, [[0, 3]])
    with pytest.raises(ValueError):
        solve_tree(gs, [[1, 1]])
    with pytest.raises(ValueError):
        solve_tree(gs, [[0, 1]], combine="median")
    single = solve_tree(gs[:1], np.zeros((0, 2), int))
    assert single.centres.shape == (100, 0, 3) and single.method == ()
