"""Passive takes: marker-ID merging against the truth, and the fit after it.

    python -m bench.passive                 # markdown to stdout
    python -m bench.passive --seeds 1 --frames 3600

For every seed the same subject and motion is generated twice: as a passive
take (``passive_rom``: a new label after every gap, ~4 gaps per marker per
minute, 25 ghosts, 10 jumps, 1 mm noise, 2 mm soft tissue) and as the active
take (``active_rom``, the same labels throughout). The passive take goes
through clean and merge-ids; every output label is mapped to the physical
marker most of its samples come from (the sources' ``truth.marker_id``), and

- *right samples* is the share of the merged output's samples that come from
  that physical marker (ghost samples count as wrong);
- *kept* is the share of the real markers' samples after clean that end up in
  an output label of their own physical marker;
- *mixed labels* counts output labels with samples of two physical markers;
  *simultaneous* counts frames where two sources of one output label are
  both seen (must be 0);
- the fit (``run_until(..., "ik")`` from the raw take) is scored with
  ``evaluate.score_skeleton`` against the truth with labels mapped to
  physical markers, next to the active take's.

A second table runs merge-ids alone on harder takes: ghosts that outlive
clean's 0.5 s, jumps left to merge-ids, twice the gaps, more soft tissue,
walking, everything lost at once (Kirk's failure case), two markers per
segment.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

import numpy as np

from bench.common import machine, table
from mocapskel import evaluate, pipeline
from mocapskel.artifacts import Markers, markers_of
from mocapskel.stages import clean, merge_ids
from mocapskel.synth.presets import active_rom, make, passive_rom
from mocapskel.synth.truth import SynthTake, Truth


def physical_ids(merged: Markers, take: SynthTake) -> np.ndarray:
    """(M,) physical marker of every label of a merge-ids output (-1: mostly ghost).

    The majority, weighted by visible samples of the take, of its source
    labels' ``truth.marker_id`` (``info["merge_ids"]["merged"]`` lists them).
    """
    src = merged.info["merge_ids"]["merged"]
    index = {lab: i for i, lab in enumerate(take.markers.labels)}
    seen = np.isfinite(take.markers.points[..., 0]).sum(axis=0)
    out = np.full(merged.n_markers, -1)
    for k, lab in enumerate(merged.labels):
        cols = np.array([index[s] for s in src[lab]])
        ids = take.truth.marker_id[cols]
        w = np.bincount(ids + 1, weights=seen[cols].astype(float))
        out[k] = int(np.argmax(w)) - 1
    return out


def merged_truth(merged: Markers, take: SynthTake) -> Truth:
    """The take's truth with one entry per merged label (segment and id of its physical marker)."""
    tr = take.truth
    pid = physical_ids(merged, take)
    seg_of_id = np.full(int(tr.marker_id.max()) + 2, -1)
    real = tr.marker_id >= 0
    seg_of_id[tr.marker_id[real]] = tr.marker_segment[real]
    seg = np.where(pid >= 0, seg_of_id[np.maximum(pid, 0)], -1)
    return replace(tr, marker_id=pid, marker_segment=seg)


def merge_scores(cleaned: Markers, merged: Markers, take: SynthTake) -> dict:
    """Sample-level accuracy of a merge (see the module docstring)."""
    src = merged.info["merge_ids"]["merged"]
    index = {lab: i for i, lab in enumerate(take.markers.labels)}
    cidx = {lab: i for i, lab in enumerate(cleaned.labels)}
    pid = physical_ids(merged, take)
    right = total = simultaneous = 0
    mixed = 0
    for k, lab in enumerate(merged.labels):
        out_vis = np.isfinite(merged.points[:, k, 0])
        ids = set()
        count = np.zeros(cleaned.n_frames, dtype=int)
        for s in src[lab]:
            v = np.isfinite(cleaned.points[:, cidx[s], 0])
            count += v
            n = int((v & out_vis).sum())
            sid = int(take.truth.marker_id[index[s]])
            total += n
            if sid == pid[k] and sid >= 0:
                right += n
            if n:
                ids.add(sid)
        simultaneous += int((count > 1).sum())
        mixed += len(ids) > 1
    real_clean = sum(
        int(np.isfinite(cleaned.points[:, j, 0]).sum())
        for j, lab in enumerate(cleaned.labels)
        if take.truth.marker_id[index[lab]] >= 0
    )
    n_phys = int(take.truth.marker_id.max()) + 1
    per = np.bincount(pid[pid >= 0], minlength=n_phys)
    return {
        "right": right / max(total, 1),
        "kept": right / max(real_clean, 1),
        "mixed": mixed,
        "simultaneous": simultaneous,
        "labels_out": merged.n_markers,
        "physical": n_phys,
        "split": int((per > 1).sum()),
        "ghost_out": int((pid < 0).sum()),
    }


