"""Skin motion of the realistic generator: marker displacements on the bone driven by the joint angles,
sliding plates, the acromion riding the shoulder girdle, and a band-limited wobble."""
from __future__ import annotations

import numpy as np

from .body import _HINGE, _JNT, PARENT, SEGMENTS, _hinge_frame, _left, _part, _side_name, _Subject
from .forward import _acromion
from .markersets import _PLATES, _Placed
from .rotations import _mirror_axial, rotvec_to_matrix
from .soft_tissue import _band_noise

_WOBBLE = 0.05  # rms of the band-limited wobble, as a fraction of the amplitude
_WOBBLE_BAND_HZ = (2.0, 8.0)
_NORMAL_DAMP = 0.6  # skin motion along the skin normal is reduced by this fraction

# everyday range (deg) of each degree of freedom (rotation-vector components X, Y, Z of a ball joint,
# left side; flexion of a hinge): the skin reaches its amplitude over these ranges
_EVERYDAY = {
    "Lumbar": ((-10, 10), (-10, 30), (-15, 15)), "Neck": ((-15, 15), (-20, 30), (-30, 30)),
    "LShoulder": ((0, 60), (-90, 20), (-30, 30)), "LWrist": ((-15, 15), (-30, 30), (-20, 20)),
    "LHip": ((-10, 20), (-60, 15), (-15, 15)), "LAnkle": ((-10, 10), (-20, 25), (-10, 10)),
    "LKnee": ((0, 90),), "LElbow": ((-120, -10),),
}  # fmt: skip
_LIMIT = 0.75  # a marker's skin displacement stays within this fraction of its amplitude from the mean
_CAL_QUANTILE = 0.5  # the amplitude is the p2p displacement of a typical everyday pose (median)

# joints whose angles drive the skin of each segment (the joints at its ends)
_DRIVERS = {
    "Pelvis": ("LHip", "RHip", "Lumbar"), "Torso": ("Lumbar", "Neck", "LShoulder", "RShoulder"), "Head": ("Neck",),
    "LUpperArm": ("LShoulder", "LElbow"), "LForearm": ("LElbow", "LWrist"), "LHand": ("LWrist",),
    "LThigh": ("LHip", "LKnee"), "LShank": ("LKnee", "LAnkle"), "LFoot": ("LAnkle",),
}  # fmt: skip


def _drivers(seg: str) -> tuple[str, ...]:
    right = seg.startswith("R")
    return tuple(_side_name(j, right) for j in _DRIVERS[_left(seg)])


# ------------------------------------------------------------------ skin motion


def _joint_features(rv: np.ndarray, joint: str) -> np.ndarray:
    """(F, K) smooth features of a joint's angles: ~[-1, 1] over its everyday range, saturating beyond."""
    s = _JNT[joint] + 1
    v = rv[:, s] if not joint.startswith("R") else _mirror_axial(rv[:, s])
    left = "L" + joint[1:] if joint.startswith("R") else joint
    box = np.deg2rad(np.array(_EVERYDAY[left], float)).reshape(-1, 2)
    if left in _HINGE:
        v = (v @ _hinge_frame(left)[0])[:, None]
    u = (v - box.mean(1)) / (0.5 * (box[:, 1] - box[:, 0]))
    return _features(u)


def _features(u: np.ndarray) -> np.ndarray:
    """Linear and quadratic terms of angles normalised to their everyday range; skin stretches only
    so far, so each saturates (tanh) beyond that range (at most ~1.3 times its in-range value)."""
    s = np.tanh(u) / np.tanh(1.0)
    return np.concatenate([s, s**2 - 0.4], axis=1)


def _joint_dim(joint: str) -> int:
    left = "L" + joint[1:] if joint.startswith("R") else joint
    return 1 if left in _HINGE else 3


