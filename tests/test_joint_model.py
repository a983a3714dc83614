"""The rigid stage's model path (``joint_model="map"``): joints by the MAP of the whole skeleton with
explicit Gaussian priors, scored against generated ground truth."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapskel import evaluate, pipeline
from mocapskel.artifacts import Segments, Topology
from mocapskel.solvers.model.refinement import pick_frames
from mocapskel.solvers.model.joint_map import (effective_frames, like_bone_pairs, noise_sigma, prior_sigmas,
                                        residual_correlation)
from mocapskel.stages import rigid
from mocapskel.synth.presets import Recipe, active_rom, make, realistic


def _joints(take):
    """The joints stage on the take's true groups and tree."""
    t = take.truth
    clean = pipeline.run_until(take.markers, "clean").artifact
    S = len(t.segment_names)
    seg = Segments(markers=clean, group=np.asarray(t.marker_segment), dist_std=np.zeros((0, 0)), eigvals=np.zeros(0))
    edges = np.stack([t.parent[t.joint_child], t.joint_child], axis=1)
    topo = Topology(segments=seg, edges=edges, cost=np.zeros(len(edges)), pair_cost=np.full((S, S), np.inf), root=0)
    return pipeline.run_until(topo, "joints").artifact


def _score(joints, params, truth):
    mot = pipeline.run_until(joints, "ik", {"rigid": params}).artifact
    return evaluate.score_motion(mot, truth), mot


def test_where_the_data_fix_the_joints_the_prior_does_not_move_them():
    """Noise-free range of motion (the hinges turn a little about their other axes, so every joint is
    fixed by the markers): the prior centred 27 mm off every joint (the joints stage's centres shifted)
    does not hold them there; the MAP with rigid joints (the take's are exact) puts them at the truth."""
    take = make(Recipe(kind="human", seed=2, frames=1200))
    j = _joints(take)
    off = np.array([20.0, -15.0, 10.0])
    shifted = replace(j, centres=j.centres + off, alt_centres=None)
    start, _ = _score(shifted, rigid.Params(joint_model="map", refine_frames=0), take.truth)
    assert start.joint_rms_mm > 8.0  # the prior's centre, and the start, are far off
    got, mot = _score(shifted, rigid.Params(joint_model="map", soft_sigma=0.0), take.truth)
    # measured 0.11 mm (the model's noise is at least 0.1 mm per axis: within it the prior has a say)
    assert got.joint_rms_mm < min(0.5, 0.1 * start.joint_rms_mm), got.joint_rms_each
    info = mot.skeleton.info["refined"]
    assert info["joint_model"] == "map" and np.isfinite(info["neg_log_posterior"])
    # centred where the joints stage put them (exactly, here), the prior leaves them there
    got, _ = _score(j, rigid.Params(joint_model="map", soft_sigma=0.0), take.truth)
    assert got.joint_rms_mm < 0.05, got.joint_rms_each


def test_map_joints_on_the_active_range_of_motion():
    """1 mm noise, 2 mm soft tissue, gaps, true groups and tree: the model's joints within 4 mm rms of the
    truth (measured 2.8 mm, 3.3 on the refinement's 300 frames alone; the rules' 4.1 mm) and no joint worse than
    12 mm (measured 6.9; 8.7; the rules' 11.8). The soft tissue is band-limited noise, independent of the pose: the
    take shows no skin motion (the skin regression's z measured -10), so the joints stay rigid, as with
    ``soft_sigma=0``, and the fit is made again on every frame."""
    take = make(active_rom(2, frames=1200))
    j = _joints(take)
    got, mot = _score(j, rigid.Params(joint_model="map"), take.truth)
    assert got.joint_rms_mm < 4.0, got.joint_rms_each
    assert max(got.joint_rms_each.values()) < 12.0
    assert mot.skeleton.info["refined"]["skin_z"] < 3.0
    rigid_joints, _ = _score(j, rigid.Params(joint_model="map", soft_sigma=0.0), take.truth)
    once, _ = _score(j, rigid.Params(joint_model="map", gross_errors=False, rigid_frames=0), take.truth)
    assert rigid_joints.joint_rms_each == once.joint_rms_each


