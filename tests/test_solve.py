"""Calibrate once, solve many: the skeleton file and ``mocapskel solve``."""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel import evaluate, pipeline
from mocapskel.cli.main import cli
from mocapskel.io.markers import read_markers, write_markers
from mocapskel.io.skeleton import read_skeleton, write_skeleton
from mocapskel.synth.presets import Recipe, active_rom, make


@pytest.fixture(scope="module")
def subject(tmp_path_factory):
    d = tmp_path_factory.mktemp("subject")
    rom = make(active_rom(seed=11, frames=3600))
    sseed = rom.truth.info["subject_seed"]
    walk = make(Recipe(kind="human", seed=12, frames=1200, motion="walk", noise_mm=1.0, soft_tissue_mm=2.0,
                       gaps_per_marker_per_minute=4.0, subject_seed=sseed))
    write_markers(d / "rom.c3d", rom.markers)
    write_markers(d / "walk.c3d", walk.markers)
    return d, rom, walk


def test_skeleton_file_round_trip(subject, tmp_path):
    d, rom, _ = subject
    res = pipeline.fit(d / "rom.c3d")
    sk = res.motion.skeleton
    write_skeleton(tmp_path / "s.skel", sk, source="rom.c3d")
    back = read_skeleton(tmp_path / "s.skel")
    assert back.names == sk.names
    np.testing.assert_array_equal(back.parent, sk.parent)
    np.testing.assert_allclose(back.origin, sk.origin, atol=1e-6)
    used = sk.marker_segment >= 0
    assert back.labels == tuple(l for l, u in zip(sk.labels, used) if u)
    np.testing.assert_allclose(back.marker_local, sk.marker_local[used], atol=1e-6)


def test_solve_other_take_of_same_subject(subject, tmp_path):
    d, _, walk = subject
    r = CliRunner().invoke(cli, ["fit", str(d / "rom.c3d"), "-o", str(tmp_path / "rom.bvh"), "--skeleton-out", str(tmp_path / "s.skel"), "--no-cache"])
    assert r.exit_code == 0, r.stderr
    r = CliRunner().invoke(cli, ["solve", str(d / "walk.c3d"), "--skeleton", str(tmp_path / "s.skel"), "-o", str(tmp_path / "walk.bvh"),
                                 "--report", str(tmp_path / "walk.json"), "--markers-out", str(tmp_path / "walk_j.trc")])
    assert r.exit_code == 0, r.stderr
    res = pipeline.solve(d / "walk.c3d", read_skeleton(tmp_path / "s.skel"))
    assert np.isfinite(res.motion.rot).all() and np.isfinite(res.motion.root_pos).all()  # all frames filled
    sc = evaluate.score_motion(res.motion, walk.truth, truth_labels=walk.markers.labels)
    assert sc.segments_ok
    assert sc.joint_rms_mm < 5.0
    rep = json.loads((tmp_path / "walk.json").read_text())
    assert rep["labels"]["matched"] == 48 and rep["ik"]["marker_rms_mm"] < 3.0
    jm = read_markers(tmp_path / "walk_j.trc", include=("*",))
    assert jm.n_markers == 48 + 14 and jm.n_frames == walk.markers.n_frames
    # one skeleton, one rest pose: the calibration take solved again has the same OFFSETs and End Sites
    again = pipeline.solve(d / "rom.c3d", read_skeleton(tmp_path / "s.skel"))
    np.testing.assert_allclose(again.bvh.skeleton.offset, res.bvh.skeleton.offset, atol=1e-9)
    np.testing.assert_allclose(again.bvh.skeleton.end_site, res.bvh.skeleton.end_site, atol=1e-9)


def test_solve_tolerates_missing_and_unknown_labels_and_refuses_too_few(subject, tmp_path):
    d, rom, walk = subject
    r = CliRunner().invoke(cli, ["fit", str(d / "rom.c3d"), "-o", str(tmp_path / "rom.bvh"), "--skeleton-out", str(tmp_path / "s.skel"), "--no-cache"])
    assert r.exit_code == 0
    from dataclasses import replace

    m = walk.markers
    keep = list(range(0, 40))
    odd = replace(m, points=np.concatenate([m.points[:, keep], m.points[:, :1] + 500.0], axis=1),
                  labels=tuple(m.labels[i] for i in keep) + ("STRANGER",))
    write_markers(tmp_path / "odd.trc", odd)
    r = CliRunner().invoke(cli, ["solve", str(tmp_path / "odd.trc"), "--skeleton", str(tmp_path / "s.skel"), "-o", str(tmp_path / "o.bvh")])
    assert r.exit_code == 0, r.stderr
    assert "STRANGER" in r.stderr and "missing" in r.stderr
    few = replace(m, points=m.points[:, :3], labels=m.labels[:3])
    write_markers(tmp_path / "few.trc", few)
    r = CliRunner().invoke(cli, ["solve", str(tmp_path / "few.trc"), "--skeleton", str(tmp_path / "s.skel"), "-o", str(tmp_path / "f.bvh")])
    assert r.exit_code == 4 and "mocapskel: error:" in r.stderr
    assert not (tmp_path / "f.bvh").exists()
    bad = tmp_path / "bad.skel"
    bad.write_text("{}")
    r = CliRunner().invoke(cli, ["solve", str(d / "walk.c3d"), "--skeleton", str(bad), "-o", str(tmp_path / "g.bvh")])
    assert r.exit_code == 3 and "skeleton" in r.stderr
