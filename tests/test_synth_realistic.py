"""The realistic generator: real marker sets, markers on joints, pose-driven skin motion, everyday motions."""
from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel.synth.body import JOINT_NAMES, PARENT, SEGMENTS
from mocapskel.synth.human import human_take
from mocapskel.synth.presets import Recipe, make, realistic
from mocapskel.synth.realistic import realistic_take
from mocapskel.synth.truth import Truth

CMU41 = set("LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAK LSHO RSHO LUPA RUPA LELB RELB LFRM RFRM LWRA RWRA LWRB RWRB "
            "LFIN RFIN LFWT RFWT LBWT RBWT LTHI RTHI LKNE RKNE LSHN RSHN LANK RANK LHEE RHEE LTOE RTOE LMT5 RMT5".split())
GAIT = set("LASI RASI LPSI RPSI LTHI RTHI LKNE RKNE LTIB RTIB LANK RANK LHEE RHEE LTOE RTOE".split())
J = {n: i for i, n in enumerate(JOINT_NAMES)}


def _take(motion="walk", markerset="cmu41", skin="realistic", noise=0.0, seed=4, frames=600, **kw):
    return realistic_take(rng=np.random.default_rng(seed), n_frames=frames, markerset=markerset, motion=motion,
                          skin=skin, noise_mm=noise, **kw)


@pytest.fixture(scope="module")
def walk():
    return _take("walk"), _take("walk", skin="none")


def _col(take, label):
    return take.markers.points[:, take.markers.labels.index(label)]


