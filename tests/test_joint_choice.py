"""The joints stage's choice among its estimators, against generated ground truth (the CMU-style 41-marker set
with skin motion, the true grouping and tree handed in): no joint runs off, and a grouping handed in gets the
take's own scales (skin level, size) that the distance penalty is made of."""
from __future__ import annotations

import numpy as np
import pytest

from mocapskel import evaluate, pipeline
from mocapskel.solvers.joints.cost import joint_cost
from mocapskel.solvers.joints.score import group_pose
from mocapskel.stages import joints as joints_stage
from mocapskel.stages import segment
from mocapskel.synth.presets import make, realistic


def _given(seed: int, motion: str):
    take = make(realistic(seed=seed, frames=600, motion=motion, markerset="cmu41"))
    clean = pipeline.run_until(take.markers, "clean").artifact
    return take, evaluate.true_topology(take.truth, clean)


@pytest.mark.parametrize("seed, motion", [(1, "kick"), (4, "kick"), (1, "walk")])
def test_no_joint_of_a_given_grouping_runs_off(seed, motion) -> None:
    """Every joint within 100 mm rms of the truth (the generator's limb segments are 250-450 mm long: a joint
    farther off is not at its segment's end). JMV, placed anew in every frame, fits skin motion into the joint
    and reaches a lower joint cost than the true joint; compared by that cost with the estimators that fix the
    joint in a segment, it won with joints 174-730 mm off on these takes."""
    take, topo = _given(seed, motion)
    joints = pipeline.run_until(topo, "joints").artifact
    sc = evaluate.score_joints(joints, take.truth)
    assert sc.segments_ok and sc.topology_ok
    worst = max(sc.joint_rms_each, key=sc.joint_rms_each.get)
    assert sc.joint_rms_each[worst] < 100.0, (worst, sc.joint_rms_each[worst], joints.method)


def test_held_cost_does_not_reward_a_joint_that_follows_the_noise() -> None:
    """The criterion: a candidate that moves in the segment's frame from frame to frame (the true joint plus
    a wobble toward lower distance variance) scores no better than the true joint once held fixed there,
    though its raw joint cost is lower."""
    take, topo = _given(1, "kick")
    seg = topo.segments
    t = take.truth
    child = t.segment_names.index("LFoot")
    e = int(np.flatnonzero(t.joint_child == child)[0])
    a, b = int(t.parent[child]), child
    A, B = seg.markers.points[:, seg.members(a)], seg.markers.points[:, seg.members(b)]
    both = np.concatenate([A, B], axis=1)
    truth = t.joints[:, e]
    # per frame, the point near the truth whose distances to the markers are closest to their means (one
    # Gauss-Newton step of JMV from the truth): lower raw cost, not a point fixed in either segment
    d = np.linalg.norm(truth[:, None] - both, axis=-1)
    u = (truth[:, None] - both) / d[..., None]
    r = d - d.mean(axis=0)
    wobble = truth - np.einsum("fij,fj->fi", np.linalg.pinv(u), r)
    assert joint_cost(wobble, both) < joint_cost(truth, both)
    pose = group_pose(B, "foot")
    held = [joints_stage.held_cost(c, both, 0.0, pose, slice(None)) for c in (truth, wobble)]
    assert held[1] >= 0.95 * held[0]


def test_a_given_grouping_gets_the_takes_own_scales() -> None:
    """The true grouping handed in (``evaluate.true_topology``) carries the take's skin level and size,
    measured as the segment stage measures them (its own values on the same take, an independent run of it,
    within 25 %), so that the joints stage's distance penalty is not zero."""
    take, topo = _given(2, "walk")
    info = pipeline.run_until(topo, "joints").artifact.topology.segments.info
    found = segment.run(topo.segments.markers).info
    for k in ("skin_level_mm", "size_mm", "rigid_tolerance_mm"):
        assert info[k] > 0
        assert abs(info[k] - found[k]) <= 0.25 * found[k], (k, info[k], found[k])


def test_the_simplex_search_takes_scipys_steps() -> None:
    """The joints stage's Nelder-Mead (written out so that a fit does not import scipy.optimize) against
    scipy's on a bent valley in three unknowns: the same steps, so the same point."""
    from scipy.optimize import minimize

    from mocapskel.solvers.joints.simplex import nelder_mead

    def f(p):
        return (1.0 - p[0]) ** 2 + 100.0 * (p[1] - p[0] ** 2) ** 2 + (p[2] - 0.5 * p[1]) ** 2

    sim = np.array([-1.2, 1.0, 0.3]) + np.vstack([np.zeros(3), 0.5 * np.eye(3)])
    ours = nelder_mead(f, sim, xatol=1e-6, fatol=1e-12)
    theirs = minimize(f, sim[0], method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-12, "initial_simplex": sim}).x
    np.testing.assert_array_equal(ours, theirs)
    np.testing.assert_allclose(ours, [1.0, 1.0, 0.5], atol=1e-4)
