"""The command line, driven through click's CliRunner; outputs are reopened and checked."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel.cli.main import cli
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.markers import read_markers, write_markers
from mocapskel.synth.presets import Recipe, make
from mocapskel.io import artifact_files


def run(*args):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    return r.exit_code, r.stdout, r.stderr


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    d = tmp_path_factory.mktemp("takes")
    link = make(Recipe(kind="linkage", frames=1200, noise_mm=0.5, seed=1))
    write_markers(d / "link.trc", link.markers)
    human = make(Recipe(kind="human", frames=1200, noise_mm=1.0, seed=2))
    write_markers(d / "human.c3d", human.markers)
    return d, link, human


def test_fit_writes_bvh_and_report(takes, tmp_path):
    d, link, _ = takes
    code, _, err = run("fit", d / "link.trc", "-o", tmp_path / "l.bvh", "--report", tmp_path / "l.json", "--no-cache")
    assert code == 0, err
    skel, root_pos, local_rot, frame_time = read_bvh(tmp_path / "l.bvh")
    assert root_pos.shape[0] == link.markers.n_frames
    assert frame_time == pytest.approx(1.0 / link.markers.rate)
    assert len(skel.names) == 3
    rep = json.loads((tmp_path / "l.json").read_text())
    for key in ("tool", "input", "clean", "segments", "topology", "joints", "bones", "ik", "seconds", "warnings"):
        assert key in rep
    assert rep["input"]["frames"] == link.markers.n_frames
    assert len(rep["topology"]["edges"]) == 2
    assert rep["ik"]["marker_rms_mm"] < 2.0
    # the middle rod: within 0.3 % of 341 mm
    mid = [b for b in rep["bones"] if b["parent"] is None][0]
    assert mid["length_mm"] == pytest.approx(341.0, rel=3e-3)
    assert "done in" in err


def test_cache_skips_early_stages_when_only_late_options_change(takes, tmp_path):
    d, _, _ = takes
    cache = tmp_path / "cache"
    code, _, err = run("fit", d / "link.trc", "-o", tmp_path / "a.bvh", "--cache-dir", cache)
    assert code == 0, err and "cached" not in err
    code, _, err = run("fit", d / "link.trc", "-o", tmp_path / "b.bvh", "--cache-dir", cache, "--up", "z", "--units", "mm")
    assert code == 0
    for stage in ("clean", "merge-ids", "segment", "topology", "joints", "rigid", "ik"):
        assert f"{stage:9s} cached — skipping" in err
    code, _, err = run("fit", d / "link.trc", "-o", tmp_path / "c.bvh", "--cache-dir", cache, "--rest-frame", "5")
    assert code == 0
    for stage in ("clean", "merge-ids", "segment", "topology", "joints"):
        assert f"{stage:9s} cached — skipping" in err
    assert "rigid     done" in err and "ik        done" in err
    # a corrupt entry is discarded, recomputed and warned about
    for f in cache.glob("*.npz"):
        f.write_bytes(b"broken")
    code, _, err = run("fit", d / "link.trc", "-o", tmp_path / "d.bvh", "--cache-dir", cache)
    assert code == 0
    assert "unreadable — deleted and recomputed" in err


def test_joint_model_option_names_the_model_and_refuses_the_removed_rules(takes, tmp_path):
    """``--joint-model map`` (the only model) fits the joints by the model's MAP, as the report says; the removed
    ``rules`` is refused as a usage error, with nothing written."""
    d, _, _ = takes
    code, _, err = run("fit", d / "human.c3d", "-o", tmp_path / "map.bvh", "--report", tmp_path / "map.json",
                       "--no-cache", "--joint-model", "map")
    assert code == 0, err
    assert json.loads((tmp_path / "map.json").read_text())["refinement"]["joint_model"] == "map"
    code, _, err = run("fit", d / "human.c3d", "-o", tmp_path / "rules.bvh", "--no-cache", "--joint-model", "rules")
    assert code == 2 and "rules" in err and "map" in err, err
    assert not (tmp_path / "rules.bvh").exists()


def test_stage_commands_chain_and_export(takes, tmp_path):
    d, link, _ = takes
    code, _, err = run("segment", d / "link.trc", "-o", tmp_path / "seg.npz", "--no-cache")
    assert code == 0, err
    seg = artifact_files.load(tmp_path / "seg.npz")
    assert seg.kind == "segments" and seg.n_segments == 3
    code, _, err = run("ik", tmp_path / "seg.npz", "-o", tmp_path / "ik.npz", "--no-cache")
    assert code == 0, err
    assert artifact_files.load(tmp_path / "ik.npz").kind == "motion"
    code, _, err = run("export", tmp_path / "ik.npz", "-o", tmp_path / "x.bvh", "--up", "z", "--units", "mm", "--no-cache")
    assert code == 0, err
    _, root_pos, _, _ = read_bvh(tmp_path / "x.bvh")
    assert root_pos.shape == (link.markers.n_frames, 3)
    # a later stage's artifact cannot go back to an earlier stage
    code, _, err = run("segment", tmp_path / "ik.npz", "-o", tmp_path / "s2.npz", "--no-cache")
    assert code == 2 and err.startswith("mocapskel: error:")


def test_inspect_every_kind(takes, tmp_path):
    d, _, _ = takes
    code, out, _ = run("inspect", d / "human.c3d")
    assert code == 0 and "markers     48" in out
    run("fit", d / "link.trc", "-o", tmp_path / "l.bvh", "--no-cache")
    code, out, _ = run("inspect", tmp_path / "l.bvh")
    assert code == 0 and "3 joints" in out
    run("topology", d / "link.trc", "-o", tmp_path / "t.npz", "--no-cache")
    code, out, _ = run("inspect", tmp_path / "t.npz")
    assert code == 0 and "artifact    topology" in out


@pytest.mark.parametrize(
    "args, code, text",
    [
        (["fit", "{d}/missing.c3d", "-o", "{t}/o.bvh"], 3, "no such file"),
        (["fit", "{d}", "-o", "{t}/o.bvh"], 3, "folder"),
        (["fit", "{d}/link.trc", "-o", "{t}/nodir/o.bvh"], 2, "does not exist"),
        (["fit", "{d}/link.trc", "-o", "{d}/link.trc"], 2, "is the input"),
        (["fit", "{d}/link.trc", "-o", "{t}/o.bvh", "--segments", "1"], 2, "--segments"),
        (["fit", "{d}/link.trc"], 2, "Missing option"),
        (["fit", "{d}/link.trc", "-o", "{t}/o.txt"], 2, ".bvh"),
        (["fit", "{t}/rigid.trc", "-o", "{t}/o.bvh", "--no-cache"], 4, "one rigid body"),
    ],
)
def test_errors_are_one_line_with_their_exit_code(takes, tmp_path, args, code, text):
    d, link, _ = takes
    write_markers(tmp_path / "rigid.trc", replace(link.markers, points=link.markers.points[:, :3], labels=link.markers.labels[:3]))
    args = [a.format(d=d, t=tmp_path) for a in args]
    got, out, err = run(*args)
    assert got == code, err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("mocapskel: error:") and text in lines[-1]
    assert "Traceback" not in err
    assert not (tmp_path / "o.bvh").exists()
    assert read_markers(d / "link.trc").n_markers == link.markers.n_markers  # input untouched


def test_synth_writes_take_and_truth(tmp_path):
    code, _, err = run("synth", "chain", "-o", tmp_path / "c.trc", "--counts", "3-2-2", "--frames", "100")
    assert code == 0, err
    m = read_markers(tmp_path / "c.trc")
    assert m.n_markers == 7 and m.n_frames == 100
    from mocapskel.synth.truth import Truth

    t = Truth.load(tmp_path / "c.truth.npz")
    assert t.joints.shape == (100, 2, 3)
    np.testing.assert_array_equal(np.bincount(t.marker_segment), [3, 2, 2])
