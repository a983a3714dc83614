"""Several subjects in one take: found from the data, each fitted on its own.

A take with two generated people 3 m apart (labels ``A:…`` and ``B:…``) once
took 140 s and gave one skeleton of 58 segments. Now each subject's markers
are fitted alone, and each fit is the one its subject's take alone gives —
same joints, same score against the subject's truth.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel import evaluate, pipeline
from mocapskel.artifacts import Markers
from mocapskel.cache import Cache
from mocapskel.cli.main import cli
from mocapskel.solvers.bvh_pose import forward_kinematics
from mocapskel.io.bvh_read import read_bvh
from mocapskel.io.markers import read_markers, write_markers
from mocapskel.subjects import split_subjects
from mocapskel.synth.presets import Recipe, make

FRAMES = 600
OFFSETS = (np.zeros(3), np.array([3000.0, 0.0, 0.0]), np.array([0.0, -2500.0, 0.0]))


def _takes(n: int):
    return [make(Recipe(kind="human", frames=FRAMES, seed=i + 1, subject_seed=20 + i, noise_mm=0.5)) for i in range(n)]


def _together(takes) -> Markers:
    pts = np.concatenate([t.markers.points + OFFSETS[i] for i, t in enumerate(takes)], axis=1)
    labels = tuple(f"{'ABC'[i]}:{l}" for i, t in enumerate(takes) for l in t.markers.labels)
    return Markers(points=pts, labels=labels, rate=takes[0].markers.rate)


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    d = tmp_path_factory.mktemp("two")
    takes = _takes(2)
    write_markers(d / "two.c3d", _together(takes))
    for i, t in enumerate(takes):  # each subject alone, where it stands in the shared take
        write_markers(d / f"alone{i + 1}.c3d", replace(t.markers, points=t.markers.points + OFFSETS[i]))
    return d, takes


def test_split_finds_the_subjects_of_a_generated_take(two) -> None:
    d, takes = two
    mk = read_markers(d / "two.c3d")
    groups = split_subjects(mk)
    assert groups is not None and len(groups) == 2
    for g, prefix in zip(groups, "AB"):
        assert sorted(mk.labels[i] for i in g) == sorted(f"{prefix}:{l}" for l in takes["AB".index(prefix)].markers.labels)


def test_three_subjects(tmp_path: Path) -> None:
    takes = _takes(3)
    mk = _together(takes)
    groups = split_subjects(mk)
    assert groups is not None and [len(g) for g in groups] == [t.markers.n_markers for t in takes]
    assert [mk.labels[g[0]][0] for g in groups] == ["A", "B", "C"]


@pytest.mark.parametrize("recipe", [
    Recipe(kind="human", frames=600, seed=4),
    Recipe(kind="human", frames=600, seed=5, markers_per_segment=1),
    Recipe(kind="linkage", frames=600, seed=1),
    Recipe(kind="chain", frames=300, seed=2, counts=(3, 2, 2, 2, 2)),
    Recipe(kind="chain", frames=300, seed=2, counts=(4, 4, 4), link_length=5000.0),  # long bones, far-apart clusters
], ids=["human", "human-1-marker", "linkage", "chain", "chain-5m-links"])
def test_one_subject_is_never_split(recipe: Recipe) -> None:
    assert split_subjects(make(recipe).markers) is None


def test_a_rigid_object_in_two_far_clusters_is_not_two_subjects() -> None:
    """Two clusters of 5 markers 3 m apart on one rigid body: far apart, but they never move relative to each other."""
    rng = np.random.default_rng(3)
    local = np.concatenate([rng.normal(size=(5, 3)) * 60, rng.normal(size=(5, 3)) * 60 + [3000, 0, 0]])
    from scipy.spatial.transform import Rotation

    t = np.arange(400) / 100
    R = Rotation.from_rotvec(np.stack([0.3 * np.sin(t), 0.2 * np.cos(t), 0.5 * t], 1)).as_matrix()
    pts = np.einsum("fij,mj->fmi", R, local) + rng.normal(0, 0.3, (400, 10, 3))
    assert split_subjects(Markers(points=pts, labels=tuple(f"R{i}" for i in range(10)), rate=100.0)) is None


def _carried_box(frames: int, seed: int, at: np.ndarray) -> np.ndarray:
    """Four markers of a rigid box turning and drifting on its own around ``at`` (F, 4, 3)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    corners = np.array([[150.0, 100.0, 75.0], [-150.0, 100.0, -75.0], [150.0, -100.0, -75.0], [-150.0, -100.0, 75.0]])
    t = np.arange(frames) / 100.0
    R = Rotation.from_rotvec(np.stack([0.4 * np.sin(t), 0.3 * np.cos(1.3 * t), 0.5 * t], 1)).as_matrix()
    path = at + np.stack([400 * np.sin(0.7 * t), 300 * np.cos(0.5 * t), 200 * np.sin(1.1 * t)], 1)
    return path[:, None] + np.einsum("fij,mj->fmi", R, corners) + rng.normal(0, 0.3, (frames, 4, 3))