def _kabsch(ref: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations R with obs[f] ~ R ref + t."""
    a = ref - ref.mean(0)
    b = obs - obs.mean(1, keepdims=True)
    U, _, Vt = np.linalg.svd(np.einsum("pi,fpj->fij", a, b))
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    V[..., 2] *= d[:, None]
    return V @ np.swapaxes(U, -1, -2)


# --------------------------------------------------------------------------- marker sets and truth


def test_marker_sets_have_the_real_labels_and_hosts():
    cmu = _take(frames=20)
    assert set(cmu.markers.labels) == CMU41 and cmu.markers.n_markers == 41
    host = dict(zip(cmu.markers.labels, (cmu.truth.segment_names[s] for s in cmu.truth.marker_segment)))
    assert host["LKNE"] == "LThigh" and host["RANK"] == "RShank" and host["LWRB"] == "LForearm"
    assert host["LELB"] == "LUpperArm" and host["LSHO"] == "Torso" and host["RFIN"] == "RHand"
    counts = np.bincount(cmu.truth.marker_segment, minlength=15)
    assert counts[SEGMENTS.index("LHand")] == 1 and counts[SEGMENTS.index("LThigh")] == 2
    assert counts[SEGMENTS.index("Head")] == 4 and counts[SEGMENTS.index("Pelvis")] == 4
    gait = _take(markerset="gait", frames=20)
    assert set(gait.markers.labels) == GAIT
    assert gait.truth.segment_names == ("Pelvis", "LThigh", "LShank", "LFoot", "RThigh", "RShank", "RFoot")
    assert gait.truth.parent.tolist() == [-1, 0, 1, 2, 0, 4, 5]
    cl = _take(markerset="cluster", frames=20)
    assert cl.markers.n_markers == 64 and set(cl.truth.info["plates"]) == {"LUA", "LFA", "LTH", "LSK", "RUA", "RFA", "RTH", "RSK"}
    # the default set is the 48 markers of human_take, with its subject
    d = _take(markerset="default", frames=20, skin="none")
    ref = human_take(rng=np.random.default_rng(4), n_frames=20)
    assert d.markers.labels == ref.markers.labels
    np.testing.assert_allclose(d.truth.info["rest_markers_mm"], ref.truth.info["rest_markers_mm"])


def test_restricted_truth_is_the_full_truth_on_the_lower_body():
    full = _take(markerset="cmu41", skin="none", frames=100)
    gait = _take(markerset="gait", skin="none", frames=100)
    names = gait.truth.segment_names
    for e, c in enumerate(gait.truth.joint_child):
        fe = list(full.truth.joint_child).index(SEGMENTS.index(names[c]))
        np.testing.assert_allclose(gait.truth.joints[:, e], full.truth.joints[:, fe])
        assert SEGMENTS[PARENT[SEGMENTS.index(names[c])]] == names[gait.truth.parent[c]]
    thigh = list(gait.truth.joint_child).index(names.index("LThigh"))
    knee = list(gait.truth.joint_child).index(names.index("LShank"))
    L = np.linalg.norm(gait.truth.joints[:, thigh] - gait.truth.joints[:, knee], axis=1)
    assert gait.truth.bone_length[thigh] == pytest.approx(L.mean(), rel=1e-6) and np.ptp(L) < 1e-6


def test_truth_saves_and_loads(tmp_path):
    t = _take(markerset="cluster", frames=30, noise=1.0)
    t.truth.save(tmp_path / "t.npz")
    u = Truth.load(tmp_path / "t.npz")
    assert u.segment_names == t.truth.segment_names and u.info["plates"] == t.truth.info["plates"]
    np.testing.assert_array_equal(u.joints, t.truth.joints)


# --------------------------------------------------------------------------- markers on joints


@pytest.mark.parametrize("label, joint, distal, motion", [
    ("LKNE", "LKnee", "LAnkle", "walk"), ("RELB", "RElbow", "RWrist", "rom"), ("LELB", "LElbow", "LWrist", "rom"),
    ("LANK", "LAnkle", None, "walk"), ("RWRA", "RWrist", None, "walk")])
def test_markers_on_a_joint_sit_on_its_axis_and_move_with_neither_segment(label, joint, distal, motion):
    clean = _take(motion, skin="none")
    info = clean.truth.info
    m = clean.markers.labels.index(label)
    rest_m = np.array(info["rest_markers_mm"][m])
    c = np.array(info["rest_joints_mm"][J[joint]])
    axis = np.array(info["hinge_axes"][joint]) if joint in info["hinge_axes"] else np.array([0.0, 1.0, 0.0])
    r = rest_m - c
    off_axis = np.linalg.norm(r - (r @ axis) * axis)
    assert off_axis <= 10.0 and 35.0 <= np.linalg.norm(r) <= 75.0
    assert info["joint_markers"][label] == joint
    assert len(info["marker_segments_ok"][m]) == 2
    if distal is not None:  # its distance to the next joint down hardly changes as the joint flexes
        to_distal = np.linalg.norm(clean.markers.points[:, m] - clean.truth.joints[:, J[distal]], axis=1)
        other = "LTHI" if label == "LKNE" else "RUPA"  # a marker of the same bone away from the joint
        far = np.linalg.norm(_col(clean, other) - clean.truth.joints[:, J[distal]], axis=1)
        assert np.ptp(far) > 4.0 * np.ptp(to_distal)


# --------------------------------------------------------------------------- skin motion


def _diameter(x: np.ndarray) -> float:
    """Peak-to-peak size of a (F, 3) path: the largest distance between two of its points."""
    x = x[::2]
    return float(np.sqrt(((x[:, None] - x[None]) ** 2).sum(-1).max()))


def _host_joint(take, m):
    """The proximal joint (column of truth.joints) of marker m's host segment (Pelvis: the lumbar joint)."""
    s = take.truth.marker_segment[m]
    child = s if take.truth.parent[s] >= 0 else int(np.flatnonzero(take.truth.parent == s)[0])
    return int(np.flatnonzero(take.truth.joint_child == child)[0])


def test_the_acromion_rides_the_shoulder_girdle_with_the_shoulder_centre():
    clean = _take("reach", skin="none")
    moved = []
    for side, joint in (("L", "LShoulder"), ("R", "RShoulder")):
        gh = clean.truth.joints[:, J[joint]]
        to_gh = np.linalg.norm(_col(clean, side + "SHO") - gh, axis=1)
        assert np.ptp(to_gh) < 1e-6 and 30.0 < to_gh.mean() < 70.0
        moved.append(np.ptp(np.linalg.norm(gh - clean.truth.joints[:, J["Lumbar"]], axis=1)))
    assert max(moved) > 5.0  # the shoulder centre moves on the thorax as an arm rises (scapulohumeral rhythm)
    assert np.ptp(np.linalg.norm(_col(clean, "C7") - clean.truth.joints[:, J["Lumbar"]], axis=1)) < 1e-6


def test_the_acromion_may_go_with_the_thorax_or_its_arm(walk):
    """The acromion rides the shoulder girdle, which has no segment in the truth: on a walk its
    distances to the thorax's markers (on average) and to its upper arm's marker vary alike (so a grouping with
    either is defensible), and the truth lists both segments for it, without naming a joint."""
    skin, _ = walk
    info = skin.truth.info
    ok = dict(zip(info["physical_labels"], info["marker_segments_ok"]))
    for side in "LR":
        assert [SEGMENTS[s] if isinstance(s, int) else s for s in ok[side + "SHO"]] == ["Torso", side + "UpperArm"]
        assert side + "SHO" not in info["joint_markers"]
        sho = _col(skin, side + "SHO")
        std = {lb: np.std(np.linalg.norm(sho - _col(skin, lb), axis=1)) for lb in ("C7", "T10", "CLAV", "STRN", side + "UPA")}
        thorax = np.mean([std[lb] for lb in ("C7", "T10", "CLAV", "STRN")])
        assert 0.5 < std[side + "UPA"] / thorax < 2.0, std


def test_rigid_markers_keep_their_distance_to_their_joints_up_to_the_skin_amplitude(walk):
    skin, clean = walk
    amp = skin.truth.info["skin_p2p_mm"]
    kinds = skin.truth.info["marker_kind"]
    for m, label in enumerate(skin.markers.labels):
        if kinds[label] == "acromion":  # also follows the arm's elevation
            continue
        e = _host_joint(skin, m)
        d_clean = np.linalg.norm(clean.markers.points[:, m] - clean.truth.joints[:, e], axis=1)
        d_skin = np.linalg.norm(skin.markers.points[:, m] - skin.truth.joints[:, e], axis=1)
        assert np.ptp(d_clean) < 1e-6, label
        assert np.ptp(d_skin) <= 1.8 * amp[label], (label, np.ptp(d_skin), amp[label])


def test_skin_amplitudes_follow_the_literature_and_the_markers_of_a_segment_move_apart(walk):
    skin, clean = walk
    amp = skin.truth.info["skin_p2p_mm"]
    ranges = {"LTHI": (10, 30), "RTHI": (10, 30), "LSHN": (5, 15), "LUPA": (5, 20), "RUPA": (5, 20),
              "LKNE": (5, 15), "LANK": (3, 8), "LFHD": (2, 5), "RBHD": (2, 5), "LFWT": (5, 15)}
    for label, (lo, hi) in ranges.items():
        assert lo <= amp[label] <= hi, label
    d = skin.markers.points - clean.markers.points
    p2p = {l: _diameter(d[:, i]) for i, l in enumerate(skin.markers.labels)}
    # walking moves the thigh's skin by centimetres, the shank's by several mm, bony landmarks by a few
    assert 8.0 <= max(p2p["LTHI"], p2p["RTHI"]) <= 45.0
    assert 3.0 <= max(p2p["LSHN"], p2p["RSHN"]) <= 23.0
    assert max(p2p["LHEE"], p2p["LFHD"], p2p["CLAV"]) <= 15.0
    # markers of one segment do not move together: their relative motion is as large as their own
    for a, b in (("LTHI", "LKNE"), ("LFHD", "LBHD"), ("LFWT", "LBWT")):
        rel = d[:, skin.markers.labels.index(a)] - d[:, skin.markers.labels.index(b)]
        assert _diameter(rel) >= 0.4 * max(p2p[a], p2p[b]), (a, b)


@pytest.mark.parametrize("motion", ["kick", "rom"])
def test_large_motions_stretch_the_skin_at_most_one_and_a_half_amplitudes(motion):
    skin, clean = _take(motion, frames=480), _take(motion, skin="none", frames=480)
    amp = skin.truth.info["skin_p2p_mm"]
    d = skin.markers.points - clean.markers.points
    for i, label in enumerate(skin.markers.labels):
        if skin.truth.info["marker_kind"][label] == "acromion":
            continue
        # 1.5 amplitudes, plus the small band-limited wobble (rms 5 % of the amplitude)
        assert _diameter(d[:, i]) <= 1.8 * amp[label], (label, _diameter(d[:, i]), amp[label])


def test_cluster_plates_stay_rigid_and_slide_as_a_whole():
    skin = _take(markerset="cluster", motion="walk")
    clean = _take(markerset="cluster", motion="walk", skin="none")
    P, labs = skin.markers.points, skin.markers.labels
    for plate, members in skin.truth.info["plates"].items():
        idx = [labs.index(l) for l in members]
        assert len(idx) == 4
        for i in range(4):
            for k in range(i + 1, 4):
                assert np.ptp(np.linalg.norm(P[:, idx[i]] - P[:, idx[k]], axis=1)) < 1e-6, plate
        d = P[:, idx[0]] - clean.markers.points[:, idx[0]]
        slide = 2 * np.linalg.norm(d - d.mean(0), axis=1).max()
        assert slide > (5.0 if plate[1:] == "TH" else 1.0), plate


# --------------------------------------------------------------------------- motion


def test_walk_has_gait_ranges_and_travels(walk):
    _, clean = walk
    tr, info = clean.truth, clean.truth.info
    labs = list(clean.markers.labels)
    rest = np.array(info["rest_markers_mm"])
    pel = [labs.index(l) for l in ("LFWT", "RFWT", "LBWT", "RBWT")]
    Rp = _kabsch(rest[pel], clean.markers.points[:, pel])  # pelvis orientation (markers rigid without skin)
    for side in "LR":
        thigh = np.einsum("fji,fj->fi", Rp, tr.joints[:, J[side + "Knee"]] - tr.joints[:, J[side + "Hip"]])
        flex = np.degrees(np.arctan2(thigh[:, 0], -thigh[:, 2]))
        assert 30.0 <= np.ptp(flex) <= 50.0
        a = tr.joints[:, J[side + "Knee"]] - tr.joints[:, J[side + "Hip"]]
        b = tr.joints[:, J[side + "Ankle"]] - tr.joints[:, J[side + "Knee"]]
        knee = np.degrees(np.arccos(np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)))
        assert 50.0 <= np.ptp(knee) <= 70.0
        # hip rotation: the knee marker's direction about the thigh axis, in the pelvis frame
        lat = np.einsum("fji,fj->fi", Rp, _col(clean, side + "KNE") - tr.joints[:, J[side + "Knee"]])
        ax = thigh / np.linalg.norm(thigh, axis=1, keepdims=True)
        lat -= np.sum(lat * ax, 1)[:, None] * ax
        rot = np.degrees(np.arctan2(lat[:, 0], np.abs(lat[:, 1])))
        assert np.ptp(rot) < 20.0
        # elbows swing through about 30 deg (CMU's walks vary the upper-arm-to-wrist distance by 6-12 mm)
        a = tr.joints[:, J[side + "Elbow"]] - tr.joints[:, J[side + "Shoulder"]]
        b = tr.joints[:, J[side + "Wrist"]] - tr.joints[:, J[side + "Elbow"]]
        elbow = np.degrees(np.arccos(np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)))
        assert 20.0 <= np.ptp(elbow) <= 45.0 and elbow.min() >= 5.0
    root = tr.joints[:, J["Lumbar"]]
    assert np.linalg.norm(root[-1, :2] - root[0, :2]) > 5000.0  # 5 s at ~1.3 m/s, straight on


