"""Joint uncertainty: is the reported 95 % region right, and what does it cost?

    python -m bench.uncertainty coverage [--seeds 1-6] [--frames 1200]
    python -m bench.uncertainty realistic [--seeds 1-6]
    python -m bench.uncertainty cost [--runs 3] [TAKE ...]
    python -m bench.uncertainty real TAKE ...

coverage: generated human range-of-motion takes (seeded), fitted to the rigid stage; each joint's error
relative to the markers it is measured against (its child's, or its parent's where only those make a
frame; the fitted joint carried into every frame by the best-fit motion of those fitted markers onto the
observed ones, against the true joint, averaged over the
frames and turned back to the rest frame's axes) against the reported posterior covariance: the share
of joints whose error falls inside the 95 % region (chi-square, 3 dof), the median radius of that
region along its largest axis and the median error. Measured at the model's MAP, with the
DESIGN's noise (1 mm noise and 2 mm soft tissue) and with white noise alone (1 mm, what the model
assumes).

realistic: the same on the realistic cmu41 takes (600 frames, skin motion, 1 mm noise; every motion), the
true grouping and tree handed in, at the model's MAP with rigid joints and with its soft joints (the default); per half (seeds
1-3, 4-6), and which joints the prior sets on walks and on ranges of motion.

cost: the rigid stage with and without the uncertainty, interleaved, medians of ``--runs``; and a
whole fit's time for scale.

real: real takes fitted: the noise, each take's least certain joints, the warnings for joints the prior sets.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace

import numpy as np

from mocapskel.evaluate import segment_map
from mocapskel.pipeline import make_params, run_until
from mocapskel.solvers.model.uncertainty import skeleton_uncertainty
from mocapskel.stages import rigid
from mocapskel.synth.presets import Recipe, active_rom, make

CHI2_3_95 = 7.814727903251178  # 95 % quantile of chi-square with 3 degrees of freedom


def _kabsch(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations R (F, 3, 3) and translations t (F, 3) with R X + t nearest Y (F, n, 3)."""
    cx, cy = X.mean(0), Y.mean(1)
    Hm = np.einsum("ni,fnj->fij", X - cx, Y - cy[:, None])
    U, _, Vt = np.linalg.svd(Hm)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    D = np.zeros((len(d), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    return R, cy - np.einsum("fij,j->fi", R, cx)


def joint_errors(skel, truth, unc: dict) -> list[tuple[float, ...]]:
    """Per joint measured against a segment of 3+ markers (its child's, or its parent's where the report
    says so: ``frame``): (Mahalanobis d^2, |error| mm, 95 % radius along its largest axis, its three sds)."""
    pts = skel.joints.topology.segments.markers.points
    smap = segment_map(skel.marker_segment, truth)
    out = []
    for c in np.flatnonzero(skel.parent >= 0):
        u = unc["joints"].get(skel.names[c])
        p = int(skel.parent[c])
        if u is None or c not in smap or p not in smap:
            continue
        tc, tp = smap[int(c)], smap[p]
        j = [k for k, ch in enumerate(truth.joint_child) if {int(ch), int(truth.parent[ch])} == {tc, tp}]
        f = skel.names.index(u.get("frame", skel.names[c]))  # the segment the joint is measured against
        ms = np.flatnonzero(skel.marker_segment == f)
        if len(j) != 1 or ms.size < 3:
            continue
        X = skel.origin[f] + skel.marker_local[ms]
        seen = np.isfinite(pts[:, ms]).all((1, 2)) & np.isfinite(truth.joints[:, j[0]]).all(1)
        R, t = _kabsch(X, pts[seen][:, ms])
        fitted = np.einsum("fij,j->fi", R, skel.origin[c]) + t
        e = np.einsum("fji,fj->i", R, fitted - truth.joints[seen, j[0]]) / seen.sum()  # back to rest axes
        V = np.asarray(u["directions"])
        sd = np.maximum(np.asarray(u["sd_mm"]), 1e-9)
        d2 = float(np.sum((V @ e / sd) ** 2))
        out.append((d2, float(np.linalg.norm(e)), float(np.sqrt(CHI2_3_95) * sd[0]), *map(float, sd)))
    return out


def calibrated_median_error(rows: np.ndarray, draws: int = 400) -> float:
    """The median error the joints of ``rows`` (:func:`joint_errors`) would show were every reported region
    exact: each joint's errors drawn from its own N(0, diag(sd^2)), pooled. A region long along one axis (a
    hinge's) has its 95 % radius 2.8 sd there and a median error of 0.67 sd: a ratio of 4.1 where an
    isotropic one has 1.8, so the bar on the ratio is read against this."""
    sd = rows[:, 3:6]
    z = np.random.default_rng(0).standard_normal((draws, len(sd), 3))
    return float(np.median(np.linalg.norm(z * sd[None], axis=2)))


def coverage(seeds: list[int], frames: int) -> None:
    cases = {"noise 1 mm + soft tissue 2 mm": lambda s: active_rom(seed=s, frames=frames),
             "white noise 1 mm": lambda s: Recipe(kind="human", seed=s, frames=frames, noise_mm=1.0)}
    print("| take | joints of | joints | inside 95 % | median 95 % radius (mm) | median error (mm) | set by prior | noise (mm) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name, recipe in cases.items():
        configs = {"the model's MAP": {}}
        rows = {k: [] for k in configs}
        prior = {k: 0 for k in configs}
        noise = {k: [] for k in configs}
        for s in seeds:
            take = make(recipe(s))
            for where, extra in configs.items():
                params = make_params()
                params["rigid"] = replace(params.get("rigid") or rigid.Params(), **extra)
                sk = run_until(take.markers, "rigid", params).artifact
                unc = sk.info.get("uncertainty")
                if not unc:
                    continue
                rows[where] += joint_errors(sk, take.truth, unc)
                prior[where] += sum(bool(j["set_by_prior"]) for j in unc["joints"].values())
                noise[where].append(unc["noise_mm"])
        for where, r in rows.items():
            if not r:
                continue
            a = np.array(r)
            print(f"| {name} | {where} | {len(a)} | {np.mean(a[:, 0] <= CHI2_3_95):.0%} | {np.median(a[:, 2]):.2f} |"
                  f" {np.median(a[:, 1]):.2f} | {prior[where]} | {np.median(noise[where]):.2f} |")
        sys.stdout.flush()


def coverage_realistic(seeds: list[int]) -> None:
    from mocapskel import evaluate
    from mocapskel.synth.presets import realistic

    motions = ("rom", "walk", "run", "kick", "reach")
    # the MAP with rigid joints, and as the model path has it (soft joints where the take shows skin motion, their
    # offsets eliminated with the poses in the curvature)
    configs = {"MAP 0.1": rigid.Params(soft_sigma=0.0), "MAP 0.1, soft joints (the default)": rigid.Params()}
    rows: dict = {}
    named: dict = {}
    for m in motions:
        for s in seeds:
            take = make(realistic(seed=s, frames=600, motion=m, markerset="cmu41"))
            clean = run_until(take.markers, "clean").artifact
            joints = run_until(evaluate.true_topology(take.truth, clean), "joints").artifact
            half = "tuning 1-3" if s <= 3 else "checking 4-6"
            for where, p in configs.items():
                sk = run_until(joints, "rigid", {"rigid": p}).artifact
                unc = sk.info.get("uncertainty")
                if not unc:
                    continue
                rows.setdefault((half, where), []).extend(joint_errors(sk, take.truth, unc))
                prior = sorted(k for k, j in unc["joints"].items() if j["set_by_prior"])
                named.setdefault((m, where), []).append(len(prior))
            print(f"  {m} {s}", file=sys.stderr)
    print("| half | joints of | joints | inside 95 % | median 95 % radius (mm) | median error (mm) | radius / error |"
          " the same were the regions exact |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for (half, where), r in sorted(rows.items()):
        a = np.array(r)
        rad = np.median(a[:, 2])
        print(f"| {half} | {where} | {len(a)} | {np.mean(a[:, 0] <= CHI2_3_95):.0%} | {rad:.2f} |"
              f" {np.median(a[:, 1]):.2f} | {rad / np.median(a[:, 1]):.2f} | {rad / calibrated_median_error(a):.2f} |")
    print("\n| motion | joints of | joints the prior sets, per seed |")
    print("|---|---|---|")
    for (m, where), n in named.items():
        print(f"| {m} | {where} | {' '.join(map(str, n))} |")


def cost(takes: list[str], runs: int) -> None:
    print("| take | frames of the fit | rigid without (s) | rigid with (s) | the uncertainty alone (s) | whole fit (s) | share of the fit |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for path in takes:
        base = run_until(path, "joints", make_params())
        joints = base.artifact
        t_off, t_on, t_unc, t_fit = [], [], [], []
        for _ in range(runs):
            t = time.perf_counter()
            rigid.run(joints, rigid.Params(uncertainty=False))
            t_off.append(time.perf_counter() - t)
            t = time.perf_counter()
            sk = rigid.run(joints, rigid.Params())
            t_on.append(time.perf_counter() - t)
            t = time.perf_counter()
            skeleton_uncertainty(sk)
            t_unc.append(time.perf_counter() - t)
            t = time.perf_counter()
            run_until(path, "ik", make_params())
            t_fit.append(time.perf_counter() - t)
        unc = sk.info.get("uncertainty") or {}
        fit_s = statistics.median(t_fit)
        extra = statistics.median(t_on) - statistics.median(t_off)
        print(f"| {path.split('/')[-1]} | {unc.get('frames')} | {statistics.median(t_off):.2f} | {statistics.median(t_on):.2f} |"
              f" {statistics.median(t_unc):.2f} | {fit_s:.2f} | {max(extra, 0.0) / fit_s:.0%} (alone: {statistics.median(t_unc) / fit_s:.0%}) |")
        sys.stdout.flush()


def real(takes: list[str]) -> None:
    """Per take: the noise, each joint's largest sd, and the joints the prior sets with what would place them."""
    from mocapskel.pipeline import fit

    for path in takes:
        try:
            rep = fit(path, make_params()).report
        except Exception as err:  # a take the tool refuses: said, and the next
            print(f"- {path.split('/')[-1]}: refused ({str(err).splitlines()[0][:120]})")
            continue
        unc = rep.get("uncertainty") or {}
        js = [j for j in rep.get("joints", []) if j.get("uncertainty")]
        big = sorted(((max(j["uncertainty"]["sd_mm"]), j["child"]) for j in js), reverse=True)[:3]
        said = [w for w in rep["warnings"] if "set by the prior" in w]
        print(f"- {path.split('/')[-1]}: noise {unc.get('noise_mm')} mm, skin share {unc.get('skin_share')}, {len(js)} joints, {unc.get('seconds')} s of"
              f" {rep['seconds'].get('total', 0):.2f} s; largest sd: " + ", ".join(f"{n} {v:.1f} mm" for v, n in big)
              + f"; set by the prior: {len(said)}")
        for w in said:
            print(f"  - {w}")
        sys.stdout.flush()


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    c = sub.add_parser("coverage")
    c.add_argument("--seeds", default="1-6")
    c.add_argument("--frames", type=int, default=1200)
    z = sub.add_parser("realistic")
    z.add_argument("--seeds", default="1-6")
    r = sub.add_parser("real")
    r.add_argument("takes", nargs="+")
    k = sub.add_parser("cost")
    k.add_argument("--runs", type=int, default=3)
    k.add_argument("takes", nargs="*", default=["sample_data/human_rom.c3d"])
    args = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):  # as the pipeline runs its stages
        if args.what == "coverage":
            coverage(_seeds(args.seeds), args.frames)
        elif args.what == "realistic":
            coverage_realistic(_seeds(args.seeds))
        elif args.what == "real":
            real(args.takes)
        else:
            cost(args.takes, args.runs)


if __name__ == "__main__":
    main()
