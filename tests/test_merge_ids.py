"""merge-ids: passive takes with planted relabelling, ghosts and jumps whose truth is known."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from mocapskel import evaluate, pipeline
from mocapskel.artifacts import Markers, markers_of
from mocapskel.cli.main import cli
from mocapskel.io.markers import read_markers, write_markers
from mocapskel.solvers.merging.cluster import repulsion_spectral, time_gaps
from mocapskel.solvers.merging.links import link_tracks
from mocapskel.solvers.merging.pairs import compact_visible, pair_sums, partners_of
from mocapskel.stages import clean, merge_ids
from mocapskel.synth import corrupt
from mocapskel.synth.presets import Recipe, active_rom, make, passive_rom
from mocapskel.synth.truth import SynthTake
from mocapskel.io import artifact_files

FRAMES = 2400  # 20 s at 120 Hz


def physical_of(merged: Markers, take: SynthTake) -> np.ndarray:
    """Physical marker of every merged label: majority (by samples) of its sources' truth ids."""
    index = {lab: i for i, lab in enumerate(take.markers.labels)}
    seen = np.isfinite(take.markers.points[..., 0]).sum(axis=0)
    out = []
    for lab in merged.labels:
        cols = np.array([index[s] for s in merged.info["merge_ids"]["merged"][lab]])
        w = np.bincount(take.truth.marker_id[cols] + 1, weights=seen[cols].astype(float))
        out.append(int(np.argmax(w)) - 1)
    return np.array(out)


def sample_truth(cleaned: Markers, merged: Markers, take: SynthTake) -> tuple[int, int, int]:
    """(right, total, mixed labels): output samples from the output label's physical marker."""
    index = {lab: i for i, lab in enumerate(take.markers.labels)}
    cidx = {lab: i for i, lab in enumerate(cleaned.labels)}
    pid = physical_of(merged, take)
    right = total = mixed = 0
    for k, lab in enumerate(merged.labels):
        out_vis = np.isfinite(merged.points[:, k, 0])
        ids = set()
        for s in merged.info["merge_ids"]["merged"][lab]:
            n = int((np.isfinite(cleaned.points[:, cidx[s], 0]) & out_vis).sum())
            sid = int(take.truth.marker_id[index[s]])
            total += n
            right += n if sid == pid[k] >= 0 else 0
            if n:
                ids.add(sid)
        mixed += len(ids) > 1
    return right, total, mixed


@pytest.fixture(scope="module")
def passive():
    take = make(passive_rom(3, FRAMES))
    cleaned = clean.run(take.markers)
    return take, cleaned, merge_ids.run(cleaned)


@pytest.fixture(scope="module")
def active():
    take = make(active_rom(3, FRAMES))
    cleaned = clean.run(take.markers)
    return take, cleaned, merge_ids.run(cleaned)


# --------------------------------------------------------------------------- passive takes


def test_relabelled_passive_take_merges_into_physical_markers(passive):
    take, cleaned, merged = passive
    info = merged.info["merge_ids"]
    assert merged.stage == "merge-ids"
    assert cleaned.n_markers > 1.5 * 48  # the take really is relabelled
    assert info["physical_markers"] == 48
    right, total, mixed = sample_truth(cleaned, merged, take)
    assert right / total >= 0.99
    assert mixed == 0
    pid = physical_of(merged, take)
    per = np.bincount(pid[pid >= 0], minlength=48)
    assert (per >= 1).all()  # every physical marker is there
    assert (per == 1).mean() >= 0.9  # and nearly all in one label
    assert merged.n_markers <= 48 + 3


def test_merged_label_never_has_two_sources_at_one_frame(passive):
    _, cleaned, merged = passive
    cidx = {lab: i for i, lab in enumerate(cleaned.labels)}
    for k, lab in enumerate(merged.labels):
        cols = [cidx[s] for s in merged.info["merge_ids"]["merged"][lab]]
        seen = np.isfinite(cleaned.points[:, cols, 0])
        assert seen.sum(axis=1).max() <= 1, lab
        # kept samples are the source's samples, unchanged
        out = merged.points[:, k]
        kept = np.isfinite(out[:, 0])
        src = np.nansum(np.where(seen[:, :, None], cleaned.points[:, cols], 0.0), axis=1)
        np.testing.assert_array_equal(out[kept], src[kept])
        assert np.all(seen.any(axis=1)[kept])