def test_a_walk_with_rigid_markers_keeps_rigid_joints():
    """A walk of the 48-marker human with rigid markers and 1 mm white noise (true groups and tree): the start's joints
    are tens of millimetres off, and its residual follows the joint angles through them (z measured 32 there); the
    rigid MAP's does not (z measured -0.7), so the joints stay rigid and the fit is made again on all 600 frames:
    2.6 mm rms, worst 4.5 (measured; the rigid MAP on the refinement's 150 frames 5.0 and 11.5), where soft joints,
    switched on by the start's residual, ended 38.5 mm (worst 89) and the rules 42.8."""
    take = make(Recipe(kind="human", seed=1, frames=600, motion="walk", noise_mm=1.0))
    j = _joints(take)
    got, mot = _score(j, rigid.Params(joint_model="map"), take.truth)
    assert mot.skeleton.info["refined"]["skin_z"] < 3.0 and not mot.skeleton.info["refined"]["soft_sigma_mm"]
    assert got.joint_rms_mm < 4.0 and max(got.joint_rms_each.values()) < 8.0, got.joint_rms_each
    rigid_joints, _ = _score(j, rigid.Params(joint_model="map", soft_sigma=0.0), take.truth)
    once, _ = _score(j, rigid.Params(joint_model="map", gross_errors=False, rigid_frames=0), take.truth)
    assert rigid_joints.joint_rms_each == once.joint_rms_each


def test_a_take_the_rigid_model_fits_is_refined_on_more_frames():
    """The 48-marker range of motion (1 mm noise, 2 mm skin motion that does not follow the joints, 3600 frames): the
    rigid MAP's residual is noise (z < 3), so the kept fit is refined again, with the same prior, on 1800 frames
    (``rigid_frames``; no stride), and its joints come nearer the truth than on the refinement's 300. There the joints
    wander as far as their offsets at the rigid fit show beyond the noise: the generator's skin moves each segment's
    markers together by 0.63 mm per axis (0.3 of its variance), so a joint by 0.89 mm relative to its parent
    (measured, mean / worst joint, without the limbs' line factor: 300 frames against 1800, seed 1 3.16 / 7.8 -> 2.11 /
    3.5 mm, seed 2 2.75 / 6.6 -> 1.97 / 2.9). A take whose residual follows the joint angles (a realistic one) keeps
    its 300 frames."""
    for seed in (1, 2):
        take = make(active_rom(seed, frames=3600))
        j = _joints(take)
        more, mot = _score(j, rigid.Params(joint_model="map", line_sigma=0.0), take.truth)
        fewer, mot0 = _score(j, rigid.Params(joint_model="map", rigid_frames=0, line_sigma=0.0), take.truth)
        fit, fit0 = mot.skeleton.info["refined"], mot0.skeleton.info["refined"]
        assert fit["skin_z"] < 3.0 and not fit0["soft_sigma_mm"]
        assert 0.75 < fit["slack_sigma_mm"] < 1.1, fit["slack_sigma_mm"]
        assert set(fit["soft_sigma_mm"].values()) == {fit["slack_sigma_mm"]} and len(fit["soft_sigma_mm"]) == 14
        assert (fit["frames"], fit0["frames"], fit["frames_scored"]) == (1800, 300, 300)
        assert fit["neg_log_posterior"] == fit0["neg_log_posterior"]  # the starts chosen on the same frames
        assert more.joint_rms_mm < fewer.joint_rms_mm - 0.1, (seed, more.joint_rms_mm, fewer.joint_rms_mm)
        assert max(more.joint_rms_each.values()) < max(fewer.joint_rms_each.values())
    skin = make(realistic(seed=1, frames=2400, motion="rom"))
    _, mot = _score(_joints(skin), rigid.Params(joint_model="map"), skin.truth)
    assert mot.skeleton.info["refined"]["skin_z"] > 3.0 and mot.skeleton.info["refined"]["frames"] == 300


def test_one_frame_of_gross_errors_does_not_make_the_joints_soft(monkeypatch):
    """A range of motion with rigid markers and 1 mm noise, four markers 50 mm off in one of the refinement's
    frames: taken as residuals, they give the skin test z = 4.0 on this seed (the torso's regression on its many
    joints' angles fits one frame's error), soft joints and 2.95 mm (worst 7.7); left out as gross errors, z = 0.2,
    rigid joints and 1.29 mm (worst 2.2) on the refinement's 300 frames, as measured (on seed 1 the test is below 3
    either way); 1.21 after the fit again on all 1200. The rigid fit is made again without them: on the 300, kept, they
    pull the joints to 1.40 mm; the take without the frame's errors gives 1.27. (Those two without the limbs' line
    factor, which on the 300 frames moves the elbows and knees the frames leave loose: with it, 1.42 and 1.45.)"""
    import mocapskel.solvers.model.skin as skin_mod

    take = make(Recipe(kind="human", seed=2, frames=1200, motion="rom", noise_mm=1.0))
    pts = take.markers.points.copy()
    pts[400, [3, 10, 20, 30]] += np.random.default_rng(0).normal(0, 1, (4, 3)) * 50 / np.sqrt(3)
    j = _joints(replace(take, markers=replace(take.markers, points=pts)))
    got, mot = _score(j, rigid.Params(joint_model="map"), take.truth)
    fit = mot.skeleton.info["refined"]
    assert fit["skin_z"] < 3.0 and not fit["soft_sigma_mm"]
    assert got.joint_rms_mm < 1.5 and max(got.joint_rms_each.values()) < 3.0, got.joint_rms_each
    out, _ = _score(j, rigid.Params(joint_model="map", rigid_frames=0, line_sigma=0.0), take.truth)
    kept, _ = _score(j, rigid.Params(joint_model="map", gross_errors=False, rigid_frames=0, line_sigma=0.0), take.truth)
    assert out.joint_rms_mm < 1.35 and kept.joint_rms_mm > out.joint_rms_mm + 0.05, (out.joint_rms_mm, kept.joint_rms_mm)
    monkeypatch.setattr(skin_mod, "gross_out", lambda r: r)
    naive, mot = _score(j, rigid.Params(joint_model="map"), take.truth)
    assert mot.skeleton.info["refined"]["skin_z"] > 3.0 and naive.joint_rms_mm > 2.0 * got.joint_rms_mm


