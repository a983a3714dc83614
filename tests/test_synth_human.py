"""The synthetic human and its corruptions: geometry, motion coverage, noise, bookkeeping."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapskel.synth import corrupt
from mocapskel.synth.body import HINGES, JOINT_NAMES, PARENT, SEGMENTS
from mocapskel.synth.human import human_take

RATE_60S = 20.0  # 1200 frames at 20 Hz = a 60 s take, cheaply


@pytest.fixture(scope="module")
def clean():
    return human_take(rng=np.random.default_rng(11), n_frames=1200, rate=RATE_60S)


@pytest.fixture(scope="module")
def take120():
    """10 s at 120 Hz, noise free: the base of the corruption tests."""
    return human_take(rng=np.random.default_rng(5), n_frames=1200, rate=120.0)


def _kabsch(ref: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations R with obs[f] ~ R ref + t (no gaps)."""
    a = ref - ref.mean(0)
    b = obs - obs.mean(1, keepdims=True)
    H = np.einsum("pi,fpj->fij", a, b)
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    V[..., 2] *= d[:, None]
    return V @ np.swapaxes(U, -1, -2)


def _segment_rotations(take) -> np.ndarray:
    """(F, S, 3, 3) global segment rotations from rest, from the noise-free markers."""
    rest = np.array(take.truth.info["rest_markers_mm"])
    seg = take.truth.marker_segment
    P = take.markers.points
    return np.stack([_kabsch(rest[seg == s], P[:, seg == s]) for s in range(len(SEGMENTS))], axis=1)


def _relative_rotvecs(take) -> np.ndarray:
    """(F, E, 3) rotation vectors (deg) of each child relative to its parent."""
    G = _segment_rotations(take)
    out = []
    for c in take.truth.joint_child:
        Rrel = np.swapaxes(G[:, PARENT[c]], -1, -2) @ G[:, c]
        out.append(Rotation.from_matrix(Rrel).as_rotvec(degrees=True))
    return np.stack(out, axis=1)


# --------------------------------------------------------------------------- the subject


def test_default_subject_has_15_segments_and_48_uniquely_labelled_markers(clean):
    tr, m = clean.truth, clean.markers
    assert tr.segment_names == SEGMENTS and len(SEGMENTS) == 15
    assert m.points.shape == (1200, 48, 3) and m.points.dtype == np.float64
    assert len(set(m.labels)) == 48 and m.labels[0] == "PELV1"
    assert {"LTHI1", "RSHN2", "HEAD4", "LFOT3"} <= set(m.labels)
    assert np.bincount(tr.marker_segment).tolist() == [4, 4, 4] + [3] * 12
    assert np.array_equal(tr.marker_id, np.arange(48))
    assert tr.joints.shape == (1200, 14, 3) and np.array_equal(tr.joint_child, np.arange(1, 15))
    assert tr.info["lab_up"] == "z" and set(tr.info["hinges"]) == set(HINGES)
    assert not np.isnan(m.points).any()
    # pelvis ~ 1 m up, nobody under the floor
    assert 900 < tr.info["pelvis_height_mm"] < 1050
    assert m.points[..., 2].min() > -10.0


@pytest.mark.parametrize("mps, total", [(2, 30), (1, 15), ({"Pelvis": 6, "LHand": 1}, 48 + 2 - 2)])
def test_markers_per_segment_sets_the_counts_and_fewer_markers_are_a_subset(mps, total):
    few = human_take(rng=np.random.default_rng(3), n_frames=50, markers_per_segment=mps)
    full = human_take(rng=np.random.default_rng(3), n_frames=50)
    assert few.markers.n_markers == total
    for lab in set(few.markers.labels) & set(full.markers.labels):
        i, j = few.markers.labels.index(lab), full.markers.labels.index(lab)
        np.testing.assert_array_equal(few.markers.points[:, i], full.markers.points[:, j])


def test_markers_are_rigid_on_their_segment_and_off_the_joints(clean):
    P, tr = clean.markers.points, clean.truth
    # joints of a segment: its own (child == s) and those of its children
    for s in range(len(SEGMENTS)):
        pts = [P[:, tr.marker_segment == s]]
        pts.append(tr.joints[:, (tr.joint_child == s) | (PARENT[tr.joint_child] == s)])
        pts = np.concatenate(pts, axis=1)
        d = np.linalg.norm(pts[:, :, None] - pts[:, None, :], axis=-1)
        assert np.ptp(d, axis=0).max() < 1e-9, SEGMENTS[s]
    rest_m = np.array(tr.info["rest_markers_mm"])
    rest_j = np.array(tr.info["rest_joints_mm"])
    assert np.linalg.norm(rest_m[:, None] - rest_j[None], axis=-1).min() > 40.0


