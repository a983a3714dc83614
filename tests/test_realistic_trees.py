"""Trees of realistic generated takes (the CMU-style 41-marker set, skin motion driven by the joint
angles, martial-arts kicks): marker groups, the tree and the humanoid names against the generator's
truth, and the segment-stage rules that make them (pairs of markers that are one body's skin)."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.model.naming import name_skeleton
from mocapskel.solvers.grouping import grouping
from mocapskel.solvers.grouping.partition import scatter_in_frame
from mocapskel.stages import segment
from mocapskel.synth.body import HUMANOID_NAMES as HUMANOID, PARENT as TRUE_PARENT, SEGMENTS as TRUE_SEGMENTS
from mocapskel.synth.presets import make, realistic



def _depth(name: str) -> int:
    s, d = TRUE_SEGMENTS.index(name), 0
    while TRUE_PARENT[s] >= 0:
        s, d = TRUE_PARENT[s], d + 1
    return d


@pytest.fixture(scope="module", params=[1, 2, 3], ids=lambda s: f"kick-seed{s}")
def kick(request):
    take = make(realistic(seed=request.param, frames=600, motion="kick", markerset="cmu41"))
    return take, pipeline.fit(take.markers, pipeline.make_params())


def _true_parts(take, labels) -> list[str]:
    """The true segment of each marker that rides on one segment only (markers over a joint left out)."""
    info = take.truth.info
    ok = dict(zip(info["physical_labels"], info["marker_segments_ok"]))
    return [ok[lb][0] for lb in labels if lb in ok and len(ok[lb]) == 1]


def _assert_named_as_a_person(take, res) -> None:
    """Recognised as a person, each fitted segment named after the most proximal true segment its markers
    ride on."""
    skel = res.motion.skeleton
    naming = name_skeleton(skel, res.motion, "auto")
    assert naming.humanoid, naming.note
    want = []
    for s in range(len(skel.names)):
        parts = _true_parts(take, [skel.labels[m] for m in np.flatnonzero(skel.marker_segment == s)])
        want.append(HUMANOID[min(set(parts), key=_depth)])
    assert list(naming.names) == want


def test_realistic_kicks_are_named_as_a_person_segment_for_segment(kick) -> None:
    """Each fitted segment gets the humanoid name of the most proximal true segment its markers ride
    on (a hand whose wrist the kick hardly moves rides with the forearm: LeftForeArm). Before pairs of
    markers that are one body's skin joined it, seed 1's pelvis came out as two diagonal pairs, and on
    seeds 1 and 3 the two acromion markers made a group of their own that hung on the head, with both
    arms on it: neither was recognised as a person."""
    _assert_named_as_a_person(*kick)


@functools.lru_cache(maxsize=None)
def _fitted(motion: str, seed: int):
    """A realistic cmu41 take (600 frames) and its fit, made once for the tests of this file that use it."""
    take = make(realistic(seed=seed, frames=600, motion=motion, markerset="cmu41"))
    return take, pipeline.fit(take.markers, pipeline.make_params())


@pytest.mark.parametrize("motion", ["walk", "run"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_realistic_walks_and_runs_are_named_as_a_person_segment_for_segment(motion, seed) -> None:
    """As the kicks: every segment of a realistic walk or run (three seeds each) gets the humanoid name
    of the most proximal true segment its markers ride on, left and right included."""
    _assert_named_as_a_person(*_fitted(motion, seed))


def test_a_pair_of_skin_markers_joins_the_body_it_straddles(kick) -> None:
    """The two acromion markers (on the thorax, moved by the arms' skin motion) go with the thorax's
    markers, and the pelvis's four markers make one group."""
    take, res = kick
    skel = res.motion.skeleton
    group = dict(zip(skel.labels, skel.marker_segment.tolist()))
    assert group["LSHO"] == group["RSHO"] == group["C7"] == group["STRN"]
    assert group["LFWT"] == group["RFWT"] == group["LBWT"] == group["RBWT"] != group["C7"]


def test_a_foot_whose_ankle_moves_is_not_absorbed_by_its_shank() -> None:
    """The lower-body gait set walking, seed 2: the right shank's group carries the knee marker (three
    markers), and the foot's two markers move against it by less than the bar a lone marker must pass.
    The foot lies below the shank, not across it, so it stays a segment (the ankle is located)."""
    take = make(realistic(seed=2, frames=600, motion="walk", markerset="gait"))
    seg = segment.run(take.markers)
    group = dict(zip(take.markers.labels, seg.group.tolist()))
    assert group["RHEE"] == group["RTOE"] != group["RANK"]
    assert group["RTIB"] == group["RANK"]
    moved = {lb for lb, how in seg.info["moved"] if how == "absorbed with its pair"}
    assert not moved & {"RHEE", "RTOE", "LHEE", "LTOE"}


def test_absorb_pairs_joins_crossing_pairs_and_a_straddling_pair_only() -> None:
    """On points made to order (a subject walking a helix and swaying, 0.5 mm noise): a rigid body of
    four markers split into two diagonal pairs that cross each other is joined; a pair straddling a
    rigid body of three, sliding 4 mm against it (skin), joins it; a pair beside that body, turning
    12 degrees about a hinge (a limb, moving against it by less than the bar too), does not."""
    rng = np.random.default_rng(3)
    K = 80
    t = np.linspace(0.0, 2.0 * np.pi, K)

    def about(axis: int, a: np.ndarray) -> np.ndarray:  # (K, 3, 3) rotations by angles a about an axis
        i, j = [k for k in range(3) if k != axis]
        R = np.zeros((K, 3, 3))
        R[:, axis, axis] = 1.0
        R[:, i, i], R[:, i, j], R[:, j, i], R[:, j, j] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
        return R

    subject = about(2, 0.6 * np.sin(t))
    place = np.column_stack([100.0 * np.cos(t), 50.0 * np.sin(t), 20.0 * t])

    def world(local: np.ndarray) -> np.ndarray:  # (K, n, 3) subject-frame points (K, n, 3) in the world
        return np.einsum("kij,knj->kni", subject, local) + place[:, None]

    def still(pts) -> np.ndarray:
        return np.broadcast_to(np.array(pts, dtype=float), (K, len(pts), 3))

    pelvis = still([[-120, 60, 0], [120, 60, 0], [-80, -60, 0], [80, -60, 0]])
    thorax = still([[0, 80, 400], [0, -80, 400], [60, 0, 520]])
    skin = still([[-180, 0, 470], [180, 0, 470]]) + 4.0 * np.sin(3.0 * t)[:, None, None] * np.array([0.0, 1.0, 0.0])
    hinge = np.array([220.0, 0.0, 470.0])
    limb = np.einsum("kij,nj->kni", about(1, 0.2 * np.sin(2.0 * t)), np.array([[30.0, 0, -70], [80, 0, -140]])) + hinge
    P = world(np.concatenate([pelvis, thorax, skin, limb], axis=1)) + rng.normal(0.0, 0.5, (K, 11, 3))
    labels = np.array([0, 1, 1, 0, 2, 2, 2, 3, 3, 4, 4])  # the pelvis paired diagonally
    d = np.linalg.norm(P[:, :, None] - P[:, None], axis=-1).mean(0)
    scatter = scatter_in_frame(P[:, [4, 5, 6, 9, 10]], np.arange(3))[3:]
    assert 8.0 < scatter.max() < 25.0  # the limb moves against the thorax, by less than the bar
    lab, moves = grouping.absorb_pairs(P, labels, reveal=25.0, mean_d=d, reach=1000.0, tau=3.0)
    assert len(set(lab[:4].tolist())) == 1  # the crossing pairs joined
    assert len(set(lab[4:9].tolist())) == 1 and lab[4] != lab[0]  # the skin pair joined the thorax
    assert lab[9] == lab[10] and lab[9] not in set(lab[:9].tolist())  # the limb stayed a segment
    assert {how for _, how in moves} == {"joined a crossing pair", "absorbed with its pair"}


def test_a_back_waist_marker_goes_with_the_pelvis_when_the_trunk_hardly_turns_on_it() -> None:
    """Realistic walk, seed 2: the lumbar joint hardly moves, and RBWT's distances vary about as much to
    the thorax's markers as to the pelvis's (2.2 against 2.1 mm), so the rigid groups put it with the
    thorax, and the right thigh then hung on the thorax. In the thorax's frame it moves as the other pelvis
    markers do (8 mm, beyond the frame's own error), in the pelvis's it hardly does (4 mm): it is moved
    there, and the walk's tree and names come out right."""
    take = make(realistic(seed=2, frames=600, motion="walk", markerset="cmu41"))
    seg = segment.run(take.markers)
    group = dict(zip(take.markers.labels, seg.group.tolist()))
    assert group["RBWT"] == group["LFWT"] == group["RFWT"] == group["LBWT"] != group["T10"]
    assert ["RBWT", "reframed"] in seg.info["moved"]
    res = pipeline.fit(take.markers, pipeline.make_params())
    skel = res.motion.skeleton
    naming = name_skeleton(skel, res.motion, "auto")
    assert naming.humanoid, naming.note
    hips = next(s for s in range(len(skel.names)) if naming.names[s] == "Hips")
    assert group["RBWT"] == hips
    assert {naming.names[c] for c in range(len(skel.names)) if skel.parent[c] == hips} >= {"LeftUpLeg", "RightUpLeg"}
    before = segment.run(take.markers, segment.Params(reframe=False))  # the step is what mends it
    old = dict(zip(take.markers.labels, before.group.tolist()))
    assert old["RBWT"] == old["T10"] != old["LFWT"]


def _lumbar_error(take, joints) -> tuple[str, float, str]:
    """The joints stage's method and rms error (mm) for the joint between the pelvis's group and the thorax's,
    and why the stage says it chose that."""
    seg = joints.topology.segments
    group = dict(zip(take.markers.labels, seg.group.tolist()))
    pair = {group["LFWT"], group["T10"]}
    e = next(k for k, (a, b) in enumerate(joints.topology.edges) if {int(a), int(b)} == pair)
    t = take.truth
    te = list(t.joint_child).index(list(t.segment_names).index("Torso"))
    err = np.linalg.norm(joints.centres[:, e] - t.joints[:, te], axis=1)
    return joints.method[e], float(np.sqrt(np.nanmean(err ** 2))), joints.info["per_joint"][e]["why"]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_trunk_that_twists_more_than_it_bends_keeps_the_lumbar_joint_the_data_give(seed, monkeypatch) -> None:
    """Realistic runs: the trunk twists on the pelvis more than it bends, so SCoRE finds the lumbar joint
    hinge-like about the trunk's long axis, along which the pelvis's and the thorax's markers lie one
    above the other. Placed on the axis nearest the markers (the placement for a hinge across a limb), the
    thorax's seven markers pulled it 170-220 mm up into the chest; the data, which fix it more tightly than
    that, put it 16-53 mm from the truth."""
    from mocapskel.stages import joints as joints_stage

    take, res = _fitted("run", seed)
    joints = res.motion.skeleton.joints
    method, err, why = _lumbar_error(take, joints)
    assert method == "score" and err < 60.0, (method, err)
    assert "axis along the chain" in why  # the report says why
    if seed == 1:  # the placement on the axis is what the rule keeps away
        monkeypatch.setattr(joints_stage, "loose_along_axis", lambda fit, on_axis: on_axis.ok)
        method, err, why = _lumbar_error(take, joints_stage.run(joints.topology))
        assert method == "score-hinge" and err > 150.0, (method, err)
        assert "nearest the markers" in why


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_realistic_runs_joints_after_ik_against_the_truth(seed) -> None:
    """Realistic runs end to end: every matched joint's rms after IK (their lumbar and neck joints placed by
    the data along the trunk's twist axis) under 55 mm, the lumbar joint under 60 mm (measured 34.5, 47.3,
    38.4 and 33, 54, 16 mm; the rules' 32.1, 43.7 and 75.3, their refinement taking seed 3's right hip 184 mm
    from the truth; before the lumbar and neck were placed by the data, 70-77 and 165-217)."""
    from mocapskel import evaluate

    take, res = _fitted("run", seed)
    sc = evaluate.score_motion(res.motion, take.truth)
    assert sc.joint_rms_mm < 55.0, sc.joint_rms_each
    assert sc.joint_rms_each["Torso"] < 60.0, sc.joint_rms_each


@pytest.mark.xfail(strict=True, reason=(
    "the model path's left hip ends 51 mm from the truth (28.5 mm over the joints; the rules' 16.7): the walk leaves"
    " it to the prior along its flexion axis, and skin motion biases it across"))
def test_a_gait_walks_hips_sit_at_the_pelvis_edge_not_its_middle() -> None:
    """The lower-body gait set walking, seed 1 (pelvis of four markers, thighs of two): the walk leaves each
    hip free along its flexion axis, and Kirk's distance penalty, spread over the four pelvis markers, held the
    left hip where it fitted the skin-moved markers best, 99 mm above the truth (the joints 50.3 mm rms after
    IK). Its pelvis's share on the marker nearest each thigh: every joint within 25 mm rms after IK (18.9)."""
    from mocapskel import evaluate

    take = make(realistic(seed=1, frames=600, motion="walk", markerset="gait"))
    res = pipeline.fit(take.markers, pipeline.make_params())
    sc = evaluate.score_motion(res.motion, take.truth)
    assert len(sc.joint_rms_each) == 6 and sc.joint_rms_mm < 25.0, sc.joint_rms_each


def _hands_alone(wrist_mm: float) -> None:
    """Realistic ranges of motion (three seeds): no hand's marker grouped with both wrist markers, five hands of
    six a segment of their own, each of those wrists within ``wrist_mm`` rms of the truth after IK."""
    from mocapskel import evaluate

    alone = 0
    for seed in [1, 2, 3]:
        take, res = _fitted("rom", seed)
        skel = res.motion.skeleton
        group = dict(zip(skel.labels, skel.marker_segment.tolist()))
        each = evaluate.score_motion(res.motion, take.truth).joint_rms_each
        for side in "LR":
            fin = group[f"{side}FIN"]
            assert not fin == group[f"{side}WRA"] == group[f"{side}WRB"], (seed, side)
            if list(skel.marker_segment).count(fin) == 1:
                alone += 1
                assert each[f"{side}Hand"] < wrist_mm, (seed, side, each)
    assert alone >= 5


def test_a_hand_that_turns_about_the_wrist_is_not_absorbed_by_the_forearm() -> None:
    """Realistic ranges of motion (three seeds): the hand's one marker (LFIN, RFIN) turns about the wrist,
    whose markers (WRA, WRB) sit on the joint, so its distances to them hardly change and it used to join
    the forearm's group. It turns about a point of that group, so it is never put with both wrist markers;
    where it is a segment of its own (five hands of six; seed 2's right one takes the forearm's FRM as its
    partner) the wrist it hangs on is found within 20 mm rms of the true wrist after inverse kinematics
    (measured 2.9-7.1 mm, seed 2's left 15.6; the rules' 2.1-8.6)."""
    _hands_alone(20.0)


@pytest.mark.xfail(strict=True, reason=(
    "the model path's left wrist of seed 2 is 15.6 mm from the truth (the rules' 3.9), its error turning with the"
    " forearm's pose frame by frame (sd 4-8 mm)"))
def test_every_lone_hands_wrist_within_12_mm() -> None:
    """The target: every lone hand's wrist within 12 mm, as the rules had them."""
    _hands_alone(12.0)
