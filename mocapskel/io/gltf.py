"""glTF 2.0 output: the skeleton as a skin with its motion as an animation.

:func:`write_gltf` writes a ``.glb`` (binary) or ``.gltf`` (JSON, buffers
embedded) file with pygltflib:

- one node per BVH joint, the hierarchy of the BVH; a joint's rest
  ``translation`` is its OFFSET, its rest rotation the identity (the BVH's
  rest pose);
- a skin over those nodes (``inverseBindMatrices``: the inverse rest
  transforms) and a small mesh skinned to it: one thin four-sided bone from
  each joint to each child joint (leaves: to their End Site), every vertex
  bound to its joint alone, so that importers show the skeleton;
- one animation: every joint's rotation per frame (quaternions, sign-continuous,
  LINEAR) and the root's translation, at the take's times.

Axes and units are glTF's: metres, +Y up. The BVH motion is first taken back
to the lab frame (mm) and then mapped with lab (x, y, z) -> glTF (x, z, -y):
Blender's glTF importer (+Y up to +Z up) puts the subject back in its lab
frame, and the subject's rest pose faces glTF +Z when it faces lab -Y (the
T-pose of :mod:`mocapskel.stages.export`).
"""
from __future__ import annotations

import os

import numpy as np

from .atomic import atomic_path
from ..solvers.bvh_pose import BvhSkeleton, bvh_rot_to_lab, bvh_to_lab, lab_rot_to_bvh, lab_to_bvh

__all__ = ["write_gltf", "to_gltf_frame"]

_FLOAT, _USHORT, _UINT = 5126, 5123, 5125
_ARRAY, _ELEMENTS = 34962, 34963


def to_gltf_frame(skel: BvhSkeleton, root_pos: np.ndarray, local_rot: np.ndarray, up: str, units: str):
    """Offsets, End Sites, root positions (m) and local rotations in glTF axes."""
    def pos(p):
        return lab_to_bvh(bvh_to_lab(p, up, units), "y", "m")

    rot = lab_rot_to_bvh(bvh_rot_to_lab(np.asarray(local_rot), up), "y")
    return pos(skel.offset), pos(skel.end_site), pos(root_pos), np.ascontiguousarray(rot)


def _quats(rot: np.ndarray) -> np.ndarray:
    """(F, S, 3, 3) -> (F, S, 4) xyzw quaternions, each joint's sign continuous over frames."""
    from scipy.spatial.transform import Rotation

    F, S = rot.shape[:2]
    q = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(F, S, 4)
    if F > 1:
        flip = np.sum(q[1:] * q[:-1], axis=-1) < 0  # (F-1, S): a sign change from the frame before
        sign = np.concatenate([np.ones((1, S)), np.cumprod(np.where(flip, -1.0, 1.0), axis=0)])
        q *= sign[..., None]
    return q


