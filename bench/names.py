"""Humanoid recognition: is every joint of a generated human named right, and do other subjects fall back?

    python -m bench.names                 # generated humans (ROM, walk; 5 seeds), linkage, chains, real takes
    python -m bench.names --no-real       # generated takes only

For each generated human the fit's segments are named twice: with the take's
labels (their L/R prefixes decide the sides) and with neutral labels
(``M000`` …: the sides from the motion alone). A segment's expected name is
that of the most proximal generated segment among its markers' (a walk may
fit forearm and hand as one segment: then it is the forearm). Prints a
markdown table.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mocapskel.synth.body import HUMANOID_NAMES

REPO = Path(__file__).resolve().parents[1]
REAL = [REPO.parent / "shared" / "realref" / f"{n}.c3d" for n in ("cmu_16_07", "opensim_test_walking", "kinova_dynamique_pierre")]

EXPECTED = HUMANOID_NAMES


def expected_names(skel) -> list[str]:
    from mocapskel.synth.body import LABEL_CODES, PARENT, SEGMENTS

    code = dict(zip(LABEL_CODES, SEGMENTS))

    def depth(s: int) -> int:
        d = 0
        while PARENT[s] >= 0:
            s, d = PARENT[s], d + 1
        return d

    out = []
    for s in range(len(skel.names)):
        segs = {code[skel.labels[m][:4]] for m in np.flatnonzero(skel.marker_segment == s)}
        out.append(EXPECTED[min(segs, key=lambda n: depth(SEGMENTS.index(n)))])
    return out


def expected_realistic(skel, truth) -> list[str]:
    """The humanoid name of each fitted segment of a realistic take: that of the most proximal true
    segment among those its markers ride on (markers over a joint, which may ride either, left out)."""
    from mocapskel.synth.body import PARENT, SEGMENTS

    ok = dict(zip(truth.info["physical_labels"], truth.info["marker_segments_ok"]))

    def depth(name: str) -> int:
        s, d = SEGMENTS.index(name), 0
        while PARENT[s] >= 0:
            s, d = PARENT[s], d + 1
        return d

    out = []
    for s in range(len(skel.names)):
        parts = {ok[lb][0] for lb in (skel.labels[m] for m in np.flatnonzero(skel.marker_segment == s))
                 if lb in ok and len(ok[lb]) == 1}
        out.append(EXPECTED[min(parts, key=depth)] if parts else "?")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--frames", type=int, default=1200)
    ap.add_argument("--no-real", action="store_true")
    a = ap.parse_args(argv)
    from mocapskel import pipeline
    from mocapskel.model.naming import name_skeleton
    from mocapskel.synth.presets import Recipe, make

    rows = ["| take | segments | recognised | names right (labels) | names right (geometry only) | note |",
            "|---|---|---|---|---|---|"]
    for motion in ("rom", "walk"):
        for seed in range(a.seeds):
            take = make(Recipe(kind="human", frames=a.frames, noise_mm=1.0, soft_tissue_mm=2.0,
                               gaps_per_marker_per_minute=4.0, seed=seed, motion=motion))
            res = pipeline.fit(take.markers, pipeline.make_params())
            sk = res.motion.skeleton
            n1 = name_skeleton(sk, res.motion)
            neutral = replace(sk, labels=tuple(f"M{i:03d}" for i in range(len(sk.labels))))
            n2 = name_skeleton(neutral, res.motion)
            want = expected_names(sk)
            ok1 = "yes" if n1.humanoid and list(n1.names) == want else "no"
            ok2 = "yes" if n2.humanoid and list(n2.names) == want else "no"
            rows.append(f"| human {motion}, seed {seed} | {len(sk.names)} | {'yes' if n1.humanoid else 'no'} | "
                        f"{ok1 if n1.humanoid else '–'} | {ok2 if n2.humanoid else '–'} | {n1.note} |")
            print(rows[-1], file=sys.stderr)
    from mocapskel.synth.presets import realistic

    for motion in ("walk", "run", "kick", "reach"):
        for seed in (1, 2, 3):
            take = make(realistic(seed=seed, frames=600, motion=motion, markerset="cmu41"))
            res = pipeline.fit(take.markers, pipeline.make_params())
            sk = res.motion.skeleton
            n1 = name_skeleton(sk, res.motion)
            ok1 = "yes" if n1.humanoid and list(n1.names) == expected_realistic(sk, take.truth) else "no"
            rows.append(f"| realistic cmu41 {motion}, seed {seed} | {len(sk.names)} | {'yes' if n1.humanoid else 'no'} | "
                        f"{ok1 if n1.humanoid else '–'} | – | {n1.note} |")
            print(rows[-1], file=sys.stderr)
    others = [("linkage", Recipe(kind="linkage", frames=2400, noise_mm=0.5, seed=1)),
              ("chain 4-3-3", Recipe(kind="chain", counts=(4, 3, 3), frames=600, seed=1)),
              ("chain 3-2-2-2-2", Recipe(kind="chain", counts=(3, 2, 2, 2, 2), frames=600, seed=1))]
    for name, recipe in others:
        res = pipeline.fit(make(recipe).markers, pipeline.make_params())
        n = name_skeleton(res.motion.skeleton, res.motion)
        rows.append(f"| {name} | {len(n.names)} | {'yes' if n.humanoid else 'no'} | – | – | {n.note} |")
    if not a.no_real:
        for path in REAL:
            if not path.exists():
                rows.append(f"| {path.name} | – | – | – | – | not found (shared real data absent) |")
                continue
            t = time.perf_counter()
            res = pipeline.fit(path, pipeline.make_params())
            n = name_skeleton(res.motion.skeleton, res.motion)
            rows.append(f"| real: {path.name} | {len(n.names)} | {'yes' if n.humanoid else 'no'} | – | – | "
                        f"{n.note} ({time.perf_counter() - t:.0f} s) |")
    print("\n".join(rows))
    print("\nA real take is recognised only when its fit has the tree of a person (trunk, head, four limbs);"
          " a fit whose segments or tree are off keeps the generic names.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
