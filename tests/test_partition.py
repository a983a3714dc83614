"""Rigid-fit residual and the split of a non-rigid group into two rigid bodies (solvers/grouping/partition.py,
grouping.split_nonrigid), against generated truth."""
from __future__ import annotations

import numpy as np
import pytest

from mocapskel.solvers.grouping import distances, grouping
from mocapskel.solvers.grouping.partition import best_split, frame_scatters, rigid_rms, scatter_in_frame
from mocapskel.solvers.rotations import rotvec_to_matrix
from mocapskel.stages import segment


def _two_bodies(rng: np.random.Generator, K: int = 200, n_a: int = 4, n_b: int = 5, amp_deg: float = 25.0,
                noise: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Two rigid bodies joined at the origin of body A: A turns in space, B turns against A about the joint.

    Returns points (K, n_a + n_b, 3) in mm (markers shuffled) and the true body of each (0 = A)."""
    a = rng.normal(0.0, 60.0, (n_a, 3)) + [0.0, 0.0, 150.0]  # A's markers above the joint
    b = rng.normal(0.0, 60.0, (n_b, 3)) + [0.0, 0.0, -250.0]  # B's below
    t = np.linspace(0.0, 2.0 * np.pi, K)
    RA = rotvec_to_matrix(np.deg2rad(10.0) * np.column_stack([np.sin(t), np.cos(2 * t), 0.3 * np.sin(3 * t)]))
    RB = rotvec_to_matrix(np.deg2rad(amp_deg) * np.column_stack([np.sin(1.3 * t), 0.4 * np.cos(t), 0.2 * np.sin(t)]))
    pos = np.array([100.0, 200.0, 900.0]) + 50.0 * np.column_stack([np.cos(t), np.sin(t), 0 * t])
    PA = np.einsum("kij,nj->kni", RA, a) + pos[:, None]
    PB = np.einsum("kij,kjl,nl->kni", RA, RB, b) + pos[:, None]
    P = np.concatenate([PA, PB], axis=1) + rng.normal(0.0, noise, (K, n_a + n_b, 3))
    body = np.array([0] * n_a + [1] * n_b)
    perm = rng.permutation(n_a + n_b)
    return P[:, perm], body[perm]


def test_rigid_rms_is_the_noise_of_a_rigid_body_and_large_across_a_joint():
    rng = np.random.default_rng(0)
    P, body = _two_bodies(rng, noise=0.5)
    a, b = np.flatnonzero(body == 0), np.flatnonzero(body == 1)
    # 3-D rms of isotropic noise of 0.5 mm per coordinate, less what the fit absorbs: about 0.5 * sqrt(3)
    for part in (a, b):
        assert 0.5 < rigid_rms(P, part) < 0.5 * np.sqrt(3) * 1.05
    assert rigid_rms(P) > 5.0
    # B's markers seen from A's frame sweep arcs; A's own stay put
    s = scatter_in_frame(P, a)
    assert s[b].min() > 10.0 * s[a].max()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_best_split_finds_the_two_bodies(seed):
    rng = np.random.default_rng(seed)
    P, body = _two_bodies(rng, n_a=3 + seed, n_b=6 - seed)
    lab = best_split(P, np.random.default_rng(0))
    assert lab is not None
    assert np.array_equal(lab, body) or np.array_equal(lab, 1 - body)


def test_best_split_needs_three_markers_a_side():
    rng = np.random.default_rng(3)
    P, _ = _two_bodies(rng, n_a=2, n_b=3)
    assert best_split(P, np.random.default_rng(0)) is None  # five markers: no split of three and three


def _labels(points: np.ndarray, std: np.ndarray, tau: float, reveal: float) -> np.ndarray:
    lab, _ = grouping.split_nonrigid(points, std, np.zeros(points.shape[1], dtype=int), tau, reveal,
                                     np.random.default_rng(0))
    return lab


def test_split_nonrigid_splits_two_bodies_and_keeps_one():
    rng = np.random.default_rng(4)
    P, body = _two_bodies(rng, noise=0.5)
    std, _ = distances.distance_std(P)
    lab = _labels(P, std, tau=2.0, reveal=10.0)
    assert np.array_equal(lab, body) or np.array_equal(lab, 1 - body)
    # one rigid body (B held still against A): rigid within the tolerance, nothing to split
    P1, _ = _two_bodies(np.random.default_rng(4), noise=0.5, amp_deg=0.0)
    std1, _ = distances.distance_std(P1)
    assert _labels(P1, std1, tau=2.0, reveal=10.0).tolist() == [0] * P1.shape[1]
    # a joint that barely moves: the bodies' markers move against each other by less than the bar
    # at which the joint could be located, so they stay one group
    P2, _ = _two_bodies(np.random.default_rng(4), noise=0.5, amp_deg=2.0)
    std2, _ = distances.distance_std(P2)
    assert rigid_rms(P2) > 1.2  # not rigid within this tolerance, and each body is
    assert _labels(P2, std2, tau=1.2, reveal=10.0).tolist() == [0] * P2.shape[1]
    assert _labels(P2, std2, tau=1.2, reveal=5.0).tolist() != [0] * P2.shape[1]  # the bar is what keeps it


def test_skin_motion_does_not_split_a_body():
    """One rigid body whose markers each slide on the skin by up to ~10 mm, smoothly and each on its own
    (not as one rigid part): non-rigid beyond the tolerance, but no two rigid parts explain it."""
    rng = np.random.default_rng(5)
    P, _ = _two_bodies(rng, noise=0.5, amp_deg=0.0)
    K, n, _ = P.shape
    t = np.linspace(0.0, 1.0, K)[:, None, None]
    phase = rng.uniform(0, 2 * np.pi, (1, n, 3))
    freq = rng.uniform(1.0, 3.0, (1, n, 3))
    skin = 6.0 * np.sin(2 * np.pi * freq * t + phase)
    Ps = P + skin
    std, _ = distances.distance_std(Ps)
    assert rigid_rms(Ps) > 4.0
    assert _labels(Ps, std, tau=4.0, reveal=10.0).tolist() == [0] * n


def test_realistic_reach_trunk_is_split_from_the_still_pelvis_and_leg():
    """Realistic CMU set, reaching: the trunk bends over a pelvis and a left leg that stay still, and its
    markers keep their distances to them to second order (average linkage puts them in one group). The
    rigid-fit residual shows the bend: the trunk's markers and the pelvis-and-leg markers end in groups
    of their own, as the generator's truth has them."""
    from mocapskel.synth.presets import make, realistic

    take = make(realistic(seed=1, frames=600, motion="reach", markerset="cmu41"))
    seg = segment.run(take.markers)
    truth = take.truth
    names = list(truth.segment_names)
    labels = [str(x) for x in take.markers.labels]
    host = {lab: names[int(truth.marker_segment[i])] for i, lab in enumerate(truth.info["physical_labels"])}
    trunk = {labels.index(x) for x in ("C7", "T10", "RBAK")}
    lower = {labels.index(x) for x in labels if host.get(x) in ("Pelvis", "LThigh", "LShank", "LFoot")}
    assert len({int(seg.group[i]) for i in trunk}) == 1
    assert not {int(seg.group[i]) for i in trunk} & {int(seg.group[i]) for i in lower}
    assert seg.info["split_nonrigid"], "the split is reported"
    # without the test, the trunk stays with the pelvis and leg (the case this guards)
    seg0 = segment.run(take.markers, segment.Params(split_nonrigid=False))
    assert {int(seg0.group[i]) for i in trunk} & {int(seg0.group[i]) for i in lower}


def test_a_marker_put_with_the_wrong_body_goes_to_the_body_whose_frame_holds_it():
    """A marker of body B labelled with body A's group moves to B's group ("reframed"): in A's frame it
    sweeps an arc as B turns, in B's it stays put. A's own markers stay."""
    rng = np.random.default_rng(6)
    P, body = _two_bodies(rng, n_a=5, n_b=5, noise=0.5)
    lab = body.copy()
    m = int(np.flatnonzero(body == 1)[0])
    lab[m] = 0
    got, moves = grouping.reassign_by_frame(P, lab)
    assert moves == [(m, "reframed")]
    assert np.array_equal(got, body) or np.array_equal(got, 1 - body)
    assert grouping.reassign_by_frame(P, body)[1] == []  # the right groups: nothing moves


def test_no_marker_moves_between_groups_that_do_not_move_apart():
    """Where two groups hardly move against each other, a marker's place between them is arbitrary: the
    frames do not tell, and nothing moves (one rigid body labelled as two groups)."""
    rng = np.random.default_rng(7)
    P, body = _two_bodies(rng, n_a=5, n_b=5, noise=0.5, amp_deg=0.0)
    lab = body.copy()
    lab[int(np.flatnonzero(body == 1)[0])] = 0
    assert grouping.reassign_by_frame(P, lab)[1] == []


def test_a_frames_own_fitting_error_is_not_taken_for_motion():
    """A point riding rigidly 250 mm from three markers 30 mm apart scatters in their frame by the
    frame's turn (its fitting error times the lever); beyond that it hardly moves, while a point that
    slides 8 mm rms on its own keeps its motion."""
    rng = np.random.default_rng(8)
    K = 400
    shape = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 30.0, 5.0], [250.0, 40.0, -30.0], [-200.0, 60.0, 40.0]])
    t = np.linspace(0.0, 2.0 * np.pi, K)
    R = rotvec_to_matrix(np.deg2rad(30.0) * np.column_stack([np.sin(t), np.cos(2 * t), 0.5 * np.sin(3 * t)]))
    P = np.einsum("kij,nj->kni", R, shape) + rng.normal(0.0, 1.0, (K, 5, 3))
    P[:, 4] += np.einsum("kij,kj->ki", R, 8.0 * np.column_stack([np.sin(3 * t), np.cos(5 * t), np.sin(7 * t)]) / np.sqrt(1.5))
    whole, loo = frame_scatters(P, np.array([0, 1, 2]), grouping.SPLIT_FRAMES, grouping.SPLIT_MIN_FRAMES)
    raw, beyond = whole
    assert np.isnan(loo).all()  # three markers: no frame without one of them
    assert raw[3] > 10.0 and beyond[3] < 0.5 * raw[3]  # rigid: the scatter is mostly the frame's turn (150 frames)
    assert 6.0 < beyond[4] < 11.0  # its own 8 mm rms kept
