"""Checks before writing (mocapskel.checks): each case that once passed silently, and invariants.

Regression tests are named after what broke; the property tests fit generated
chains (hypothesis) and check the invariants every written BVH must keep.
"""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocapskel import checks, pipeline
from mocapskel.artifacts import markers_of
from mocapskel.cli.main import cli
from mocapskel.solvers.bvh_pose import bvh_rot_to_lab, bvh_to_lab, forward_kinematics
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.bvh import write_bvh
from mocapskel.io.markers import write_markers
from mocapskel.io.skeleton import write_skeleton
from mocapskel.synth.chains import hang_chain
from mocapskel.synth.human import human_take


def _fit(markers):
    return pipeline.fit(markers, pipeline.make_params())


def _names(findings, check):
    return {f.name for f in findings if f.check == check}


@pytest.fixture(scope="module")
def human_fit():
    """A generated human (1 mm noise, 1 mm soft tissue), 10 s at 120 Hz."""
    take = human_take(rng=np.random.default_rng(11), n_frames=1200, noise_mm=1.0, soft_tissue_mm=1.0)
    return take, _fit(take.markers)


@pytest.fixture(scope="module")
def chain_fit():
    take = hang_chain((4, 3, 3), 300, rng=np.random.default_rng(3), link_length=300.0)
    res = _fit(take.markers)
    return res.motion, markers_of(res.motion).points


def test_a_good_human_fit_passes_every_check(human_fit) -> None:
    _, res = human_fit
    assert res.report["checks"] == []
    assert not any(w.startswith("check ") for w in res.report["warnings"])


def test_micrometre_take_labelled_mm_warns() -> None:
    """A noise-free take scaled by 1,000 (micrometres in a file that says mm) fitted with exit 0 and no warning.

    (A generated chain: the same as the human of the report, and fast to fit.)"""
    take = hang_chain((4, 3, 3, 3), 600, rng=np.random.default_rng(2), link_length=300.0)
    for k in (1000.0, 0.001):  # micrometres, and metres, labelled mm
        res = _fit(replace(take.markers, points=take.markers.points * k))
        assert "units" in {c["check"] for c in res.report["checks"]}, (k, res.report["checks"])
        assert any(w.startswith("check units:") and "other units" in w for w in res.report["warnings"])


def test_a_take_in_mm_passes_the_units_check(human_fit) -> None:
    assert "units" not in {c["check"] for c in human_fit[1].report["checks"]}


@pytest.fixture(scope="module")
def subject_skel(tmp_path_factory):
    d = tmp_path_factory.mktemp("subject")
    cal = human_take(rng=np.random.default_rng(6), n_frames=1200, subject_seed=1, noise_mm=1.0)
    res = _fit(cal.markers)
    write_skeleton(d / "subject.skel", res.motion.skeleton)
    return d


def test_solve_with_a_subject_of_08_the_size_warns(subject_skel) -> None:
    """`solve` with another subject's skeleton (same labels, 0.8 of the size): exit 0, 79 mm residual, no warning."""
    from mocapskel.io.skeleton import read_skeleton

    skel = read_skeleton(subject_skel / "subject.skel")
    small = human_take(rng=np.random.default_rng(5), n_frames=1200, subject_seed=1, scale=0.8, noise_mm=1.0)
    res = pipeline.solve(small.markers, skel, pipeline.make_params())
    assert "residual" in {c["check"] for c in res.report["checks"]}
    # the control: the same subject solves without a residual warning
    same = human_take(rng=np.random.default_rng(5), n_frames=1200, subject_seed=1, noise_mm=1.0)
    ok = pipeline.solve(same.markers, skel, pipeline.make_params())
    assert "residual" not in {c["check"] for c in ok.report["checks"]}


