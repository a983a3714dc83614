"""Humanoid names without a template, re-rooting at the pelvis, T-pose/A-pose rest: joints stay put."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.solvers.bvh_pose import bvh_to_lab, forward_kinematics
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.bvh import write_bvh
from mocapskel.model.naming import name_skeleton
from mocapskel.stages import export
from mocapskel.synth.body import HUMANOID_NAMES, LABEL_CODES, PARENT, SEGMENTS
from mocapskel.synth.presets import Recipe, make

EXPECTED = HUMANOID_NAMES
CODE_TO_SEGMENT = dict(zip(LABEL_CODES, SEGMENTS))
CASES = [("rom", 0), ("rom", 1), ("rom", 2), ("run", 0), ("walk", 0)]

def _depth(s: int) -> int:
    d = 0
    while PARENT[s] >= 0:
        s, d = PARENT[s], d + 1
    return d


def _fit(motion: str, seed: int, mirror: bool = False, neutral_labels: bool = False):
    take = make(Recipe(kind="human", frames=400 if motion == "rom" else 600, noise_mm=1.0, soft_tissue_mm=2.0,
                       gaps_per_marker_per_minute=4.0, seed=seed, motion=motion))
    mk = take.markers
    if mirror:  # the subject's mirror image: its left is the generated right
        pts = mk.points.copy()
        pts[..., 1] *= -1
        mk = replace(mk, points=pts)
    if neutral_labels:
        mk = replace(mk, labels=tuple(f"M{i:03d}" for i in range(len(mk.labels))))
    return take, pipeline.fit(mk, pipeline.make_params())


@pytest.fixture(scope="module", params=[pytest.param(c, id=f"{c[0]}-seed{c[1]}") for c in CASES])
def fitted(request):
    return _fit(*request.param)


def _expected_names(take, skel, swap_sides: bool = False) -> list[str]:
    """Each fitted segment's name from the truth: that of its most proximal generated segment."""
    out = []
    for s in range(len(skel.names)):
        segs = {CODE_TO_SEGMENT[skel.labels[m][:4]] for m in np.flatnonzero(skel.marker_segment == s)}
        prox = min(segs, key=lambda n: _depth(SEGMENTS.index(n)))
        name = EXPECTED[prox]
        if swap_sides:
            name = name.replace("Left", "R_").replace("Right", "Left").replace("R_", "Right")
        out.append(name)
    return out


def test_generated_human_gets_every_joint_named_right_left_and_right_included(fitted) -> None:
    take, res = fitted
    skel = res.motion.skeleton
    naming = name_skeleton(skel, res.motion, "auto")
    assert naming.humanoid, naming.note
    assert list(naming.names) == _expected_names(take, skel)
    # without the labels' L/R prefixes, from the geometry alone: the same names
    neutral = replace(skel, labels=tuple(f"M{i:03d}" for i in range(len(skel.labels))))
    geo = name_skeleton(neutral, res.motion, "auto")
    assert geo.side_from == "geometry"
    assert geo.names == naming.names


def test_mirrored_subject_swaps_left_and_right_from_geometry() -> None:
    take, res = _fit("rom", 4, mirror=True, neutral_labels=True)
    skel = res.motion.skeleton
    naming = name_skeleton(skel, res.motion, "auto")
    assert naming.humanoid and naming.side_from == "geometry", naming.note
    # skeleton labels are neutral; map them back to the generated ones by position in the take
    skel_true = replace(skel, labels=tuple(take.markers.labels[int(l[1:])] for l in skel.labels))
    assert list(naming.names) == _expected_names(take, skel_true, swap_sides=True)


@pytest.mark.parametrize("kind", ["linkage", "chain"])
def test_non_humans_keep_generic_names_with_a_note(kind: str) -> None:
    take = make(Recipe(kind=kind, frames=600, seed=1, noise_mm=0.5))
    res = pipeline.fit(take.markers, pipeline.make_params(names="humanoid", rest="tpose"))
    b = res.bvh
    assert not b.naming.humanoid
    assert b.skeleton.names[0] == res.motion.skeleton.names[int(np.flatnonzero(res.motion.skeleton.parent < 0)[0])]
    assert res.report["export"]["names"]["scheme"] == "segments"
    assert "not recognised as a person" in res.report["export"]["names"]["note"]
    assert any("--names humanoid" in w for w in res.report["warnings"])
    assert any("--rest tpose" in w for w in res.report["warnings"]) and b.rest == "frame"


def _edge_positions(b, up: str, units: str) -> dict[frozenset, np.ndarray]:
    """World position (lab mm) of every joint of the fitted tree, keyed by the two segments it joins."""
    P = bvh_to_lab(forward_kinematics(b.skeleton, b.root_pos, b.local_rot), up, units)
    seg = b.segment
    return {frozenset((int(seg[i]), int(seg[p]))): P[:, i] for i, p in enumerate(b.skeleton.parent.tolist()) if p >= 0}


