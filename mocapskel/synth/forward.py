"""Posing the synthetic human: forward kinematics, the feet's floor contact and the shoulder girdles' rhythm."""
from __future__ import annotations

import numpy as np

from .body import _MARKER_SPEC, _S, _SEG, PARENT, SEGMENTS, _Subject
from .rotations import _apply33, _matmul33, _mirror, rotvec_to_matrix

_ACROMION_RHYTHM = 0.2  # the clavicle rises about the SC joint by this fraction of the arm's elevation
_PROTRACTION = 0.25  # and turns forward by this fraction of the arm's forward flexion


def _forward(subj: _Subject, root_pos: np.ndarray, root_rot: np.ndarray, rv: np.ndarray):
    """Global rotations (F, S, 3, 3), segment origins (F, S, 3) and clean markers (F, M, 3)."""
    F = root_pos.shape[0]
    G = np.empty((F, _S, 3, 3))
    O = np.empty((F, _S, 3))
    G[:, 0], O[:, 0] = root_rot, root_pos
    rel = rotvec_to_matrix(rv[:, 1:])  # (F, S-1, 3, 3)
    for s in range(1, _S):
        p = PARENT[s]
        G[:, s] = _matmul33(G[:, p], rel[:, s - 1])
        O[:, s] = O[:, p] + _apply33(G[:, p], (subj.joint_rest[s] - subj.joint_rest[p])[None])[:, 0]
    pts = np.empty((F, subj.marker_rest.shape[0], 3))
    for s in range(_S):
        idx = np.flatnonzero(subj.marker_segment == s)
        local = subj.marker_rest[idx] - subj.joint_rest[s]
        pts[:, idx] = O[:, s, None, :] + _apply33(G[:, s], local)
    return G, O, pts


def _floor_lift(subj: _Subject, G: np.ndarray, O: np.ndarray) -> np.ndarray:
    """(F,) vertical shift that puts the lowest heel or toe point (a smooth minimum) at its rest height."""
    spec = _MARKER_SPEC["LFoot"]
    tau = 8.0 * subj.seg_factor[SEGMENTS.index("LFoot")]  # mm
    lows, rest_low = [], np.inf
    for name in ("LFoot", "RFoot"):
        s = SEGMENTS.index(name)
        pts = np.array([spec.p0, spec.p1], float) * subj.seg_factor[s]
        if name.startswith("R"):
            pts = _mirror(pts)
        lows.append(O[:, s, None, 2] + np.einsum("fj,pj->fp", G[:, s, 2], pts))
        rest_low = min(rest_low, subj.pelvis_height + subj.joint_rest[s, 2] + pts[:, 2].min())
    z = np.concatenate(lows, axis=1)  # (F, 4)
    # smooth minimum (no kink when the supporting foot changes)
    zmin = z.min(1, keepdims=True)
    soft = zmin[:, 0] - tau * np.log(np.exp(-(z - zmin) / tau).sum(1))
    return rest_low - soft

def _girdle(subj: _Subject, rv: np.ndarray, right: bool) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3, 3) rotation of a shoulder girdle in the thorax frame and (3,) its pivot (the
    sterno-clavicular joint, body frame at rest): the scapulohumeral rhythm. About the pivot the girdle
    rises by a fifth of the arm's elevation and turns forward (protraction) by a quarter of its forward
    flexion; it carries the acromion and the shoulder joint centre."""
    sh = _SEG["RUpperArm" if right else "LUpperArm"]
    R = rotvec_to_matrix(rv[:, sh])  # upper arm relative to the thorax (thorax axes)
    v = -R[:, :, 2]  # the arm's long axis (rest: straight down)
    elev = np.arccos(np.clip(-v[:, 2], -1.0, 1.0))
    fwd = np.clip(np.arctan2(v[:, 0], -v[:, 2]), 0.0, None)
    sign = -1.0 if right else 1.0
    zero = np.zeros_like(elev)
    up = rotvec_to_matrix(np.column_stack([sign * _ACROMION_RHYTHM * elev, zero, zero]))
    forward = rotvec_to_matrix(np.column_stack([zero, zero, -sign * _PROTRACTION * fwd]))
    sc = subj.joint_rest[_SEG["Head"]] + np.array([60.0, 20.0 * sign, -50.0]) * subj.seg_factor[1]
    return _matmul33(forward, up), sc


def _girdle_shift(subj: _Subject, rv: np.ndarray, right: bool, p: np.ndarray) -> np.ndarray:
    """(F, 3) displacement (thorax frame) of a point ``p`` (body frame at rest) carried by a shoulder girdle."""
    Rc, sc = _girdle(subj, rv, right)
    arm = p - sc
    return np.einsum("fij,j->fi", Rc, arm) - arm


def _acromion(subj: _Subject, rv: np.ndarray, m: int) -> np.ndarray:
    """(F, 3) displacement of an acromion marker in the thorax frame (it rides the shoulder girdle)."""
    p = subj.marker_rest[m]
    return _girdle_shift(subj, rv, bool(p[1] < 0), p)
