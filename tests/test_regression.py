"""Regression over sample_data/: the fitted skeleton against the takes' ground truth,
and the written BVH re-read by an independent parser (bvhio)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from mocapskel import evaluate, pipeline
from mocapskel.solvers.bvh_pose import bvh_to_lab
from mocapskel.io.bvh import write_bvh
from mocapskel.synth.truth import Truth

from pathlib import Path

SAMPLE_DATA = Path(__file__).resolve().parents[1] / "sample_data"

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="Importing PyGLM", category=PendingDeprecationWarning)
    import bvhio


@pytest.fixture(scope="module")
def human_fit():
    res = pipeline.fit(SAMPLE_DATA / "human_rom.c3d")
    return res, Truth.load(SAMPLE_DATA / "human_rom.truth.npz")


def test_human_rom_sample_matches_truth(human_fit):
    res, truth = human_fit
    sc = evaluate.score_motion(res.motion, truth)
    assert sc.segments_ok and sc.topology_ok
    assert sc.joint_rms_mm < 7.0  # 20 s take; the 1-minute benchmark reaches < 5 mm
    assert sc.bone_err_max < 0.015
    assert res.report["ik"]["marker_rms_mm"] < 3.5


def test_linkage_sample_middle_rod_length():
    res = pipeline.fit(SAMPLE_DATA / "linkage.trc")
    truth = Truth.load(SAMPLE_DATA / "linkage.truth.npz")
    sc = evaluate.score_skeleton(res.motion.skeleton, truth)
    assert sc.topology_ok
    skel = res.motion.skeleton
    mid = int(np.flatnonzero(skel.parent < 0)[0])
    assert skel.bone_length[mid] == pytest.approx(341.0, rel=3e-3)


def test_noise_free_chain_sample_joints_at_rounding_level():
    res = pipeline.run_until(SAMPLE_DATA / "chain_4-3-3.trc", "joints")
    truth = Truth.load(SAMPLE_DATA / "chain_4-3-3.truth.npz")
    sc = evaluate.score_joints(res.artifact, truth)
    assert sc.segments_ok and sc.topology_ok
    # the TRC stores 6 decimals (mm): the joints are exact to that rounding
    assert sc.joint_rms_mm <= 1e-6 * 300.0


def _bvhio_positions(path, frames):
    root = bvhio.readAsHierarchy(str(path))
    out = {}
    for f in frames:
        root.loadPose(f)
        for joint, _, _ in root.layout():
            out.setdefault(joint.Name, []).append(list(joint.PositionWorld))
    return {k: np.array(v, dtype=float) for k, v in out.items()}


@pytest.mark.parametrize("up, units", [("y", "cm"), ("z", "mm")])
def test_bvh_read_by_bvhio_matches_our_forward_kinematics(human_fit, tmp_path, up, units):
    from mocapskel.stages import export

    res, _ = human_fit
    b = export.run(res.motion, export.Params(up=up, units=units, names="segments"))
    path = tmp_path / "h.bvh"
    write_bvh(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    frames = [0, 1, res.motion.rot.shape[0] // 2, res.motion.rot.shape[0] - 1]
    theirs = _bvhio_positions(path, frames)
    ours = evaluate.joint_positions(res.motion)  # lab mm
    names = res.motion.skeleton.names
    assert set(names) <= set(theirs)
    for s, name in enumerate(names):
        lab = bvh_to_lab(theirs[name], up=up, units=units)
        # bvhio computes in float32: allow its rounding (about 1e-7 relative of ~2 m coordinates)
        np.testing.assert_allclose(lab, ours[frames, s], atol=0.05)


@pytest.mark.parametrize("rest", ["frame", "tpose"])
def test_humanoid_bvh_read_by_bvhio_puts_every_joint_where_the_fit_does(human_fit, tmp_path, rest):
    from mocapskel.stages import export

    res, _ = human_fit
    b = export.run(res.motion, export.Params(rest=rest))  # the default: humanoid names, rooted at the hips
    assert b.naming.humanoid and b.skeleton.names[0] == "Hips"
    path = tmp_path / "h.bvh"
    write_bvh(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
    frames = [0, 1, res.motion.rot.shape[0] // 2, res.motion.rot.shape[0] - 1]
    theirs = _bvhio_positions(path, frames)
    ours = export.joint_positions_lab(res.motion, b)  # from the fitted tree's joints alone
    for i, name in enumerate(b.skeleton.names):
        np.testing.assert_allclose(bvh_to_lab(theirs[name]), ours[frames, i], atol=0.05)