@pytest.mark.parametrize(("up", "units"), [("y", "cm"), ("z", "mm")])
def test_humanoid_root_and_rest_poses_keep_every_joint_where_it_was(fitted, tmp_path: Path, up: str, units: str) -> None:
    _, res = fitted
    m = res.motion
    base = export.run(m, export.Params(up=up, units=units, names="segments"))
    assert base.skeleton.names[0] == m.skeleton.names[int(np.flatnonzero(m.skeleton.parent < 0)[0])]
    want = _edge_positions(base, up, units)
    for rest in ("frame", "tpose", "apose"):
        b = export.run(m, export.Params(up=up, units=units, names="auto", rest=rest))
        assert b.skeleton.names[0] == "Hips" and b.rest == rest
        path = tmp_path / f"{rest}.bvh"
        write_bvh(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
        skel, root_pos, local_rot, _ = read_bvh(path)  # through the file: its rounding included
        got = _edge_positions(replace(b, skeleton=skel, root_pos=root_pos, local_rot=local_rot), up, units)
        assert got.keys() == want.keys()
        err = max(float(np.abs(got[k] - want[k]).max()) for k in want)
        assert err < 0.01, (rest, err)  # mm, every joint, every frame


def test_tpose_has_limbs_along_the_axes_and_a_visible_hips_bone(fitted) -> None:
    _, res = fitted
    for rest in ("tpose", "apose"):
        b = export.run(res.motion, export.Params(up="z", units="mm", rest=rest))  # BVH axes = lab axes
        off = dict(zip(b.skeleton.names, b.skeleton.offset))

        def direction(name: str) -> np.ndarray:
            return off[name] / np.linalg.norm(off[name])

        # a child's OFFSET is its parent bone at rest: thigh and shank down, upper arm and forearm sideways
        for child in ("LeftLeg", "LeftFoot", "RightLeg", "RightFoot"):
            assert np.allclose(direction(child), [0, 0, -1], atol=1e-9), child
        s = np.sqrt(0.5)
        arm_dir = {"tpose": [1.0, 0, 0], "apose": [s, 0, -s]}[rest]
        for child in [c for c in ("LeftForeArm", "LeftHand") if c in off]:
            assert np.allclose(direction(child), arm_dir, atol=1e-9), child
        for child in [c for c in ("RightForeArm", "RightHand") if c in off]:
            assert np.allclose(direction(child), [-arm_dir[0], 0, arm_dir[2]], atol=1e-9), child
        if "Spine" in off:  # a walk hardly moves the lumbar joint: its trunk is one segment, with no spine
            spine = direction("Spine")  # up; sideways only as far as the fitted lumbar joint is off the hips' midline
            assert abs(spine[1]) < 1e-9 and spine[2] > 0.9
            assert np.linalg.norm(off["Spine"]) > 50.0  # the bone from the pelvis to the spine is visible
        else:
            assert "Chest" not in off and {"Neck", "Head"} & set(off)  # the head hangs on the one trunk segment
        hips = off["LeftUpLeg"] - off["RightUpLeg"]
        assert np.allclose(hips / np.linalg.norm(hips), [1, 0, 0], atol=1e-9)  # facing -Y, left +X


def _rerooted(motion, new_root: int):
    """The same fitted motion with its tree rooted at ``new_root`` (a child's origin is its joint with the parent)."""
    from mocapskel.model.kinematics import segment_origins

    sk = motion.skeleton
    parent = export.tree_from(np.asarray(sk.parent), new_root)
    origin = sk.origin.copy()
    O = segment_origins(motion)
    for s, q in enumerate(parent.tolist()):
        if q >= 0 and sk.parent[s] != q:  # a reversed edge: the joint is the old child's origin
            origin[s] = sk.origin[q]
    leaf_before = np.ones(len(parent), bool)
    leaf_before[sk.parent[sk.parent >= 0]] = False
    end = np.where(leaf_before[:, None], sk.end_site, 0.0)
    new_sk = replace(sk, parent=parent, origin=origin, end_site=end)
    root_pos = O[:, new_root] + np.einsum("fij,j->fi", motion.rot[:, new_root], origin[new_root] - sk.origin[new_root])
    return replace(motion, skeleton=new_sk, root_pos=root_pos)


def test_a_fitted_root_in_a_limb_gives_the_same_humanoid_bvh(fitted) -> None:
    _, res = fitted
    m = res.motion
    b0 = export.run(m, export.Params(rest="tpose"))
    thigh = int(b0.segment[list(b0.skeleton.names).index("LeftUpLeg")])
    b1 = export.run(_rerooted(m, thigh), export.Params(rest="tpose"))
    assert b1.skeleton.names == b0.skeleton.names and b1.skeleton.names[0] == "Hips"
    assert np.allclose(b1.skeleton.offset, b0.skeleton.offset, atol=1e-9)
    assert np.allclose(b1.root_pos, b0.root_pos, atol=1e-9)
    assert np.allclose(b1.local_rot, b0.local_rot, atol=1e-9)


def test_one_segment_origin_is_the_column_of_all_of_them(fitted) -> None:
    """The export's root origin from its path alone (re-rooting) is :func:`segment_origins`' column, to the bit."""
    from mocapskel.model.kinematics import segment_origin, segment_origins

    m = fitted[1].motion
    O = segment_origins(m)
    for s in range(O.shape[1]):
        np.testing.assert_array_equal(segment_origin(m, s), O[:, s])