def _bone_mesh(heads: np.ndarray, tails: list[tuple[int, np.ndarray]], width: float):
    """Vertices, joint indices and triangles of thin pyramids from heads[j] to each tail."""
    verts, joints, tris = [], [], []
    for j, tail in tails:
        h = heads[j]
        d = tail - h
        L = float(np.linalg.norm(d))
        if L < 1e-9:
            continue
        d /= L
        a = np.cross(d, [0.0, 1.0, 0.0] if abs(d[1]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(d, a)
        w = min(width, 0.15 * L)
        mid = h + 0.2 * L * d
        ring = [mid + w * a, mid + w * b, mid - w * a, mid - w * b]
        base = len(verts)
        verts += [h, *ring, tail]
        joints += [j] * 6
        for k in range(4):
            r0, r1 = base + 1 + k, base + 1 + (k + 1) % 4
            tris += [(base, r1, r0), (base + 5, r0, r1)]
    return np.asarray(verts, dtype=np.float32), np.asarray(joints, dtype=np.uint16), np.asarray(tris, dtype=np.uint32)


def write_gltf(
    path: str | os.PathLike,
    skel: BvhSkeleton,
    root_pos: np.ndarray,
    local_rot: np.ndarray,
    frame_time: float,
    *,
    up: str = "y",
    units: str = "cm",
) -> None:
    """Write a BVH motion (its skeleton, root positions, local rotations) as glTF 2.0, atomically.

    Parameters
    ----------
    path : str or PathLike
        ``.glb`` (binary) or ``.gltf`` (JSON with the buffer embedded).
    skel, root_pos, local_rot, frame_time
        As :func:`mocapskel.io.bvh.write_bvh` takes them, in the BVH frame
        given by ``up`` and ``units``.
    """
    import pygltflib as g

    local_rot = np.asarray(local_rot, dtype=np.float64)
    root_pos = np.asarray(root_pos, dtype=np.float64)
    if not (np.isfinite(local_rot).all() and np.isfinite(root_pos).all()):
        raise ValueError("the motion has NaN: fill every frame first")
    off, end, root, rot = to_gltf_frame(skel, root_pos, local_rot, up, units)
    S, F = skel.n_joints, local_rot.shape[0]
    par = skel.parent
    # rest pose: global positions (all rotations identity)
    rest = np.zeros((S, 3))
    rest[0] = root[0] if F else 0.0
    for s in range(1, S):
        rest[s] = rest[par[s]] + off[s]
    kids = [[c for c in range(S) if par[c] == s] for s in range(S)]
    tails = []
    lengths = np.linalg.norm(off[1:], axis=1) if S > 1 else np.array([0.1])
    for s in range(S):
        if kids[s]:
            tails += [(s, rest[c]) for c in kids[s]]
        else:
            e = end[s] if np.linalg.norm(end[s]) > 1e-9 else (0.5 * off[s] if s else np.array([0.0, 0.1, 0.0]))
            tails.append((s, rest[s] + e))
    width = 0.04 * float(np.median(lengths[lengths > 0])) if np.any(lengths > 0) else 0.01
    verts, vjoint, tris = _bone_mesh(rest, tails, width)
    weights = np.zeros((len(verts), 4), dtype=np.float32)
    weights[:, 0] = 1.0
    joints4 = np.zeros((len(verts), 4), dtype=np.uint16)
    joints4[:, 0] = vjoint
    ibm = np.tile(np.eye(4, dtype=np.float32), (S, 1, 1))
    ibm[:, :3, 3] = -rest  # the inverse of a pure translation
    ibm_colmajor = np.ascontiguousarray(ibm.transpose(0, 2, 1))
    times = (np.arange(F) * frame_time).astype(np.float32)
    quats = _quats(rot).astype(np.float32)  # (F, S, 4)

    blobs: list[bytes] = []
    views: list[g.BufferView] = []
    accessors: list[g.Accessor] = []
    offset = 0

    def add(arr: np.ndarray, typ: str, ctype: int, target: int | None = None, minmax: bool = False) -> int:
        nonlocal offset
        data = np.ascontiguousarray(arr).tobytes()
        pad = (-len(data)) % 4
        views.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
        blobs.append(data + b"\0" * pad)
        offset += len(data) + pad
        count = arr.shape[0]
        acc = g.Accessor(bufferView=len(views) - 1, componentType=ctype, count=int(count), type=typ)
        if minmax:
            flat = arr.reshape(count, -1)
            acc.min = [float(x) for x in flat.min(axis=0)] if count else None
            acc.max = [float(x) for x in flat.max(axis=0)] if count else None
        accessors.append(acc)
        return len(accessors) - 1

    a_pos = add(verts, "VEC3", _FLOAT, _ARRAY, minmax=True)
    a_jnt = add(joints4, "VEC4", _USHORT, _ARRAY)
    a_wgt = add(weights, "VEC4", _FLOAT, _ARRAY)
    a_idx = add(tris.reshape(-1), "SCALAR", _UINT, _ELEMENTS)
    a_ibm = add(ibm_colmajor.reshape(S, 16), "MAT4", _FLOAT)
    a_time = add(times, "SCALAR", _FLOAT, minmax=True)
    samplers, channels = [], []
    for s in range(S):
        a_q = add(np.ascontiguousarray(quats[:, s]), "VEC4", _FLOAT)
        samplers.append(g.AnimationSampler(input=a_time, output=a_q, interpolation="LINEAR"))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1, target=g.AnimationChannelTarget(node=s, path="rotation")))
    a_t = add(root.astype(np.float32), "VEC3", _FLOAT)
    samplers.append(g.AnimationSampler(input=a_time, output=a_t, interpolation="LINEAR"))
    channels.append(g.AnimationChannel(sampler=len(samplers) - 1, target=g.AnimationChannelTarget(node=0, path="translation")))

    nodes = []
    for s in range(S):
        t = (root[0] if F else np.zeros(3)) if s == 0 else off[s]
        q0 = quats[0, s] if F else np.array([0.0, 0.0, 0.0, 1.0])
        nodes.append(g.Node(name=skel.names[s], translation=[float(x) for x in t],
                            rotation=[float(x) for x in q0], children=kids[s] or None))
    mesh_node = len(nodes)
    nodes.append(g.Node(name="skeleton_mesh", mesh=0, skin=0))
    blob = b"".join(blobs)
    gl = g.GLTF2(
        asset=g.Asset(version="2.0", generator="mocapskel"),
        scene=0,
        scenes=[g.Scene(nodes=[0, mesh_node])],
        nodes=nodes,
        meshes=[g.Mesh(name="skeleton", primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=a_pos, JOINTS_0=a_jnt, WEIGHTS_0=a_wgt), indices=a_idx)])],
        skins=[g.Skin(name="skeleton", joints=list(range(S)), inverseBindMatrices=a_ibm, skeleton=0)],
        animations=[g.Animation(name="take", samplers=samplers, channels=channels)],
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
    )
    gl.set_binary_blob(blob)
    binary = str(path).lower().endswith(".glb")
    with atomic_path(path) as tmp:
        if binary:
            gl.save_binary(tmp)
        else:
            gl.convert_buffers(g.BufferFormat.DATAURI)
            gl.save_json(tmp)