def test_the_fit_on_more_frames_leaves_out_its_gross_residuals_before_its_one_fit(monkeypatch):
    """The same range of motion, four markers 50 mm off in a frame the refinement's 300 do not hold: the fit again on
    all 1200 frames finds them from the kept fit posed there and leaves them out before it fits, once (a second fit
    from where the first ended cost the longest real take a third of its time), and its joints are those of the take
    without the errors to 0.05 mm (measured 1.229 against 1.218)."""
    import mocapskel.solvers.model.joint_map as joint_map

    take = make(Recipe(kind="human", seed=2, frames=1200, motion="rom", noise_mm=1.0))
    clean, _ = _score(_joints(take), rigid.Params(joint_model="map"), take.truth)
    pts = take.markers.points.copy()
    pts[401, [3, 10, 20, 30]] += np.random.default_rng(0).normal(0, 1, (4, 3)) * 50 / np.sqrt(3)
    j = _joints(replace(take, markers=replace(take.markers, points=pts)))
    frames = []
    fit = joint_map.refine_skeleton
    monkeypatch.setattr(joint_map, "refine_skeleton", lambda *a, **k: frames.append(a[4].shape[0]) or fit(*a, **k))
    got, mot = _score(j, rigid.Params(joint_model="map"), take.truth)
    info = mot.skeleton.info["refined"]
    assert info["frames"] == 1200 and frames.count(1200) == 1, frames
    assert info["gross_residuals"] >= 4
    assert abs(got.joint_rms_mm - clean.joint_rms_mm) < 0.05, (got.joint_rms_mm, clean.joint_rms_mm)


def test_prior_sigmas_scale_with_the_segments_reach():
    """Each prior's sigma is the scale times the rms distance of the segment's markers from the joint,
    computed here independently; the root has none."""
    take = make(active_rom(3, frames=600))
    skel = rigid.run(_joints(take), rigid.Params(joint_model="map", refine_frames=0))
    sig = prior_sigmas(skel, 0.5)
    assert np.isnan(sig[skel.parent < 0]).all()
    pos = skel.origin[skel.marker_segment] + skel.marker_local
    for c in np.flatnonzero(skel.parent >= 0):
        for k, s in enumerate((skel.parent[c], c)):
            d = pos[skel.marker_segment == s] - skel.origin[c]
            assert sig[c, k] == pytest.approx(0.5 * np.sqrt(np.mean(np.sum(d**2, axis=1))))


def test_noise_from_the_markers_alone():
    """The model's marker noise per axis, from the segments' markers as rigid shapes: the generator's
    1 mm (and 3 mm) Gaussian noise, within 5 %; a noise-free take gets the floor."""
    for sigma in (1.0, 3.0):
        take = make(Recipe(kind="human", seed=4, frames=600, noise_mm=sigma))
        got = noise_sigma(take.markers.points, np.asarray(take.truth.marker_segment))
        assert got == pytest.approx(sigma, rel=0.05)
    take = make(Recipe(kind="human", seed=4, frames=600))
    assert noise_sigma(take.markers.points, np.asarray(take.truth.marker_segment)) == 0.1