def test_a_rigid_object_apart_from_the_subjects_is_no_subject(two) -> None:
    """A box moving on its own 2 m from both subjects: a group of its own at the cut, but one rigid body, so it
    goes with the nearer subject (whose fit leaves it out); with one subject the take is not split at all."""
    d, takes = two
    mk = read_markers(d / "two.c3d")
    box = _carried_box(mk.n_frames, 1, np.array([1500.0, 0.0, 2500.0]) + np.array([1000.0, 0.0, 0.0]))
    with_box = replace(mk, points=np.concatenate([mk.points, box], axis=1), labels=tuple(mk.labels) + ("X1", "X2", "X3", "X4"))
    groups = split_subjects(with_box)
    assert groups is not None and len(groups) == 2
    subject_of = [sorted({with_box.labels[i][0] for i in g if with_box.labels[i][0] in "AB"}) for g in groups]
    assert subject_of == [["A"], ["B"]]
    assert sorted(with_box.labels[i] for i in groups[1] if with_box.labels[i].startswith("X")) == ["X1", "X2", "X3", "X4"]
    one = takes[0].markers
    alone = replace(one, points=np.concatenate([one.points, box[: one.n_frames]], axis=1),
                    labels=tuple(one.labels) + ("X1", "X2", "X3", "X4"))
    assert split_subjects(alone) is None


def test_a_rigid_object_listed_between_the_subjects_goes_with_one_of_them_once(two) -> None:
    """The box's markers listed between the two subjects' and the box beside the second: every marker is in
    exactly one group (the box with the second subject), whatever the order of the groups."""
    d, takes = two
    mk = read_markers(d / "two.c3d")
    nA = takes[0].markers.n_markers
    box = _carried_box(mk.n_frames, 2, np.array([3000.0, 0.0, 2500.0]))
    pts = np.concatenate([mk.points[:, :nA], box, mk.points[:, nA:]], axis=1)
    labels = tuple(mk.labels[:nA]) + ("X1", "X2", "X3", "X4") + tuple(mk.labels[nA:])
    groups = split_subjects(replace(mk, points=pts, labels=labels))
    assert groups is not None and len(groups) == 2
    every = np.concatenate(groups)
    assert sorted(every.tolist()) == list(range(len(labels)))
    assert sorted(labels[i] for i in groups[1] if labels[i].startswith("X")) == ["X1", "X2", "X3", "X4"]