@pytest.mark.parametrize("motion, lo, hi", [("kick", 5.0, 12.0), ("run", 5.0, 12.0), ("walk", 2.5, 7.0)])
def test_feet_move_as_fast_as_in_real_motion(motion, lo, hi):
    t = _take(motion, skin="none", frames=720)
    v = [np.linalg.norm(np.diff(_col(t, l), axis=0), axis=1).max() * 120.0 / 1000.0 for l in ("LTOE", "RTOE")]
    assert lo <= max(v) <= hi, v


def test_climb_rises_and_reach_moves_the_hands_not_the_feet():
    climb = _take("climb", skin="none", frames=600)
    root = climb.truth.joints[:, J["Lumbar"]]
    assert root[-1, 2] - root[0, 2] > 800.0  # ~5 steps of 170 mm in 5 s
    reach = _take("reach", skin="none", frames=600)
    feet = np.ptp(_col(reach, "LHEE"), axis=0).max()
    hands = max(np.ptp(_col(reach, l), axis=0).max() for l in ("LFIN", "RFIN"))
    assert hands > 400.0 and feet < 60.0


# --------------------------------------------------------------------------- determinism and the CLI


def test_same_seed_same_take_and_the_subject_is_kept_across_motions():
    a, b = _take("kick", noise=1.0, seed=9, frames=100), _take("kick", noise=1.0, seed=9, frames=100)
    np.testing.assert_array_equal(a.markers.points, b.markers.points)
    np.testing.assert_array_equal(a.truth.joints, b.truth.joints)
    c = _take("kick", noise=1.0, seed=10, frames=100)
    assert not np.allclose(a.markers.points, c.markers.points)
    w = _take("walk", seed=9, frames=100)
    assert w.truth.info["subject_seed"] == a.truth.info["subject_seed"]
    assert w.truth.info["skin_p2p_mm"] == a.truth.info["skin_p2p_mm"]
    np.testing.assert_allclose(w.truth.info["rest_markers_mm"], a.truth.info["rest_markers_mm"])