def test_strict_solve_of_another_subject_exits_4_and_writes_nothing(subject_skel) -> None:
    d = subject_skel
    small = human_take(rng=np.random.default_rng(5), n_frames=1200, subject_seed=1, scale=0.8, noise_mm=1.0)
    write_markers(d / "small.trc", small.markers)
    args = ["solve", str(d / "small.trc"), "--skeleton", str(d / "subject.skel"), "-o", str(d / "s.bvh"),
            "--report", str(d / "s.json")]
    r = CliRunner().invoke(cli, args + ["--strict"])
    assert r.exit_code == 4, r.output
    assert "output checks failed" in r.output and "residual" in r.output
    assert not (d / "s.bvh").exists() and not (d / "s.json").exists()
    r = CliRunner().invoke(cli, args)  # without --strict: written, with the warnings
    assert r.exit_code == 0, r.output
    rep = json.loads((d / "s.json").read_text())
    assert any(c["check"] == "residual" for c in rep["checks"])


def test_joint_pop_and_flip_name_the_joint_and_frame(chain_fit) -> None:
    """A joint that pops (its segment turned half a turn for one frame) while the markers hardly move."""
    motion, pts = chain_fit
    assert checks.run_checks(motion, pts) == []
    s = int(np.flatnonzero(motion.skeleton.parent >= 0)[0])
    rot = motion.rot.copy()
    flip = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x
    rot[150, s] = rot[150, s] @ flip
    bad = replace(motion, rot=rot)
    found = checks.run_checks(bad, pts)
    sk = motion.skeleton
    kids = [k for k in range(len(sk.names)) if sk.parent[k] == s]
    jn = f"{sk.names[sk.parent[s]]}-{sk.names[s]}"
    flips = {f.name: f.frames for f in found if f.check == "rotation_flip"}
    assert jn in flips and set(flips[jn]) == {150, 151}
    steps = {f.name: f.frames for f in found if f.check == "joint_step"}
    for k in kids:  # the child joints of the turned segment pop at frames 150 and 151
        assert set(steps[f"{sk.names[s]}-{sk.names[k]}"]) == {150, 151}


def test_five_metre_shin_warns(chain_fit) -> None:
    """A leaf joint slid 5 m along a direction its markers do not fix: a bone longer than the subject, a joint far from its markers."""
    motion, pts = chain_fit
    sk = motion.skeleton
    leaf = int(next(s for s in range(len(sk.names)) if sk.parent[s] >= 0 and s not in sk.parent))
    origin = sk.origin.copy()
    origin[leaf] += np.array([5000.0, 0.0, 0.0])
    local = sk.marker_local.copy()
    local[sk.marker_segment == leaf] -= np.array([5000.0, 0.0, 0.0])  # its markers stay where they are
    bad = replace(motion, skeleton=replace(sk, origin=origin, marker_local=local))
    found = checks.run_checks(bad, pts)
    jn = f"{sk.names[sk.parent[leaf]]}-{sk.names[leaf]}"
    assert jn in _names(found, "bone_length")
    assert jn in _names(found, "joint_far")
    assert "bone_length" in {f.check for f in found} and all(f.name == jn for f in found if f.check == "joint_far")


def test_unconverged_joint_fit_warns(chain_fit) -> None:
    motion, pts = chain_fit
    j = motion.skeleton.joints
    per = [dict(p) for p in j.info["per_joint"]]
    per[0]["note"] = "iteration limit reached before convergence"
    sk = replace(motion.skeleton, joints=replace(j, info={**j.info, "per_joint": per}))
    bad = replace(motion, skeleton=sk)
    notes = checks.joint_notes(bad)
    child = int(j.topology.edges[0][1])
    assert list(notes) == [child]
    assert {f.check for f in checks.run_checks(bad, pts, joint_notes=notes)} == {"not_converged"}


def test_frames_text_lists_runs() -> None:
    assert checks.frames_text([3, 4, 5, 9, 11, 12]) == "3-5, 9, 11-12"
    assert checks.frames_text([]) == ""
    assert checks.frames_text(list(range(0, 40, 2)), most=3) == "0, 2, 4 (+17 more runs)"


