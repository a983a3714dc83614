"""Two joints with a link of no markers between them (:mod:`mocapskel.solvers.model.links`): the model path puts a
segment of no markers where one joint cannot fit, and only there."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapskel import pipeline
from mocapskel.model.kinematics import segment_origins
from mocapskel.solvers.model.links import fit_link
from mocapskel.stages import rigid
from test_held_joints import _planar_arm, _turn_z

MAP = rigid.Params(joint_model="map")


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], axis=1)


def test_a_link_is_found_from_the_child_s_motion_about_its_parent() -> None:
    """Exact data: a child turning freely at the end of a 150 mm link that turns freely about a point of the
    parent. From a start 30 mm off, the link's two ends and its length come back to a micrometre."""
    rng = np.random.default_rng(3)
    F = 300
    a, b, L = np.array([40.0, -20.0, 10.0]), np.array([-30.0, 50.0, 20.0]), 150.0
    u = rng.normal(size=(F, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    Rr = _random_rotations(rng, F)
    tr = a + L * u - Rr @ b
    got_a, got_b, got_L, rms = fit_link(Rr, tr, b + np.array([30.0, 0, 0]))
    np.testing.assert_allclose(got_a, a, atol=1e-3)
    np.testing.assert_allclose(got_b, b, atol=1e-3)
    assert got_L == pytest.approx(L, abs=1e-3) and rms < 1e-3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_arm_s_unmarked_link_becomes_a_segment_and_every_joint_lands_on_its_axis(seed: int) -> None:
    """The planar arm whose middle link carries no marker (links 120, 92 and 120 mm, 0.3 mm noise): one joint
    between the two marked links ran 220-340 mm down its axis with the model path and left a 1 mm marker rms; with
    the link the model finds, the three joints lie on their three axes and the markers fit to the noise."""
    mk, axes = _planar_arm(seed, 0.3)
    res = pipeline.fit(mk, {"rigid": MAP})
    rep = res.report
    skel = res.motion.skeleton
    assert len(skel.names) == 4 and len(rep["links"]) == 1, rep.get("links")
    link = rep["links"][0]
    assert link["length_mm"] == pytest.approx(92.0, abs=3.0)
    assert any(w.startswith(f"joint {link['parent']}–{link['child']}: two joints with a link") for w in rep["warnings"])
    assert not [c for c in rep["checks"] if c["check"] in ("joint_far", "bone_length", "joint_jump")], rep["checks"]
    assert rep["ik"]["marker_rms_mm"] < 0.5
    pos = segment_origins(res.motion)
    z = mk.points[..., 2]
    on = []
    for s in np.flatnonzero(skel.parent >= 0):
        xy = [float(np.sqrt(np.mean(np.sum((pos[:, s, :2] - axes[:, k]) ** 2, axis=1)))) for k in range(3)]
        on.append(int(np.argmin(xy)))
        assert min(xy) < 2.0, xy
        # along the vertical axes only the prior holds a joint: near its markers' heights
        assert np.nanmin(z) - 25 <= np.nanmedian(pos[:, s, 2]) <= np.nanmax(z) + 25
    assert sorted(on) == [0, 1, 2]


def _planar_hinges(seed: int, frames: int = 900) -> tuple:
    """A still base of three markers, a link of two and one of three (120 mm), every joint a hinge about the
    vertical: no link without markers."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 100.0
    q = [a * np.sin(2 * np.pi * rng.uniform(0.15, 0.6) * t + rng.uniform(0, 2 * np.pi)) for a in (0.9, 0.8)]
    R1 = _turn_z(q[0])
    R2 = R1 @ _turn_z(q[1])
    o2 = np.einsum("fij,j->fi", R1, np.array([120.0, 0, 0]))
    base = np.array([[-60.0, -40, 0], [-50, 50, 10], [-80, 0, 60]])
    pts = np.concatenate([np.broadcast_to(base, (frames, 3, 3)),
                          np.einsum("fij,mj->fmi", R1, np.array([[50.0, 25, 40], [90, -20, 70]])),
                          np.einsum("fij,mj->fmi", R2, np.array([[30.0, 30, 20], [80, -20, 50], [100, 10, 90]])) + o2[:, None]],
                         axis=1) + rng.normal(0.0, 0.3, (frames, 8, 3))
    from mocapskel.artifacts import Markers

    return Markers(points=pts, labels=("B1", "B2", "B3", "L1a", "L1b", "L2a", "L2b", "L2c"), rate=100.0, source="hinges")


def test_a_hinge_the_joints_stage_held_stays_one_joint() -> None:
    """Every joint of a planar arm flagged as held where it ran off (as the joints stage flags a joint it brought
    back along a free line): a hinge fits a link of any length along its axis no better than one joint, and the
    model's score keeps one joint each."""
    mk = _planar_hinges(4)
    joints = pipeline.run_until(mk, "joints").artifact
    per = [dict(p, held_mm=1.0) for p in joints.info["per_joint"]]
    skel = rigid.run(replace(joints, info=dict(joints.info, per_joint=per)), replace(MAP, uncertainty=False))
    assert len(skel.names) == 3 and not skel.info.get("links")


def test_the_link_s_segment_takes_a_name_no_segment_has() -> None:
    """Segment names can have gaps (a segment left out of the skeleton); the link's is the next name free."""
    from mocapskel.solvers.model.links import Link, with_link

    mk, _ = _planar_arm(0, 0.3)
    skel = pipeline.run_until(mk, "rigid", {"rigid": replace(MAP, refine_frames=0, uncertainty=False)}).artifact
    skel = replace(skel, names=("seg00", "seg03", "seg01"))
    c = int(np.flatnonzero(skel.parent >= 0)[0])
    got = with_link(skel, Link(child=c, a=np.zeros(3), b=np.zeros(3), length=0.0, rms=0.0, ball_rms=0.0))
    assert got.names[-1] == "seg04" and len(set(got.names)) == 4 and got.info["links"][0]["segment"] == "seg04"