def test_noise_of_a_take_of_two_marker_segments_from_their_distances():
    """With no segment of three markers, the noise comes from the pairs' distances: the generator's 1 mm (and 3 mm)
    Gaussian noise within 10 %, where the rigid shapes find nothing and the floor (0.1 mm) was taken."""
    for sigma in (1.0, 3.0):
        take = make(Recipe(kind="human", seed=4, frames=600, noise_mm=sigma, markers_per_segment=2))
        assert np.bincount(take.truth.marker_segment).max() == 2
        got = noise_sigma(take.markers.points, np.asarray(take.truth.marker_segment))
        assert got == pytest.approx(sigma, rel=0.10)


def test_a_two_marker_range_of_motion_is_tested_for_skin_at_the_fit_that_counts():
    """Where no joint could be soft (every segment of two markers), the fit that counts is rigid, and the skin test
    carried from the first MAP (20 iterations, z 6.95 on this take) is made again at it (z below 3): the fit on more
    frames follows, and the joints come within the issue's bar for two markers a segment (6 mm; 11.0 mm when the
    carried test was kept, 3.6 mm measured)."""
    take = make(active_rom(5, frames=3600, markers_per_segment=2))
    mot = pipeline.run_until(take.markers, "ik", {"rigid": rigid.Params(uncertainty=False)}).artifact
    ref = mot.skeleton.info["refined"]
    assert not ref["soft_sigma_mm"] and ref["skin_z"] <= 3.0 and ref["frames"] > 300
    sc = evaluate.score_motion(mot, take.truth)
    assert sc.segments_ok and len(sc.joint_rms_each) == 14
    assert sc.joint_rms_mm <= 6.0, sc.joint_rms_each
    assert all(abs(v) < 0.05 for v in sc.bone_err.values()), sc.bone_err


def test_a_joint_the_first_fit_left_off_is_not_taken_for_skin():
    """Two markers a segment (no joint can be soft), the generator's skin independent of the pose, the refinement on
    100 frames of 1200: its fit leaves elbows and knees off along their axes, and the residual follows those joints'
    angles (z 12.0 measured) as skin would, so without the test made again the fit keeps its 100 frames (36.6 mm,
    worst joint 83.6). The rigid model fitted on every frame from there shows noise (z -5.6): that fit is kept and
    refined as any rigid take's (3.7 mm, worst 6.8, measured)."""
    take = make(active_rom(2, frames=1200, markers_per_segment=2))
    j = pipeline.run_until(evaluate.true_topology(take.truth, pipeline.run_until(take.markers, "clean").artifact),
                           "joints").artifact
    kw = dict(joint_model="map", refine_frames=100, rigid_frames=1200, uncertainty=False)
    before, mot0 = _score(j, rigid.Params(skin_retest=False, **kw), take.truth)
    got, mot = _score(j, rigid.Params(**kw), take.truth)
    fit0, fit = mot0.skeleton.info["refined"], mot.skeleton.info["refined"]
    assert fit0["skin_z"] > 3.0 and fit0["frames"] == 100 and before.joint_rms_mm > 20.0
    assert fit["skin_z_first"] == fit0["skin_z"] and fit["skin_z"] <= 3.0 and fit["frames"] == 1200
    assert not fit["soft_sigma_mm"] and fit["frames_scored"] == 100
    assert got.joint_rms_mm < 6.0 and max(got.joint_rms_each.values()) < 10.0, got.joint_rms_each


def test_a_real_take_whose_residual_follows_its_joints_at_the_fit_on_more_frames_keeps_its_fit():
    """A real arm take (joint-localization, two and three markers a segment, no two joined segments of three): its
    skin test fires (z 8.7 measured), and at the rigid fit on more frames the residual still follows the joint angles
    (z 7.9): that is skin, and the fit on the refinement's frames stays, the same skeleton as without the test made
    again."""
    src = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "joint-localization" / "arm-4-2-3_clean_120fps.c3d"
    if not src.is_file():
        pytest.skip(f"REAL DATA NOT FOUND at {src} — the real skin retest test did NOT run")
    j = pipeline.run_until(str(src), "joints").artifact
    kept = rigid.run(j, rigid.Params(uncertainty=False))
    plain = rigid.run(j, rigid.Params(uncertainty=False, skin_retest=False))
    ref = kept.info["refined"]
    assert ref["skin_z"] > 3.0 and ref["skin_z_retest"] > 3.0 and "skin_z_first" not in ref
    assert ref["frames"] == plain.info["refined"]["frames"]
    np.testing.assert_array_equal(kept.origin, plain.origin)


def test_joint_model_must_be_map():
    take = make(Recipe(kind="human", seed=1, frames=300))
    for other in ("bayes", "rules"):  # the rules were removed
        with pytest.raises(ValueError, match="joint_model"):
            rigid.run(_joints(take), rigid.Params(joint_model=other))
    with pytest.raises(ValueError, match="data_weight"):
        rigid.run(_joints(take), rigid.Params(joint_model="map", data_weight="some"))


