"""An OpenSim model of a solved skeleton, and the joint coordinates that replay its motion.

One body per segment, its frame at its joint with its parent (the root's: the BVH root point, for
a person midway between the hips) with the rest pose's axes; the root on a FreeJoint to ground,
every other body on a PinJoint about its hinge axis (:func:`hinge_fit`) where the solved motion
turns about that one axis (its turn moves the child's markers by more than their rigid-fit rms, and
what it does off the axis by at most :data:`PIN_OFF_AXIS_SHARE` of that: :func:`pin_misfit`), else
on a BallJoint, which replays the solved motion exactly. Coordinates are those
of OpenSim's joints: a BallJoint's and a FreeJoint's rotations are a body-fixed X-Y-Z sequence of
the joint frame (``R = Rx(q1) Ry(q2) Rz(q3)``), a FreeJoint's translations are along the joint
frame's axes, a PinJoint turns about the joint frame's Z. A ball or free joint's frame is one of
the three cyclic relabellings of the body axes, the one whose middle axis the motion turns least
about (farthest from gimbal lock). Axes are the BVH's (``up="y"``: lab (x, y, z) -> (x, z, -y),
OpenSim's Y up; ``up="z"``: the lab's), lengths in metres, angles in degrees.

Mass and inertia are not known from markers: every body gets a nominal 1 kg uniform cylinder
along its bone (:data:`NOMINAL_MASS_KG`), so that OpenSim's dynamics tools run, not to be read as
the subject's.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..artifacts import Motion
from ..errors import DataError
from ..model.kinematics import joint_points_rest, segment_origins
from ..model.naming import Naming, generic
from ..model.tree import depth_first_order, tree_from
from .rotations import matrix_to_euler, matrix_to_quat, rotation_between, rotvec_to_matrix, unwrap_euler

#: A joint is a PinJoint when the part of its solved motion off its hinge axis moves the child's
#: markers by at most this share of what its turn about the axis does (:func:`pin_misfit`).
#: Measured (``bench``-style, the off/turn ratio): generated hinge chains 0.002-0.011 (noise-free
#: and 0.2 mm); every other joint of the generated ROM and of the shared real walks 0.07 or more
#: (generated elbows and knees with soft tissue 0.07-0.14, real knees and elbows 0.11-0.13): a
#: pin there would move markers by 3.7-8.7 mm rms, and the model would not replay the solved motion.
PIN_OFF_AXIS_SHARE = 0.02
#: Nominal mass of every body (kg): markers say nothing of mass.
NOMINAL_MASS_KG = 1.0
#: Nominal radius of a body's cylinder, as a share of its bone length.
NOMINAL_RADIUS_SHARE = 0.1
#: Shortest bone the nominal inertia is computed for (m): a body of no length would get none.
NOMINAL_MIN_LENGTH_M = 0.05

_CYCLIC = (np.eye(3), np.eye(3)[:, [1, 2, 0]], np.eye(3)[:, [2, 0, 1]])  # joint axes (columns) in body axes
_NAME_BAD = re.compile(r"[^A-Za-z0-9_.\-]")


def axes_matrix(up: str) -> np.ndarray:
    """(3, 3) rotation from lab axes to the model's: ``up="y"``: (x, y, z) -> (x, z, -y); ``"z"``: none."""
    if up == "y":
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    if up == "z":
        return np.eye(3)
    raise ValueError(f"up must be 'y' or 'z', got {up!r}")


def osim_names(names) -> list[str]:
    """Names OpenSim takes, unique: every character but letters, digits, ``_ . -`` becomes ``_``
    (OpenSim refuses whitespace and ``\\ / * +``; colons and the rest are replaced as well, so that
    every OpenSim tool and file reads them), an empty name ``unnamed``, a repeat gets ``_2``, ``_3`` …"""
    out: list[str] = []
    taken: set[str] = set()
    for n in names:
        base = _NAME_BAD.sub("_", str(n)) or "unnamed"
        cand, k = base, 1
        while cand in taken:
            k += 1
            cand = f"{base}_{k}"
        taken.add(cand)
        out.append(cand)
    return out


@dataclass(frozen=True, eq=False)
class OsimBody:
    name: str
    mass: float
    mass_center: np.ndarray  # (3,) m, body frame
    inertia: np.ndarray  # (6,) Ixx Iyy Izz Ixy Ixz Iyz about the mass centre, kg m^2
    lines: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3) m: bone lines drawn from the origin