def test_merged_label_is_named_after_its_longest_source(passive):
    _, cleaned, merged = passive
    seen = {lab: int(np.isfinite(cleaned.points[:, i, 0]).sum()) for i, lab in enumerate(cleaned.labels)}
    src = merged.info["merge_ids"]["merged"]
    assert set(src) == set(merged.labels)
    for lab, sources in src.items():
        assert lab in sources
        assert seen[lab] == max(seen[s] for s in sources)
    # every source label is used at most once
    all_src = [s for v in src.values() for s in v]
    assert len(all_src) == len(set(all_src))


def test_merge_is_deterministic(passive):
    _, cleaned, merged = passive
    again = merge_ids.run(cleaned)
    assert again.labels == merged.labels
    np.testing.assert_array_equal(again.points, merged.points)


def test_passive_fit_finds_the_skeleton(passive):
    take, _, _ = passive
    run = pipeline.run_until(take.markers, "ik")
    mk = markers_of(run.artifact)
    tr = take.truth
    pid = physical_of(mk, take)
    seg_of = {int(i): int(s) for i, s in zip(tr.marker_id, tr.marker_segment) if i >= 0}
    truth = replace(tr, marker_id=pid, marker_segment=np.array([seg_of.get(int(i), -1) for i in pid]))
    sc = evaluate.score_skeleton(run.artifact.skeleton, truth)
    assert sc.topology_ok
    assert sc.joint_rms_mm < 8.0


# --------------------------------------------------------------------------- active takes


def test_active_take_passes_through_unchanged(active):
    _, cleaned, merged = active
    assert merged.labels == cleaned.labels
    np.testing.assert_array_equal(merged.points, cleaned.points)
    info = merged.info["merge_ids"]
    assert all(v == [k] for k, v in info["merged"].items())
    assert info["dropped"]["ghost_labels"] == [] and info["dropped"]["jump_samples"] == 0
    assert "warnings" not in merged.info


def test_disabled_merge_passes_labels_through(passive):
    _, cleaned, _ = passive
    out = merge_ids.run(cleaned, merge_ids.Params(enabled=False))
    assert out.labels == cleaned.labels and out.stage == "merge-ids"
    assert out.info["merge_ids"]["physical_markers"] == 48


def test_active_take_with_everything_lost_needs_no_pieces():
    take = corrupt.everything_lost(make(active_rom(4, FRAMES)), (1000, 1060))
    cleaned = clean.run(take.markers)
    merged = merge_ids.run(cleaned)
    assert merged.labels == cleaned.labels
    assert merged.info["merge_ids"]["pieces"] == []
    assert "warnings" not in merged.info


# --------------------------------------------------------------------------- planted trouble


def _segment_relabelled(n_lost: int) -> tuple[SynthTake, list[tuple[str, str]]]:
    """An active take in which ``n_lost`` markers of the left thigh are lost at once and come back
    with new labels (so one, two or three markers of a rigid triangle have no partner across)."""
    take = make(Recipe(kind="human", seed=5, frames=FRAMES, noise_mm=1.0, soft_tissue_mm=2.0))
    m, tr = take.markers, take.truth
    thigh = np.flatnonzero(tr.marker_segment == tr.segment_names.index("LThigh"))[:n_lost]
    pts = m.points.copy()
    pts[1200:1225, thigh] = np.nan
    late = pts[:, thigh].copy()
    late[:1225] = np.nan
    pts[1225:, thigh] = np.nan
    labels = m.labels + tuple(f"NEW{k}" for k in range(len(thigh)))
    pts = np.concatenate([pts, late], axis=1)
    take = SynthTake(
        replace(m, points=pts, labels=labels),
        replace(tr, marker_id=np.concatenate([tr.marker_id, tr.marker_id[thigh]]),
                marker_segment=np.concatenate([tr.marker_segment, tr.marker_segment[thigh]])),
    )
    return take, [(m.labels[t], f"NEW{k}") for k, t in enumerate(thigh)]


@pytest.mark.parametrize("n_lost", [1, 2, 3])
def test_markers_of_one_segment_relabelled_together_are_joined(n_lost):
    take, pairs = _segment_relabelled(n_lost)
    merged = merge_ids.run(clean.run(take.markers))
    src = merged.info["merge_ids"]["merged"]
    assert merged.n_markers == 48
    for old, new in pairs:
        assert sorted(src[old]) == sorted([old, new])


