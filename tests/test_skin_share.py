"""How much of the residual follows the joint angles (``solvers.model.skin.skin_motion``): against a known
mixture of pose-independent noise and skin displacement made from the joint angle, and on generated takes
whose skin motion is known to be independent of the pose or driven by the joint angles."""
from __future__ import annotations

import numpy as np
import pytest

from mocapskel import evaluate, pipeline
from mocapskel.solvers.model.skin import gross_mask, skin_motion
from mocapskel.solvers.rotations import rotvec_to_matrix


def _two_segments(rng: np.random.Generator, F: int = 600):
    """A thigh and a shank (3 markers each) joined at a knee that bends 0-90 degrees about y and sways a
    little about the other axes, the thigh turning and the root moving: skeleton, poses, exact markers, the
    knee's rotation vectors."""
    parent = np.array([-1, 0])
    origin = np.array([[0.0, 0.0, 900.0], [0.0, 0.0, 480.0]])
    seg = np.array([0, 0, 0, 1, 1, 1])
    local = np.array([[60, 40, -150], [-50, 60, -250], [20, -70, -330],
                      [55, 45, -120], [-40, 55, -220], [15, -65, -300]], dtype=float)
    t = np.linspace(0, 12 * np.pi, F)
    knee = np.stack([0.15 * np.sin(0.7 * t), 0.8 + 0.75 * np.sin(t), 0.1 * np.cos(1.3 * t)], axis=1)
    hip = np.stack([0.3 * np.sin(0.5 * t + 1), 0.5 * np.sin(0.9 * t), 0.2 * np.cos(0.4 * t)], axis=1)
    rot = np.empty((F, 2, 3, 3))
    rot[:, 0] = rotvec_to_matrix(hip)
    rot[:, 1] = rot[:, 0] @ rotvec_to_matrix(knee)
    root = np.stack([300 * np.sin(0.2 * t), 100 * np.cos(0.3 * t), np.full(F, 900.0)], axis=1)
    bone = origin[1] - origin[0]
    joint = root + np.einsum("fij,j->fi", rot[:, 0], bone)
    pts = np.empty((F, 6, 3))
    for m in range(6):
        s = seg[m]
        pts[:, m] = (root if s == 0 else joint) + np.einsum("fij,j->fi", rot[:, s], local[m])
    return parent, seg, origin, local, rot, root, pts, knee


def test_the_share_is_the_part_of_the_residual_the_joint_angle_makes():
    """At the true skeleton and poses: white noise alone gives a share near 0; adding to each shank marker a
    displacement (in the shank's axes) that is a quadratic function of the knee's angles, of the same variance
    in all as the noise, gives the share it makes of the residual's variance: 3 s^2 / (6 sigma^2 + 3 s^2)."""
    rng = np.random.default_rng(3)
    parent, seg, origin, local, rot, root, pts, knee = _two_segments(rng)
    sigma = 1.0
    noisy = pts + rng.normal(0.0, sigma, pts.shape)
    white = skin_motion(parent, seg, origin, local, noisy, rot, root)
    assert abs(white.share) < 0.03 and white.z < 3.0, white

    k = knee - knee.mean(0)
    feats = np.concatenate([k, k[:, [0, 1, 2, 0, 0, 1]] * k[:, [0, 1, 2, 1, 2, 2]]], axis=1)
    feats -= feats.mean(0)
    for s_mm in (np.sqrt(2.0) * sigma, 2.0 * sigma):
        skin = np.einsum("fk,mki->fmi", feats, rng.normal(size=(3, feats.shape[1], 3)))
        skin *= s_mm / np.sqrt(np.mean(skin**2))  # rms s per coordinate over the three shank markers
        moved = noisy.copy()
        moved[:, 3:] += np.einsum("fij,fmj->fmi", rot[:, 1], skin)  # the shank's axes to the lab's
        expected = 3 * s_mm**2 / (6 * sigma**2 + 3 * s_mm**2)
        sm = skin_motion(parent, seg, origin, local, moved, rot, root)
        assert abs(sm.share - expected) < 0.04, (sm.share, expected)
        assert sm.z > 10.0, sm.z  # far beyond chance
        # per segment: the shank's markers' explained variance per coordinate is the skin's, the thigh's none;
        # the knee's angular variance is its turn's
        assert abs(sm.explained[1] - s_mm**2) < 0.1 * s_mm**2, (sm.explained, s_mm**2)
        assert sm.explained[0] < 0.05 * s_mm**2
        assert np.isclose(sm.angle_var[1], np.sum(knee.var(0)), rtol=1e-6)
    # noise correlated in time (an AR(1) process of lag-one correlation 0.9, independent of the pose): smooth
    # regressors explain more of it than of white noise, and the test counts the frames as the fewer they are worth
    ar = rng.normal(0.0, sigma, pts.shape)
    for f in range(1, ar.shape[0]):
        ar[f] = 0.9 * ar[f - 1] + np.sqrt(1 - 0.81) * ar[f]
    corr = skin_motion(parent, seg, origin, local, pts + ar, rot, root)
    assert corr.z < 3.0, corr
    # unseen markers are left out of their frames, not taken as zeros
    holed = noisy.copy()
    holed[rng.random(holed.shape[:2]) < 0.1] = np.nan
    assert abs(skin_motion(parent, seg, origin, local, holed, rot, root).share) < 0.03


