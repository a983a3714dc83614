"""Real takes scored against another party's skeleton (``../shared/realref/``).

The folder sits beside the repository and is not committed; when it is absent
these tests are skipped and say so loudly. Each test fits a take through the
command line, as a user would, and scores the BVH with the folder's own
``score.py``.

The bars asserted here are what the pipeline reaches today, so that a change
that makes a real take worse fails; they are below the targets the project
aims at (for ``cmu_16_07``: 14 of 20 joints within 35 mm rms), which BENCHMARKS.md
tracks; the walking take's (30 mm) is met and asserted.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel import pipeline
from mocapskel.cli.main import cli

REALREF = Path(__file__).resolve().parents[2] / "shared" / "realref"
REALDATA = REALREF.parent / "realdata"
MISSING = f"REFERENCE TAKES NOT FOUND at {REALREF} — the real-take quality tests did NOT run (see shared/realref/README.md)"


_SCORES: dict[str, tuple[dict, Path]] = {}


def _score(name: str, tmp_path: Path) -> dict:
    """score.py's scores of our BVH of a reference take, fitted once per test run (the BVH and the report copied
    into ``tmp_path``)."""
    if not (REALREF / "score.py").is_file():
        pytest.skip(MISSING)
    if name not in _SCORES:
        _SCORES[name] = (_fit_and_score(name, tmp_path), tmp_path)
    s, where = _SCORES[name]
    if where != tmp_path:
        for ext in (".bvh", ".json"):
            shutil.copy(where / f"{name}{ext}", tmp_path / f"{name}{ext}")
    return s


def _fit_and_score(name: str, tmp_path: Path) -> dict:
    out = tmp_path / f"{name}.bvh"
    r = CliRunner().invoke(cli, ["fit", str(REALREF / f"{name}.c3d"), "-o", str(out), "--up", "z", "--units", "mm",
                                 "--no-cache", "-q", "--report", str(tmp_path / f"{name}.json")])
    assert r.exit_code == 0, r.stderr
    s = subprocess.run([sys.executable, str(REALREF / "score.py"), name, str(out)], capture_output=True, text=True,
                       check=True)
    return json.loads(s.stdout.strip().splitlines()[-1])


def test_walking_take_finds_the_leg_joints(tmp_path: Path) -> None:
    """A 26-marker gait take: hips, knees and ankles in the right tree, all six found, within 30 mm
    rms (the project's bar; 28.9 now), bones within 12 mm. Regressions: walking turns hip, knee and
    ankle about one axis, and the refinement slid the chain along it (each hinge held only against its
    parent's origin), a knee 128 mm out of the leg; the left ankle, which SCoRE fixes in full but which
    turns about one axis, slid 45 mm along it until such joints were held too (41.6 mm rms before); the
    right ankle sat 46 mm medial along its axis (57 mm rms; 34.3 overall) until the ends of limbs were
    put at the middle of their markers along the axis (26 mm)."""
    s = _score("opensim_test_walking", tmp_path)
    assert s["joints_matched"] == 6, s["unmatched_ref"]
    assert s["joint_rms_mean_mm"] <= 30.0, s["per_joint_rms_mm"]
    assert s["pairs_adjacent_in_bvh"] == s["pairs_scored"] >= 3  # every scored leg bone is a bone of the tree
    assert s["bone_err_mm_mean"] <= 12.0, s["bones"]


def _walk_on_the_model_path(tmp_path: Path, **kw) -> dict:
    """opensim_test_walking fitted on the model path with ``rigid.Params`` ``kw``, scored against its reference."""
    if not (REALREF / "score.py").is_file():
        pytest.skip(MISSING)
    from mocapskel.io.bvh import write_bvh
    from mocapskel.stages import rigid

    params = pipeline.make_params(up="z", units="mm")
    params["rigid"] = rigid.Params(joint_model="map", **kw)
    b = pipeline.fit(REALREF / "opensim_test_walking.c3d", params).bvh
    bvh = tmp_path / ("walk_" + "_".join(f"{k}{v}" for k, v in kw.items()) + ".bvh")
    write_bvh(bvh, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    r = subprocess.run([sys.executable, str(REALREF / "score.py"), "opensim_test_walking", str(bvh)],
                       capture_output=True, text=True, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_the_model_paths_knees_lie_in_line_with_hips_and_ankles_on_a_gait_lab_walk(tmp_path: Path) -> None:
    """The same walk on the model path (``joint_model="map"``): no knee markers, lateral thigh and shank clusters, so
    the data leave each knee free along its flexion axis. Lined up with its hip and ankle (``line_sigma``), the right
    knee ends within 45 mm of the reference (37.4 now; 56.3 without the line factor, the joints stage's 43.6 pulled
    further along the axis), all six joints within 32 mm rms (30.2; 33.2 without)."""
    free, lined = (_walk_on_the_model_path(tmp_path, line_sigma=ls) for ls in (0.0, 0.01))
    knee = next(k for k in lined["per_joint_rms_mm"] if k.startswith("RKJC"))
    assert lined["joints_matched"] == 6 and lined["joint_rms_mean_mm"] <= 32.0, lined["per_joint_rms_mm"]
    assert lined["per_joint_rms_mm"][knee] <= 45.0 < free["per_joint_rms_mm"][knee], (lined, free)


def test_the_model_paths_prior_mean_deepens_without_a_hinge_test(tmp_path: Path) -> None:
    """The same walk: the prior's mean deepens and centres every joint that qualifies, about the axis it turns about
    most (``mean_ratio=1``), not only those that pass the hinge test: the left ankle 27.0 -> 20.6 mm from the reference,
    the six joints 29.6 -> 28.2 mm rms."""
    tested, untested = (_walk_on_the_model_path(tmp_path, mean_ratio=r) for r in (None, 1.0))
    ankle = next(k for k in untested["per_joint_rms_mm"] if k.startswith("LAJC"))
    assert untested["joints_matched"] == 6 and untested["joint_rms_mean_mm"] <= 29.0, untested["per_joint_rms_mm"]
    assert untested["per_joint_rms_mm"][ankle] <= tested["per_joint_rms_mm"][ankle] - 4.0, (untested, tested)


def test_robot_arm_links_between_parallel_axes_within_five_percent(tmp_path: Path) -> None:
    """The Kinova arm: links whose joints are hinges on parallel axes (no centre along the axis) get
    their axis-to-axis length, not a joint that slid metres along the axis."""
    s = _score("kinova_dynamique_pierre", tmp_path)
    good = [lk for lk in s["links"] if lk["err_pct"] <= 5.0]
    assert len(good) >= 2, s["links"]
    # no bone metres long: the joint between the two links with an unmarked link between them ran 1.7 m
    # down the axes (bones of 3.5 m) until it was held where the axes pass nearest the markers
    rep = json.loads((tmp_path / "kinova_dynamique_pierre.json").read_text())
    assert not [c for c in rep["checks"] if c["check"] in ("bone_length", "joint_far")], rep["checks"]
    assert max(b["length_mm"] for b in rep["bones"] if b["length_mm"] is not None) < 300.0, rep["bones"]


def test_cmu_full_body_take_joints_and_bones(tmp_path: Path) -> None:
    """The 41-marker CMU set on a two-footed jump: at least 12 of the 20 reference joints, joints within
    52 mm rms (50.0 now; the rules' 48.8, knees within 40 mm, are the target below), both hips within 40 mm
    (17 and 35 now). The fitted tree is a person's (pelvis; thorax with the head and both arms; two legs of three),
    and the BVH carries humanoid names, rooted at the pelvis.
    The legs move together, so the markers fix neither hip along the line between them: the fit
    slid both 90-100 mm to one side (the left hip unmatched, the right 95 mm off, 12 joints at 64.8 mm)
    until like limbs were put back into their parent's plane of symmetry; and it slid them together,
    13 mm apart, until a start whose hips had slid together lost to one whose had not, and hips slid
    together were held where the start had them. Nor do the markers fix a knee along
    its flexion axis: the left knee slid 76 mm past its knee marker, out of the leg (unmatched, 148 mm
    lateral), and the right stayed at its marker, 74 mm lateral (78 mm off; 13 joints at 55.1 mm),
    until knees were put a limb half-width inside their marker, with the half-widths measured from the
    axis at the marker's level and the thigh's and shank's own twist left out of the hinge test.
    Fewer joints than the 14 of an earlier fit: the thorax is one segment now (C7 and T10 made a
    group of their own, on which the chest group hung from the head, one joint more), and the 14th,
    CMU's lumbar joint, had been matched by the root's origin (the mean of its children's joints).
    Bones within 30 mm on average over the pairs scored (27.2 over 9 now; 37.1 while Kirk's distance
    penalty pulled each hip towards the middle of the pelvis's four markers, the hips 146 mm apart against
    CMU's 173, now 204 with the pelvis's share on its marker nearest each thigh): what is left is the
    thighs (22 and 34 mm long), the left upper arm (its elbow at the marker: the forearm carries the hand's
    markers, so only one limb measures a half-width), and the pairs to CMU's lumbar joint, matched by our
    root (the hips' midpoint, as humanoid rigs have it). The target is 25 mm."""
    s = _score("cmu_16_07", tmp_path)
    assert s["joints_matched"] >= 12, s["unmatched_ref"]
    hips = {k: v for k, v in s["per_joint_rms_mm"].items() if k.startswith(("lhip", "rhip"))}
    assert len(hips) == 2 and max(hips.values()) <= 40.0, s["per_joint_rms_mm"]
    knees = {k: v for k, v in s["per_joint_rms_mm"].items() if k.startswith(("lknee", "rknee"))}
    assert len(knees) == 2, s["per_joint_rms_mm"]
    assert s["bone_err_mm_mean"] <= 30.0, s["bones"]
    assert s["joint_rms_mean_mm"] <= 52.0, s["per_joint_rms_mm"]
    names = set(s["matched"].values())  # recognised as a person: humanoid names, each where CMU has it
    assert {"LeftUpLeg", "RightUpLeg", "LeftLeg", "RightLeg", "Head", "LeftArm", "LeftForeArm"} <= names, s["matched"]
    assert s["matched"]["lhip[lfemur]"] == "LeftUpLeg" and s["matched"]["rknee[rtibia]"] == "RightLeg"


@pytest.mark.xfail(strict=True, reason=(
    "the model path's left knee is 61 mm from CMU's (the right 46; the rules' 37 and 24): its prior's mean is not"
    " deepened inside its knee marker, the two knees' pooled half-width (33 mm) finding no marker over its axis"))
def test_cmu_take_knees_within_40_mm(tmp_path: Path) -> None:
    """cmu_16_07's knees within 40 mm of CMU's and the joints within 50 mm rms: what the rules reached and the
    model path does not yet (the target)."""
    s = _score("cmu_16_07", tmp_path)
    knees = {k: v for k, v in s["per_joint_rms_mm"].items() if k.startswith(("lknee", "rknee"))}
    assert len(knees) == 2 and max(knees.values()) <= 40.0, s["per_joint_rms_mm"]
    assert s["joint_rms_mean_mm"] <= 50.0, s["per_joint_rms_mm"]


def test_cmu_take_says_its_shoulders_are_not_mirrored_where_the_reference_shows_one_misplaced(tmp_path: Path) -> None:
    """The CMU jump's right upper-arm segment holds the back and acromion markers too (RBAC, RSHO), and its
    shoulder joint comes out in the neck: 31 mm from the thorax's midline against the left's 130 (the
    reference's right shoulder 130 mm away). Bones of equal length, so nothing said it until the midline
    joints were checked against the shoulders' mid-plane. The check names the shoulders, and the reference
    agrees: one of the two shoulders is more than 100 mm from CMU's. The hips, both within 40 mm of CMU's
    (asserted above), are not named."""
    import gc
    import importlib.util
    import warnings

    if not (REALREF / "score.py").is_file():
        pytest.skip(MISSING)
    out, rep = tmp_path / "cmu.bvh", tmp_path / "cmu.json"
    r = CliRunner().invoke(cli, ["fit", str(REALREF / "cmu_16_07.c3d"), "-o", str(out), "--up", "z", "--units", "mm",
                                 "--no-cache", "-q", "--report", str(rep)])
    assert r.exit_code == 0, r.stderr
    found = [c for c in json.loads(rep.read_text())["checks"] if c["check"] == "limb_mirror"]
    assert len(found) == 1 and "the shoulders" in found[0]["message"], found
    spec = importlib.util.spec_from_file_location("realref_bvh", REALREF / "bvh.py")  # the scorer's own reader
    rbvh = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rbvh)
    with warnings.catch_warnings():  # the scorer's reader leaves its file to the garbage collector
        warnings.simplefilter("ignore", ResourceWarning)
        nodes, motion, _ = rbvh.parse(str(out))
        gc.collect()
    P = rbvh.fk(nodes, motion)
    names = [n.name for n in nodes]
    ref = np.load(REALREF / "cmu_16_07.ref.npz")
    rn = [str(n) for n in ref["names"]]
    off = {}
    for side, s in (("Left", "l"), ("Right", "r")):
        J = ref["joints"][: len(P), rn.index(f"{s}shoulder[{s}humerus]")]
        off[side] = float(np.nanmean(np.linalg.norm(P[: len(J), names.index(f"{side}Arm")] - J, axis=1)))
    assert max(off.values()) > 100.0, off


@pytest.mark.parametrize("rel,want", [
    ("joint-localization/arm-4-4-4_clean_30fps.c3d", [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]]),
    ("joint-localization/arm-4-2-3_clean_120fps.c3d", [[0, 1, 2, 3], [4, 5], [6, 7, 8]]),
])
def test_unlabelled_arm_takes_give_their_authors_grouping(rel: str, want: list) -> None:
    """The grouping the takes' author gives (../shared/realref/README.md): exactly three segments."""
    p = REALDATA / rel
    if not p.is_file():
        pytest.skip(f"REAL DATA NOT FOUND at {p} — the arm grouping test did NOT run")
    from mocapskel import pipeline

    seg = pipeline.run_until(p, "segment").artifact
    got = sorted(sorted(int(i) for i in seg.members(s)) for s in range(seg.n_segments))
    assert got == sorted(want)


def test_knee_trial_gives_thigh_shank_and_a_still_body() -> None:
    """A functional knee trial (biobuddy, 73 markers: rigid plates and anatomical markers): only the right
    knee moves, so the take supports three segments: the femur's markers, the shank's with the foot's
    (the ankle hardly moves), and the still body. Its marker plates are rigid to 0.2 mm among themselves,
    but the still body's parts sway against each other by a few mm: that does not locate a joint, and
    the body must not be cut into its plates (26 segments before)."""
    p = REALDATA / "biobuddy/functional_trials/right_knee.c3d"
    if not p.is_file():
        pytest.skip(f"REAL DATA NOT FOUND at {p} — the knee-trial segmentation test did NOT run")
    from mocapskel import pipeline

    groups = [set(g) for g in pipeline.run_until(p, "segment").artifact.info["groups"]]
    femur = {"RGT", "RLFE", "RMFE", "RTHI1", "RTHI2", "RTHI3"}  # trochanter, epicondyles, thigh plate
    shank = {"RLM", "RLEG1", "RLEG2", "RLEG3"}  # lateral malleolus, shank plate
    assert len(groups) == 3
    assert femur in groups
    assert any(shank <= g and not g & femur for g in groups)
    assert any({"LASIS", "RASIS", "C7", "LLEG1", "LARM1"} <= g for g in groups)


@pytest.mark.parametrize("rel", [
    "biobuddy/functional_trials/static_lower_body.c3d",
    "biobuddy/lower_limb_calibration/anatomical_posture.c3d",
    "kineticstoolkit/sample_static.c3d",
    "opensim-models/subject01_static.trc",
])
def test_static_trials_are_refused_as_one_rigid_body(rel: str, tmp_path: Path) -> None:
    """A standing still subject sways by a few mm: no joint to find, exit 4 and the reason."""
    p = REALDATA / rel
    if not p.is_file():
        pytest.skip(f"REAL DATA NOT FOUND at {p} — the static-trial test did NOT run")
    out = tmp_path / "o.bvh"
    r = CliRunner().invoke(cli, ["fit", str(p), "-o", str(out), "--no-cache", "-q"])
    assert r.exit_code == 4, r.stderr
    assert "all markers move as one rigid body" in r.stderr and not out.exists()


def test_gait_take_with_one_marker_pelvis_pieces_has_no_bone_of_metres(tmp_path: Path) -> None:
    """Eb015pr (c3d.org gait sample, rigid thigh and shank plates, skin markers on the pelvis): a pelvis
    marker that hardly moves against its neighbours became a one-marker segment whose sphere fit put
    its joint with the thigh 13 m away (a 13 m thigh bone). Such a marker now joins its group, and a
    one-marker joint keeps JMV's centre where the sphere fit's costs more."""
    p = REALDATA / "c3d_org_samples/Eb015pr.c3d"
    if not p.is_file():
        pytest.skip(f"REAL DATA NOT FOUND at {p} — the one-marker-segment test did NOT run")
    rep = tmp_path / "r.json"
    r = CliRunner().invoke(cli, ["fit", str(p), "-o", str(tmp_path / "o.bvh"), "--report", str(rep), "--no-cache", "-q"])
    assert r.exit_code == 0, r.stderr
    d = json.loads(rep.read_text())
    failing = {c["check"] for c in d["checks"]}
    assert not failing & {"bone_length", "joint_far"}, d["checks"]
    assert max(b["length_mm"] for b in d["bones"] if b.get("length_mm") is not None) < 1000.0


#: The CMU/HDM05 41-marker set (Vicon's full-body set as these takes label it): the body part each
#: marker rides on, and markers over a joint, which may ride either part.
_ON = {**dict.fromkeys(("LFHD", "RFHD", "LBHD", "RBHD"), "head"), **dict.fromkeys(("C7", "T10", "CLAV", "STRN", "RBAC"), "thorax"),
       **dict.fromkeys(("LFWT", "RFWT", "LBWT", "RBWT"), "pelvis")}
_OVER = {}
_PARENT = {"thorax": "pelvis", "head": "thorax"}
for _s in "LR":
    _ON.update({_s + "UPA": _s + "uarm", _s + "FRM": _s + "farm", _s + "FIN": _s + "hand", _s + "THI": _s + "thigh",
                _s + "SHN": _s + "shank", **dict.fromkeys((_s + "HEE", _s + "TOE", _s + "MT5"), _s + "foot")})
    _OVER.update({_s + "SHO": ("thorax", _s + "uarm"), _s + "ELB": (_s + "uarm", _s + "farm"),
                  _s + "WRA": (_s + "farm", _s + "hand"), _s + "WRB": (_s + "farm", _s + "hand"),
                  _s + "KNE": (_s + "thigh", _s + "shank"), _s + "ANK": (_s + "shank", _s + "foot")})
    _PARENT.update({_s + "uarm": "thorax", _s + "farm": _s + "uarm", _s + "hand": _s + "farm", _s + "thigh": "pelvis",
                    _s + "shank": _s + "thigh", _s + "foot": _s + "shank"})


def _parts(labels: list[str]) -> set[str]:
    """The body parts a group of markers rides on: its markers' parts, or, for a group of markers over
    joints only, the parts on either side."""
    names = [lb.split(":")[-1] for lb in labels]
    on = {_ON[n] for n in names if n in _ON}
    return on or {p for n in names if n in _OVER for p in _OVER[n]}


@pytest.mark.parametrize("path", ["realref/cmu_16_07.c3d", "realdata/cmu/07_12.c3d", "realdata/hdm05/HDM_mm_01-02_03_120.c3d"])
def test_cmu_marker_set_trees_join_only_neighbouring_body_parts(path: str) -> None:
    """Three real takes of the CMU set (a two-footed jump, a walk, HDM05's): every joint of the tree joins
    groups that ride on the same or neighbouring body parts. Regressions: in the jump the thighs move
    together and a two-marker thigh "joined" the other thigh anywhere their marker circles met; in the
    others an upper arm joined the other elbow, and a thigh a toe."""
    p = REALREF.parent / path
    if not p.is_file():
        pytest.skip(MISSING)
    topo = pipeline.run_until(p, "topology").artifact
    seg = topo.segments
    bad = []
    for a, b in topo.edges.tolist():
        A, B = (_parts([seg.markers.labels[i] for i in seg.members(s)]) for s in (a, b))
        if A and B and not any(x == y or _PARENT.get(x) == y or _PARENT.get(y) == x for x in A for y in B):
            bad.append((sorted(A), sorted(B)))
    assert not bad, bad


@pytest.mark.parametrize("path", ["realref/cmu_16_07.c3d", "realdata/cmu/07_01.c3d", "realdata/cmu/07_12.c3d",
                                  "realdata/cmu/85_02.c3d", "realdata/hdm05/HDM_bd_05-01_01_120.c3d",
                                  "realdata/hdm05/HDM_mm_01-02_03_120.c3d"])
def test_cmu_marker_set_head_hangs_on_the_thorax(path: str) -> None:
    """Six real takes of the CMU set: the head group joins only groups with a thorax marker (C7, T10,
    CLAV, STRN, RBAC). Regressions: in a walk (07_12) and HDM05's bd take the head moves with the trunk,
    and a two-marker upper-arm or shoulder group given the trunk's shoulder as an extra point "joined"
    the head on that point by dilution alone."""
    p = REALREF.parent / path
    if not p.is_file():
        pytest.skip(MISSING)
    topo = pipeline.run_until(p, "topology").artifact
    seg = topo.segments
    names = [[str(seg.markers.labels[i]).split(":")[-1] for i in seg.members(s)] for s in range(seg.n_segments)]
    head = [s for s in range(seg.n_segments) if {"LFHD", "RFHD", "LBHD", "RBHD"} & set(names[s])]
    assert len(head) == 1, [names[s] for s in head]
    nbrs = [b if a == head[0] else a for a, b in topo.edges.tolist() if head[0] in (a, b)]
    thorax = {"C7", "T10", "CLAV", "STRN", "RBAC"}
    assert nbrs and all(thorax & set(names[s]) for s in nbrs), [names[s] for s in nbrs]


def _fit_report(rel: str, tmp_path: Path, what: str) -> dict:
    """The report of ``mocapskel fit`` on a take of the real-data folder (skipped, saying so, without it)."""
    p = REALDATA / rel
    if not p.is_file():
        pytest.skip(f"REAL DATA NOT FOUND at {p} — {what} did NOT run")
    rep = tmp_path / "r.json"
    r = CliRunner().invoke(cli, ["fit", str(p), "-o", str(tmp_path / "o.bvh"), "--no-cache", "-q", "--report", str(rep)])
    assert r.exit_code == 0, r.stderr
    return json.loads(rep.read_text())


@pytest.mark.parametrize("rel,what,how", [
    # the right foot split in two (rigid plates on the shank: the foot's own flexion of 1.4-2.5 mm is above
    # the take's tolerance), a rear-foot bone of 472-493 mm where the left foot's is 153: legs of 3 and 4
    # segments, 48-52 % apart in length (said by their lengths above half apart, else by their numbers of
    # segments: where the held refinement leaves the rear foot's joint decides which; since the joints stage
    # scores its estimators' candidates held in a segment, the rear foot's bone is 205 mm)
    ("addbiomechanics/stairdown_markers.trc", "legs", ("mm long from the trunk", "have 3 and 4 segments")),
    # a short walk whose left elbow hardly bends: upper arm and forearm one segment on that side
    ("cmu/07_12.c3d", "arms", "have 2 and 1 segments"),
])
def test_person_shaped_trees_with_unlike_limbs_say_so(rel: str, what: str, how: str | tuple[str, ...], tmp_path: Path) -> None:
    """A tree that is a person's but for its two legs (or arms) of unequal length or of unequal numbers of
    segments is not named as a person, and was written with no warning: a skeleton no person has. Said now
    (``limb_asymmetry``), naming the two limbs."""
    report = _fit_report(rel, tmp_path, "the unlike-limbs test")
    assert "not recognised as a person" in report["export"]["names"]["note"]
    found = [c for c in report["checks"] if c["check"] == "limb_asymmetry" and f"the two {what}" in c["message"]]
    assert len(found) == 1 and any(h in found[0]["message"] for h in ((how,) if isinstance(how, str) else how)), report["checks"]
    if what == "legs":  # the split foot made one leg a segment longer
        kids = {}
        for b in report["bones"]:
            kids.setdefault(b["parent"], []).append(b["segment"])
        length = {b["segment"]: b["length_mm"] for b in report["bones"]}
        chains = []
        for first in found[0]["name"].split("/"):
            chain = [first]
            while len(kids.get(chain[-1], [])) == 1:
                chain.append(kids[chain[-1]][0])
            chains.append(chain)
        assert sorted(len(c) for c in chains) == [3, 4], chains
        # the split foot's bones are a foot's, not longer than a shank (472-493 mm before the joints stage
        # scored its estimators' candidates held in a segment; 205 mm since)
        long = max(chains, key=len)
        assert all(0.0 < length[s] < 400.0 for s in long[2:]), length


@pytest.mark.xfail(strict=True, reason=(
    "on the model path the thighs come out 471 and 364 mm (limb_asymmetry says so): the right thigh carries one"
    " marker and its knee marker rides on the shank, so the two legs are no like limbs for the bone-length tie"
    " (tying legs of the same shape whatever their marker counts cost the found groupings of the generated bench)"))
def test_a_walks_legs_keep_their_like_bones_when_two_starts_tie(tmp_path: Path) -> None:
    """CMU 07_01 (a walk): the rigid stage's two starts end 0.3 % apart in marker residual, which the markers
    do not tell apart; the lower one had the right thigh (one marker) 323 mm long against the left's 469.
    Between starts that tie, the one whose like limbs' bones are alike wins: the thighs within a fifth of each
    other, and no limb_asymmetry said of them."""
    report = _fit_report("cmu/07_01.c3d", tmp_path, "the tied-starts test")
    segs = {x["name"]: x["markers"] for x in report["segments"]}
    length = {b["segment"]: b["length_mm"] for b in report["bones"]}
    thighs = [n for n, m in segs.items() if {"LTHI"} <= set(m) or {"RTHI"} <= set(m)]
    assert len(thighs) == 2, segs
    a, b = (length[t] for t in thighs)
    assert max(a, b) <= 1.2 * min(a, b), (thighs, a, b)
    assert not [c for c in report["checks"] if c["check"] == "limb_asymmetry" and set(c["name"].split("/")) == set(thighs)]
