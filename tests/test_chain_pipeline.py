"""Hang's noise-free 8-link chain <4-3-3-4-3-3-3-3> through the whole pipeline, from a C3D file: every joint
at rounding level, after the joints stage and after IK, in the configurations that once lost it.

- 100 frames (1 s), links of 300 mm: the far links whip at up to 38 m/s; clean asked rigid partners to be
  seen together for 2 s, which no pair of a 1 s take can be, so every sample off its smooth path was a
  jump, and IK made up the last two links for 0.4 s (0.46 of a link off);
- 300 frames, links of 1 mm: IK's continuity pass took poses within 0.5 mm of the markers as "as good"
  as exact ones, half a link here, in the refinement's spread frames (3e-4 of a link after the fit).

The model path (``--joint-model map``) assumes at least ``NOISE_FLOOR_MM`` of noise, against which its priors pull
the joints a little even on exact data: 1-2 micrometres here, held under a tenth of that floor. (Its skin test had
read the priors' tiny pull, a smooth function of the pose, as skin motion, z = 18-21, and made the joints soft: 2-19
mm off; it now tests against a residual of at least that floor.)
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapskel import evaluate, pipeline
from mocapskel.io.markers import write_markers
from mocapskel.solvers.model.joint_map import NOISE_FLOOR_MM
from mocapskel.stages import clean
from mocapskel.synth.presets import Recipe, make

LONG_CHAIN = (4, 3, 3, 4, 3, 3, 3, 3)


@pytest.mark.parametrize("frames,link,seed", [(100, 300.0, 8), (300, 1.0, 7)])
def test_long_chain_joints_at_rounding_level(tmp_path, frames, link, seed):
    take = make(Recipe(kind="chain", seed=seed, frames=frames, counts=LONG_CHAIN, link_length=link))
    path = tmp_path / "chain.c3d"
    write_markers(path, replace(take.markers, source=path.name))
    res = pipeline.fit(path, pipeline.make_params())
    after_ik = evaluate.score_motion(res.motion, take.truth)
    joints_stage = evaluate.score_joints(res.motion.skeleton.joints, take.truth)
    assert after_ik.segments_ok and after_ik.topology_ok
    assert len(after_ik.joint_rms_each) == len(joints_stage.joint_rms_each) == len(LONG_CHAIN) - 1
    assert not res.motion.skeleton.info["refined"]["soft_sigma_mm"]
    assert max(after_ik.joint_rms_each.values()) < 0.1 * NOISE_FLOOR_MM, after_ik.joint_rms_each
    worst = {k: v / link for k, v in joints_stage.joint_rms_each.items()}
    assert max(worst.values()) < 1e-6, worst
    assert np.isfinite(res.motion.skeleton.joints.centres).all()  # no frame lost


@pytest.mark.parametrize("seed", [1, 3, 8])
def test_a_short_fast_chain_keeps_every_sample(seed):
    """A take of 1 s judges its jump candidates against rigid partners seen together for half of it."""
    take = make(Recipe(kind="chain", seed=seed, frames=100, counts=LONG_CHAIN, link_length=300.0))
    out = clean.run(take.markers)
    info = out.info["clean"]
    assert info["jump_candidates"] > 0  # the fast links leave their smooth-path test
    assert info["jump_samples"] == 0 and info["visible_after"] == info["visible_before"]
    np.testing.assert_array_equal(out.points, take.markers.points)