# --------------------------------------------------------------------------- invariants (hypothesis)


@settings(max_examples=12, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(counts=st.lists(st.integers(3, 4), min_size=2, max_size=4), seed=st.integers(0, 10_000),
       up=st.sampled_from(["y", "z"]), noise=st.sampled_from([0.0, 0.5]))
def test_fit_invariants_on_generated_chains(tmp_path, counts, seed, up, noise) -> None:
    """FK of the written BVH puts every marker within noise of where it was seen; no bone longer
    than the marker extent, no joint farther than half of it from its markers, no joint step above
    the fastest marker's plus 20 mm, no flip."""
    take = hang_chain(tuple(counts), 240, rng=np.random.default_rng(seed), link_length=300.0, noise=noise)
    params = pipeline.make_params(up=up, units="mm")
    res = pipeline.fit(take.markers, params)
    assert res.report["checks"] == [], res.report["checks"]
    b = res.bvh
    path = tmp_path / f"c{seed}{up}.bvh"
    write_bvh(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    skel, root, local, _ = read_bvh(path)
    pos, G = forward_kinematics(skel, root, local, with_rot=True)
    # BVH joints are depth first: map back to the motion's segments by name
    sk = res.motion.skeleton
    idx = [skel.names.index(n) for n in sk.names]
    pos_lab = bvh_to_lab(pos[:, idx], up, "mm")
    G_lab = bvh_rot_to_lab(G[:, idx], up)
    pts = markers_of(res.motion).points
    seg = sk.marker_segment
    on = seg >= 0
    # the markers' offsets in the BVH's rest pose (another frame's than the skeleton's, when chosen so)
    local_m = np.einsum("mij,mj->mi", b.rest_rot[np.argsort(b.segment)][seg[on]], sk.marker_local[on])
    pred = pos_lab[:, seg[on]] + np.einsum("fmij,mj->fmi", G_lab[:, seg[on]], local_m)
    err = np.linalg.norm(pred - pts[:, on], axis=-1)
    rms = float(np.sqrt(np.nanmean(err**2)))
    assert rms < 3.0 * noise + 0.5, rms


def test_strict_fit_of_a_micrometre_take_exits_4_and_writes_nothing(tmp_path) -> None:
    take = hang_chain((4, 3, 3, 3), 600, rng=np.random.default_rng(2), link_length=300.0)
    src = tmp_path / "micro.trc"
    write_markers(src, replace(take.markers, points=take.markers.points * 1000.0))
    out, rep = tmp_path / "o.bvh", tmp_path / "o.json"
    r = CliRunner().invoke(cli, ["fit", str(src), "-o", str(out), "--report", str(rep), "--no-cache", "--strict"])
    assert r.exit_code == 4, r.output
    assert "units" in r.output and not out.exists() and not rep.exists()
    assert not list(tmp_path.glob(".*part"))


def test_a_hip_slid_along_the_thigh_warns_of_asymmetric_limbs(human_fit) -> None:
    """A hip slid 30 % of the thigh along it (the markers of a walk hardly fix it there: a generated gait take's
    left thigh came out 557 mm against the right's 463, though that lower-body tree is not taken for a person)
    makes one thigh of this full-body person longer than the other: said, naming both."""
    from mocapskel.model.naming import recognise

    _, res = human_fit
    motion = res.motion
    sk = motion.skeleton
    naming = recognise(sk, motion)
    role = {n: s for s, n in enumerate(naming.names)}
    hip, knee = role["LeftUpLeg"], role["LeftLeg"]
    d = 0.3 * (sk.origin[hip] - sk.origin[knee])
    origin = sk.origin.copy()
    origin[hip] += d
    local = sk.marker_local.copy()
    local[sk.marker_segment == hip] -= d  # its markers stay where they are, and the knee
    bad = replace(motion, skeleton=replace(sk, origin=origin, marker_local=local))
    found = checks.run_checks(bad, markers_of(motion).points)
    assert _names(found, "limb_asymmetry") == {f"{sk.names[hip]}/{sk.names[role['RightUpLeg']]}"}
    msg = next(f.message for f in found if f.check == "limb_asymmetry")
    assert "left and right UpLeg" in msg and "30 % apart" in msg
    # the untouched fit has none, and a non-person (a chain) is not compared
    assert not _names(checks.run_checks(motion, markers_of(motion).points), "limb_asymmetry")


def test_like_limbs_of_a_skeleton_not_taken_for_a_person_are_compared_too(human_fit, monkeypatch) -> None:
    """A lower-body gait set is not taken for a person (no head, no arms), yet its two legs are like limbs:
    two chains of the same length on the pelvis (a generated gait walk's right thigh came out 324 mm against
    the left's 442, its thigh marker alone on its segment, and nothing said so). The same hip slid 30 % of the
    thigh, in this person's skeleton looked at as not a person: said, naming both first segments of the two
    legs; the untouched fit has none."""
    from mocapskel.model import naming as naming_mod

    _, res = human_fit
    motion = res.motion
    sk = motion.skeleton
    role = {n: s for s, n in enumerate(naming_mod.recognise(sk, motion).names)}
    hip, knee, right = role["LeftUpLeg"], role["LeftLeg"], role["RightUpLeg"]
    monkeypatch.setattr(naming_mod, "recognise", lambda *a, **k: "not recognised as a person: (test)")
    assert not _names(checks.run_checks(motion, markers_of(motion).points), "limb_asymmetry")
    d = 0.3 * (sk.origin[hip] - sk.origin[knee])
    origin = sk.origin.copy()
    origin[hip] += d
    local = sk.marker_local.copy()
    local[sk.marker_segment == hip] -= d
    bad = replace(motion, skeleton=replace(sk, origin=origin, marker_local=local))
    found = checks.run_checks(bad, markers_of(motion).points)
    assert _names(found, "limb_asymmetry") == {f"{sk.names[min(hip, right)]}/{sk.names[max(hip, right)]}"}
    msg = next(f.message for f in found if f.check == "limb_asymmetry")
    assert "like limbs' first segments" in msg and "30 % apart" in msg


def _moved(motion, s: int, d: np.ndarray):
    """``motion`` with segment ``s``'s joint moved by ``d`` (rest pose), its markers left where they are."""
    sk = motion.skeleton
    origin = sk.origin.copy()
    origin[s] += d
    local = sk.marker_local.copy()
    local[sk.marker_segment == s] -= d
    return replace(motion, skeleton=replace(sk, origin=origin, marker_local=local))


def _mirror_said(motion, s: int, step: np.ndarray, fracs: tuple[float, float], pair: str) -> str:
    """``limb_mirror`` names ``pair`` when segment ``s``'s joint is moved by ``fracs[0]`` of ``step``, and nothing
    when by ``fracs[1]``; returns the message said."""
    pts = markers_of(motion).points
    said = checks.run_checks(_moved(motion, s, fracs[0] * step), pts)
    assert _names(said, "limb_mirror") == {pair}, said
    assert not _names(checks.run_checks(_moved(motion, s, fracs[1] * step), pts), "limb_mirror")
    return next(f.message for f in said if f.check == "limb_mirror")


def test_a_shoulder_put_in_the_neck_warns_that_the_shoulders_are_not_mirrored(human_fit) -> None:
    """A real CMU jump's right shoulder came out in the neck (its segment held the back and acromion markers
    too): 31 mm from the thorax's midline against the left's 130 (three quarters of the way in; 130 mm from
    the reference's shoulder), and generated walks' one shoulder 115-173 mm off; nothing said. The right
    shoulder moved 80 % of the way to the midline: said, naming both shoulders; 20 % of the way (a shoulder the
    fit left a little inside): not said; the untouched fit, whose midline joints lie on the shoulders'
    mid-plane, has none."""
    from mocapskel.model.naming import recognise

    _, res = human_fit
    motion = res.motion
    sk = motion.skeleton
    role = {n: s for s, n in enumerate(recognise(sk, motion).names)}
    left, right = role["LeftArm"], role["RightArm"]
    assert not _names(checks.run_checks(motion, markers_of(motion).points), "limb_mirror")
    half = 0.5 * (sk.origin[left] - sk.origin[right])  # the right shoulder to the midline
    msg = _mirror_said(motion, right, half, (0.8, 0.2), f"{sk.names[left]}/{sk.names[right]}")
    assert "shoulders" in msg and "mid-plane" in msg
    # which side: the moved right shoulder a fifth as far from the midline as the left
    import re

    far_l, far_r = (float(x) for x in re.search(r"the left (\d+) mm and the right (\d+) mm", msg).groups())
    assert far_r < 0.35 * far_l, msg


def test_hips_in_the_wrong_order_warn_that_the_limbs_cross(human_fit) -> None:
    """A generated gait walk's right hip (two-marker thighs, the model path) slid 300 mm along its flexion axis,
    past the left one; nothing said (a lower-body set has no midline joint for ``limb_mirror``). The right hip
    moved past the left by a third of their spacing: said, naming the two legs; moved 0.9 of the way to the left
    one (still on its own side): not said; the untouched fit has none."""
    from mocapskel.model.naming import recognise

    _, res = human_fit
    motion = res.motion
    sk = motion.skeleton
    pts = markers_of(motion).points
    role = {n: s for s, n in enumerate(recognise(sk, motion).names)}
    left, right = role["LeftUpLeg"], role["RightUpLeg"]
    assert not _names(checks.run_checks(motion, pts), "limb_cross")
    w = sk.origin[left] - sk.origin[right]
    said = checks.run_checks(_moved(motion, right, 1.33 * w), pts)
    assert _names(said, "limb_cross") == {f"{sk.names[a]}/{sk.names[b]}" for a, b in [sorted((left, right))]}, said
    assert not _names(checks.run_checks(_moved(motion, right, 0.9 * w), pts), "limb_cross")


def test_a_lumbar_joint_off_the_hips_midline_warns(human_fit) -> None:
    """A real CMU walk's (07_01) lumbar joint came out 91 mm to one side of its hips' mid-plane (a third of their
    spacing). The spine's joint moved sideways by 0.3 of the hips' spacing: said, naming the hips and the
    lumbar joint; by 0.1 of it (a lumbar joint the fit left a little to one side): not said."""
    from mocapskel.model.naming import recognise

    _, res = human_fit
    motion = res.motion
    sk = motion.skeleton
    role = {n: s for s, n in enumerate(recognise(sk, motion).names)}
    left, right = role["LeftUpLeg"], role["RightUpLeg"]
    # the lumbar joint: the origin of whichever of pelvis and spine is the other's child
    lumbar = role["Spine"] if sk.parent[role["Spine"]] == role["Hips"] else role["Hips"]
    msg = _mirror_said(motion, lumbar, sk.origin[left] - sk.origin[right], (0.3, 0.1), f"{sk.names[left]}/{sk.names[right]}")
    assert "hips" in msg and f"{sk.names[sk.parent[lumbar]]}-{sk.names[lumbar]}" in msg


def test_limbs_that_keep_a_person_shaped_tree_from_being_named_a_person_are_said(human_fit, monkeypatch) -> None:
    """A tree that is a person's but for two arms of 2 and 1 segments (a real CMU walk whose elbow hardly
    bends on one side) or two legs of unequal length (a real stair descent's, 1087 and 1644 mm, its foot
    split in two) was written without a word. The naming's reason names the two limbs; the check says it,
    naming their first segments; a reason without limbs (a head chain of three segments) says nothing."""
    from mocapskel.model import naming as naming_mod
    from mocapskel.model.naming import NotPerson, recognise

    _, res = human_fit
    motion = res.motion
    sk = motion.skeleton
    role = {n: s for s, n in enumerate(recognise(sk, motion).names)}
    la, fa, ra = role["LeftArm"], role["LeftForeArm"], role["RightArm"]
    pts = markers_of(motion).points
    for limbs, how in (((("arms", (la, fa), (ra,), 600.0, 550.0)), "have 2 and 1 segments"),
                       ((("legs", (la, fa), (ra, role["RightForeArm"]), 1087.0, 1644.0)), "1087 and 1644 mm")):
        monkeypatch.setattr(naming_mod, "recognise", lambda *a, limbs=limbs, **k: NotPerson("(test)", limbs))
        found = [f for f in checks.run_checks(motion, pts) if f.check == "limb_asymmetry"]
        assert [f.name for f in found] == [f"{sk.names[la]}/{sk.names[ra]}"], found
        assert how in found[0].message and f"the two {limbs[0]}" in found[0].message
    monkeypatch.setattr(naming_mod, "recognise", lambda *a, **k: NotPerson("a head chain of 3 segments"))
    assert not [f for f in checks.run_checks(motion, pts) if f.check == "limb_asymmetry"]


def test_naming_gives_the_unlike_limbs_it_stops_at(human_fit) -> None:
    """The naming's reason carries the two limbs when they alone keep the tree from a person's: the right
    leg lengthened by 700 mm below the knee (its shank's and foot's joints moved down, markers with them)."""
    from mocapskel.model.naming import NotPerson, recognise

    _, res = human_fit
    motion = res.motion
    sk = motion.skeleton
    role = {n: s for s, n in enumerate(recognise(sk, motion).names)}
    origin = sk.origin.copy()
    along = sk.origin[role["RightLeg"]] - sk.origin[role["RightUpLeg"]]  # hip to knee
    for n in ("RightLeg", "RightFoot"):
        origin[role[n]] += 700.0 * along / np.linalg.norm(along)
    why = recognise(replace(sk, origin=origin), motion)
    assert isinstance(why, NotPerson) and "legs of unequal length" in why
    what, ca, cb, a, b = why.limbs
    assert what == "legs" and {ca[0], cb[0]} == {role["LeftUpLeg"], role["RightUpLeg"]} and max(a, b) > 1.5 * min(a, b)


def test_step_lengths_are_numpys_norm_of_the_differences_to_the_bit():
    """The checks' frame-to-frame steps, a block of frames at a time, against ``np.linalg.norm(np.diff(x))``."""
    from mocapskel.checks import _steps

    rng = np.random.default_rng(1)
    for F in (1, 2, 3, 100, 5000):
        x = rng.normal(0, 500, (F, 7, 3))
        x[rng.random((F, 7)) < 0.1] = np.nan
        with np.errstate(invalid="ignore"):
            ref = np.linalg.norm(np.diff(x, axis=0), axis=-1)
        got = _steps(x, block=37)
        assert got.shape == ref.shape
        np.testing.assert_array_equal(got, ref)


def test_joint_turns_are_the_angles_of_the_relative_rotations_steps():
    """The rotation_flip check's per-frame turn of every joint against the angle of ``L[f]^T L[f+1]``,
    ``L = G[parent]^T G`` formed with scipy's rotations."""
    from scipy.spatial.transform import Rotation

    from mocapskel.checks import _joint_turns

    rng = np.random.default_rng(4)
    F, parent = 50, np.array([-1, 0, 1, 1])
    G = Rotation.from_rotvec(rng.normal(0, 1.2, (F * 4, 3))).as_matrix().reshape(F, 4, 3, 3)
    got = _joint_turns(G, parent)
    for s, p in enumerate(parent):
        L = Rotation.from_matrix(G[:, s]) if p < 0 else Rotation.from_matrix(G[:, p]).inv() * Rotation.from_matrix(G[:, s])
        want = np.degrees((L[:-1].inv() * L[1:]).magnitude())
        np.testing.assert_allclose(got[:, s], want, atol=1e-6)
