"""Euler spikes in the written BVH: rotation channels that step by more than the rotation turns.

    python -m bench.euler_spikes                    # generated ROM takes (active, passive; seeds 1-6) and a few real takes
    python -m bench.euler_spikes --only gen --frames 3600 --seeds 0 1

For every joint and frame step of a BVH, the rotation step is the geodesic angle
of the relative rotation between the two frames (from the file's own channels,
read back by :func:`mocapskel.io.bvh_read.read_bvh`), the channel step the largest
change of one of its rotation channels, modulo 360 (a true wrap by 360 is no
step). A spike is a channel step above the rotation step plus 5 degrees: an
importer that resamples or filters the curves turns the limb there although the
joint hardly moves. Each take is fitted once (default options) and written with
``--up y`` and ``--up z``, and, for comparison, with the skeleton's own rest frame
kept (the rest the BVH had before the rest frame was chosen with the order).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import REPO, table

REALDATA = REPO.parent / "shared" / "realdata"
REAL = ["cmu/135_02.c3d", "cmu/85_02.c3d", "hdm05/HDM_mm_01-02_03_120.c3d", "hdm05/HDM_bd_05-01_01_120.c3d",
        "joint-localization/fullbody_44Markers_clean_120fps.c3d", "ezc3d/Qualisys.c3d", "cmu/07_01.c3d"]


def channel_angles(path: Path) -> np.ndarray:
    """(F, S, 3) rotation channel values of a BVH, joints in file order."""
    text = Path(path).read_text().splitlines()
    k = next(i for i, l in enumerate(text) if l.startswith("Frame Time"))
    vals = np.loadtxt(text[k + 1 :], ndmin=2)
    cols, c = [], 0
    for l in text[:k]:
        t = l.split()
        if t[:1] == ["CHANNELS"]:
            cols.append([c + i for i, n in enumerate(t[2:]) if n.endswith("rotation")])
            c += len(t) - 2
    return np.stack([vals[:, r] for r in cols], axis=1)


def spikes_of(path: Path, margin_deg: float = 5.0) -> dict:
    """Spikes of a BVH file: count, largest channel step among them, largest excess over the rotation step."""
    from mocapskel.io.bvh_read import read_bvh
    from mocapskel.solvers.euler_continuity import euler_spikes, rotation_steps

    skel, _, local, _ = read_bvh(path)
    ang = channel_angles(path)
    bad = euler_spikes(ang, local, margin_deg)
    step = np.abs(np.diff(ang, axis=0))
    step = np.minimum(step % 360.0, 360.0 - step % 360.0).max(-1)
    turn = rotation_steps(local)
    excess = step - turn
    old = (step > 10.0) & (turn < 2.0)
    return {"spikes": int(bad.sum()), "old": int(old.sum()), "old_worst": float(step[old].max()) if old.any() else 0.0, "worst": float(step[bad].max()) if bad.any() else 0.0,
            "excess": float(excess.max()) if excess.size else 0.0, "order": skel.order,
            "joints": sorted({skel.names[s] for s in np.flatnonzero(bad.any(axis=0))})}


def measure(path: Path, ups=("y", "z")) -> dict:
    """Fit a take once and measure the BVH written with each ``--up``."""
    from mocapskel import pipeline
    from mocapskel.io.bvh import write_bvh
    from mocapskel.stages import export

    res = pipeline.fit(path, pipeline.make_params())
    out = {}
    with tempfile.TemporaryDirectory() as d:
        for up in ups:
            t = time.perf_counter()
            b = export.run(res.motion, export.Params(up=up))
            t_exp = time.perf_counter() - t
            p = Path(d) / f"{up}.bvh"
            write_bvh(p, b.skeleton, b.root_pos, b.local_rot, b.frame_time)
            t = time.perf_counter()
            old = export.run(res.motion, export.Params(up=up, rest_frame="skeleton"))
            t_old = time.perf_counter() - t
            q = Path(d) / f"{up}_kept.bvh"
            write_bvh(q, old.skeleton, old.root_pos, old.local_rot, old.frame_time)
            out[up] = {**spikes_of(p), "rest_frame": b.rest_frame, "kept": spikes_of(q),
                       "kept_rest": old.rest_frame, "export_s": t_exp, "export_kept_s": t_old,
                       "frames": b.root_pos.shape[0]}
    return out


def _cells(r: dict) -> list:
    k = r["kept"]
    return [f"{k['spikes']}" + (f" (up to {k['worst']:.0f}°)" if k["spikes"] else "") + f", {k['order']}, frame {r['kept_rest']}",
            f"{r['spikes']}" + (f" (up to {r['worst']:.0f}°)" if r["spikes"] else ""),
            f"{r['old']}" + (f" (up to {r['old_worst']:.0f}°)" if r["old"] else ""), f"{r['excess']:.1f}",
            r["order"], str(r["rest_frame"]), ", ".join(r["joints"][:4]) + (" …" if len(r["joints"]) > 4 else ""),
            f"{r['export_kept_s']:.2f} → {r['export_s']:.2f}"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", choices=["gen", "real"], default=None)
    ap.add_argument("--frames", type=int, default=3600)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6],
                    help="generated takes' seeds (the rest frame's choice was developed on 1-3 and checked on 4-6)")
    a = ap.parse_args()
    from mocapskel.io.markers import write_markers
    from mocapskel.synth.presets import active_rom, make, passive_rom

    rows = []
    if a.only != "real":
        with tempfile.TemporaryDirectory() as d:
            for kind, recipe in (("active", active_rom), ("passive", passive_rom)):
                for seed in a.seeds:
                    take = make(recipe(seed=seed, frames=a.frames))
                    p = Path(d) / "take.c3d"
                    write_markers(p, replace(take.markers, source=p.name))
                    m = measure(p)
                    for up, r in m.items():
                        rows.append([f"{kind} ROM seed {seed}, {a.frames} frames", f"--up {up}", *_cells(r)])
                        print(f"  {rows[-1]}", file=sys.stderr)
    if a.only != "gen" and REALDATA.is_dir():
        for name in REAL:
            p = REALDATA / name
            if not p.is_file():
                continue
            m = measure(p)
            for up, r in m.items():
                rows.append([name, f"--up {up}", *_cells(r)])
                print(f"  {rows[-1]}", file=sys.stderr)
    print(table(["take", "BVH", "spikes with the skeleton's rest frame (order, frame)", "spikes (largest channel step)",
                 "steps > 10° where the turn < 2°", "largest channel step - rotation step (°)", "order", "rest frame",
                 "joints", "export (s), kept → chosen"], rows))


if __name__ == "__main__":
    main()
