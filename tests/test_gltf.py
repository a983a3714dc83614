"""glTF 2.0 output: valid for pygltflib's reader, the same motion as the BVH, and (where Blender is) the same in Blender."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sysconfig
from pathlib import Path

import numpy as np
import pytest

from mocapskel.stages import export


@pytest.fixture(scope="module")
def fitted():
    """A short human take at 100 Hz, fitted in memory."""
    from mocapskel import pipeline
    from mocapskel.synth.presets import Recipe, make

    take = make(Recipe(kind="human", frames=200, rate=100.0, noise_mm=1.0, soft_tissue_mm=1.0, seed=5))
    return pipeline.fit(take.markers, pipeline.make_params())


def _accessor(gl, blob: bytes, i: int) -> np.ndarray:
    acc = gl.accessors[i]
    view = gl.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}[acc.componentType]
    n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(blob, dtype=dtype, count=acc.count * n, offset=start).reshape(acc.count, n)


def _gltf_joint_positions(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, world joint positions (F, S, 3) (glTF axes, m) and times, by forward kinematics of the file."""
    import pygltflib
    from scipy.spatial.transform import Rotation

    gl = pygltflib.GLTF2.load(str(path))
    blob = gl.binary_blob() if str(path).endswith(".glb") else None
    if blob is None:
        import base64

        blob = base64.b64decode(gl.buffers[0].uri.split(",", 1)[1])
    skin = gl.skins[0]
    joints = skin.joints
    anim = gl.animations[0]
    times = None
    rot: dict[int, np.ndarray] = {}
    trans: dict[int, np.ndarray] = {}
    for ch in anim.channels:
        smp = anim.samplers[ch.sampler]
        times = _accessor(gl, blob, smp.input)[:, 0]
        out = _accessor(gl, blob, smp.output).astype(np.float64)
        (rot if ch.target.path == "rotation" else trans)[ch.target.node] = out
    F = len(times)
    parent = {c: n for n, node in enumerate(gl.nodes) for c in (node.children or [])}
    P = np.zeros((F, len(joints), 3))
    G = np.zeros((F, len(joints), 3, 3))
    for k, n in enumerate(joints):  # parents first (depth-first node order)
        node = gl.nodes[n]
        t = trans.get(n, np.broadcast_to(np.asarray(node.translation, dtype=np.float64), (F, 3)))
        R = Rotation.from_quat(rot[n]).as_matrix()
        if n in parent and parent[n] in joints:
            pk = joints.index(parent[n])
            P[:, k] = P[:, pk] + np.einsum("fij,fj->fi", G[:, pk], t)
            G[:, k] = G[:, pk] @ R
        else:
            P[:, k], G[:, k] = t, R
    # the skin's bind pose: inverse bind matrices undo the rest (all-identity) positions
    ibm = _accessor(gl, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    assert np.allclose(ibm[:, :3, :3], np.eye(3))
    return [gl.nodes[n].name for n in joints], P, times


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
@pytest.mark.parametrize("rest", ["frame", "tpose"])
def test_gltf_reads_back_with_pygltflib_and_holds_the_fitted_motion(fitted, tmp_path: Path, suffix: str, rest: str) -> None:
    from mocapskel.solvers.bvh_pose import lab_to_bvh
    from mocapskel.io.gltf import write_gltf

    b = export.run(fitted.motion, export.Params(rest=rest))
    path = tmp_path / f"take{suffix}"
    write_gltf(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time, up=b.up, units=b.units)
    names, P, times = _gltf_joint_positions(path)
    assert names == list(b.skeleton.names)
    assert np.allclose(times, np.arange(len(times)) * 0.01, atol=1e-6)
    want = lab_to_bvh(export.joint_positions_lab(fitted.motion, b), "y", "m")  # glTF: m, +Y up
    err_mm = 1000 * np.abs(P - want).max()
    assert err_mm < 0.01, err_mm


def test_fit_writes_glb_as_the_output_or_beside_the_bvh(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from mocapskel.cli.main import cli
    from mocapskel.io.markers import write_markers
    from mocapskel.synth.presets import Recipe, make

    take = make(Recipe(kind="chain", frames=300, seed=2, noise_mm=0.2))
    src = tmp_path / "c.trc"
    write_markers(src, take.markers)
    r = CliRunner().invoke(cli, ["fit", str(src), "-o", str(tmp_path / "c.glb"), "--no-cache", "-q"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["fit", str(src), "-o", str(tmp_path / "c.bvh"), "--gltf", str(tmp_path / "d.gltf"), "--no-cache", "-q"])
    assert r.exit_code == 0, r.output
    n1, P1, _ = _gltf_joint_positions(tmp_path / "c.glb")
    n2, P2, _ = _gltf_joint_positions(tmp_path / "d.gltf")
    assert n1 == n2 and np.array_equal(P1, P2)
    assert (tmp_path / "c.bvh").exists() and not (tmp_path / "c.bvh.glb").exists()


# --------------------------------------------------------------------------- Blender

def _blender() -> str | None:
    return os.environ.get("BLENDER") or shutil.which("blender")


GLTF_DRIVER = r'''
import json
import sys

args = json.loads(open(sys.argv[sys.argv.index("--") + 1]).read())
try:
    import numpy
except ImportError:  # Debian's Blender without python3-numpy: the test's own numpy, if Blender's Python takes it
    sys.path.append(args["site"])
    try:
        import numpy
    except ImportError:
        with open(args["out"], "w") as fh:
            json.dump({"no_numpy": sys.version}, fh)
        sys.exit(0)

if not hasattr(numpy, "bool"):  # Blender 3.4's glTF importer uses np.bool, gone since numpy 1.24 (Debian's python3-numpy)
    numpy.bool = bool

import bpy

scene = bpy.context.scene
scene.render.fps = args["fps"]
scene.render.fps_base = 1.0
before = set(bpy.data.objects)
bpy.ops.import_scene.gltf(filepath=args["path"])
arms = [o for o in bpy.data.objects if o not in before and o.type == "ARMATURE"]
arm = arms[0]
action = arm.animation_data.action
keys = sorted({kp.co[0] for c in action.fcurves for kp in c.keyframe_points})
out = {"blender": bpy.app.version_string, "bones": [b.name for b in arm.pose.bones], "keys": [keys[0], keys[-1], len(keys)],
       "heads": []}
mw = arm.matrix_world
for f in args["frames"]:
    scene.frame_set(int(keys[0]) + f)
    out["heads"].append([list(mw @ b.head) for b in arm.pose.bones])
with open(args["out"], "w") as fh:
    json.dump(out, fh)
'''


@pytest.mark.skipif(_blender() is None, reason="Blender is not installed (no 'blender' on PATH and $BLENDER unset): "
                    "install it (e.g. apt-get install blender) to check that the glTF imports in Blender")
def test_blender_gltf_import_puts_every_joint_where_our_forward_kinematics_does(fitted, tmp_path: Path) -> None:
    from mocapskel.io.gltf import write_gltf

    b = export.run(fitted.motion, export.Params(rest="tpose"))
    path = tmp_path / "take.glb"
    write_gltf(path, b.skeleton, b.root_pos, b.local_rot, b.frame_time, up=b.up, units=b.units)
    F = b.root_pos.shape[0]
    frames = list(range(F))
    (tmp_path / "driver.py").write_text(GLTF_DRIVER)
    (tmp_path / "args.json").write_text(json.dumps({"path": str(path), "fps": 100, "frames": frames,
                                                    "out": str(tmp_path / "out.json"),
                                                    "site": sysconfig.get_paths()["platlib"]}))
    proc = subprocess.run([_blender(), "-b", "--factory-startup", "--python", str(tmp_path / "driver.py"), "--",
                           str(tmp_path / "args.json")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and (tmp_path / "out.json").exists(), proc.stderr[-2000:]
    got = json.loads((tmp_path / "out.json").read_text())
    if "no_numpy" in got:
        pytest.skip(f"Blender's Python ({got['no_numpy'].split()[0]}) has no numpy, which its glTF importer needs, and "
                    "cannot load this environment's: install it for Blender (apt-get install python3-numpy)")
    assert got["keys"][2] == F
    bones = got["bones"]
    assert sorted(bones) == sorted(b.skeleton.names)
    heads = np.asarray(got["heads"]) * 1000.0  # Blender world (m, Z up) = lab (m)
    want = export.joint_positions_lab(fitted.motion, b)[frames][:, [list(b.skeleton.names).index(n) for n in bones]]
    err = np.linalg.norm(heads - want, axis=-1)
    assert err.max() <= 0.05, err.max()  # mm, every joint, every frame
