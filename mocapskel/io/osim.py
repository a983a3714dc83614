"""OpenSim files of a solved take: the model (.osim), its coordinates (.mot) and its markers (.trc).

Written with the standard library (xml.etree): OpenSim is not needed to write them. The model
follows OpenSim 4's schema (``OpenSimDocument Version="40000"``): a BodySet, a JointSet whose
joints own their two PhysicalOffsetFrames, a MarkerSet; metres, gravity along minus the up axis.
The .mot is an OpenSim Storage file (``inDegrees=yes``, a ``time`` column, one column per
coordinate named as in the model); the .trc holds the markers the fit used, in the model's axes
(mm; OpenSim converts by the header's ``Units``), under the model's marker names, gaps as ``NaN``. What is in the
model and why: :mod:`mocapskel.solvers.osim_model`.
"""
from __future__ import annotations

import io
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..artifacts import Markers
from ..solvers.osim_model import OsimModel
from .atomic import atomic_open
from .trc import write_trc

#: The schema version written: OpenSim 4.0's, which every 4.x reads.
DOCUMENT_VERSION = "40000"
#: Radius (m) of the sphere drawn at every body's origin (its joint): what the visualiser shows.
JOINT_SPHERE_M = 0.015


def _vec(v) -> str:
    return " ".join(repr(float(x)) if x != 0 else "0" for x in np.asarray(v, dtype=np.float64).ravel())


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrib) -> ET.Element:
    e = ET.SubElement(parent, tag, attrib)
    if text is not None:
        e.text = text
    return e


def _offset_frame(frames: ET.Element, name: str, body: str, translation, orientation) -> None:
    f = _sub(frames, "PhysicalOffsetFrame", name=name)
    _sub(f, "socket_parent", "/ground" if body == "ground" else f"/bodyset/{body}")
    _sub(f, "translation", _vec(translation))
    _sub(f, "orientation", _vec(orientation))


def model_xml(model: OsimModel) -> bytes:
    """The .osim document of ``model`` (UTF-8 bytes)."""
    doc = ET.Element("OpenSimDocument", Version=DOCUMENT_VERSION)
    m = _sub(doc, "Model", name=model.name)
    _sub(m, "credits", model.notes)
    _sub(m, "publications", "Kirk, O'Brien, Forsyth 2005; Hang, Lasenby, Li 2015; Knight, Semwal 2009;"
                            " Ehrig et al. 2006 (SCoRE)")
    _sub(m, "length_units", "meters")
    _sub(m, "force_units", "N")
    _sub(m, "gravity", _vec(model.gravity))
    _sub(m, "Ground", name="ground")
    objs = _sub(_sub(m, "BodySet", name="bodyset"), "objects")
    for b in model.bodies:
        e = _sub(objs, "Body", name=b.name)
        _sub(e, "mass", repr(float(b.mass)))
        _sub(e, "mass_center", _vec(b.mass_center))
        _sub(e, "inertia", _vec(b.inertia))
        geo = _sub(e, "attached_geometry")  # drawn only: a sphere at the joint, a line along each bone
        sph = _sub(geo, "Sphere", name=f"{b.name}_joint")
        _sub(sph, "socket_frame", "..")
        _sub(sph, "radius", repr(JOINT_SPHERE_M))
        for k, end in enumerate(b.lines):
            ln = _sub(geo, "LineGeometry", name=f"{b.name}_bone{k + 1}")
            _sub(ln, "socket_frame", "..")
            _sub(ln, "start_point", "0 0 0")
            _sub(ln, "end_point", _vec(end))
    objs = _sub(_sub(m, "JointSet", name="jointset"), "objects")
    for j in model.joints:
        e = _sub(objs, j.kind, name=j.name)
        pf, cf = f"{j.parent}_offset", f"{j.child}_offset"
        _sub(e, "socket_parent_frame", pf)
        _sub(e, "socket_child_frame", cf)
        cs = _sub(e, "coordinates")
        for c, rotational in zip(j.coordinates, j.rotational):
            ce = _sub(cs, "Coordinate", name=c)
            _sub(ce, "default_value", "0")
            lim = 4.0 * np.pi if rotational else 100.0
            _sub(ce, "range", _vec([-lim, lim]))
            _sub(ce, "clamped", "false")
            _sub(ce, "locked", "false")
        frames = _sub(e, "frames")
        _offset_frame(frames, pf, j.parent, j.location, j.orientation)
        _offset_frame(frames, cf, j.child, np.zeros(3), j.orientation)
    objs = _sub(_sub(m, "MarkerSet", name="markerset"), "objects")
    for name, body, loc in zip(model.markers, model.marker_body, model.marker_location):
        e = _sub(objs, "Marker", name=name)
        _sub(e, "socket_parent_frame", f"/bodyset/{body}")
        _sub(e, "location", _vec(loc))
        _sub(e, "fixed", "false")
    ET.indent(doc, space="\t")
    return b'<?xml version="1.0" encoding="UTF-8" ?>\n' + ET.tostring(doc, encoding="utf-8") + b"\n"


def write_osim(path: str | os.PathLike, model: OsimModel) -> None:
    """Write the model as an .osim file, atomically."""
    with atomic_open(path, "wb") as f:
        f.write(model_xml(model))


def write_mot(path: str | os.PathLike, model: OsimModel) -> None:
    """Write the coordinates of every frame as an OpenSim Storage (.mot) file, atomically."""
    names = model.coordinate_names
    F = len(model.time)
    head = (f"{Path(path).name}\nversion=1\nnRows={F}\nnColumns={len(names) + 1}\ninDegrees=yes\nendheader\n"
            + "\t".join(["time"] + names) + "\n")
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack([model.time, model.values]), fmt="%.8f", delimiter="\t")
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(head)
        f.write(buf.getvalue())


def write_osim_trc(path: str | os.PathLike, model: OsimModel, points: np.ndarray, rate: float, source: str = "") -> None:
    """Write the markers ``points`` (F, M, 3; lab, mm, one column per skeleton label) that the model
    carries as a TRC in the model's axes and names."""
    pts = np.asarray(points, dtype=np.float64)[:, model.marker_index] @ model.axes.T
    write_trc(path, Markers(points=pts, labels=model.markers, rate=float(rate), units="mm", source=source), missing="NaN")


def osim_companions(path: str | os.PathLike) -> tuple[str, str]:
    """The .trc and .mot written beside ``subject.osim``: ``subject.trc``, ``subject.mot``."""
    p = Path(path)
    return str(p.with_suffix(".trc")), str(p.with_suffix(".mot"))


def write_osim_outputs(paths: tuple, model: OsimModel, points: np.ndarray, rate: float, source: str = "") -> None:
    """The model, its markers and its coordinates, at ``paths`` = (.osim, .trc, .mot)."""
    osim, trc, mot = paths
    write_osim(osim, model)
    write_osim_trc(trc, model, points, rate, source)
    write_mot(mot, model)


__all__ = ["model_xml", "write_osim", "write_mot", "write_osim_trc", "osim_companions", "write_osim_outputs"]
