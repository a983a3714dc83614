"""Does Blender put every bone where our forward kinematics does?

    python -m bench.blender_check                      # sample_data/human_rom.c3d, every frame
    python -m bench.blender_check --frames 9           # 9 evenly spaced frames (and frame 1)
    python -m bench.blender_check INPUT.c3d --keep DIR # keep the BVH files and Blender's JSON

Fits the take once (``mocapskel.pipeline.fit``), writes its BVH in both frames
that DESIGN promises Blender handles (``--up y --units cm``, the default, and
``--up z --units mm``) with ``mocapskel.io.bvh.write_bvh``, imports each file
with Blender's own BVH importer in a background Blender, and compares every
pose bone's head in Blender's world (``armature.matrix_world @ pbone.head``)
with ``mocapskel.model.kinematics.segment_origins`` (lab frame, mm), bone by bone by
name. It also compares the leaves' tails with our End Sites, reports the
error of the file alone (our own float64 reader and forward kinematics of the
same file: its rounding), and checks the frame count and the frame rate
Blender reads. Prints a markdown table; exits 1 when any error exceeds the
tolerance (0.5 mm) or a count or rate is wrong, 2 when Blender is missing or
fails. Blender's importer makes each BVH joint a bone from the joint to its
child (the mean of its children, or its End Site): the bone's HEAD is the
joint, which is what ``segment_origins`` gives.

Import options (Blender 3.4's ``bpy.ops.import_anim.bvh``):

- ``global_scale=1.0``: Blender units are the file's units (cm or mm); the
  check multiplies by 10 or 1 to compare in mm.
- ``--up y``: Blender's default axes (``axis_forward='-Z', axis_up='Y'``) map
  BVH (x, y, z) to Blender (x, -z, y); our writer maps lab (x, y, z) to BVH
  (x, z, -y); together: Blender world = lab. ``--up z``: BVH axes are the
  lab's, so the identity conversion (``axis_forward='Y', axis_up='Z'``, which
  is Blender's own frame) gives Blender world = lab again. So in both cases the
  expected Blender position is the lab position divided by the unit (no axis
  change), and a wrong axis option shows up as errors of metres.
- ``rotate_mode='NATIVE'``: each bone keeps the file's rotation order.
- ``frame_start=1``: BVH frame ``i`` (0-based) is Blender frame ``i + 1``.
- The root's position channels: the importer keys the root bone's location
  as (channel values - root OFFSET) in the bone's rest frame, so the posed
  head lands on the channel values: absolute, as we write them (our root
  OFFSET is zero; a non-zero one gives the same heads too, checked by hand).
- ``update_scene_fps=True`` (the issue's recipe said False): it is the only
  way Blender reports the rate it read from ``Frame Time:``. The keys are one
  per Blender frame either way (the importer turns ``use_fps_scale`` off when
  it updates the scene rate, and we pass ``use_fps_scale=False`` anyway).
- ``update_scene_duration=True``: Blender 3.4 sets ``frame_end`` to
  ``frame_start + Frames``, one frame past the last key (an importer quirk);
  the frame count checked is the number of keys and the action's frame range.

Blender 3.4's importer opens the file with mode ``'rU'``, which Python 3.11
refuses; the driver wraps ``builtins.open`` to drop the ``'U'`` during import.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_INPUT = REPO / "sample_data" / "human_rom.c3d"
TOLERANCE_MM = 0.5

#: (up, units) -> Blender's axis_forward, axis_up that reproduce the lab frame.
FRAMES: dict[tuple[str, str], tuple[str, str]] = {
    ("y", "cm"): ("-Z", "Y"),  # Blender's default import options
    ("z", "mm"): ("Y", "Z"),  # identity: the file is already Z up
}

# Runs inside Blender: `blender -b --factory-startup --python DRIVER -- ARGS.json`.
# Only Blender's Python and the standard library are available there.
DRIVER = r'''
import builtins
import json
import sys

_open = builtins.open


def _open_without_u(file, mode="r", *args, **kwargs):
    # Blender 3.4's BVH importer opens with mode 'rU', refused by Python >= 3.11.
    if isinstance(mode, str) and "U" in mode:
        mode = mode.replace("U", "") or "r"
    return _open(file, mode, *args, **kwargs)


import bpy

args = json.loads(_open(sys.argv[sys.argv.index("--") + 1]).read())
scene = bpy.context.scene
before = set(bpy.data.objects)
builtins.open = _open_without_u
try:
    result = bpy.ops.import_anim.bvh(
        filepath=args["bvh"],
        target="ARMATURE",
        global_scale=1.0,
        frame_start=1,
        use_fps_scale=False,
        update_scene_fps=True,
        update_scene_duration=True,
        use_cyclic=False,
        rotate_mode="NATIVE",
        axis_forward=args["axis_forward"],
        axis_up=args["axis_up"],
    )
finally:
    builtins.open = _open
if "FINISHED" not in result:
    raise SystemExit(f"import_anim.bvh returned {result}")
arms = [o for o in bpy.data.objects if o not in before and o.type == "ARMATURE"]
if len(arms) != 1:
    raise SystemExit(f"expected one new armature, found {len(arms)}")
arm = arms[0]
action = arm.animation_data.action
root = next(b for b in arm.pose.bones if b.parent is None)
loc_keys = [len(c.keyframe_points) for c in action.fcurves
            if c.data_path == f'pose.bones["{root.name}"].location']
key_frames = sorted({kp.co[0] for c in action.fcurves for kp in c.keyframe_points})
out = {
    "blender": bpy.app.version_string,
    "fps": scene.render.fps,
    "fps_base": scene.render.fps_base,
    "frame_start": scene.frame_start,
    "frame_end": scene.frame_end,
    "action_range": list(action.frame_range),
    "n_keys": len(key_frames),
    "first_key": key_frames[0] if key_frames else None,
    "last_key": key_frames[-1] if key_frames else None,
    "root": root.name,
    "root_location_keys": loc_keys,
    "matrix_world": [list(r) for r in arm.matrix_world],
    "rotation_modes": sorted({b.rotation_mode for b in arm.pose.bones}),
    "bones": [b.name for b in arm.pose.bones],
    "leaves": [b.name for b in arm.pose.bones if not b.children],
    "frames": args["frames"],
    "rest": {b.name: [list(arm.matrix_world @ b.head_local), list(arm.matrix_world @ b.tail_local)]
             for b in arm.data.bones},
    "heads": [],
    "tails": [],
}
mw = arm.matrix_world
for f in args["frames"]:
    scene.frame_set(f + 1)  # BVH frame f (0-based) is Blender frame frame_start + f
    out["heads"].append([list(mw @ b.head) for b in arm.pose.bones])
    out["tails"].append([list(mw @ b.tail) for b in arm.pose.bones])
with _open(args["out"], "w") as fh:
    json.dump(out, fh)
'''


@dataclass
class Result:
    """One frame setting's comparison (errors in mm)."""

    up: str
    units: str
    axis_forward: str
    axis_up: str
    frames_compared: int
    bones_compared: int
    max_mm: float
    rms_mm: float
    worst: str
    end_site_max_mm: float
    file_max_mm: float
    frames_in_file: int
    frames_in_blender: int
    fps_expected: float
    fps_in_blender: float
    blender: str
    seconds: float
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    rest_bones: dict = field(default_factory=dict)  # bone name -> (head, tail) at rest, Blender world in mm

    @property
    def ok(self) -> bool:
        return not self.problems