def case(seed: int, frames: int, repeats: int = 3) -> dict:
    take = make(passive_rom(seed, frames))
    active = make(active_rom(seed, frames))
    cleaned = clean.run(take.markers)
    times = []
    merged = None
    for _ in range(repeats):
        t = time.perf_counter()
        merged = merge_ids.run(cleaned)
        times.append(time.perf_counter() - t)
    ms = merge_scores(cleaned, merged, take)
    info = merged.info["merge_ids"]
    index = {lab: i for i, lab in enumerate(take.markers.labels)}
    ms["ghosts_in"] = int((take.truth.marker_id < 0).sum())
    ms["ghosts_after_clean"] = int(sum(take.truth.marker_id[index[lab]] < 0 for lab in cleaned.labels))
    t = time.perf_counter()
    run = pipeline.run_until(take.markers, "ik")
    fit_s = time.perf_counter() - t
    skel = run.artifact.skeleton
    sc = evaluate.score_skeleton(skel, merged_truth(markers_of(run.artifact), take))
    run_a = pipeline.run_until(active.markers, "ik")
    sa = evaluate.score_skeleton(run_a.artifact.skeleton, active.truth)
    return {
        "seed": seed, "frames": frames, "labels_in": take.markers.n_markers, "after_clean": cleaned.n_markers,
        "merge_s": float(np.median(times)), "fit_s": fit_s, **ms, "info": info,
        "passive": sc, "active": sa,
    }


