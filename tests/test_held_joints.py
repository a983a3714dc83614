"""A joint that the markers leave free along a line (a hinge whose links all turn about parallel axes, two
joints with no markers between them) runs off along it; it is held where the line passes nearest its
segments' markers and said, instead of a bone metres long (see :func:`mocapskel.stages.joints.hold_far_joints`)."""
from __future__ import annotations

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.artifacts import Markers
from mocapskel.stages.joints import hold_far_joints


def _turn_z(q: np.ndarray) -> np.ndarray:
    c, s = np.cos(q), np.sin(q)
    R = np.zeros((q.size, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _planar_arm(seed: int, noise: float, frames: int = 900) -> tuple[Markers, np.ndarray]:
    """A robot arm on a table whose joints all turn about vertical axes: a still base of three markers,
    a link of two, a link of none, a link of three (links 120, 92 and 120 mm). Returns the markers and
    the true joint axes' (x, y) in every frame (F, 3, 2)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 100.0
    f = rng.uniform(0.15, 0.6, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    q = [a * np.sin(2 * np.pi * fk * t + pk) for a, fk, pk in zip((0.9, 0.8, 0.7), f, ph)]
    R1 = _turn_z(q[0])
    R2 = R1 @ _turn_z(q[1])
    R3 = R2 @ _turn_z(q[2])
    o1 = np.zeros((frames, 3))
    o2 = o1 + R1 @ np.array([120.0, 0, 0])
    o3 = o2 + R2 @ np.array([92.0, 0, 0])
    base = np.array([[-60.0, -40, 0], [-50, 50, 10], [-80, 0, 60]])
    l1 = np.array([[50.0, 25, 40], [90, -20, 70]])
    l3 = np.array([[30.0, 30, 20], [80, -20, 50], [100, 10, 90]])
    pts = np.concatenate([np.broadcast_to(base, (frames, 3, 3)),
                          np.einsum("fij,mj->fmi", R1, l1) + o1[:, None],
                          np.einsum("fij,mj->fmi", R3, l3) + o3[:, None]], axis=1)
    pts = pts + rng.normal(0.0, noise, pts.shape)
    labels = ("B1", "B2", "B3", "L1a", "L1b", "L3a", "L3b", "L3c")
    axes = np.stack([o1, o2, o3], axis=1)[:, :, :2]
    return Markers(points=pts, labels=labels, rate=100.0, source="arm"), axes


def test_a_hinge_joint_far_down_its_axis_comes_back_to_the_markers() -> None:
    """Exact data: a still segment of three markers, another of two turning about the vertical line
    through the origin; a joint put 2 m down that line comes back up it to the markers' mean height,
    without moving across it."""
    F = 400
    q = 0.8 * np.sin(np.linspace(0, 6 * np.pi, F))
    A = np.broadcast_to(np.array([[-50.0, -40, 0], [-40, 60, 20], [-70, 0, 80]]), (F, 3, 3)).copy()
    B = np.einsum("fij,mj->fmi", _turn_z(q), np.array([[80.0, 20, 30], [150, -30, 70]]))
    centres = np.zeros((F, 1, 3))
    centres[:, 0, 2] = -2000.0
    held = hold_far_joints(centres, [A, B], np.array([[0, 1]]), 0.5, slice(None))
    assert set(held) == {0}
    dist, step = held[0]
    assert dist > 1900 and step == pytest.approx(2000.0 + np.concatenate([A, B], axis=1)[..., 2].mean(), abs=1e-6)
    np.testing.assert_allclose(centres[:, 0, :2], 0.0, atol=1e-9)
    np.testing.assert_allclose(centres[:, 0, 2], np.concatenate([A, B], axis=1)[..., 2].mean(), atol=1e-6)


def test_a_joint_near_its_markers_is_not_touched() -> None:
    F = 200
    q = 0.8 * np.sin(np.linspace(0, 4 * np.pi, F))
    A = np.broadcast_to(np.array([[-50.0, -40, 0], [-40, 60, 20], [-70, 0, 80]]), (F, 3, 3)).copy()
    B = np.einsum("fij,mj->fmi", _turn_z(q), np.array([[80.0, 20, 30], [150, -30, 70]]))
    centres = np.zeros((F, 1, 3))
    centres[:, 0, 2] = 40.0
    before = centres.copy()
    assert hold_far_joints(centres, [A, B], np.array([[0, 1]]), 0.5, slice(None)) == {}
    np.testing.assert_array_equal(centres, before)


def test_a_leaf_whose_joint_cannot_be_placed_is_left_out_and_said() -> None:
    """A chain <4-3-1-1>: the last two links carry one marker each, and a joint needs three or more markers
    of its two segments seen together; the last one's could not be placed in any frame, and the rigid
    stage refused the whole take ("segment 2 is never seen well enough to fit"). The last marker is left
    out instead, with a warning, and the rest is fitted to the truth."""
    from mocapskel import evaluate
    from mocapskel.synth.presets import Recipe, make

    take = make(Recipe(kind="chain", counts=(4, 3, 1, 1), frames=900, noise_mm=0.3, seed=1))
    res = pipeline.fit(take.markers)
    rep = res.report
    assert rep["segments_left_out"] == ["S3M0"]
    said = [w for w in rep["warnings"] if w.startswith("marker S3M0 left out of the skeleton: its joint with")]
    assert len(said) == 1, rep["warnings"]
    assert len(rep["segments"]) == 3
    sc = evaluate.score_motion(res.motion, take.truth)
    assert len(sc.joint_rms_each) == 2 and sc.joint_rms_mm < 2.0, sc.joint_rms_each