def test_joints_follow_forward_kinematics_with_constant_bone_lengths(clean):
    tr = clean.truth
    J = tr.joints
    for e, c in enumerate(tr.joint_child):
        kids = np.flatnonzero(PARENT[tr.joint_child] == c)
        if kids.size == 0:
            assert np.isnan(tr.bone_length[e])
            continue
        d = np.linalg.norm(J[:, kids].mean(1) - J[:, e], axis=-1)
        assert np.ptp(d) < 1e-9
        assert d[0] == pytest.approx(tr.bone_length[e], abs=1e-9)
    thigh = tr.bone_length[JOINT_NAMES.index("LHip")]
    shank = tr.bone_length[JOINT_NAMES.index("LKnee")]
    assert 400 < thigh < 460 and 390 < shank < 450
    assert np.isnan(tr.bone_length[[JOINT_NAMES.index(j) for j in ("Neck", "LWrist", "RAnkle")]]).all()


def test_hinges_turn_about_one_axis_and_every_dof_is_exercised_over_60s(clean):
    rv = _relative_rotvecs(clean)  # (F, E, 3) deg
    info = clean.truth.info
    for e, name in enumerate(JOINT_NAMES):
        if name in HINGES:
            a = np.array(info["hinge_axes"][name])
            along = rv[:, e] @ a
            off = np.linalg.norm(rv[:, e] - along[:, None] * a, axis=1)
            assert np.ptp(along) > 100.0, name
            assert off.max() <= np.hypot(*info["hinge_off_axis_deg"][name]) + 1e-6, name
            assert off.max() > 1.0, name  # a little varus/valgus, so the centre is observable
        else:
            assert (np.ptp(rv[:, e], axis=0) >= 20.0).all(), (name, np.ptp(rv[:, e], axis=0))


def test_zero_hinge_slack_gives_pure_hinges():
    take = human_take(rng=np.random.default_rng(1), n_frames=200, hinge_slack_deg=(0.0, 0.0))
    rv = _relative_rotvecs(take)
    for name in HINGES:
        e = JOINT_NAMES.index(name)
        a = np.array(take.truth.info["hinge_axes"][name])
        assert np.abs(np.cross(rv[:, e], a)).max() < 1e-6


def test_root_wanders_over_the_capture_volume(clean):
    pelvis = clean.markers.points[:, clean.truth.marker_segment == 0].mean(1)
    assert np.ptp(pelvis[:, 0]) > 1000 and np.ptp(pelvis[:, 1]) > 1000
    yaw = np.unwrap(np.arctan2(*(_segment_rotations(clean)[:, 0, 1::-1, 0].T)))
    assert np.ptp(np.degrees(yaw)) > 180


def test_walk_is_the_same_subject_travelling(clean):
    walk = human_take(rng=np.random.default_rng(11), n_frames=1200, rate=RATE_60S, motion="walk")
    assert walk.truth.info["rest_markers_mm"] == clean.truth.info["rest_markers_mm"]
    np.testing.assert_allclose(walk.truth.bone_length, clean.truth.bone_length)
    hips = walk.truth.joints[:, JOINT_NAMES.index("LHip")]
    assert np.linalg.norm(np.diff(hips[:, :2], axis=0), axis=1).sum() > 40_000  # ~1 m/s for 60 s
    assert not np.array_equal(walk.markers.points, clean.markers.points)
    # feet reach the floor but do not go through it
    feet = walk.markers.points[:, np.isin(walk.truth.marker_segment, [11, 14]), 2]
    assert 0 < feet.min() < 80


def test_subject_seed_fixes_the_subject_across_generators(clean):
    other = human_take(rng=np.random.default_rng(99), n_frames=100, subject_seed=clean.truth.info["subject_seed"])
    assert other.truth.info["rest_markers_mm"] == clean.truth.info["rest_markers_mm"]


def test_scale_multiplies_lengths():
    a = human_take(rng=np.random.default_rng(4), n_frames=20)
    b = human_take(rng=np.random.default_rng(4), n_frames=20, scale=0.5)
    np.testing.assert_allclose(b.truth.bone_length, 0.5 * a.truth.bone_length)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="motion"):
        human_take(rng=np.random.default_rng(0), n_frames=10, motion="dance")
    with pytest.raises(ValueError, match="15 counts"):
        human_take(rng=np.random.default_rng(0), n_frames=10, markers_per_segment=[3, 3])
    with pytest.raises(ValueError, match="unknown segment"):
        human_take(rng=np.random.default_rng(0), n_frames=10, markers_per_segment={"Tail": 2})


# --------------------------------------------------------------------------- noise