def _ar1_take(phi: float, frames: int, seed: int):
    """Two rigid 4-marker bodies tumbling, every marker coordinate carrying AR(1) noise of lag-one
    correlation ``phi`` (2 mm): the residuals' true correlation is phi^k."""
    rng = np.random.default_rng(seed)
    from scipy.spatial.transform import Rotation

    shape = rng.normal(0.0, 80.0, (2, 4, 3))
    t = np.arange(frames)
    pts = np.empty((frames, 8, 3))
    for b in range(2):
        rv = np.stack([np.sin(t / (40.0 + 13 * b) + k) for k in range(3)], 1) * 1.2
        R = Rotation.from_rotvec(rv).as_matrix()
        pts[:, 4 * b:4 * b + 4] = np.einsum("fij,pj->fpi", R, shape[b]) + 500.0 * np.sin(t / 90.0)[:, None, None]
    e = np.empty((frames, 8, 3))
    e[0] = rng.normal(0.0, 1.0, (8, 3))
    kick = rng.normal(0.0, np.sqrt(1.0 - phi**2), (frames, 8, 3))
    for f in range(1, frames):  # the generator's recursion, not the estimator's
        e[f] = phi * e[f - 1] + kick[f]
    return pts + 2.0 * e, np.repeat([0, 1], 4)


@pytest.mark.parametrize("phi", [0.0, 0.6, 0.9])
def test_effective_frames_of_correlated_residuals(phi):
    """Markers whose residuals follow AR(1) of known phi: the estimated effective count of 300 frames
    spread over 3000 (10 apart) and of 300 consecutive ones within 20 % of the exact count
    n^2 / sum_ij phi^|t_i - t_j| (closed form for consecutive frames)."""
    pts, group = _ar1_take(phi, 3000, seed=7)
    rho = residual_correlation(pts, group)
    assert rho[0] == 1.0
    for step in (10, 1):
        use = np.arange(300) * step
        k = np.arange(1, 300)
        exact = 300**2 / (300 + 2 * np.sum((300 - k) * phi ** (k * step)))
        got = effective_frames(rho, use)
        assert got == pytest.approx(exact, rel=0.2), (step, got, exact)
    if phi == 0.0:
        assert effective_frames(rho, np.arange(300)) > 240


def test_effective_frames_bounds():
    """Uncorrelated residuals: every frame counts; perfectly correlated: the frames are one."""
    use = np.array([3, 10, 50, 51])
    assert effective_frames(np.ones(1), use) == pytest.approx(4.0)
    assert effective_frames(np.ones(100), use) == pytest.approx(1.0)


def test_effective_weighting_leaves_true_joints_nearer_the_truth():
    """Realistic skin motion (cmu41 ROM, true grouping and tree), the prior centred on the true joints:
    counting every frame as independent, the markers pull the joints away from the truth (measured
    23.9 mm rms after IK, knees 33-35 mm); weighted by the effective frame count, the prior holds them
    closer (12.2 mm, knees 7-9 mm; the count 6 of 150 frames). Without the limbs' line factor, which ties the knees
    to the true hips and ankles here (with it: 13.5 and 11.7 mm)."""
    take = make(realistic(seed=1, frames=600, motion="rom", markerset="cmu41"))
    j = replace(_joints(take), centres=np.asarray(take.truth.joints, dtype=float), alt_centres=None)
    frames, _ = _score(j, rigid.Params(joint_model="map", prior_mean="start", line_sigma=0.0, data_weight="frames"),
                       take.truth)
    eff, mot = _score(j, rigid.Params(joint_model="map", prior_mean="start", data_weight="effective", line_sigma=0.0),
                      take.truth)
    info = mot.skeleton.info["refined"]
    assert info["effective_frames"] < 0.5 * info["frames"]
    assert eff.joint_rms_mm < 0.7 * frames.joint_rms_mm, (eff.joint_rms_mm, frames.joint_rms_mm)