def harder_cases(seed: int = 1, frames: int = 7200) -> list[list]:
    """merge-ids alone on harder passive takes (planted trouble whose truth is known)."""
    from mocapskel.synth import corrupt
    from mocapskel.synth.presets import Recipe

    base = dict(kind="human", seed=seed, frames=frames, noise_mm=1.0, soft_tissue_mm=2.0)
    rows = []

    def build(name: str):
        rng = np.random.default_rng(seed)
        clean_p = clean.Params()
        if name == "long ghosts (30, 0.6–1.8 s: outlive clean)":
            t = make(Recipe(**base, gaps_per_marker_per_minute=4.0))
            t = corrupt.relabel_passive(corrupt.add_ghosts(t, rng, n_ghosts=30, duration_s=(0.6, 1.8)), rng)
        elif name == "40 jumps, clean's own jump filter off":
            t = make(Recipe(**base, gaps_per_marker_per_minute=4.0))
            t = corrupt.relabel_passive(corrupt.add_jumps(t, rng, n_jumps=40), rng)
            clean_p = clean.Params(jump_mm=1e9)
        elif name == "8 gaps per marker per minute":
            t = make(Recipe(**base, gaps_per_marker_per_minute=8.0, ghosts=25, jumps=10, passive=True))
        elif name == "5 mm soft tissue":
            t = make(Recipe(**{**base, "soft_tissue_mm": 5.0}, gaps_per_marker_per_minute=4.0, ghosts=25, jumps=10,
                            passive=True))
        elif name == "walking instead of ROM":
            t = make(passive_rom(seed, frames, motion="walk"))
        elif name == "everything lost for 0.5 s":
            t = make(Recipe(**base, gaps_per_marker_per_minute=4.0))
            t = corrupt.relabel_passive(corrupt.everything_lost(t, (frames // 2, frames // 2 + 60)), rng)
        else:  # "2 markers per segment"
            t = make(passive_rom(seed, frames, markers_per_segment=2))
        return t, clean_p

    for name in ("long ghosts (30, 0.6–1.8 s: outlive clean)", "40 jumps, clean's own jump filter off",
                 "8 gaps per marker per minute", "5 mm soft tissue", "walking instead of ROM",
                 "everything lost for 0.5 s", "2 markers per segment"):
        take, clean_p = build(name)
        cleaned = clean.run(take.markers, clean_p)
        t = time.perf_counter()
        merged = merge_ids.run(cleaned)
        dt = time.perf_counter() - t
        ms = merge_scores(cleaned, merged, take)
        index = {lab: i for i, lab in enumerate(take.markers.labels)}
        ghosts_left = sum(take.truth.marker_id[index[lab]] < 0 for lab in cleaned.labels)
        from mocapskel.synth.corrupt import bad_sample_mask

        jump = bad_sample_mask(take)[:, [index[lab] for lab in cleaned.labels]] & np.isfinite(cleaned.points[..., 0])
        kept = np.zeros_like(jump)
        cidx = {lab: i for i, lab in enumerate(cleaned.labels)}
        for k, lab in enumerate(merged.labels):
            out = np.isfinite(merged.points[:, k, 0])
            for src in merged.info["merge_ids"]["merged"][lab]:
                kept[:, cidx[src]] = out & np.isfinite(cleaned.points[:, cidx[src], 0])
        d = merged.info["merge_ids"]["dropped"]
        rows.append([
            name, take.markers.n_markers, cleaned.n_markers, ms["physical"], merged.n_markers,
            f"{100 * ms['right']:.3f}", ms["mixed"], f"{len(d['ghost_labels'])} / {ghosts_left}",
            f"{int((jump & ~kept).sum())} / {int(jump.sum())}", round(dt, 2),
            max(1, len(merged.info["merge_ids"]["pieces"])),
        ])
        print(f"  {rows[-1]}", file=sys.stderr)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--frames", type=int, default=7200)
    ap.add_argument("--no-harder", action="store_true", help="skip the table of harder takes")
    a = ap.parse_args()
    rows_m, rows_f = [], []
    for seed in a.seeds:
        r = case(seed, a.frames)
        info = r["info"]
        d = info["dropped"]
        rows_m.append([
            seed, r["labels_in"], r["after_clean"], info["physical_markers"], r["labels_out"], r["split"],
            f"{100 * r['right']:.3f}", f"{100 * r['kept']:.2f}", r["mixed"], r["simultaneous"],
            f"{r['ghosts_in'] - r['ghosts_after_clean']} / {len(d['ghost_labels'])} / {r['ghosts_in']}",
            d["jump_samples"], d["edge_samples"], round(r["merge_s"], 2),
        ])
        p, q = r["passive"], r["active"]
        rows_f.append([
            seed, "yes" if p.segments_ok else "NO", "yes" if p.topology_ok else "NO", round(p.joint_rms_mm, 2),
            round(100 * p.bone_err_max, 2), "yes" if q.segments_ok else "NO", "yes" if q.topology_ok else "NO",
            round(q.joint_rms_mm, 2), round(100 * q.bone_err_max, 2), round(r["fit_s"], 2),
        ])
        print(f"  seed {seed}: {rows_m[-1]} {rows_f[-1]}", file=sys.stderr)
    minutes = a.frames / 120.0 / 60.0
    print(f"Passive human ROM takes (`passive_rom`, {a.frames} frames = {minutes:.3g} min at 120 Hz, 48 markers; "
          f"{machine()}).\n")
    print(table(
        ["seed", "labels in", "after clean", "physical (most seen at once)", "labels out", "markers split",
         "right samples (%)", "kept (%)", "mixed labels", "simultaneous",
         "ghosts dropped (clean / merge-ids / planted)",
         "jump samples", "edge samples", "merge-ids (s)"], rows_m))
    print()
    print(table(
        ["seed", "passive: segments", "passive: topology", "passive: joint rms (mm)", "passive: worst bone (%)",
         "active: segments", "active: topology", "active: joint rms (mm)", "active: worst bone (%)",
         "passive fit to IK (s)"], rows_f))
    if not a.no_harder:
        print(f"\nHarder passive takes, merge-ids alone (seed {a.seeds[0]}, {a.frames} frames; ghosts dropped by "
              "merge-ids / ghosts left by clean; bad samples removed by merge-ids / bad samples left by clean):\n")
        print(table(
            ["take", "labels in", "after clean", "physical markers", "labels out", "right samples (%)",
             "mixed labels", "ghosts dropped", "jump / bad samples removed", "merge-ids (s)", "pieces"],
            harder_cases(a.seeds[0], a.frames)))


if __name__ == "__main__":
    main()