def test_long_ghosts_are_dropped_and_never_merged():
    rng = np.random.default_rng(11)
    take = make(Recipe(kind="human", seed=11, frames=FRAMES, noise_mm=1.0, soft_tissue_mm=2.0,
                       gaps_per_marker_per_minute=4.0))
    take = corrupt.add_ghosts(take, rng, n_ghosts=20, duration_s=(0.6, 1.8))  # outlive clean's 0.5 s
    take = corrupt.relabel_passive(take, rng)
    cleaned = clean.run(take.markers)
    merged = merge_ids.run(cleaned)
    index = {lab: i for i, lab in enumerate(take.markers.labels)}
    dropped = merged.info["merge_ids"]["dropped"]["ghost_labels"]
    ghosts = [lab for lab in cleaned.labels if take.truth.marker_id[index[lab]] < 0]
    assert len(ghosts) >= 15
    assert all(take.truth.marker_id[index[lab]] < 0 for lab in dropped)  # no real marker dropped
    assert len(set(dropped) & set(ghosts)) >= 0.8 * len(ghosts)
    _, _, mixed = sample_truth(cleaned, merged, take)
    assert mixed == 0  # a ghost that stays is never merged into a marker


def test_planted_jumps_become_gaps():
    rng = np.random.default_rng(12)
    take = make(Recipe(kind="human", seed=12, frames=FRAMES, noise_mm=1.0, soft_tissue_mm=2.0,
                       gaps_per_marker_per_minute=4.0))
    take = corrupt.add_jumps(take, rng, n_jumps=25)
    take = corrupt.relabel_passive(take, rng)
    cleaned = clean.run(take.markers, clean.Params(jump_mm=1e9))  # leave the jumps to merge-ids
    merged = merge_ids.run(cleaned)
    index = {lab: i for i, lab in enumerate(take.markers.labels)}
    jump = corrupt.bad_sample_mask(take)[:, [index[lab] for lab in cleaned.labels]]
    jump &= np.isfinite(cleaned.points[..., 0])
    kept = np.zeros_like(jump)
    for k, lab in enumerate(merged.labels):
        out = np.isfinite(merged.points[:, k, 0])
        for s in merged.info["merge_ids"]["merged"][lab]:
            kept[:, cleaned.labels.index(s)] = out & np.isfinite(cleaned.points[:, cleaned.labels.index(s), 0])
    seen = np.isfinite(cleaned.points[..., 0])
    assert jump.sum() > 100
    assert (jump & ~kept).sum() >= 0.9 * jump.sum()  # jumps turned into gaps
    assert (seen & ~jump & ~kept).sum() <= 1e-3 * (seen & ~jump).sum()  # little else
    assert merged.info["merge_ids"]["dropped"]["jump_samples"] >= 0.9 * jump.sum()
    assert merged.n_markers <= 48 + 2


def test_everything_lost_merges_in_pieces_with_a_warning():
    rng = np.random.default_rng(13)
    take = make(Recipe(kind="human", seed=13, frames=FRAMES, noise_mm=1.0, soft_tissue_mm=2.0,
                       gaps_per_marker_per_minute=4.0))
    take = corrupt.everything_lost(take, (1100, 1160))
    take = corrupt.relabel_passive(take, rng)
    cleaned = clean.run(take.markers)
    merged = merge_ids.run(cleaned)
    info = merged.info["merge_ids"]
    assert len(info["pieces"]) == 2
    assert any("every marker was lost at once" in w and "2 pieces" in w for w in merged.info["warnings"])
    # within each piece labels are merged; across the loss never
    cidx = {lab: i for i, lab in enumerate(cleaned.labels)}
    for lab, sources in info["merged"].items():
        seen = np.isfinite(cleaned.points[:, [cidx[s] for s in sources], 0]).any(axis=1)
        assert not (seen[:1100].any() and seen[1160:].any()), lab
    assert merged.n_markers <= 2 * 48 + 4
    right, total, mixed = sample_truth(cleaned, merged, take)
    assert mixed == 0 and right / total >= 0.99


# --------------------------------------------------------------------------- command line