def test_like_limbs_bones_agree_under_their_factor():
    """Generated walk (cmu41 marker set, true grouping and tree): the like limbs found from the tree and
    marker counts are the generator's left and right limbs, segment for segment (their names say so);
    with a tight factor (sigma 0.5 % of the length) the pairs' lengths differ by half as much as without
    it, or less, on average (the generator's are equal left and right)."""
    take = make(realistic(seed=2, frames=600, motion="walk", markerset="cmu41"))
    j = _joints(take)
    names = take.truth.segment_names
    base = rigid.run(j, rigid.Params(joint_model="map", data_weight="effective", bone_sigma=0.0))
    tied = rigid.run(j, rigid.Params(joint_model="map", data_weight="effective", bone_sigma=0.005))
    pairs = like_bone_pairs(tied)
    assert {tuple(sorted((names[x], names[y]))) for x, y in pairs} == {
        tuple(sorted((n, "R" + n[1:]))) for n in names if n.startswith("L")}
    assert tied.info["refined"]["like_bones"] == len(pairs)

    def lengths(skel, x):
        return float(np.linalg.norm(skel.origin[x] - skel.origin[skel.parent[x]]))

    def gap(skel):
        return np.array([abs(lengths(skel, x) - lengths(skel, y)) / (0.5 * (lengths(skel, x) + lengths(skel, y)))
                         for x, y in pairs])

    assert gap(tied).mean() < 0.5 * gap(base).mean(), (gap(tied), gap(base))


def test_soft_joints_keep_sliding_clusters_from_moving_the_joints():
    """A run with marker plates that slide on the skin as a whole (realistic generator, cluster set, true grouping
    and tree): with rigid joints the model path ends 77 mm from the true joints (measured), with soft joints 48 mm;
    the rules' 57 mm."""
    take = make(realistic(seed=1, frames=600, motion="run", markerset="cluster"))
    j = _joints(take)
    rigid_joints, _ = _score(j, rigid.Params(joint_model="map", soft_sigma=0.0), take.truth)
    soft, mot = _score(j, rigid.Params(joint_model="map"), take.truth)
    assert mot.skeleton.info["refined"]["skin_z"] > 3.0  # the take shows its skin motion
    assert soft.joint_rms_mm < 55.0 and rigid_joints.joint_rms_mm > 1.4 * soft.joint_rms_mm, (soft, rigid_joints)


def test_a_one_marker_hand_that_hardly_turns_keeps_its_wrist_at_the_forearms_end():
    """A generated walk (cmu41 markers, true grouping and tree): each hand carries one marker and hardly turns on its
    forearm, so the data leave its wrist free. The prior's mean at the forearm's end (the mean of its markers nearer
    the hand's marker than their centroid: the two wrist markers) puts both wrists within 12 mm of the truth
    (measured 3.6 and 7.8 mm; with the joints stage's sphere fit as the mean, 52 and 62 mm)."""
    from mocapskel.solvers.model import joint_map

    take = make(realistic(seed=1, frames=600, motion="walk", markerset="cmu41"))
    j = _joints(take)
    got, _ = _score(j, rigid.Params(joint_model="map"), take.truth)
    hands = [k for k in got.joint_rms_each if k.endswith("Hand")]
    assert len(hands) == 2 and all(got.joint_rms_each[k] < 12.0 for k in hands), got.joint_rms_each
    before = joint_map.one_marker_ends
    try:
        joint_map.one_marker_ends = lambda skel: skel
        without, _ = _score(j, rigid.Params(joint_model="map"), take.truth)
    finally:
        joint_map.one_marker_ends = before
    assert all(without.joint_rms_each[k] > 2 * got.joint_rms_each[k] for k in hands), without.joint_rms_each


def test_limb_lines_are_the_knees_and_elbows_of_a_range_of_motion():
    """The 48-marker range of motion (true grouping): the limbs' middle joints are the two knees and the two elbows,
    each between its limb's two other joints (at rest, 0.3-0.7 of the way) with the axis it turns about across the
    limb; no joint of the trunk (a shoulder lies between the lumbar joint and an elbow, on a trunk that carries other
    limbs) and no leaf's."""
    from mocapskel.solvers.model.joint_map import limb_lines

    take = make(active_rom(1, frames=1200))
    sk = rigid.run(_joints(take), rigid.Params(joint_model="map"))
    pts = take.markers.points
    smap = evaluate.segment_map(sk.marker_segment, take.truth)
    names = take.truth.segment_names
    lines = limb_lines(sk, sk.pose_rot, pts[sk.pose_frames])
    assert sorted(names[smap[k]] for k, *_ in lines) == ["LForearm", "LShank", "RForearm", "RShank"]
    for k, j, u, t, length in lines:
        assert sk.parent[j] == k and 0.3 < t < 0.7, (names[smap[k]], t)
        v = sk.origin[j] - sk.origin[sk.parent[k]]
        assert abs(float(u @ v)) < 0.3 * length and abs(np.linalg.norm(u) - 1.0) < 1e-9


