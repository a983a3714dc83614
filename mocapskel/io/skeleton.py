"""The subject skeleton file (``.skel``): calibrate once, solve many takes.

A JSON document, versioned::

    {
      "format": "mocapskel-skeleton",
      "version": 1,
      "units": "mm",
      "axes": "lab",                      # rest pose axes = the calibration take's lab axes
      "source": "rom.c3d",               # the take it was fitted on
      "rest_frame": 12,
      "segments": [                       # parents before children is not required
        {"name": "TRSO", "parent": null, "origin": [x, y, z],
         "end_site": [0, 0, 0], "bone_length": null, "noise_mm": 1.9},
        {"name": "LUPA", "parent": "TRSO", "origin": [...], ...}
      ],
      "markers": [                        # position relative to the segment's origin, rest axes
        {"label": "LUPA1", "segment": "LUPA", "local": [x, y, z]}
      ]
    }

A segment's ``origin`` is its rest-pose position (a child's origin is its joint
with the parent). Markers that were left out of every segment are not listed.
"""
from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from ..artifacts import Skeleton
from ..errors import InputError
from .atomic import atomic_open

FORMAT = "mocapskel-skeleton"
VERSION = 1


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def to_dict(skel: Skeleton, source: str = "") -> dict[str, Any]:
    names = skel.names
    segs = [
        {
            "name": names[s],
            "parent": names[int(p)] if p >= 0 else None,
            "origin": [round(float(v), 6) for v in skel.origin[s]],
            "end_site": [round(float(v), 6) for v in skel.end_site[s]],
            "bone_length": _num(skel.bone_length[s]),
            "noise_mm": _num(skel.noise[s]),
        }
        for s, p in enumerate(skel.parent.tolist())
    ]
    marks = [
        {"label": skel.labels[m], "segment": names[int(g)], "local": [round(float(v), 6) for v in skel.marker_local[m]]}
        for m, g in enumerate(skel.marker_segment.tolist())
        if g >= 0 and np.isfinite(skel.marker_local[m]).all()
    ]
    return {
        "format": FORMAT, "version": VERSION, "units": "mm", "axes": "lab", "source": source,
        "rest_frame": int(skel.rest_frame), "segments": segs, "markers": marks,
    }


def write_skeleton(path: str | os.PathLike, skel: Skeleton, source: str = "") -> None:
    """Write a subject skeleton file atomically."""
    with atomic_open(path, "w", encoding="utf-8") as f:
        json.dump(to_dict(skel, source), f, indent=1)
        f.write("\n")


def read_skeleton(path: str | os.PathLike) -> Skeleton:
    """Read a subject skeleton file. Raises InputError when it is not one or is damaged."""
    p = str(path)
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except FileNotFoundError:
        raise InputError("no such skeleton file — check the path", p) from None
    except IsADirectoryError:
        raise InputError("is a folder, not a skeleton file", p) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"not a mocapskel skeleton file ({type(e).__name__}) — write one with 'fit --skeleton-out'", p) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError("not a mocapskel skeleton file — write one with 'fit --skeleton-out'", p)
    if doc.get("version") != VERSION:
        raise InputError(f"skeleton file version {doc.get('version')} is not supported (this mocapskel reads version {VERSION})", p)
    try:
        segs = doc["segments"]
        names = tuple(str(s["name"]) for s in segs)
        index = {n: i for i, n in enumerate(names)}
        parent = np.array([index[s["parent"]] if s["parent"] is not None else -1 for s in segs], dtype=int)
        origin = np.array([s["origin"] for s in segs], dtype=float).reshape(-1, 3)
        end_site = np.array([s.get("end_site", [0, 0, 0]) for s in segs], dtype=float).reshape(-1, 3)
        bone = np.array([np.nan if s.get("bone_length") is None else s["bone_length"] for s in segs], dtype=float)
        noise = np.array([np.nan if s.get("noise_mm") is None else s["noise_mm"] for s in segs], dtype=float)
        marks = doc["markers"]
        labels = tuple(str(m["label"]) for m in marks)
        mseg = np.array([index[m["segment"]] for m in marks], dtype=int)
        local = np.array([m["local"] for m in marks], dtype=float).reshape(-1, 3)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"damaged skeleton file ({type(e).__name__}: {e}) — write it again with 'fit --skeleton-out'", p) from None
    if (parent < 0).sum() != 1 or not np.isfinite(origin).all() or not np.isfinite(local).all() or len(set(labels)) != len(labels):
        raise InputError("damaged skeleton file (one root, finite offsets and unique labels are needed)", p)
    return Skeleton(
        names=names, parent=parent, origin=origin, marker_segment=mseg, marker_local=local, end_site=end_site,
        bone_length=bone, noise=noise, rest_frame=int(doc.get("rest_frame", 0)), labels=labels, joints=None,
        info={"source": doc.get("source", "")},
    )