def test_soft_tissue_and_noise_have_the_requested_size_and_band(take120):
    soft = human_take(rng=np.random.default_rng(5), n_frames=1200, soft_tissue_mm=2.0)
    d = soft.markers.points - take120.markers.points
    assert np.sqrt(np.mean(np.sum(d**2, -1))) == pytest.approx(2.0, rel=0.02)
    spec = np.abs(np.fft.rfft(d, axis=0)) ** 2
    f = np.fft.rfftfreq(1200, 1 / 120.0)
    assert spec[(f >= 0.9) & (f <= 5.1)].sum() / spec.sum() > 0.99
    # correlated within a segment a bit, not across segments
    lthi = d[:, soft.truth.marker_segment == 9, 0]
    assert np.corrcoef(lthi.T)[0, 1:].mean() > 0.1

    noisy = human_take(rng=np.random.default_rng(5), n_frames=1200, soft_tissue_mm=2.0, noise_mm=1.0)
    n = noisy.markers.points - soft.markers.points
    assert n.std() == pytest.approx(1.0, rel=0.03)
    added = corrupt.add_noise(take120, 0.5, np.random.default_rng(1))
    assert (added.markers.points - take120.markers.points).std() == pytest.approx(0.5, rel=0.03)


def test_same_seed_same_take_other_seed_other_take():
    kw = dict(n_frames=300, noise_mm=1.0, soft_tissue_mm=2.0)
    a = human_take(rng=np.random.default_rng(8), **kw)
    b = human_take(rng=np.random.default_rng(8), **kw)
    c = human_take(rng=np.random.default_rng(9), **kw)
    np.testing.assert_array_equal(a.markers.points, b.markers.points)
    np.testing.assert_array_equal(a.truth.joints, b.truth.joints)
    assert a.truth.info == b.truth.info
    assert not np.array_equal(a.markers.points, c.markers.points)


# --------------------------------------------------------------------------- corruptions


def _corrupt_all(take, seed):
    rng = np.random.default_rng(seed)
    t = corrupt.add_gaps(take, rng)
    t = corrupt.add_jumps(t, rng, n_jumps=8)
    t = corrupt.add_ghosts(t, rng, n_ghosts=12)
    return corrupt.relabel_passive(t, rng)


def test_gaps_come_at_the_requested_rate_with_bad_edges(take120):
    g = corrupt.add_gaps(take120, np.random.default_rng(2), gaps_per_marker_per_minute=4.0, bad_edge_mm=30.0)
    P0, P = take120.markers.points, g.markers.points
    nan = np.isnan(P[..., 0])
    n_runs = sum(corrupt.visible_runs(nan[:, m])[0].size for m in range(48))
    expected = 4.0 * 48 * (1200 / 120.0 / 60.0)
    assert 0.5 * expected <= n_runs <= 1.5 * expected
    assert n_runs == len(g.truth.info["gaps"])
    # the displaced samples are exactly the recorded bad ones, each by >= 15 mm
    moved = np.linalg.norm(P - P0, axis=-1) > 1e-9
    bad = corrupt.bad_sample_mask(g)
    np.testing.assert_array_equal(moved, bad)
    assert bad.sum() > n_runs  # up to 2 frames each side
    assert np.linalg.norm(P - P0, axis=-1)[bad].min() >= 15.0 - 1e-9
    # bad frames sit right next to a gap
    for m in range(48):
        near = np.zeros(1200, bool)
        for s, e in zip(*corrupt.visible_runs(nan[:, m])):
            near[max(0, s - 2) : e + 2] = True
        assert not (bad[:, m] & ~near).any()


def test_jumps_move_a_marker_for_a_few_frames(take120):
    j = corrupt.add_jumps(take120, np.random.default_rng(3), n_jumps=6, jump_mm=(50, 150), duration_frames=(2, 10))
    recs = j.truth.info["jumps"]
    assert len(recs) == 6
    d = np.linalg.norm(j.markers.points - take120.markers.points, axis=-1)
    np.testing.assert_array_equal(d > 1e-9, corrupt.bad_sample_mask(j))
    for p, s, e, *vec in recs:
        assert 2 <= e - s <= 10 and 50 <= np.linalg.norm(vec) <= 150
        assert np.all(d[s:e, p] > 49.0)


def test_ghosts_are_short_lived_and_attached_to_nothing(take120):
    g = corrupt.add_ghosts(take120, np.random.default_rng(4), n_ghosts=25, duration_s=(0.05, 0.4))
    tr = g.truth
    assert g.markers.n_markers == 48 + 25 and len(set(g.markers.labels)) == 73
    assert (tr.marker_segment[48:] == -1).all() and (tr.marker_id[48:] == -1).all()
    seen = (~np.isnan(g.markers.points[:, 48:, 0])).sum(0)
    assert (seen >= 1).all() and (seen <= round(0.4 * 120)).all()
    np.testing.assert_array_equal(g.markers.points[:, :48], take120.markers.points)