def test_a_walks_knees_in_line_keep_a_hip_from_sliding_along_its_axis():
    """A gait lab's walk (two markers a thigh, shank and foot; true grouping and tree; seed 2): the model's right hip
    slides along its flexion axis, 337 mm from the truth (measured; the joints stage's 121). With each knee in line
    with its hip and ankle (``line_sigma`` 0.01) the leg slides as one, and the hip ends 229 mm off, the mean over the
    joints 141 -> 99 mm."""
    take = make(realistic(seed=2, frames=600, motion="walk", markerset="gait"))
    j = _joints(take)
    free, _ = _score(j, rigid.Params(joint_model="map", line_sigma=0.0), take.truth)
    lined, mot = _score(j, rigid.Params(joint_model="map", line_sigma=0.01), take.truth)
    assert free.joint_rms_each["RThigh"] > 300.0  # the slide
    assert lined.joint_rms_each["RThigh"] < free.joint_rms_each["RThigh"] - 80.0, (lined.joint_rms_each, free.joint_rms_each)
    assert lined.joint_rms_mm < 0.8 * free.joint_rms_mm


def test_the_scores_spread_says_when_frames_are_worth_less_than_independent_ones():
    """A chain with white noise: the joints' estimates spread as the model says (measured 1.00-1.08 over seeds 1-3);
    a slow drift of 4 mm (0.1-0.5 Hz) shared by one segment's markers, a cluster sliding on its bone, pulls that
    segment's joints the same way over whole seconds: the frames overstate what they say (4.8-7.6)."""
    from mocapskel.solvers.model.worth import joint_overdispersion
    from mocapskel.synth.chains import hang_chain
    from mocapskel.synth.soft_tissue import _band_noise

    take = hang_chain((4, 3, 3), 600, rng=np.random.default_rng(1), link_length=300.0, noise=0.5)
    fit = {"rigid": rigid.Params(joint_model="map", soft_sigma=0.0, data_weight="frames")}
    white = joint_overdispersion(pipeline.run_until(take.markers, "rigid", fit).artifact)
    pts = take.markers.points.copy()
    drift = 4.0 * _band_noise(np.random.default_rng(11), pts.shape[0], 3, take.markers.rate, (0.1, 0.5))
    pts[:, take.truth.marker_segment == 2] += drift[:, None, :]
    sliding = joint_overdispersion(pipeline.run_until(replace(take.markers, points=pts), "rigid", fit).artifact)
    assert 1.0 <= white < 1.3 and sliding > 3.0, (white, sliding)
    # weighed by it, the sliding take's fit says how much less its frames count; the white one's hardly changes
    got = pipeline.run_until(replace(take.markers, points=pts), "rigid", {"rigid": rigid.Params(joint_model="map")}).artifact
    assert got.info["refined"]["data_inflate"] == pytest.approx(sliding, rel=0.05)


def test_a_skin_test_carried_from_the_first_map_gives_the_same_fit(monkeypatch):
    """With the data weighed by their scores' spread, the first MAP's skin test is carried to the fit that counts,
    which then makes its soft fit without the rigid one that test would be measured at: the same skeleton as
    measuring it again (the soft fit starts from the start either way)."""
    import mocapskel.solvers.model.joint_map as joint_map
    import mocapskel.stages.rigid as rigid_stage

    take = make(realistic(seed=1, frames=300, motion="walk", markerset="cmu41"))
    j = pipeline.run_until(evaluate.true_topology(take.truth, pipeline.run_until(take.markers, "clean").artifact), "joints").artifact
    fit = {"rigid": rigid.Params(joint_model="map", uncertainty=False)}
    monkeypatch.setattr(rigid_stage, "run_forked", lambda fn, items: [fn(x) for x in items])  # calls counted here
    calls = []
    refine = joint_map.refine_skeleton
    monkeypatch.setattr(joint_map, "refine_skeleton", lambda *a, **k: calls.append(bool(k.get("soft"))) or refine(*a, **k))
    carried = pipeline.run_until(j, "rigid", fit).artifact
    assert carried.info["refined"]["skin_z"] > 3.0 and carried.info["refined"]["soft_sigma_mm"]
    n_carried, calls[:] = len(calls), []
    orig = rigid_stage.map_refine
    monkeypatch.setattr(rigid_stage, "map_refine", lambda *a, skin=None, **k: orig(*a, **k))
    again = pipeline.run_until(j, "rigid", fit).artifact
    assert again.info["refined"]["skin_z"] > 3.0
    assert n_carried < len(calls), (n_carried, calls)  # the rigid fits skipped
    np.testing.assert_allclose(carried.origin, again.origin, atol=1e-9)
    np.testing.assert_allclose(carried.marker_local, again.marker_local, atol=1e-9, equal_nan=True)


