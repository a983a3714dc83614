"""One end-to-end fit of a generated take, in a fresh process: time, memory, accuracy.

    python -m bench.fit_case --json --kind human --frames 7200 --seed 1 --noise 1 --soft-tissue 2 --gaps 4

The take is generated and written to a temporary C3D first, in another
process (neither timed nor in this process's peak memory); then ``fit`` runs
from that file with no cache (read, all stages, BVH written).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from bench.common import REPO, peak_rss_mb
from mocapskel import evaluate, pipeline
from mocapskel.io.bvh import write_bvh
from mocapskel.io.markers import write_markers
from mocapskel.synth.presets import Recipe, make
from mocapskel.synth.truth import Truth


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--kind", default="human")
    ap.add_argument("--frames", type=int, default=7200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--soft-tissue", type=float, default=0.0)
    ap.add_argument("--gaps", type=float, default=0.0)
    ap.add_argument("--mps", type=int, default=None, help="markers per segment (human)")
    ap.add_argument("--counts", default="4-3-3")
    ap.add_argument("--link-length", type=float, default=300.0)
    ap.add_argument("--format", default="c3d")
    ap.add_argument("--joint-method", default="auto")
    ap.add_argument("--jumps", type=int, default=0)
    ap.add_argument("--ghosts", type=int, default=0)
    ap.add_argument("--passive", action="store_true", help="new label after every gap")
    ap.add_argument("--write", default=None, help=argparse.SUPPRESS)  # internal: generate into this folder, then stop
    a = ap.parse_args()
    rec = Recipe(kind=a.kind, seed=a.seed, frames=a.frames, noise_mm=a.noise, soft_tissue_mm=a.soft_tissue,
                 gaps_per_marker_per_minute=a.gaps, markers_per_segment=a.mps,
                 counts=tuple(int(c) for c in a.counts.split("-")), link_length=a.link_length,
                 jumps=a.jumps, ghosts=a.ghosts, passive=a.passive)
    if a.write:
        take = make(rec)
        path = Path(a.write) / f"take.{a.format}"
        write_markers(path, replace(take.markers, source=path.name))
        take.truth.save(Path(a.write) / "truth.npz")
        return
    with tempfile.TemporaryDirectory() as d:
        # the take is generated in another process: this one's time and memory are the fit's alone,
        # from the file, as `mocapskel fit` runs
        subprocess.run([sys.executable, "-m", "bench.fit_case", *sys.argv[1:], "--write", d], check=True, cwd=REPO)
        path = Path(d) / f"take.{a.format}"
        truth = Truth.load(Path(d) / "truth.npz")
        n_markers = int(truth.marker_segment.size)
        base_rss = peak_rss_mb()
        t = time.perf_counter()
        res = pipeline.fit(path, pipeline.make_params(joint_method=a.joint_method))
        b = res.bvh
        t_w = time.perf_counter()
        write_bvh(Path(d) / "out.bvh", b.skeleton, b.root_pos, b.local_rot, b.frame_time)
        res.run.seconds["write"] = time.perf_counter() - t_w
        total = time.perf_counter() - t
        if a.passive or a.ghosts:  # score against the truth of the merged labels (not timed)
            from bench.passive import merged_truth
            from mocapskel.artifacts import markers_of
            from mocapskel.io.markers import read_markers
            from mocapskel.synth.truth import SynthTake

            truth = merged_truth(markers_of(res.motion), SynthTake(markers=read_markers(path), truth=truth))
    sc = evaluate.score_motion(res.motion, truth)
    sj = evaluate.score_joints(res.motion.skeleton.joints, truth)
    out = {
        "frames": a.frames, "markers": n_markers, "total_s": total,
        "seconds": {k: v for k, v in res.run.seconds.items() if k != "total"},
        "peak_rss_mb": peak_rss_mb(), "rss_before_fit_mb": base_rss,
        "segments_ok": sc.segments_ok, "topology_ok": sc.topology_ok,
        "joint_rms_mm": sc.joint_rms_mm, "joint_rms_joints_stage_mm": sj.joint_rms_mm, "rse": sj.rse,
        "joint_rms_max_mm": max(sc.joint_rms_each.values(), default=float("nan")),
        "bone_err_max": sc.bone_err_max, "bone_err": sc.bone_err,
        "ik_rms_mm": res.report["ik"]["marker_rms_mm"],
        "methods": list(res.motion.skeleton.joints.method),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