def test_recipes_keep_the_default_generator_and_route_the_realistic_one():
    old = make(Recipe(kind="human", frames=50, seed=3, motion="walk"))
    ref = human_take(rng=np.random.default_rng(3), n_frames=50, motion="walk")
    np.testing.assert_array_equal(old.markers.points, ref.markers.points)
    new = make(realistic(seed=3, frames=50, motion="kick", markerset="gait"))
    assert new.truth.info["generator"] == "realistic" and new.markers.n_markers == 16
    with pytest.raises(ValueError):
        realistic_take(rng=np.random.default_rng(0), markerset="cmu41", markers_per_segment=2)
    with pytest.raises(ValueError):
        realistic_take(rng=np.random.default_rng(0), motion="swim")


def test_cli_writes_a_realistic_take_and_refuses_mixed_options(tmp_path):
    from mocapskel.cli.main import cli
    from mocapskel.io.markers import read_markers

    r = CliRunner().invoke(cli, ["synth", "human", "-o", str(tmp_path / "k.c3d"), "--markerset", "cmu41", "--motion",
                                 "kick", "--skin", "realistic", "--noise", "1", "--frames", "120", "--gaps", "4"])
    assert r.exit_code == 0, r.output
    m = read_markers(tmp_path / "k.c3d")
    t = Truth.load(tmp_path / "k.truth.npz")
    assert set(m.labels) == CMU41 and m.n_frames == 120 and t.info["skin"] == "realistic"
    r = CliRunner().invoke(cli, ["synth", "human", "-o", str(tmp_path / "x.c3d"), "--markerset", "gait",
                                 "--markers-per-segment", "2"])
    assert r.exit_code == 2 and not (tmp_path / "x.c3d").exists()
