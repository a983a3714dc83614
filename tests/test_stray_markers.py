"""A marker or object that rides on nothing of the subject (a sync light, a ball, a carried box) is left
out of the skeleton and said, instead of hanging on it as a leaf segment with a joint metres away; a
marker that stands still (a robot's base on its table: the lab's own frame) stays (see
:func:`mocapskel.stages.joints.stray_leaves`)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.synth.presets import Recipe, make

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
MISSING = f"REAL DATA NOT FOUND at {REALDATA} — the real stray-marker test did NOT run (see shared/realdata/README.md)"


def _with_extra(markers, path: np.ndarray, label: str):
    return replace(markers, points=np.concatenate([markers.points, path[:, None]], axis=1),
                   labels=tuple(markers.labels) + (label,))


def _ball(frames: int, rate: float, seed: int, centre: np.ndarray) -> np.ndarray:
    """A marker thrown about on its own: a smooth random path over a couple of metres."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / rate
    path = np.zeros((frames, 3))
    for k in range(3):
        for f, a, ph in zip(rng.uniform(0.2, 1.2, 3), rng.uniform(200, 600, 3), rng.uniform(0, 2 * np.pi, 3)):
            path[:, k] += a * np.sin(2 * np.pi * f * t + ph)
    return path + centre


@pytest.mark.parametrize("seed", [1, 2])
def test_a_marker_on_nothing_is_left_out_and_said(seed: int) -> None:
    take = make(Recipe(kind="chain", counts=(4, 3, 3), frames=900, noise_mm=0.3, seed=seed))
    mk = take.markers
    centre = np.nanmean(mk.points.reshape(-1, 3), axis=0) + np.array([0.0, 0.0, 1500.0])
    stray = _with_extra(mk, _ball(mk.n_frames, mk.rate, seed, centre), "SYNC")
    alone = pipeline.fit(mk)
    got = pipeline.fit(stray)
    rep = got.report
    assert [s["markers"] for s in rep["segments"]] == [s["markers"] for s in alone.report["segments"]]
    assert rep["segments_left_out"] == ["SYNC"]
    said = [w for w in rep["warnings"] if w.startswith("marker SYNC left out of the skeleton")]
    assert len(said) == 1, rep["warnings"]
    assert not [c for c in rep["checks"] if c["check"] in ("joint_far", "bone_length")]


def _box(path: np.ndarray, seed: int) -> np.ndarray:
    """Four markers of a rigid box (300 x 200 x 150 mm) carried along ``path``, turning slowly on its own."""
    from mocapskel.solvers.rotations import rotvec_to_matrix

    rng = np.random.default_rng(seed)
    corners = np.array([[150.0, 100.0, 75.0], [-150.0, 100.0, -75.0], [150.0, -100.0, -75.0], [-150.0, -100.0, 75.0]])
    t = np.linspace(0.0, 1.0, len(path))
    rv = np.column_stack([a * np.sin(2 * np.pi * f * t + p) for a, f, p in
                          zip(rng.uniform(0.3, 0.8, 3), rng.uniform(1.0, 3.0, 3), rng.uniform(0, 2 * np.pi, 3))])
    R = rotvec_to_matrix(rv)
    return path[:, None] + np.einsum("fij,mj->fmi", R, corners)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_carried_object_is_left_out_and_said(seed: int) -> None:
    take = make(Recipe(kind="chain", counts=(4, 3, 3), frames=900, noise_mm=0.3, seed=seed))
    mk = take.markers
    centre = np.nanmean(mk.points.reshape(-1, 3), axis=0) + np.array([0.0, 0.0, 1500.0])
    box = _box(_ball(mk.n_frames, mk.rate, seed, centre), seed)
    names = ("BOX1", "BOX2", "BOX3", "BOX4")
    with_box = replace(mk, points=np.concatenate([mk.points, box], axis=1), labels=tuple(mk.labels) + names)
    rep = pipeline.fit(with_box).report
    assert [s["markers"] for s in rep["segments"]] == [s["markers"] for s in pipeline.fit(mk).report["segments"]]
    assert rep["segments_left_out"] == list(names)
    assert any(w.startswith("segment BOX") and "left out of the skeleton" in w for w in rep["warnings"]), rep["warnings"]


