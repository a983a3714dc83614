"""The model's variants side by side: the rigid stage's joints by the model's MAP with explicit priors, as it is
(``model``) and with some of its terms set otherwise (``WEIGHTS``), at several prior scales.

    python -m bench.joint_model                       # markdown to stdout (slow: every case, both halves)
    python -m bench.joint_model --tune                # the prior's scale on the tuning seeds only
    python -m bench.joint_model --tune --markerset gait   # the realistic takes with a gait lab's marker set
    python -m bench.joint_model --json --case realistic rom 1 --scales 0.5   # one case (internal)

Generated cases are scored against their ground truth: joint rms over frames and joints (mean) and the
worst joint's rms, after IK. Each is fitted twice from the same joints stage: with the true grouping and
tree handed in, and with both found by the pipeline. Seeds 1-3 tune the prior's scale, seeds 4-6 check
it. Real takes with a reference skeleton (``../shared/realref/``) are fitted and scored by the reference
folder's ``score.py``; a few real takes (``../shared/realdata/``) are counted for the output checks'
warnings. Every case runs in a fresh process.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.common import REPO, run_isolated, table

FRAMES = 600
MOTIONS = ("rom", "walk", "run", "kick", "reach")
TUNE, CHECK = (1, 2, 3), (4, 5, 6)
ROM48_FRAMES = 3600
REALREF = REPO.parent / "shared" / "realref"
REALDATA = REPO.parent / "shared" / "realdata"
#: real takes whose output checks are counted (a walk, a run-like take, a gait-lab trial, a full-body sample)
REAL_TAKES = ("cmu/07_01.c3d", "cmu/85_02.c3d", "c3d_org_samples/Eb015pr.c3d", "ezc3d/Qualisys.c3d")


#: each model variant's data term weight, prior mean, like limbs' bone sigma, hinge prior, its placed hinges and
#: soft joints (``rigid.Params.data_weight``, ``prior_mean``, ``bone_sigma``, ``hinge_scale``, ``hinge_placed``,
#: ``soft_sigma``, ``mirror_prior``); what a variant leaves out is 0 (``hinge_placed``: True)
WEIGHTS = {"map": ("frames", "deepened", 0.0), "map-eff": ("effective", "deepened", 0.0),
           "map-eff-start": ("effective", "start", 0.0), "map-eff-like": ("effective", "deepened", 0.03),
           "map-like": ("frames", "deepened", 0.03),
           "map-hinge": ("frames", "deepened+leaf", 0.03, 0.01),
           "map-hinge-moved": ("frames", "deepened+leaf", 0.03, 0.01, False),
           "map-hinge-03": ("frames", "deepened+leaf", 0.03, 0.03, False),
           "map-eff-now": ("effective", "deepened+leaf", 0.03, 0.01, False),
           "map-soft-15": ("frames", "deepened+leaf", 0.03, 0.01, False, 15.0),
           "map-soft-30": ("frames", "deepened+leaf", 0.03, 0.01, False, 30.0),
           "map-soft-60": ("frames", "deepened+leaf", 0.03, 0.01, False, 60.0),
           "map-mirror": ("frames", "deepened+leaf", 0.03, 0.01, False, 15.0, True),
           "map-soft-placed": ("frames", "deepened+leaf", 0.03, 0.01, True, 15.0)}
#: the variants measured (``--variants``; "model" the model path with
#: ``rigid.Params``' own defaults, whatever they are now)
VARIANTS = ["model"]


def _rigid(mode: str, scale: float):
    from mocapskel.stages import rigid

    if mode == "model":
        return rigid.Params(joint_model="map", prior_scale=scale)
    w, mean, bone, *hinge = WEIGHTS[mode]
    return rigid.Params(joint_model="map", prior_scale=scale, data_weight=w, prior_mean=mean, bone_sigma=bone,
                        hinge_scale=hinge[0] if hinge else 0.0, hinge_placed=hinge[1] if len(hinge) > 1 else True,
                        soft_sigma=hinge[2] if len(hinge) > 2 else 0.0, mirror_prior=len(hinge) > 3 and hinge[3])


def _modes(scales: list[float]) -> list[tuple[str, str, float]]:
    return [(f"{v} {s:g}", v, s) for v in VARIANTS for s in scales]


def _vargs() -> list[str]:
    return ["--variants", *VARIANTS]


def generated_case(kind: str, motion: str, seed: int, scales: list[float]) -> dict:
    """{tree ("true" / "auto"): {mode: {"mean": mm, "worst": mm, "matched": joints}}} for one generated take."""
    from mocapskel import evaluate, pipeline
    from mocapskel.errors import MocapskelError
    from mocapskel.synth.presets import active_rom, make, realistic

    if kind in ("realistic", "gait", "cluster"):  # the cmu41 marker set, a gait lab's, or sliding cluster plates
        take = make(realistic(seed=seed, frames=FRAMES, motion=motion, markerset="cmu41" if kind == "realistic" else kind))
    else:
        take = make(active_rom(seed, frames=ROM48_FRAMES))
    clean = pipeline.run_until(take.markers, "clean").artifact
    out: dict = {}
    for tree in ("true", "auto"):
        try:
            src = evaluate.true_topology(take.truth, clean) if tree == "true" else pipeline.run_until(clean, "topology").artifact
            joints = pipeline.run_until(src, "joints").artifact
        except MocapskelError as e:
            out[tree] = {"error": str(e).splitlines()[0][:80]}
            continue
        out[tree] = {}
        for name, mode, s in _modes(scales):
            try:
                mot = pipeline.run_until(joints, "ik", {"rigid": _rigid(mode, s)}).artifact
            except MocapskelError as e:
                out[tree][name] = {"error": str(e).splitlines()[0][:80]}
                continue
            sc = evaluate.score_motion(mot, take.truth)
            each = [v for v in sc.joint_rms_each.values() if np.isfinite(v)]
            out[tree][name] = {"mean": sc.joint_rms_mm, "worst": float(max(each)) if each else float("nan"),
                               "matched": len(each), "start": mot.skeleton.info.get("refined", {}).get("start")}
    return out


def _fits(path: Path, scales: list[float]):
    """(label, the fit's result or {"error": message}) for every joint model, ``path`` fitted in this process."""
    from mocapskel import pipeline
    from mocapskel.errors import MocapskelError

    for label, mode, s in _modes(scales):
        params = pipeline.make_params(up="z", units="mm")
        params["rigid"] = _rigid(mode, s)
        try:
            yield label, pipeline.fit(path, params)
        except MocapskelError as e:
            yield label, {"error": str(e).splitlines()[0][:80]}


def real_case(name: str, scales: list[float]) -> dict:
    """{mode: score.py's fields} for one reference take (fitted in this process, scored by score.py)."""
    from mocapskel.io.bvh import write_bvh

    out = {}
    for label, res in _fits(REALREF / f"{name}.c3d", scales):
        if isinstance(res, dict):
            out[label] = res
            continue
        with tempfile.TemporaryDirectory() as d:
            bvh = Path(d) / f"{name}.bvh"
            b = res.bvh
            write_bvh(bvh, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
            r = subprocess.run([sys.executable, str(REALREF / "score.py"), name, str(bvh)], capture_output=True, text=True)
            out[label] = json.loads(r.stdout.strip().splitlines()[-1])
    return out


def checks_case(rel: str, scales: list[float]) -> dict:
    """{mode: the number of output-check warnings} for one real take."""
    return {label: res if isinstance(res, dict) else
            {"warnings": sum(1 for w in res.report["warnings"] if w.startswith("check "))}
            for label, res in _fits(REALDATA / rel, scales)}


def _cell(r: dict, key: str) -> str:
    return "error" if "error" in r else f"{r[key]:.1f}"


def generated_table(seeds, scales: list[float], cases=None, raw_path=None) -> tuple[str, dict]:
    cases = cases or [("realistic", m) for m in MOTIONS] + [("rom48", "rom")]
    rows, raw = [], {}
    modes = [n for n, _, _ in _modes(scales)]
    for kind, motion in cases:
        for seed in seeds:
            r = run_isolated("joint_model", "--case", kind, motion, str(seed), "--scales", *map(str, scales), *_vargs())
            raw[f"{kind} {motion} {seed}"] = r
            if raw_path:  # kept as it grows: a long run stopped early keeps what it measured
                Path(raw_path).write_text(json.dumps(raw, indent=1))
            for tree in ("true", "auto"):
                t = r[tree]
                if "error" in t:
                    rows.append([f"{kind} {motion}", seed, tree] + ["error"] * (2 * len(modes)))
                    continue
                rows.append([f"{kind} {motion}", seed, tree] + [_cell(t[m], k) for m in modes for k in ("mean", "worst")])
            print(f"  {rows[-2]}\n  {rows[-1]}", file=sys.stderr)
    head = ["case", "seed", "grouping and tree"] + [f"{m} {k} (mm)" for m in modes for k in ("mean", "worst")]
    return table(head, rows), raw


def summary(raw: dict, scales: list[float]) -> str:
    """Per case and half: the mean over seeds of the joint rms (mean and worst joint) for every mode."""
    modes = [n for n, _, _ in _modes(scales)]
    rows = []
    keys = sorted({k.rsplit(" ", 1)[0] for k in raw}, key=lambda k: list(raw).index(next(x for x in raw if x.startswith(k))))
    for case in keys:
        for half, seeds in (("tuning 1-3", TUNE), ("checking 4-6", CHECK)):
            for tree in ("true", "auto"):
                got = [raw[f"{case} {s}"][tree] for s in seeds if f"{case} {s}" in raw]
                if not got:
                    continue
                row = [case, half, tree]
                for m in modes:
                    for k in ("mean", "worst"):
                        v = [g[m][k] for g in got if "error" not in g and "error" not in g.get(m, {"error": 1})]
                        row.append(f"{np.mean(v):.1f}" + ("" if len(v) == len(got) else f" ({len(got) - len(v)} failed)")
                                   if v else "error")
                rows.append(row)
    return table(["case", "seeds", "grouping and tree"] + [f"{m} {k} (mm)" for m in modes for k in ("mean", "worst")], rows)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--case", nargs=3, metavar=("KIND", "MOTION", "SEED"))
    ap.add_argument("--real", metavar="NAME")
    ap.add_argument("--checks", metavar="REL")
    ap.add_argument("--scales", nargs="+", type=float, default=[0.5])
    ap.add_argument("--tune", action="store_true", help="the tuning seeds only, several scales")
    ap.add_argument("--real-only", action="store_true", help="the real takes only")
    ap.add_argument("--raw", default=None, help="write the per-case JSON here too")
    ap.add_argument("--variants", nargs="+", default=VARIANTS, choices=[*WEIGHTS, "model"],
                    help="the variants measured: model (rigid.Params' defaults), map (every frame independent), map-eff "
                         "(effective frames), map-eff-start (effective frames, the prior centred on the joints stage's "
                         "joints), map-eff-like (effective frames, like limbs' bones within 3 %%), map-like (every frame, "
                         "like limbs), and the others of WEIGHTS")
    ap.add_argument("--motions", nargs="+", default=None, help="the realistic motions only (and no rom48 unless named)")
    ap.add_argument("--seeds", nargs="+", type=int, default=None)
    ap.add_argument("--markerset", choices=["cmu41", "gait", "cluster"], default="cmu41",
                    help="the realistic takes' marker set (gait, cluster: without the 48-marker range of motion)")
    a = ap.parse_args()
    VARIANTS[:] = a.variants
    if a.case:
        print(json.dumps(generated_case(a.case[0], a.case[1], int(a.case[2]), a.scales)))
        return
    if a.real:
        print(json.dumps(real_case(a.real, a.scales)))
        return
    if a.checks:
        print(json.dumps(checks_case(a.checks, a.scales)))
        return
    if not a.real_only:
        generated(a)
    if not a.tune:
        real(a)


def generated(a) -> None:
    seeds = a.seeds or (TUNE if a.tune else TUNE + CHECK)
    cases = None
    if a.motions:
        cases = [("realistic", m) for m in a.motions if m != "rom48"] + ([("rom48", "rom")] if "rom48" in a.motions else [])
    if a.markerset != "cmu41":
        cases = [(a.markerset, m) for m in (a.motions or MOTIONS) if m != "rom48"]
    text, raw = generated_table(seeds, a.scales, cases, a.raw)
    if a.raw:
        Path(a.raw).write_text(json.dumps(raw, indent=1))
    print("Generated takes (cmu41 realistic: 600 frames, 120 Hz, 1 mm noise, skin motion; rom48: the active human "
          f"ROM take, 48 markers, {ROM48_FRAMES} frames): joint rms after IK against the truth, mean over joints "
          "and frames, and the worst joint's. Seeds 1-3 tune the prior's scale, 4-6 check it.\n")
    print(summary(raw, a.scales))
    print("\nEvery seed:\n")
    print(text)


def real(a) -> None:
    if (REALREF / "score.py").is_file():
        rows = []
        for name in sorted(p.name[: -len(".ref.npz")] for p in REALREF.glob("*.ref.npz")):
            r = run_isolated("joint_model", "--real", name, "--scales", *map(str, a.scales), *_vargs())
            row = [name]
            for m in r.values():
                if "error" in m:
                    row += ["error", ""]
                elif m.get("kind") == "lengths":
                    row += [f"{m['links_matched']} of {m['links_ref']} links", f"{m.get('bone_err_pct_mean', float('nan')):.2f} %"]
                else:
                    row += [f"{m['joints_matched']} of {m['joints_ref']}: {m['joint_rms_mean_mm']:.1f} mm",
                            f"{m['bone_err_mm_mean']:.1f} mm"]
            rows.append(row)
            print(f"  {row}", file=sys.stderr)
        modes = [n for n, _, _ in _modes(a.scales)]
        print("\nReal takes with a reference skeleton (`../shared/realref/score.py`):\n")
        print(table(["take"] + [f"{m} {k}" for m in modes for k in ("joints", "bone error")], rows))
    else:
        print("\n(the reference folder `../shared/realref/` is absent: real references not measured)")
    rows = []
    for rel in REAL_TAKES:
        if not (REALDATA / rel).is_file():
            continue
        r = run_isolated("joint_model", "--checks", rel, "--scales", *map(str, a.scales), *_vargs())
        rows.append([rel] + [m.get("warnings", "error") for m in r.values()])
        print(f"  {rows[-1]}", file=sys.stderr)
    if rows:
        modes = [n for n, _, _ in _modes(a.scales)]
        print("\nReal takes (`../shared/realdata/`): output-check warnings (bone lengths, joints off their markers, jumps):\n")
        print(table(["take"] + modes, rows))


if __name__ == "__main__":
    main()
