"""Output checks over real and generated takes: can a user trust what `fit` writes?

    python -m bench.checks                  # markdown to stdout
    python -m bench.checks --only gen       # generated takes only (or: real)

Every take is fitted in a fresh process (`pipeline.fit`, default options: BVH
with `--up y`, cm) and judged by :mod:`mocapskel.checks` (bones against the
subject's marker extent, joints against their segments' markers, joint steps
against the fastest marker, rotation flips, residual against the rigid fit's
noise) and by the written BVH itself: Euler steps above 10 degrees between
frames where the joint's rotation changes by less than 2 degrees (gimbal
spikes). For generated takes, markers and segments lost against the truth.
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

import numpy as np

from bench.common import REPO, table

REALDATA = REPO.parent / "shared" / "realdata"

#: generated cases: (name, recipe keyword arguments)
GENERATED: list[tuple[str, dict]] = [
    *[(f"human 2 markers/segment, seed {s}", dict(kind="human", seed=s, frames=7200, noise_mm=1.0, soft_tissue_mm=2.0,
                                                  gaps_per_marker_per_minute=4.0, markers_per_segment=2)) for s in range(1, 6)],
    ("human ROM 1 min (sample settings)", dict(kind="human", seed=0, frames=7200, noise_mm=1.0, soft_tissue_mm=2.0,
                                              gaps_per_marker_per_minute=4.0)),
    ("human walk 1 min (sample settings)", dict(kind="human", seed=0, frames=7200, noise_mm=1.0, soft_tissue_mm=2.0,
                                               gaps_per_marker_per_minute=4.0, motion="walk")),
    *[(f"chain 8 links of 1 m, 100 Hz, seed {s}", dict(kind="chain", seed=s, frames=1000, counts=(4, 3, 3, 4, 3, 3, 3, 3),
                                                      link_length=1000.0)) for s in range(3)],
    *[(f"chain 5 links of 1 m, 2-marker links, seed {s}", dict(kind="chain", seed=s, frames=1000, counts=(3, 2, 2, 2, 2),
                                                              link_length=1000.0)) for s in range(2)],
    *[(f"passive ROM 1 min, seed {s}", dict(kind="human", seed=s, frames=7200, noise_mm=1.0, soft_tissue_mm=2.0,
                                            gaps_per_marker_per_minute=4.0, ghosts=25, jumps=10, passive=True)) for s in (1, 2)],
    ("active ROM with 10 jumps", dict(kind="human", seed=3, frames=3600, noise_mm=1.0, soft_tissue_mm=2.0, jumps=10)),
]

CHECKS = ("residual", "bone_length", "joint_far", "joint_step", "rotation_flip", "limb_asymmetry", "limb_mirror", "limb_cross",
          "not_converged")


def euler_spikes(path: Path) -> tuple[int, float, str]:
    """(joint-frames with a rotation channel step > 10 deg where the rotation turns < 2 deg, largest such step, orders)."""
    from mocapskel.io.bvh_read import read_bvh

    skel, _, local, _ = read_bvh(path)
    text = path.read_text().splitlines()
    k = next(i for i, l in enumerate(text) if l.startswith("Frame Time"))
    vals = np.loadtxt(text[k + 1 :], ndmin=2)
    orders, cols, c = [], [], 0
    for l in text[:k]:
        t = l.split()
        if t[:1] == ["CHANNELS"]:
            ch = t[2:]
            rot = [c + i for i, n in enumerate(ch) if n.endswith("rotation")]
            orders.append("".join(n[0] for n in ch if n.endswith("rotation")))
            cols.append(rot)
            c += len(ch)
    ang = np.stack([vals[:, r] for r in cols], axis=1)  # (F, S, 3), file order = skel order
    step = np.abs(np.diff(ang, axis=0)).max(-1)
    cosang = (np.einsum("fsij,fsij->fs", local[1:], local[:-1]) - 1.0) / 2.0
    true = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    bad = (step > 10.0) & (true < 2.0)
    return int(bad.sum()), float(step[bad].max()) if bad.any() else 0.0, ",".join(sorted(set(orders)))


def one(path: str, truth_path: str | None) -> dict:
    """Fit one take and judge it (run in a fresh process)."""
    from mocapskel import checks, pipeline
    from mocapskel.artifacts import markers_of
    from mocapskel.errors import MocapskelError
    from mocapskel.io.bvh import write_bvh

    t = time.perf_counter()
    try:
        res = pipeline.fit(path, pipeline.make_params())
    except MocapskelError as e:
        return {"result": f"exit {e.exit_code}: {str(e).split(': ', 1)[-1][:80]}", "seconds": time.perf_counter() - t}
    secs = time.perf_counter() - t
    motion = res.motion
    mk = markers_of(motion)
    found = checks.run_checks(motion, mk.points, joint_notes=checks.joint_notes(motion))
    with tempfile.TemporaryDirectory() as d:
        b = res.bvh
        out = Path(d) / "o.bvh"
        write_bvh(out, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
        spikes, worst, orders = euler_spikes(out)
    r = {"result": "ok", "seconds": secs, "frames": mk.n_frames, "segments": len(motion.skeleton.names),
         "markers_kept": mk.n_markers, "markers_dropped": len((res.report.get("clean") or {}).get("dropped_markers", [])),
         "ik_rms": res.report["ik"]["marker_rms_mm"], "spikes": spikes, "worst_spike": worst, "orders": orders,
         "clean_jumps": int((mk.info.get("clean") or {}).get("jump_samples", 0)), "checks": {}}
    for f in found:
        c = r["checks"].setdefault(f.check, {"names": [], "frames": 0})
        c["names"].append(f.name)
        c["frames"] = max(c["frames"], len(f.frames))
    if truth_path:
        from mocapskel.synth.truth import Truth

        tr = Truth.load(truth_path)
        r["segments_true"] = len(tr.segment_names)
    return r


def _cell(r: dict, check: str) -> str:
    c = r.get("checks", {}).get(check)
    if not c:
        return "0"
    n = len(c["names"])
    return f"{n} ({c['frames']} fr)" if c["frames"] else str(n)


def _run(path: Path, truth: Path | None) -> dict:
    cmd = [sys.executable, "-m", "bench.checks", "--one", str(path)] + (["--truth", str(truth)] if truth else [])
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if out.returncode != 0:
        return {"result": f"crash: {out.stderr.strip().splitlines()[-1][:80] if out.stderr.strip() else out.returncode}"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _row(name: str, r: dict) -> list:
    if r.get("result") != "ok":
        return [name, r.get("result", "?")] + [""] * (len(CHECKS) + 5)
    seg = f"{r['segments']}/{r['segments_true']}" if "segments_true" in r else str(r["segments"])
    return [name, "ok", seg, f"{r['markers_kept']} ({r['markers_dropped']} dropped, {r['clean_jumps']} jump samples)",
            *[_cell(r, c) for c in CHECKS],
            f"{r['spikes']}" + (f" (up to {r['worst_spike']:.0f}°)" if r["spikes"] else ""), r["orders"],
            round(r["seconds"], 1)]


HEADER = ["take", "result", "segments", "markers kept by clean", "residual", "bone > extent", "joint far", "joint step",
          "rotation flip", "limb asymmetry", "limb mirror", "limb cross", "not converged", "Euler spikes", "order", "fit (s)"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--truth", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--only", choices=["gen", "real"], default=None)
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one(a.one, a.truth)))
        return
    print("Each take fitted with default options (`--up y`) in a fresh process and judged by `mocapskel.checks` "
          "(the report's `checks`): cells give the joints or segments failing, and the most frames one of them "
          "fails in. Bone > extent: a bone longer than the subject's marker extent; joint far: a joint farther than "
          "half of it from every marker of its two segments; joint step: a joint moving more in one frame than the "
          "fastest marker plus 20 mm; rotation flip: a joint turning > 90° in one frame while its markers hardly "
          "move; limb asymmetry: in a skeleton recognised as a person, the same left and right bone more than 20 % apart; "
          "limb mirror: in one, a midline joint more than a fifth of the hips' (shoulders') spacing off their mid-plane; "
          "limb cross: like limbs' first joints in the opposite order to their own markers; "
          "residual: IK rms above 3 × the rigid fit's noise + 10 mm. Euler spikes: joint-frames of the written "
          "BVH whose rotation channels step > 10° while the rotation turns < 2°. Markers kept: after clean and merge-ids "
          "(dropped: markers clean left with nothing; jump samples: samples clean turned into gaps as jumps).\n")
    if a.only != "real":
        from mocapskel.io.markers import write_markers
        from mocapskel.synth.presets import Recipe, make

        rows = []
        with tempfile.TemporaryDirectory() as d:
            for name, kw in GENERATED:
                take = make(Recipe(**kw))
                p = Path(d) / "take.c3d"
                write_markers(p, replace(take.markers, source=p.name))
                take.truth.save(Path(d) / "truth.npz")
                rows.append(_row(name, _run(p, Path(d) / "truth.npz")))
                print(f"  {rows[-1]}", file=sys.stderr)
        print("### Generated takes\n")
        print(table(HEADER, rows) + "\n")
    if a.only != "gen":
        if not REALDATA.is_dir():
            print("(the real-take folder is absent: nothing measured)\n")
            return
        rows = []
        for p in sorted(p for p in REALDATA.rglob("*") if p.is_file() and p.suffix.lower() in (".c3d", ".trc")):
            rows.append(_row(str(p.relative_to(REALDATA)), _run(p, None)))
            print(f"  {rows[-1]}", file=sys.stderr)
        print("### Real takes (`../shared/realdata/`)\n")
        print(table(HEADER, rows) + "\n")


if __name__ == "__main__":
    main()