def _skin(placed: _Placed, rv: np.ndarray, rate: float, seed: int, nrng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(F, M, 3) skin displacements in the host segments' frames, and the (M,) amplitudes used."""
    subj = placed.subj
    F, M = rv.shape[0], placed.host.size
    out = np.zeros((F, M, 3))
    crng = np.random.default_rng([seed, 21])  # the subject's skin: fixed by the subject seed
    n_cal = 512
    feats: dict[str, np.ndarray] = {}
    cal: dict[str, np.ndarray] = {}
    for s in np.unique(placed.host):
        for j in _drivers(SEGMENTS[s]):
            if j not in feats:
                feats[j] = _joint_features(rv, j)
                d = _joint_dim(j)
                u = np.random.default_rng([seed, 22, _JNT[j]]).uniform(-1.0, 1.0, (n_cal, d))
                cal[j] = _features(u)
    done_plates: dict[str, np.ndarray] = {}
    for m in range(M):
        h = int(placed.host[m])
        drv = _drivers(SEGMENTS[h])
        phi = np.concatenate([feats[j] for j in drv], axis=1)
        phic = np.concatenate([cal[j] for j in drv], axis=1)
        plate = placed.plate[m]
        if plate is not None:
            if plate not in done_plates:
                done_plates[plate] = _plate_motion(crng, phi, phic, placed, plate, h)
            T, W = done_plates[plate]  # (F, 3), (F, 3) rad
            local = subj.marker_rest[m] - placed.plate_centre[plate]
            R = rotvec_to_matrix(W)
            out[:, m] = T + np.einsum("fij,j->fi", R, local) - local
            continue
        C = crng.normal(0.0, 1.0, (3, phi.shape[1]))
        # mostly along the skin: damp the component along the outward normal
        n = _outward_normal(subj, h, subj.marker_rest[m])
        C = C - _NORMAL_DAMP * np.outer(n, n @ C)
        dc = phic @ C.T
        dc -= dc.mean(0)
        scale = placed.amp[m] / (2.0 * np.quantile(np.linalg.norm(dc, axis=1), _CAL_QUANTILE))
        out[:, m] = _soft_limit((phi - phic.mean(0)) @ C.T * scale, _LIMIT * placed.amp[m])
    if placed.kind.count("acromion"):
        for m in (i for i, k in enumerate(placed.kind) if k == "acromion"):
            out[:, m] += _acromion(subj, rv, m)
    # band-limited wobble (inertia), independent per marker, rigid per plate
    wob = _band_noise(nrng, F, M * 3, rate, _WOBBLE_BAND_HZ).reshape(F, M, 3)
    for plate in set(p for p in placed.plate if p is not None):
        idx = [i for i, p in enumerate(placed.plate) if p == plate]
        wob[:, idx] = wob[:, idx[:1]]
    out += wob * (_WOBBLE * placed.amp / np.sqrt(3.0))[None, :, None]
    return out, placed.amp


def _plate_motion(crng, phi, phic, placed: _Placed, plate: str, h: int):
    """(F, 3) translation (mm) and (F, 3) rotation vector (rad) of a sliding plate."""
    left = plate if not plate.startswith("R") else "L" + plate[1:]
    _, _, _, tr_amp, rot_deg = _PLATES[left]
    C = crng.normal(0.0, 1.0, (6, phi.shape[1]))
    dc = phic @ C.T
    dc -= dc.mean(0)
    a_tr = crng.uniform(*tr_amp)
    C[:3] *= a_tr / (2.0 * np.quantile(np.linalg.norm(dc[:, :3], axis=1), _CAL_QUANTILE))
    C[3:] *= np.deg2rad(rot_deg) / (2.0 * np.quantile(np.linalg.norm(dc[:, 3:], axis=1), _CAL_QUANTILE))
    idx = [i for i, p in enumerate(placed.plate) if p == plate]
    placed.amp[idx] = a_tr  # a plate's markers share its translation amplitude
    d = (phi - phic.mean(0)) @ C.T
    return _soft_limit(d[:, :3], _LIMIT * a_tr), _soft_limit(d[:, 3:], _LIMIT * np.deg2rad(rot_deg))


def _soft_limit(d: np.ndarray, limit: float) -> np.ndarray:
    """(F, 3) displacements shrunk smoothly so that their length stays under ``limit`` (skin stretches
    only so far): nearly unchanged below ~60 % of it."""
    n = np.linalg.norm(d, axis=1, keepdims=True) / max(limit, 1e-9)
    return d / (1.0 + n**4) ** 0.25


def _outward_normal(subj: _Subject, h: int, p: np.ndarray) -> np.ndarray:
    kids = np.flatnonzero(PARENT == h)
    o = subj.joint_rest[h]
    leaf_axis = {"Foot": (1.0, 0.0, 0.0), "Hand": (0.0, 0.0, -1.0)}.get(_part(SEGMENTS[h]), (0.0, 0.0, 1.0))
    axis = (subj.joint_rest[kids].mean(0) - o) if kids.size else np.array(leaf_axis)
    axis = axis / np.linalg.norm(axis)
    r = (p - o) - ((p - o) @ axis) * axis
    nr = np.linalg.norm(r)
    return r / nr if nr > 1e-6 else np.zeros(3)