def test_a_few_gross_errors_are_found_by_the_noise_they_are_not():
    """Markers swapped or jumping in one frame are no draw of the noise: at the true skeleton, white noise of 1 mm
    with four markers 50 mm off in one frame of 600: the mask (beyond chi-square 3 at 1 - 1e-6 of the noise, which
    the residuals' median measures) finds those four and nothing else, and the skin test stays below 3."""
    rng = np.random.default_rng(5)
    parent, seg, origin, local, rot, root, pts, _ = _two_segments(rng)
    jumped = pts + rng.normal(0.0, 1.0, pts.shape)
    jumped[300, [0, 2, 3, 5]] += rng.normal(0.0, 1.0, (4, 3)) * 50.0 / np.sqrt(3.0)
    mask, bound = gross_mask(jumped - pts)
    assert sorted(zip(*np.nonzero(mask))) == [(300, 0), (300, 2), (300, 3), (300, 5)]
    assert np.sqrt(bound / 30.66) == pytest.approx(1.0, rel=0.05)  # the noise's sd per axis
    assert skin_motion(parent, seg, origin, local, jumped, rot, root).z < 3.0


def test_the_report_tells_skin_that_follows_the_joints_from_skin_that_does_not():
    """The fit's report (``uncertainty.skin_share``): near 0 on a generated range of motion whose soft tissue is
    band-limited noise independent of the pose, what the model assumes (0.03-0.05 on 1,200 frames, seeds 1-3: its
    300 frames 33 ms apart are not independent; -0.03 on 3,600); well above it on a generated walk whose skin is
    moved by the joint angles (0.35; bench/skin_share.py: 0.28-0.42 over six seeds, real takes 0.41-0.79). Both
    with the true grouping and tree."""
    from mocapskel.synth.presets import active_rom, make, realistic

    got = {}
    for name, take in (("rom", make(active_rom(1, frames=1200))),
                       ("walk", make(realistic(seed=1, frames=600, motion="walk", markerset="cmu41")))):
        clean = pipeline.run_until(take.markers, "clean").artifact
        sk = pipeline.run_until(evaluate.true_topology(take.truth, clean), "rigid").artifact
        got[name] = sk.info["uncertainty"]["skin_share"]
    assert abs(got["rom"]) < 0.1, got
    assert got["walk"] > 0.2, got


@pytest.fixture(scope="module")
def skin_regions():
    """(with the skin's part, the model's covariance alone): each joint's (chi-square of its error, its error, the
    region's radius) over generated walks, a kick and a run whose skin slides with the joint angles (cmu41, the
    true grouping and tree)."""
    from bench.uncertainty import joint_errors
    from mocapskel.solvers.model import uncertainty as um
    from mocapskel.solvers.model.skin import SkinMotion
    from mocapskel.synth.presets import make, realistic

    takes = []
    for motion, seed in (("walk", 1), ("walk", 2), ("kick", 1), ("run", 1)):
        take = make(realistic(seed=seed, frames=600, motion=motion, markerset="cmu41"))
        clean = pipeline.run_until(take.markers, "clean").artifact
        takes.append((take, pipeline.run_until(evaluate.true_topology(take.truth, clean), "rigid").artifact))
    with_skin = np.array([e for take, sk in takes for e in joint_errors(sk, take.truth, um.skeleton_uncertainty(sk))])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(SkinMotion, "joint_sd", lambda self, parent: np.zeros(len(parent)))
        model = np.array([e for take, sk in takes for e in joint_errors(sk, take.truth, um.skeleton_uncertainty(sk))])
    return with_skin, model


def test_the_skin_part_brings_the_truth_inside_the_regions(skin_regions):
    """The true joints fall inside the reported 95 % regions far more often with the skin's part (``skin_sd_mm``)
    than with the model's covariance alone (measured 0.92 against 0.58 of these 48 joints). bench/uncertainty.py realistic has
    both halves of the benchmark."""
    from bench.uncertainty import CHI2_3_95

    with_skin, model = skin_regions
    inside, inside_model = np.mean(with_skin[:, 0] <= CHI2_3_95), np.mean(model[:, 0] <= CHI2_3_95)
    assert inside >= inside_model + 0.15 and inside >= 0.6, (inside, inside_model)


@pytest.mark.xfail(strict=True, reason=(
    "on the model path the regions' median radius is 3.8 times the median error (66 against 17.5 mm): the data's"
    " weight factor widens every joint's region, those the data fix as well"))
def test_the_regions_are_not_inflated(skin_regions):
    """The target: the regions stay in proportion to the errors (median radius at most 3 times the median error),
    as they did on the rules' joints."""
    with_skin, _ = skin_regions
    assert np.median(with_skin[:, 2]) <= 3 * np.median(with_skin[:, 1]), (np.median(with_skin[:, 2]), np.median(with_skin[:, 1]))
