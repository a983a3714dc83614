"""Seeded chain / tree / linkage generators: shapes, rigidity, joints, determinism."""
from __future__ import annotations

import numpy as np
import pytest

from mocapskel.artifacts import Markers
from mocapskel.synth.chains import hang_chain, hang_tree, kirk_linkage
from mocapskel.synth.truth import SynthTake, Truth


def _dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=-1)


def _rel_rotvecs(pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """(F, 3) rotation vectors of segment b relative to segment a, from their markers (Kabsch)."""
    from scipy.spatial.transform import Rotation

    def rot(p: np.ndarray) -> np.ndarray:  # rotation of the group from frame 0 to frame f
        x0 = p[0] - p[0].mean(0)
        x = p - p.mean(1, keepdims=True)
        H = np.einsum("mi,fmj->fij", x0, x)
        U, _, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(np.matmul(U, Vt)))
        D = np.stack([np.ones_like(d), np.ones_like(d), d], axis=1)
        return np.matmul(np.swapaxes(Vt, 1, 2) * D[:, None, :], np.swapaxes(U, 1, 2))

    Ra, Rb = rot(pa), rot(pb)
    return Rotation.from_matrix(np.matmul(np.swapaxes(Ra, 1, 2), Rb)).as_rotvec()


@pytest.mark.parametrize("counts", [[4, 3, 3], [3, 1, 2, 2, 2, 2], [2, 2], [1]])
def test_hang_chain_records(counts):
    take = hang_chain(counts, 50, rng=np.random.default_rng(1))
    assert isinstance(take, SynthTake) and isinstance(take.markers, Markers) and isinstance(take.truth, Truth)
    m, t = take.markers, take.truth
    L, M = len(counts), sum(counts)
    assert m.points.shape == (50, M, 3) and np.isfinite(m.points).all()
    assert len(m.labels) == M == len(set(m.labels))
    assert m.units == "mm" and m.rate > 0
    np.testing.assert_array_equal(t.parent, np.arange(L) - 1)
    np.testing.assert_array_equal(t.marker_segment, np.repeat(np.arange(L), counts))
    np.testing.assert_array_equal(t.marker_id, np.arange(M))
    np.testing.assert_array_equal(t.joint_child, np.arange(1, L))
    assert t.joints.shape == (50, L - 1, 3)
    assert t.bone_length.shape == (L - 1,)
    if L > 1:
        assert np.isnan(t.bone_length[-1])
        np.testing.assert_allclose(t.bone_length[:-1], 1.0)


def test_hang_chain_geometry_is_rigid_and_jointed():
    link = 2.5
    take = hang_chain([4, 3, 3, 2, 1], 120, rng=np.random.default_rng(7), link_length=link)
    P, t = take.markers.points, take.truth
    J = t.joints
    # successive joints are link_length apart in every frame
    np.testing.assert_allclose(_dist(J[:, 1:], J[:, :-1]), link, rtol=1e-12)
    for s in range(5):
        pts = P[:, t.marker_segment == s]
        # markers of a segment are rigid together ...
        dd = _dist(pts[:, :, None], pts[:, None])
        np.testing.assert_allclose(dd, dd[:1].repeat(120, 0), atol=1e-12)
        # ... and keep constant distances to the segment's joints, never sitting on one
        for e in (s - 1, s):
            if 0 <= e < J.shape[1]:
                d = _dist(pts, J[:, e][:, None])
                np.testing.assert_allclose(d, d[:1].repeat(120, 0), atol=1e-12)
                assert d.min() > 0.1 * link


def test_hang_chain_marker_placement_not_degenerate():
    for seed in range(5):
        take = hang_chain([4, 3], 10, rng=np.random.default_rng(seed))
        for s, n in ((0, 4), (1, 3)):
            x = take.markers.points[0, take.truth.marker_segment == s]
            sv = np.linalg.svd(x - x.mean(0), compute_uv=False)
            assert sv[1] > 0.1 * sv[0]  # not collinear
            if n == 4:
                assert sv[2] > 0.1 * sv[0]  # not coplanar


def test_hang_chain_exercises_all_three_rotational_dofs():
    take = hang_chain([4, 4], 200, rng=np.random.default_rng(3))
    P, seg = take.markers.points, take.truth.marker_segment
    rv = _rel_rotvecs(P[:, seg == 0], P[:, seg == 1])
    sd = np.sqrt(np.linalg.eigvalsh(np.cov(rv.T)))
    assert sd.min() > 0.1  # radians of spread along the least-exercised axis
    # the root moves too
    assert np.ptp(P[:, 0], axis=0).min() > 0.1