def blender_path(explicit: str | None = None) -> str | None:
    """The Blender executable: ``explicit``, $BLENDER, or ``blender`` on PATH."""
    return explicit or os.environ.get("BLENDER") or shutil.which("blender")


def fit_motion(source, log=lambda m: None):
    """Fit a take (path or Markers artifact) with the default parameters; returns the FitResult."""
    from mocapskel import pipeline

    t = time.perf_counter()
    res = pipeline.fit(source, pipeline.make_params())
    log(f"fitted in {time.perf_counter() - t:.1f} s: {res.motion.rot.shape[0]} frames, "
        f"{len(res.motion.skeleton.names)} segments")
    return res


def pick_frames(n_frames: int, count: int | None) -> list[int]:
    """0-based frames to compare: all of them (``count`` None) or ``count`` evenly spaced plus frame 1."""
    if count is None or count >= n_frames:
        return list(range(n_frames))
    picks = set(np.linspace(0, n_frames - 1, max(count, 2)).round().astype(int).tolist())
    picks.add(min(1, n_frames - 1))
    return sorted(picks)


def run_blender(bvh: Path, out: Path, axis_forward: str, axis_up: str, frames: list[int], *,
                blender: str, timeout: float) -> dict:
    """Import ``bvh`` in a background Blender; returns what the driver wrote."""
    work = out.parent
    driver = work / "blender_driver.py"
    driver.write_text(DRIVER)
    args = work / (out.stem + "_args.json")
    args.write_text(json.dumps({"bvh": str(bvh), "out": str(out), "frames": frames,
                                "axis_forward": axis_forward, "axis_up": axis_up}))
    if out.exists():
        out.unlink()
    cmd = [blender, "-b", "--factory-startup", "--python-exit-code", "3", "--python", str(driver), "--", str(args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, errors="replace", timeout=timeout)
    if proc.returncode != 0 or not out.exists():
        tail = (proc.stdout[-2000:] + "\n" + proc.stderr[-2000:]).strip()
        raise RuntimeError(f"blender failed (exit {proc.returncode}):\n{tail}")
    return json.loads(out.read_text())


def check_frame(motion, up: str, units: str, work: Path, frames: list[int], *,
                blender: str, timeout: float = 600.0, tolerance: float = TOLERANCE_MM,
                names: str = "auto", rest: str = "frame") -> Result:
    """Write the BVH of a fitted ``motion`` for (up, units) into ``work``, import it in Blender
    and compare with ``export.joint_positions_lab(motion, bvh)`` (the fitted tree's joints,
    by BVH joint name, from the motion alone) at the 0-based ``frames``.

    Raises RuntimeError when Blender fails, subprocess.TimeoutExpired after ``timeout`` s.
    """
    from mocapskel.solvers.bvh_pose import UNIT_SCALE, bvh_to_lab, forward_kinematics
    from mocapskel.io.bvh_read import read_bvh
    from mocapskel.io.bvh import write_bvh
    from mocapskel.stages import export

    p = export.Params(up=up, units=units, names=names, rest=rest)
    bvh = export.run(motion, p)  # the export stage fit() ends with, in this frame
    path = work / f"take_up{up}_{units}_{names}_{rest}.bvh"
    write_bvh(path, bvh.skeleton, bvh.root_pos, bvh.local_rot, bvh.frame_time)
    axis_forward, axis_up = FRAMES[(up, units)]
    t = time.perf_counter()
    got = run_blender(path, work / f"blender_up{up}_{units}.json", axis_forward, axis_up, frames,
                      blender=blender, timeout=timeout)
    seconds = time.perf_counter() - t

    scale = UNIT_SCALE[units]
    names = list(bvh.skeleton.names)
    F = motion.rot.shape[0]
    expect = export.joint_positions_lab(motion, bvh)[frames]  # (n, S, 3) lab mm, BVH joint order
    bones = got["bones"]
    problems: list[str] = []
    notes: list[str] = []
    missing = [n for n in names if n not in bones]
    extra = [b for b in bones if b not in names]
    if missing or extra:
        problems.append(f"bones missing in Blender {missing}, unknown bones {extra}")
    common = [n for n in names if n in bones]
    if not common:
        raise RuntimeError(f"no bone of the take in Blender's armature (Blender's bones: {bones})")
    si = [names.index(n) for n in common]
    bi = [bones.index(n) for n in common]
    heads = np.asarray(got["heads"], dtype=np.float64)[:, bi] * scale  # Blender world -> lab mm
    err = np.linalg.norm(heads - expect[:, si], axis=-1)  # (n, bones)
    k = np.unravel_index(int(np.argmax(err)), err.shape)
    worst = f"{common[k[1]]} @ frame {frames[k[0]]}"

    # the file alone (its rounding), by our own float64 reader: the part of the error that is not Blender's
    wskel, wroot, wlocal, _ = read_bvh(path)
    mine_bvh, mine_rot = forward_kinematics(wskel, wroot[frames], wlocal[frames], with_rot=True)
    mine = bvh_to_lab(mine_bvh, up, units)
    file_err = np.linalg.norm(mine[:, [list(wskel.names).index(n) for n in common]] - expect[:, si], axis=-1)

    # leaves: Blender's tail is the End Site as written in the file
    leaf_names = [n for n in got["leaves"] if n in names]
    es_err = np.zeros((len(frames), 0))
    if leaf_names:
        S_lab = [names.index(n) for n in leaf_names]
        # the End Site as written, carried by the file's own rotations (float64)
        wi = [wskel.names.index(n) for n in leaf_names]
        tails_bvh = mine_bvh[:, wi] + np.einsum("flij,lj->fli", mine_rot[:, wi], wskel.end_site[wi])
        tails_expect = expect[:, S_lab] + (bvh_to_lab(tails_bvh, up, units) - mine[:, wi])
        tails = np.asarray(got["tails"], dtype=np.float64)[:, [bones.index(n) for n in leaf_names]] * scale
        es_err = np.linalg.norm(tails - tails_expect, axis=-1)

    fps_expected = 1.0 / bvh.frame_time
    fps_got = got["fps"] / got["fps_base"]
    n_keys = got["n_keys"]
    if not err.max() <= tolerance:  # NaN fails too
        problems.append(f"bone heads off by up to {err.max():.3g} mm ({worst})")
    if es_err.size and not es_err.max() <= tolerance:
        problems.append(f"End Sites off by up to {es_err.max():.3g} mm")
    if n_keys != F or got["first_key"] != 1 or got["last_key"] != F or got["action_range"] != [1.0, float(F)]:
        problems.append(f"Blender has {n_keys} keyed frames ({got['first_key']}..{got['last_key']}, action range "
                        f"{got['action_range']}), the take {F} (1..{F})")
    if abs(fps_got - fps_expected) > 1e-6 * fps_expected:
        problems.append(f"Blender's scene rate is {fps_got:.6g} fps, the take's {fps_expected:.6g}")
    if got["frame_end"] != F:
        notes.append(f"`--up {up} --units {units}`: Blender set the scene's frame_end to {got['frame_end']} for {F} "
                     f"keys at 1..{F} (its importer sets frame_start + Frames)")
    mw = np.asarray(got["matrix_world"])
    if np.abs(mw - np.eye(4)).max() > 1e-6:
        # not wrong in itself (heads are compared in world space), but worth knowing
        notes.append(f"armature matrix_world is not the identity: {mw.round(6).tolist()}")
    return Result(
        up=up, units=units, axis_forward=axis_forward, axis_up=axis_up,
        frames_compared=len(frames), bones_compared=len(common),
        max_mm=float(err.max()), rms_mm=float(np.sqrt(np.mean(err**2))), worst=worst,
        end_site_max_mm=float(es_err.max()) if es_err.size else float("nan"),
        file_max_mm=float(file_err.max()),
        frames_in_file=F, frames_in_blender=n_keys, fps_expected=fps_expected, fps_in_blender=fps_got,
        blender=got["blender"], seconds=seconds, problems=problems, notes=notes,
        rest_bones={k: np.asarray(v, dtype=np.float64) * scale for k, v in got["rest"].items()},
    )


def markdown(results: list[Result], tolerance: float = TOLERANCE_MM) -> str:
    head = ["frame setting", "Blender import axes", "frames compared", "bones", "max error (mm)",
            "rms error (mm)", "worst bone", "End Sites max (mm)", "file alone max (mm)", "frames file / Blender",
            "fps file / Blender", f"≤ {tolerance} mm"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        lines.append("| " + " | ".join([
            f"`--up {r.up} --units {r.units}`",
            f"forward {r.axis_forward}, up {r.axis_up}",
            str(r.frames_compared),
            str(r.bones_compared),
            f"{r.max_mm:.2e}",
            f"{r.rms_mm:.2e}",
            r.worst,
            f"{r.end_site_max_mm:.2e}",
            f"{r.file_max_mm:.2e}",
            f"{r.frames_in_file} / {r.frames_in_blender}",
            f"{r.fps_expected:g} / {r.fps_in_blender:g}",
            "yes" if r.ok else "**NO**",
        ]) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.blender_check", description=__doc__.split("\n\n")[0])
    ap.add_argument("input", nargs="?", default=str(DEFAULT_INPUT), help="take to fit (default: sample human ROM)")
    ap.add_argument("--frames", type=int, default=None,
                    help="compare this many evenly spaced frames (default: every frame)")
    ap.add_argument("--blender", default=None, help="Blender executable (default: $BLENDER or blender on PATH)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds allowed per Blender run")
    ap.add_argument("--tolerance", type=float, default=TOLERANCE_MM, help="mm")
    ap.add_argument("--keep", default=None, help="folder for the BVH files and Blender's JSON (default: temporary)")
    a = ap.parse_args(argv)

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    blender = blender_path(a.blender)
    if not blender:
        log("blender_check: Blender not found (install it, put it on PATH or pass --blender)")
        return 2
    res = fit_motion(a.input, log)
    frames = pick_frames(res.motion.rot.shape[0], a.frames)
    with tempfile.TemporaryDirectory(prefix="mocapskel-blender-") as tmp:
        work = Path(a.keep) if a.keep else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        results = []
        for up, units in FRAMES:
            log(f"--up {up} --units {units}: importing in Blender …")
            try:
                r = check_frame(res.motion, up, units, work, frames, blender=blender, timeout=a.timeout,
                                tolerance=a.tolerance)
            except (RuntimeError, subprocess.TimeoutExpired) as e:
                log(f"blender_check: {e}")
                return 2
            log(f"  done in {r.seconds:.1f} s")
            results.append(r)
    inp = Path(a.input)
    shown = inp.resolve().relative_to(REPO) if inp.resolve().is_relative_to(REPO) else inp.name
    print(f"Blender {results[0].blender}; input `{shown}`, {res.motion.rot.shape[0]} frames, "
          f"{len(res.motion.skeleton.names)} segments; Blender world (`matrix_world @ pose_bone.head`, "
          f"× 10 for cm) against `segment_origins` (lab mm), bone by bone by name.\n")
    print(markdown(results, a.tolerance))
    print("\n*End Sites*: the leaves' posed tails against our End Sites. *File alone*: our own float64 "
          "`read_bvh` + `forward_kinematics` of the same file (its 6-decimal rounding), so the rest of the "
          "error is Blender's single precision.")
    bad = [p for r in results for p in r.problems]
    notes = [n for r in results for n in r.notes]
    for n in notes:
        print(f"\n- note: {n}")
    for p in bad:
        print(f"\n- FAILED: {p}")
    return 1 if bad else 0

if __name__ == "__main__":
    sys.exit(main())