@dataclass(frozen=True, eq=False)
class OsimJoint:
    """A joint: ``kind`` FreeJoint, PinJoint or BallJoint; ``parent`` a body name or ``ground``.

    location : (3,) m, the joint centre in the parent's frame (the child's frame has its origin there).
    orientation : (3,) rad, the joint frame in both bodies' frames, body-fixed X-Y-Z.
    axis : (3,) the hinge axis in the parent's (and the child's) frame for a PinJoint, else None.
    off_axis_mm, turn_mm : how far a pin would move the child's markers from where the solved motion
    puts them, and how far its turn moves them (rms, :func:`pin_misfit`; NaN: not tried).
    """

    name: str
    kind: str
    parent: str
    child: str
    location: np.ndarray
    orientation: np.ndarray
    coordinates: tuple[str, ...]
    rotational: tuple[bool, ...]
    axis: np.ndarray | None = None
    off_axis_mm: float = float("nan")
    turn_mm: float = float("nan")


@dataclass(frozen=True, eq=False)
class OsimModel:
    """Everything the .osim, .mot and TRC files hold.

    markers : model marker names (sanitised labels), their bodies, (M, 3) locations (m, body frames);
    marker_index : (M,) the skeleton marker (label index) of each.
    values : (F, C) coordinate values per frame (degrees for rotations, metres for translations),
    columns in the order of the joints' coordinates; time : (F,) s.
    body_segment : (B,) the skeleton segment of each body (bodies listed parents first).
    """

    name: str
    bodies: tuple[OsimBody, ...]
    joints: tuple[OsimJoint, ...]
    markers: tuple[str, ...]
    marker_body: tuple[str, ...]
    marker_location: np.ndarray
    marker_index: np.ndarray
    values: np.ndarray
    time: np.ndarray
    body_segment: np.ndarray
    up: str
    axes: np.ndarray
    gravity: np.ndarray
    notes: str
    info: dict = field(default_factory=dict)

    @property
    def coordinate_names(self) -> list[str]:
        return [c for j in self.joints for c in j.coordinates]

    def report(self) -> dict:
        """The report's ``osim`` entry: every joint, its type, coordinates and (a pin) its axis."""
        out = []
        for j in self.joints:
            item = {"name": j.name, "type": j.kind, "parent": j.parent, "child": j.child,
                    "coordinates": list(j.coordinates)}
            if j.axis is not None:
                item["axis"] = [round(float(v), 6) for v in j.axis]
            if np.isfinite(j.off_axis_mm):
                item["off_axis_mm"] = round(float(j.off_axis_mm), 4)
                item["turn_mm"] = round(float(j.turn_mm), 4)
            out.append(item)
        return {"axes": "lab (x, z, -y): Y up" if self.up == "y" else "lab axes", "units": "m, degrees",
                "joints": out, "nominal_mass_kg": NOMINAL_MASS_KG, "notes": self.notes}