def test_a_marker_that_stands_still_stays() -> None:
    """A marker fixed in the lab is a body too (a robot's base): it keeps its segment."""
    take = make(Recipe(kind="chain", counts=(4, 3, 3), frames=900, noise_mm=0.3, seed=1))
    mk = take.markers
    still = np.nanmean(mk.points.reshape(-1, 3), axis=0) + np.array([0.0, 0.0, 1500.0])
    got = pipeline.fit(_with_extra(mk, np.repeat(still[None], mk.n_frames, axis=0), "BASE"))
    assert "BASE" not in got.report["segments_left_out"]
    assert ["BASE"] in [s["markers"] for s in got.report["segments"]]


def test_real_sync_marker_is_left_out() -> None:
    """A wheelchair sprint's sync marker moves by metres on its own; it hung on the forearm with a 2.4 m bone."""
    src = REALDATA / "kineticstoolkit" / "sprintbasket.c3d"
    if not src.is_file():
        pytest.skip(MISSING)
    rep = pipeline.fit(src).report
    assert "Sync:Sync" in rep["segments_left_out"]
    assert "Sync:Sync" not in [m for s in rep["segments"] for m in s["markers"]]
    assert any(w.startswith("marker Sync:Sync left out of the skeleton") for w in rep["warnings"])
    assert not [c for c in rep["checks"] if c["check"] in ("joint_far", "bone_length")]


def test_real_carried_box_is_left_out() -> None:
    """A Vicon sample whose subject handles an 8-marker box: it hung on the scapula, its joint 0.7 m away."""
    src = REALDATA / "ezc3d" / "Vicon.c3d"
    if not src.is_file():
        pytest.skip(MISSING)
    rep = pipeline.fit(src).report
    box = ["gauche_ext", "gauche_int", "droite_int", "droite_ext", "avant_gauche", "avant_droit", "arriere_droit",
           "arriere_gauche"]
    assert sorted(rep["segments_left_out"]) == sorted(box)
    assert not [c for c in rep["checks"] if c["check"] in ("joint_far", "bone_length")]
    assert len(rep["segments"]) == 12


def test_no_leaf_of_a_right_tree_is_a_stray() -> None:
    """Random trees of 3-5 links of 300 mm with one-marker leaves (their markers anywhere along the link, up to
    a link's length from their joint, in a subject barely two links across): wherever the tree found is the
    true one, no leaf is left out."""
    from mocapskel.errors import MocapskelError
    from mocapskel.stages import joints as J
    from mocapskel.synth.chains import hang_tree

    rng = np.random.default_rng(7)
    right = 0
    for k in range(40):
        S = int(rng.integers(3, 6))
        parent = [-1] + [int(rng.integers(0, i)) for i in range(1, S)]
        counts = [int(rng.integers(1, 5)) for _ in range(S)]
        counts[-1] = 1
        take = hang_tree(parent, counts, int(rng.integers(150, 400)), rng=np.random.default_rng(k), link_length=300.0,
                         noise=float(rng.choice([0.0, 0.5, 2.0])))
        try:
            jt = pipeline.run_until(take.markers, "joints", {"joints": J.Params(stray_far=0)}).artifact
        except MocapskelError:
            continue
        seg = jt.topology.segments
        to_true = {int(g): int(t) for g, t in zip(seg.group, take.truth.marker_segment) if g >= 0}
        found = {frozenset((to_true[a], to_true[b])) for a, b in jt.topology.edges}
        truth = {frozenset((int(p), c)) for c, p in enumerate(parent) if p >= 0}
        if len(to_true) != len(set(to_true.values())) or found != truth:
            continue
        right += 1
        assert J.stray_leaves(jt, J.Params().stray_far) == [], (k, parent, counts)
    assert right >= 25