def test_hang_chain_is_seeded_and_noise_has_its_std():
    a = hang_chain([3, 3], 300, rng=np.random.default_rng(5))
    b = hang_chain([3, 3], 300, rng=np.random.default_rng(5))
    np.testing.assert_array_equal(a.markers.points, b.markers.points)
    c = hang_chain([3, 3], 300, rng=np.random.default_rng(6))
    assert not np.allclose(a.markers.points, c.markers.points)
    noisy = hang_chain([3, 3], 300, rng=np.random.default_rng(5), noise=0.01)
    np.testing.assert_array_equal(noisy.truth.joints, a.truth.joints)
    diff = noisy.markers.points - a.markers.points
    assert abs(diff.std() / 0.01 - 1.0) < 0.05


def test_hang_chain_rejects_bad_counts():
    with pytest.raises(ValueError):
        hang_chain([3, 0, 2], rng=np.random.default_rng(0))
    with pytest.raises(ValueError):
        hang_chain([], rng=np.random.default_rng(0))


def test_hang_tree_branches():
    parent = [-1, 0, 0, 1, 1]
    take = hang_tree(parent, [3, 1, 3, 2, 2], 80, rng=np.random.default_rng(2))
    t = take.truth
    assert t.joints.shape == (80, 4, 3)
    np.testing.assert_array_equal(t.parent, parent)
    np.testing.assert_array_equal(t.joint_child, [1, 2, 3, 4])
    # joints 2 and 3 (children of segment 1) sit link_length from segment 1's proximal joint
    J = t.joints
    np.testing.assert_allclose(_dist(J[:, 2], J[:, 0]), 1.0, rtol=1e-12)
    np.testing.assert_allclose(_dist(J[:, 3], J[:, 0]), 1.0, rtol=1e-12)
    d23 = _dist(J[:, 2], J[:, 3])
    np.testing.assert_allclose(d23, d23[0], rtol=1e-12)  # rigid on segment 1
    assert d23[0] > 0.5  # different directions (40+ degrees)
    np.testing.assert_array_equal(np.isnan(t.bone_length), [False, True, True, True])
    with pytest.raises(ValueError):
        hang_tree([-1, 2, 0], [1, 1, 1], rng=np.random.default_rng(0))


def test_kirk_linkage_geometry():
    take = kirk_linkage(600, rng=np.random.default_rng(0), noise_mm=0.0)
    m, t = take.markers, take.truth
    assert m.points.shape == (600, 9, 3) and m.units == "mm" and m.rate == 120.0
    J = t.joints
    assert J.shape == (600, 2, 3)
    np.testing.assert_allclose(_dist(J[:, 1], J[:, 0]), 341.0, rtol=1e-12)
    assert t.bone_length[0] == 341.0 and np.isnan(t.bone_length[1])
    for s in range(3):
        pts = m.points[:, t.marker_segment == s]
        assert pts.shape[1] == 3
        dd = _dist(pts[:, :, None], pts[:, None])
        np.testing.assert_allclose(dd, dd[:1].repeat(600, 0), atol=1e-9)
        x = pts[0] - pts[0].mean(0)
        sv = np.linalg.svd(x, compute_uv=False)
        assert 0.05 < sv[1] / sv[0] < 0.6  # near a rod but not in line
        for e in (s - 1, s):
            if 0 <= e < 2:
                d = _dist(pts, J[:, e][:, None])
                np.testing.assert_allclose(d, d[:1].repeat(600, 0), atol=1e-9)
    lengths = t.info["rod_lengths_mm"]
    assert 290 <= lengths[0] <= 390 and 290 <= lengths[2] <= 390
    # waved about: the held rod travels and turns
    assert np.ptp(m.points[:, 0], axis=0).max() > 200


def test_kirk_linkage_universal_joints_have_two_dofs():
    take = kirk_linkage(1200, rng=np.random.default_rng(4), noise_mm=0.0)
    P = take.markers.points
    rv = _rel_rotvecs(P[:, 0:3], P[:, 3:6])
    ev = np.linalg.eigvalsh(np.cov(rv.T))
    # two exercised degrees of freedom, and (to first order) no twist about the rod
    assert np.sqrt(ev[1]) > 0.2
    assert np.sqrt(ev[0]) < 0.5 * np.sqrt(ev[1])


def test_kirk_linkage_noise():
    a = kirk_linkage(400, rng=np.random.default_rng(9), noise_mm=0.0)
    b = kirk_linkage(400, rng=np.random.default_rng(9), noise_mm=0.5)
    np.testing.assert_array_equal(a.truth.joints, b.truth.joints)
    assert abs((b.markers.points - a.markers.points).std() / 0.5 - 1.0) < 0.05