def hinge_fit(rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hinge that relative rotations ``rel`` (F, 3, 3; the identity at rest) come nearest to.

    Returns the axis (the unit vector the rotations move least: the eigenvector of
    ``sum (R - I)^T (R - I)`` of the smallest eigenvalue, its largest component positive) and the
    angle about it per frame (rad: the twist of a swing-twist split, in [-pi, pi]; NaN where
    ``rel`` is).
    """
    ok = np.isfinite(rel).all((1, 2))
    D = rel[ok] - np.eye(3)
    A = np.einsum("fki,fkj->ij", D, D) if ok.any() else np.eye(3)
    a = np.linalg.eigh(A)[1][:, 0]
    a = a if a[np.argmax(np.abs(a))] > 0 else -a
    theta = np.full(len(rel), np.nan)
    if ok.any():
        q = matrix_to_quat(rel[ok])
        theta[ok] = 2.0 * np.arctan2(q[:, 1:] @ a, q[:, 0])
    return a, theta


def pin_angles(rel: np.ndarray, a: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(F,) angle (rad) about ``a`` that puts ``points`` (K, 3; about the joint, rest axes) nearest
    where ``rel`` (F, 3, 3) puts them: least squares, in closed form
    (``atan2(sum (a x p).q, sum p_perp.q_perp)`` with ``q = R p``); NaN where ``rel`` is."""
    pp = points - np.outer(points @ a, a)
    q = np.einsum("fij,kj->fki", rel, points)
    s = np.einsum("kj,fkj->f", np.cross(a, pp), q)
    c = np.einsum("kj,fkj->f", pp, q)
    return np.where(np.isfinite(s) & np.isfinite(c), np.arctan2(s, c), np.nan)


def pin_misfit(rel: np.ndarray, a: np.ndarray, theta: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """How far a pin about ``a`` by ``theta`` (from :func:`hinge_fit`) would move ``points`` (K, 3; the
    child's markers about the joint, rest axes) from where ``rel`` puts them, and how far the pin's
    own turn moves them: both rms over frames and points (NaN without frames or points)."""
    ok = np.isfinite(theta)
    if not ok.any() or not len(points):
        return float("nan"), float("nan")
    Rt = rotvec_to_matrix(theta[ok, None] * a)
    off = np.einsum("fij,kj->fki", rel[ok] - Rt, points)
    turn = np.einsum("fij,kj->fki", Rt - np.eye(3), points)
    return float(np.sqrt(np.mean(np.sum(off**2, -1)))), float(np.sqrt(np.mean(np.sum(turn**2, -1))))


def _fill(values: np.ndarray) -> np.ndarray:
    """Columns with NaN frames filled by linear interpolation over frames (held at the ends; 0 if none known)."""
    out = values.copy()
    t = np.arange(len(values))
    for c in np.flatnonzero(~np.isfinite(values).all(axis=0)):
        ok = np.isfinite(values[:, c])
        out[:, c] = np.interp(t, t[ok], values[ok, c]) if ok.any() else 0.0
    return out


def _ball_frame(Rm: np.ndarray) -> np.ndarray:
    """The cyclic relabelling of the body axes whose middle (Y) axis keeps ``Rm`` (F, 3, 3) farthest from gimbal lock."""
    ok = np.isfinite(Rm).all((1, 2))
    if not ok.any():
        return _CYCLIC[0]
    worst = [np.max(np.abs(np.einsum("i,fij,j->f", O[:, 0], Rm[ok], O[:, 2]))) for O in _CYCLIC]
    return _CYCLIC[int(np.argmin(np.round(worst, 12)))]


def _xyz_deg(Rj: np.ndarray) -> np.ndarray:
    """(F, 3) body-fixed X-Y-Z angles (degrees) of joint rotations ``Rj`` (F, 3, 3), continuous over frames."""
    ok = np.isfinite(Rj).all((1, 2))
    ang = np.full((len(Rj), 3), np.nan)
    if ok.any():
        ang[ok] = unwrap_euler(matrix_to_euler(Rj[ok], "XYZ"), "XYZ")
    return ang


def _inertia(bone_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mass centre (the bone's middle) and inertia of a nominal 1 kg cylinder along ``bone_m`` (3,)."""
    L = float(np.linalg.norm(bone_m))
    u = bone_m / L if L > 0 else np.array([0.0, 1.0, 0.0])
    L = max(L, NOMINAL_MIN_LENGTH_M)
    m, rho = NOMINAL_MASS_KG, NOMINAL_RADIUS_SHARE * L
    i_axis, i_perp = m * rho**2 / 2.0, m * (3.0 * rho**2 + L**2) / 12.0
    Inn = i_perp * np.eye(3) + (i_axis - i_perp) * np.outer(u, u)
    return bone_m / 2.0, np.array([Inn[0, 0], Inn[1, 1], Inn[2, 2], Inn[0, 1], Inn[0, 2], Inn[1, 2]])


def build_model(motion: Motion, naming: Naming | None = None, up: str = "y", name: str = "mocapskel") -> OsimModel:
    """The OpenSim model of ``motion``'s skeleton and its coordinates on every frame (see the module)."""
    sk = motion.skeleton
    S = len(sk.names)
    if S < 2:
        raise DataError("the skeleton has one segment and no joint: an OpenSim model needs two or more bodies",
                        motion.source or None)
    naming = naming if naming is not None else generic(sk)
    M = axes_matrix(up)
    old = np.asarray(sk.parent)
    root = int(naming.root)
    parent = tree_from(old, root) if old[root] >= 0 else old
    r = joint_points_rest(sk, parent, naming)
    origin = np.asarray(sk.origin, dtype=np.float64)
    rot = np.asarray(motion.rot, dtype=np.float64)
    F = rot.shape[0]
    # body origins per frame (lab mm): points fixed in their segments
    P = segment_origins(motion) + np.einsum("fsij,sj->fsi", rot, r - origin)
    order = depth_first_order(parent)
    kids = [np.flatnonzero(parent == s) for s in range(S)]
    mseg = np.asarray(sk.marker_segment)
    mrest = origin[np.maximum(mseg, 0)] + np.asarray(sk.marker_local, dtype=np.float64)
    bnames = osim_names(["ground"] + [naming.names[s] for s in range(S)])[1:]  # no body called ground
    jraw = [f"ground_{bnames[s]}" if parent[s] < 0 else
            (naming.joint_names[s] if old[s] == parent[s] else naming.joint_names[parent[s]]) or f"{bnames[parent[s]]}_{bnames[s]}"
            for s in range(S)]
    jnames = osim_names(jraw)

    bodies, joints, cols = [], [], []
    for s in order.tolist():
        own = mrest[mseg == s]
        if len(kids[s]):
            bone = r[kids[s]].mean(axis=0) - r[s]
        elif np.linalg.norm(sk.end_site[s]) > 0 and old[s] == parent[s]:
            bone = origin[s] + np.asarray(sk.end_site[s]) - r[s]
        else:
            bone = own.mean(axis=0) - r[s] if len(own) else np.zeros(3)
        mc, inertia = _inertia(M @ bone / 1000.0)
        ends = (r[kids[s]] - r[s]) if len(kids[s]) else bone[None]
        bodies.append(OsimBody(bnames[s], NOMINAL_MASS_KG, mc, inertia, lines=ends @ M.T / 1000.0))
        p = int(parent[s])
        if p < 0:
            Rm = M @ rot[:, s] @ M.T
            O = _ball_frame(Rm)
            ax = ["xyz"[int(np.argmax(O[:, k]))] for k in range(3)]
            coords = tuple(f"{jnames[s]}_r{a}" for a in ax) + tuple(f"{jnames[s]}_t{a}" for a in ax)
            vals = np.concatenate([_xyz_deg(O.T @ Rm @ O), (P[:, s] @ M.T / 1000.0) @ O], axis=1)
            joints.append(OsimJoint(jnames[s], "FreeJoint", "ground", bnames[s], np.zeros(3), _orientation(O),
                                    coords, (True,) * 3 + (False,) * 3))
            cols.append(vals)
            continue
        rel = np.swapaxes(rot[:, p], 1, 2) @ rot[:, s]
        Rm = M @ rel @ M.T
        a, theta = hinge_fit(Rm)
        # what the pin must place: the child's markers and its own joints (its children's bodies hang there)
        pts = np.concatenate([own, r[kids[s]]]) - r[s]
        pts = pts @ M.T
        if len(pts) and np.linalg.norm(pts - np.outer(pts @ a, a)) > 0:
            theta = pin_angles(Rm, a, pts)
        off, turn = pin_misfit(Rm, a, theta, pts)
        bar = float(sk.noise[s]) if np.isfinite(sk.noise[s]) else 0.0
        loc = M @ (r[s] - r[p]) / 1000.0
        if turn > bar and off <= PIN_OFF_AXIS_SHARE * turn:  # turns about one axis: a measured turn, little else
            O = rotation_between(np.array([0.0, 0.0, 1.0]), a)
            joints.append(OsimJoint(jnames[s], "PinJoint", bnames[p], bnames[s], loc, _orientation(O),
                                    (f"{jnames[s]}_angle",), (True,), axis=a, off_axis_mm=off, turn_mm=turn))
            cols.append(np.degrees(np.unwrap(_fill(theta[:, None]), axis=0)))
        else:
            O = _ball_frame(Rm)
            ax = ["xyz"[int(np.argmax(O[:, k]))] for k in range(3)]
            joints.append(OsimJoint(jnames[s], "BallJoint", bnames[p], bnames[s], loc, _orientation(O),
                                    tuple(f"{jnames[s]}_r{x}" for x in ax), (True,) * 3, off_axis_mm=off, turn_mm=turn))
            cols.append(_xyz_deg(O.T @ Rm @ O))
    values = _fill(np.concatenate(cols, axis=1))
    use = np.flatnonzero(mseg >= 0)
    mnames = osim_names([sk.labels[m] for m in use])
    loc = (mrest[use] - r[mseg[use]]) @ M.T / 1000.0
    rate = motion.rate if motion.rate and motion.rate > 0 else 1.0
    g = M @ np.array([0.0, 0.0, -9.80665])
    notes = ("Made by mocapskel from the markers alone, without a template: bodies, joint centres, hinge axes and"
             " marker offsets are fitted; mass and inertia are not known from markers and are nominal (every body"
             f" a {NOMINAL_MASS_KG:g} kg uniform cylinder along its bone, radius {NOMINAL_RADIUS_SHARE:g} of its"
             " length): scale or replace them before dynamics.")
    return OsimModel(name=osim_names([name])[0], bodies=tuple(bodies), joints=tuple(joints), markers=tuple(mnames),
                     marker_body=tuple(bnames[s] for s in mseg[use]), marker_location=loc, marker_index=use,
                     values=values, time=np.arange(F) / rate, body_segment=order, up=up, axes=M, gravity=g,
                     notes=notes)


def _orientation(O: np.ndarray) -> np.ndarray:
    """Body-fixed X-Y-Z angles (rad) of the frame whose axes are the columns of ``O``."""
    return np.radians(matrix_to_euler(O, "XYZ"))