def test_merge_ids_command_writes_artifact_and_merged_c3d(tmp_path):
    take = make(passive_rom(6, 1200))
    write_markers(tmp_path / "take.c3d", take.markers)
    r = CliRunner().invoke(cli, ["merge-ids", str(tmp_path / "take.c3d"), "-o", str(tmp_path / "m.npz"),
                                 "--write-c3d", str(tmp_path / "merged.c3d"), "--no-cache"])
    assert r.exit_code == 0, r.stderr
    art = artifact_files.load(tmp_path / "m.npz")
    assert art.kind == "markers" and art.stage == "merge-ids"
    back = read_markers(tmp_path / "merged.c3d")
    assert back.labels == art.labels
    assert back.n_markers < take.markers.n_markers
    np.testing.assert_allclose(back.points, art.points, atol=1e-3, equal_nan=True)
    # --write-c3d wants a .c3d file
    r = CliRunner().invoke(cli, ["merge-ids", str(tmp_path / "take.c3d"), "-o", str(tmp_path / "n.npz"),
                                 "--write-c3d", str(tmp_path / "merged.trc"), "--no-cache"])
    assert r.exit_code == 2 and not (tmp_path / "n.npz").exists()


# --------------------------------------------------------------------------- kernels


def test_pair_sums_keep_a_rigid_pair_rigid_despite_a_jump():
    rng = np.random.default_rng(0)
    F = 600
    t = np.linspace(0, 6, F)
    a = np.stack([100 * np.cos(t), 100 * np.sin(t), np.zeros(F)], 1)
    b = a + np.stack([30 * np.cos(t), 30 * np.sin(t), np.full(F, 40.0)], 1)  # 50 mm away, same body
    c = np.stack([200 * np.cos(3 * t), np.zeros(F), 50 * t], 1)  # another body
    pts = np.stack([a, b, c], 1) + rng.normal(0, 0.5, (F, 3, 3))
    pts[300:305, 1] += 80.0  # a jump
    vis = np.isfinite(pts).all(-1)
    mean, std = pair_sums(pts, vis).stats()
    assert mean[0, 1] == pytest.approx(50.0, abs=0.5) and std[0, 1] < 1.5
    assert std[0, 2] > 20
    partner = partners_of(mean, std, pair_sums(pts, vis).n, 3.0, 10)
    assert partner[0, 1] and not partner[0, 2]


def test_link_tracks_joins_the_end_to_the_start_its_partners_predict():
    # tracks 0, 1: two partners seen throughout; 2 ends at 99; 3 and 4 start at 110
    first = np.array([0, 0, 0, 110, 110])
    last = np.array([199, 199, 99, 199, 199])
    p = np.zeros((5, 3))
    mean = np.full((5, 5), np.nan)
    partner = np.zeros((5, 5), dtype=bool)
    for i, j, d in [(0, 1, 80.0), (0, 2, 50.0), (1, 2, 60.0), (0, 3, 50.3), (1, 3, 59.8), (0, 4, 70.0), (1, 4, 40.0),
                    (3, 4, 45.0)]:
        mean[i, j] = mean[j, i] = d
        partner[i, j] = partner[j, i] = True
    overlap = np.ones((5, 5), dtype=int)
    overlap[2, 3:] = overlap[3:, 2] = 0
    lk = link_tracks(first, last, p, p, mean, partner, overlap, n_frames=200, max_gap=50)
    assert lk.pairs.tolist() == [[2, 3]]
    # the rival start that fits nearly as well is refused: no clear best
    mean[0, 4] = mean[4, 0] = 50.5
    mean[1, 4] = mean[4, 1] = 60.2
    lk = link_tracks(first, last, p, p, mean, partner, overlap, n_frames=200, max_gap=50)
    assert lk.pairs.size == 0 and lk.ambiguous == 1


def test_repulsion_keeps_items_seen_together_apart():
    # items 0..3: 0-1 and 2-3 attract; 1 and 2 attract too but repel (seen together)
    A = np.eye(4)
    for i, j, w in [(0, 1, 1.0), (2, 3, 1.0), (1, 2, 0.9)]:
        A[i, j] = A[j, i] = w
    R = np.zeros((4, 4))
    R[1, 2] = R[2, 1] = 1.0
    lab = repulsion_spectral(A, R, 2, rng=np.random.default_rng(0))
    assert lab[0] == lab[1] and lab[2] == lab[3] and lab[1] != lab[2]


def test_time_gaps_and_compact_table():
    vis = np.zeros((10, 3), dtype=bool)
    vis[0:3, 0] = True
    vis[6:10, 1] = True
    vis[2:5, 2] = True
    g = time_gaps(vis)
    assert g[0, 1] == 4 and g[0, 2] == 0 and g[1, 2] == 2
    idx = compact_visible(vis)
    assert idx.shape == (10, 2)
    assert idx[2].tolist() == [0, 2] and idx[5].tolist() == [-1, -1]
