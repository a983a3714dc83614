"""A fitted human take imports into Blender with every bone where our forward kinematics puts it.

Runs only where Blender is installed (``blender`` on PATH, or $BLENDER); the
full-size check is ``python -m bench.blender_check``. See that module for the
import options and why they reproduce the lab frame.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # `bench` is a folder of the repository, not an installed package
    sys.path.insert(0, str(REPO))

from bench.blender_check import FRAMES, TOLERANCE_MM, blender_path, check_frame, fit_motion, pick_frames  # noqa: E402

BLENDER = blender_path()
pytestmark = pytest.mark.skipif(
    BLENDER is None,
    reason="Blender is not installed (shutil.which('blender') is None and $BLENDER is unset); "
    "install it (e.g. apt-get install blender) to check that BVH files import in Blender",
)

TIMEOUT_S = 180  # one Blender run on this take takes a few seconds


@pytest.fixture(scope="module")
def motion():
    """A short human ROM take at 100 Hz (a rate other than the sample's 120), fitted in memory."""
    from mocapskel.synth.presets import Recipe, make

    take = make(Recipe(kind="human", frames=300, rate=100.0, noise_mm=1.0, soft_tissue_mm=1.0,
                       gaps_per_marker_per_minute=4, seed=5))
    return fit_motion(take.markers).motion


CASES = [(up, units, "frame") for up, units in FRAMES] + [("y", "cm", "tpose"), ("z", "mm", "apose")]


@pytest.mark.parametrize(("up", "units", "rest"), CASES)
def test_blender_puts_every_bone_where_our_forward_kinematics_does(motion, up, units, rest, tmp_path):
    F = motion.rot.shape[0]
    frames = pick_frames(F, None)  # every frame
    r = check_frame(motion, up, units, tmp_path, frames, blender=BLENDER, timeout=TIMEOUT_S, rest=rest)
    assert r.bones_compared == len(motion.skeleton.names)
    assert r.frames_compared == F
    assert r.max_mm <= TOLERANCE_MM, r.problems
    assert np.isfinite(r.end_site_max_mm) and r.end_site_max_mm <= TOLERANCE_MM, r.problems
    assert r.frames_in_blender == F
    assert r.fps_in_blender == pytest.approx(100.0, rel=1e-9)
    assert r.ok, r.problems


@pytest.mark.parametrize("rest", ["tpose", "apose"])
def test_blender_shows_the_tpose_or_apose_at_rest(motion, rest, tmp_path):
    r = check_frame(motion, "y", "cm", tmp_path, [0], blender=BLENDER, timeout=TIMEOUT_S, rest=rest)
    assert r.ok, r.problems

    def direction(bone: str) -> np.ndarray:
        head, tail = r.rest_bones[bone]
        return (tail - head) / np.linalg.norm(tail - head)  # Blender world = lab: Z up, the subject's left +X

    s = np.sqrt(0.5)
    arm = {"tpose": [1.0, 0.0, 0.0], "apose": [s, 0.0, -s]}[rest]
    for bone in ("LeftArm", "LeftForeArm"):
        np.testing.assert_allclose(direction(bone), arm, atol=1e-4)
    for bone in ("RightArm", "RightForeArm"):
        np.testing.assert_allclose(direction(bone), [-arm[0], 0.0, arm[2]], atol=1e-4)
    for bone in ("LeftUpLeg", "LeftLeg", "RightUpLeg", "RightLeg"):
        np.testing.assert_allclose(direction(bone), [0.0, 0.0, -1.0], atol=1e-4)
    assert direction("Spine")[2] > 0.95