def test_each_start_is_set_up_once_and_fits_as_if_set_up_anew(monkeypatch):
    """A start's frames, IK pose and prior means (``map_setup``) are made by its first fit and handed to the later
    ones: the same skeleton, bit for bit, as each fit making its own, with one setup per start instead of one per fit."""
    import mocapskel.stages.rigid as rigid_stage

    take = make(realistic(seed=2, frames=300, motion="kick", markerset="cmu41"))
    j = pipeline.run_until(evaluate.true_topology(take.truth, pipeline.run_until(take.markers, "clean").artifact), "joints").artifact
    fit = {"rigid": rigid.Params(uncertainty=False)}
    monkeypatch.setattr(rigid_stage, "run_forked", lambda fn, items: [fn(x) for x in items])  # calls counted here
    made = []
    setup = rigid_stage.map_setup
    monkeypatch.setattr(rigid_stage, "map_setup", lambda *a, **k: made.append(1) or setup(*a, **k))
    once = pipeline.run_until(j, "rigid", fit).artifact
    starts = len(once.info["refined"]["neg_log_posterior_starts"])
    assert starts == 2 and len(made) == starts  # two fits a start: the first MAP and the fit that counts
    orig = rigid_stage.map_refine
    monkeypatch.setattr(rigid_stage, "map_refine", lambda *a, setup=None, **k: orig(*a, **k))
    anew = pipeline.run_until(j, "rigid", fit).artifact
    np.testing.assert_array_equal(once.origin, anew.origin)
    np.testing.assert_array_equal(once.marker_local, anew.marker_local)
    assert once.info["refined"]["neg_log_posterior"] == anew.info["refined"]["neg_log_posterior"]


def test_a_knee_left_beyond_its_limb_along_its_axis_has_its_prior_at_the_limbs_edge():
    """A gait lab's walk (seed 4) whose left shank and foot are grouped as one segment: the joints stage puts the
    knee between the two-marker thigh and that segment 430 mm out along its flexion axis, where the markers do not
    place it, and a prior centred there keeps it (measured 446 mm from the truth). With the prior's mean brought
    within the limb (``mean_within``: to the nearest of its two segments' markers along that axis) the knee ends
    within 100 mm of the truth (measured 68) and the walk's joints within 100 mm on average (76 against 206)."""
    take = make(realistic(seed=4, frames=600, motion="walk", markerset="gait"))
    clean = pipeline.run_until(take.markers, "clean").artifact
    j = pipeline.run_until(clean, "joints").artifact
    beyond, _ = _score(j, rigid.Params(joint_model="map", mean_within=False), take.truth)
    within, mot = _score(j, rigid.Params(joint_model="map", mean_within=True), take.truth)
    assert beyond.joint_rms_each["LShank"] > 300.0, beyond.joint_rms_each  # the case: the knee beyond its limb
    assert within.joint_rms_each["LShank"] < 100.0 and within.joint_rms_mm < 100.0, within.joint_rms_each


def test_a_runs_shoulders_have_their_prior_level_with_their_elbows():
    """A generated run (cmu41 markers, true grouping and tree, seed 2): the arms swing about one axis, along which the
    markers do not place the shoulders, and the joints stage's answer there falls towards the middle of the thorax's
    seven markers; a prior centred there keeps both shoulders 92-93 mm from the truth (measured). With the prior's mean
    of a shoulder level with its elbow along the axis the arm swings about (``square_limbs``), the shoulders end within
    65 mm (measured 48 and 58) and the take's joints 41.4 -> 29.6 mm. No other joint gets that mean."""
    take = make(realistic(seed=2, frames=600, motion="run", markerset="cmu41"))
    j = _joints(take)
    free, _ = _score(j, rigid.Params(joint_model="map", square_limbs=False), take.truth)
    level, mot = _score(j, rigid.Params(joint_model="map", square_limbs=True), take.truth)
    arms = ("LUpperArm", "RUpperArm")
    assert all(free.joint_rms_each[k] > 80.0 for k in arms), free.joint_rms_each  # the case
    assert all(level.joint_rms_each[k] < 65.0 for k in arms), level.joint_rms_each
    assert level.joint_rms_mm < free.joint_rms_mm - 8.0, (level.joint_rms_mm, free.joint_rms_mm)
    others = [k for k in free.joint_rms_each if k not in arms and "Arm" not in k and "Fore" not in k and "Hand" not in k]
    assert all(abs(level.joint_rms_each[k] - free.joint_rms_each[k]) < 1.0 for k in others), level.joint_rms_each
    smap = evaluate.segment_map(mot.skeleton.marker_segment, take.truth)
    squared = {take.truth.segment_names[smap[mot.skeleton.names.index(n)]]
               for n in mot.skeleton.info["refined"]["mean_squared_mm"]}
    assert squared == set(arms), squared