def test_each_subject_is_fitted_as_its_take_alone(two) -> None:
    """Every subject's joints equal those of the fit of its markers alone, and score as well against its truth."""
    d, takes = two
    res = pipeline.fit(d / "two.c3d", pipeline.make_params(up="z", units="mm"), cache=Cache(d / "cache"))
    assert len(res.subjects) == 2
    for i, (sub, take) in enumerate(zip(res.subjects, takes)):
        alone = pipeline.fit(d / f"alone{i + 1}.c3d", pipeline.make_params(up="z", units="mm"))
        assert len(sub.bvh.skeleton.names) == len(alone.bvh.skeleton.names) == len(take.truth.segment_names)
        p_sub = forward_kinematics(sub.bvh.skeleton, sub.bvh.root_pos, sub.bvh.local_rot)
        p_alone = forward_kinematics(alone.bvh.skeleton, alone.bvh.root_pos, alone.bvh.local_rot)
        np.testing.assert_allclose(p_sub, p_alone, atol=1e-6)
        truth = replace(take.truth, joints=take.truth.joints + OFFSETS[i])
        # (alone, the labels lose their "A:" prefix: it no longer tells two subjects apart)
        s_sub = evaluate.score_motion(sub.motion, truth, truth_labels=tuple(f"{'AB'[i]}:{l}" for l in take.markers.labels))
        s_alone = evaluate.score_motion(alone.motion, truth, truth_labels=take.markers.labels)
        assert s_sub.segments_ok and s_alone.segments_ok
        assert s_sub.joint_rms_mm == pytest.approx(s_alone.joint_rms_mm, abs=1e-6)
        # joints found, not luck: most within a few mm (a joint the 5 s of motion hardly turns may be far off)
        assert np.median(list(s_sub.joint_rms_each.values())) < 5.0, s_sub.joint_rms_each
        assert sub.report["subject"] == {"index": i + 1, "of": 2}


def test_fit_writes_one_bvh_per_subject_and_the_reports_list_them(two, tmp_path: Path) -> None:
    d, takes = two
    cache = d / "cache"  # (filled by the test above, when it ran: then every stage is loaded)
    out = tmp_path / "take.bvh"
    r = CliRunner().invoke(cli, ["fit", str(d / "two.c3d"), "-o", str(out), "--report", str(tmp_path / "take.json"),
                                 "--skeleton-out", str(tmp_path / "take.skel"), "--cache-dir", str(cache)])
    assert r.exit_code == 0, r.stderr
    assert not out.exists() and not (tmp_path / "take.json").exists()
    for i in (1, 2):
        skel, root_pos, _, _ = read_bvh(tmp_path / f"take_{i}.bvh")
        assert len(skel.names) == 15 and root_pos.shape[0] == FRAMES
        rep = json.loads((tmp_path / f"take_{i}.json").read_text())
        assert rep["subject"] == {"index": i, "of": 2}
        assert [s["bvh"] for s in rep["subjects"]] == [str(tmp_path / "take_1.bvh"), str(tmp_path / "take_2.bvh")]
        assert sorted(rep["subjects"][i - 1]["markers"]) == sorted(f"{'AB'[i - 1]}:{l}" for l in takes[i - 1].markers.labels)
        assert rep["input"]["markers"] == takes[i - 1].markers.n_markers
        assert (tmp_path / f"take_{i}.skel").exists()
    # again: every stage of both subjects from the cache
    r = CliRunner().invoke(cli, ["fit", str(d / "two.c3d"), "-o", str(out), "--cache-dir", str(cache)])
    assert r.exit_code == 0, r.stderr
    assert r.stderr.count("cached — skipping") == 2 + 2 * 5


def test_single_linkage_matches_scipy():
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    from mocapskel.subjects import _components, single_linkage

    rng = np.random.default_rng(5)
    for M in (2, 3, 8, 40, 120):
        X = rng.normal(size=(M, 3)) * rng.uniform(0.1, 10, size=(M, 1))
        D = np.linalg.norm(X[:, None] - X[None], axis=-1)
        Z = linkage(squareform(D, checks=False), method="single")
        edges = single_linkage(D)
        np.testing.assert_allclose(edges[:, 2], Z[:, 2], rtol=1e-12)
        for k in range(1, M):  # every cut: the same partition as scipy's
            ours = _components(M, edges[:k])
            theirs = fcluster(Z, t=Z[k - 1, 2], criterion="distance")
            pairs = ours[:, None] == ours[None]
            assert np.array_equal(pairs, theirs[:, None] == theirs[None])