def test_relabelled_labels_never_overlap_and_map_back_exactly(take120):
    r = _corrupt_all(take120, 7)
    base = corrupt.add_jumps(corrupt.add_gaps(take120, rng := np.random.default_rng(7)), rng, n_jumps=8)
    P, tr = r.markers.points, r.truth
    vis = ~np.isnan(P[..., 0])
    assert all(lab.startswith("M") for lab in r.markers.labels)
    base_runs = sum(corrupt.visible_runs(~np.isnan(base.markers.points[:, p, 0]))[0].size for p in range(48))
    assert r.markers.n_markers == base_runs + 12 > 48 + 12 + 20  # a new label after every gap
    first = vis.argmax(0)
    assert (np.diff(first) >= 0).all()  # numbered in order of first appearance
    for p in range(48):
        cols = tr.marker_id == p
        assert vis[:, cols].sum(1).max() <= 1, p
        assert (tr.marker_segment[cols] == take120.truth.marker_segment[p]).all()
        # every visible sample is the (corrupted) physical marker's sample
        f, c = np.nonzero(vis[:, cols])
        np.testing.assert_array_equal(P[:, cols][f, c], base.markers.points[f, p])
        assert (~np.isnan(base.markers.points[:, p, 0])).sum() == f.size
    assert (tr.marker_id == -1).sum() == 12 and (tr.marker_segment[tr.marker_id == -1] == -1).all()
    # the bad-sample records survive relabelling
    np.testing.assert_array_equal(corrupt.bad_sample_mask(r).sum(), corrupt.bad_sample_mask(base).sum())


def test_relabelling_a_clean_take_maps_back_to_the_true_positions(take120):
    g = corrupt.add_gaps(take120, np.random.default_rng(1), bad_edge_frames=0)
    r = corrupt.relabel_passive(g, np.random.default_rng(1))
    P, mid = r.markers.points, r.truth.marker_id
    vis = ~np.isnan(P[..., 0])
    f, lab = np.nonzero(vis)
    np.testing.assert_array_equal(P[f, lab], take120.markers.points[f, mid[lab]])


def test_drop_markers_keeps_a_few_per_segment(take120):
    r = _corrupt_all(take120, 2)
    d = corrupt.drop_markers(r, 2, np.random.default_rng(0))
    tr = d.truth
    phys = tr.marker_id >= 0
    for s in range(15):
        assert np.unique(tr.marker_id[phys & (tr.marker_segment == s)]).size == 2
    assert np.array_equal(np.unique(tr.marker_id[phys]), np.arange(30))
    kept = np.array(tr.info["kept_markers"])
    # the kept labels are the same data, and the rest poses follow the renumbering
    src = [r.markers.labels.index(lab) for lab in d.markers.labels]
    np.testing.assert_array_equal(d.markers.points, r.markers.points[:, src])
    np.testing.assert_array_equal(kept[tr.marker_id[phys]], r.truth.marker_id[src][phys])
    assert len(tr.info["rest_markers_mm"]) == 30
    one = corrupt.drop_markers(take120, 1, np.random.default_rng(0))
    assert one.markers.n_markers == 15


def test_everything_lost_blanks_a_range_and_keeps_the_truth(take120):
    lost = corrupt.everything_lost(take120, (100, 250))
    assert np.isnan(lost.markers.points[100:250]).all()
    assert not np.isnan(lost.markers.points[:100]).any() and not np.isnan(lost.markers.points[250:]).any()
    np.testing.assert_array_equal(lost.truth.joints, take120.truth.joints)
    assert lost.truth.info["lost"] == [[100, 250]]


def test_corruptions_are_deterministic_and_leave_the_input_alone(take120):
    before = take120.markers.points.copy()
    a, b = _corrupt_all(take120, 3), _corrupt_all(take120, 3)
    np.testing.assert_array_equal(a.markers.points, b.markers.points)
    assert a.markers.labels == b.markers.labels
    np.testing.assert_array_equal(a.truth.marker_id, b.truth.marker_id)
    assert a.truth.info == b.truth.info
    np.testing.assert_array_equal(take120.markers.points, before)
    assert "corruptions" not in take120.truth.info
    assert [c["op"] for c in a.truth.info["corruptions"]] == ["add_gaps", "add_jumps", "add_ghosts", "relabel_passive"]


def test_truth_of_a_corrupted_take_saves_and_loads(tmp_path, take120):
    from mocapskel.synth.truth import Truth

    r = _corrupt_all(take120, 4)
    r.truth.save(tmp_path / "t.npz")
    back = Truth.load(tmp_path / "t.npz")
    assert back.info == r.truth.info
    np.testing.assert_array_equal(back.marker_id, r.truth.marker_id)
