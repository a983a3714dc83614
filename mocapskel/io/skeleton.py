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

from ..artifacts import Skeleton, name_problem
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


_FIX = "write it again with 'fit --skeleton-out'"
#: Offsets beyond this (mm, 10 km) come from no subject.
_MAX_MM = 1e7


def _number(x: Any, what: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise ValueError(f"{what} is {type(x).__name__}, not a number")
    v = float(x)
    if not np.isfinite(v) or abs(v) > _MAX_MM:
        raise ValueError(f"{what} is {v:g}, beyond {_MAX_MM:g} mm")
    return v


def _vector(x: Any, what: str) -> list[float]:
    if not isinstance(x, list) or len(x) != 3:
        raise ValueError(f"{what} is not 3 numbers")
    return [_number(v, what) for v in x]


def _optional(x: Any, what: str) -> float:
    return np.nan if x is None else _number(x, what)


def read_skeleton(path: str | os.PathLike) -> Skeleton:
    """Read a subject skeleton file. Raises InputError when it is not one or is damaged.

    Checked: the JSON types, one root and parents that form a tree (no cycle, no
    segment its own parent), unique segment names that are BVH joint names and unique marker labels, finite
    offsets within 10 km, a rest frame that is a frame number.
    """
    from .paths import require_regular_file

    p = str(path)
    require_regular_file(path, "a .skel file written by 'fit --skeleton-out'")
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except FileNotFoundError:
        raise InputError("no such skeleton file — check the path", p) from None
    except IsADirectoryError:
        raise InputError("is a folder, not a skeleton file — give a .skel file written by 'fit --skeleton-out'", p) from None
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise InputError(f"not a mocapskel skeleton file ({type(e).__name__}) — write one with 'fit --skeleton-out'", p) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError("not a mocapskel skeleton file — write one with 'fit --skeleton-out'", p)
    version = doc.get("version")
    if isinstance(version, bool) or version != VERSION:
        raise InputError(
            f"skeleton file version {str(version)[:20]} is not supported (this mocapskel reads version {VERSION})"
            " — write it again with this version's 'fit --skeleton-out'", p)
    try:
        segs = doc["segments"]
        marks = doc["markers"]
        if not isinstance(segs, list) or not isinstance(marks, list) or not all(isinstance(x, dict) for x in segs + marks):
            raise ValueError("'segments' and 'markers' must be lists of objects")
        names = tuple(s["name"] for s in segs)
        labels = tuple(m["label"] for m in marks)
        if not all(isinstance(n, str) and n for n in names + labels):
            raise ValueError("segment names and marker labels must be non-empty text")
        if len(set(names)) != len(names):
            raise ValueError("repeated segment names")
        if problem := name_problem(names):  # 'fit' writes BVH joint names; 'solve' writes them as they are
            raise ValueError(f"segment names: {problem}")
        if len(set(labels)) != len(labels):
            raise ValueError("repeated marker labels")
        index = {n: i for i, n in enumerate(names)}
        for s_ in segs:
            if s_["parent"] is not None and s_["parent"] not in index:
                raise ValueError(f"parent {str(s_['parent'])[:40]!r} is not a segment")
        parent = np.array([index[s_["parent"]] if s_["parent"] is not None else -1 for s_ in segs], dtype=int)
        origin = np.array([_vector(s_["origin"], "a segment origin") for s_ in segs], dtype=float).reshape(-1, 3)
        end_site = np.array([_vector(s_.get("end_site", [0, 0, 0]), "an end site") for s_ in segs], dtype=float).reshape(-1, 3)
        bone = np.array([_optional(s_.get("bone_length"), "a bone length") for s_ in segs], dtype=float)
        noise = np.array([_optional(s_.get("noise_mm"), "a noise") for s_ in segs], dtype=float)
        for m in marks:
            if m["segment"] not in index:
                raise ValueError(f"marker {m['label']!r} is on {str(m['segment'])[:40]!r}, not a segment")
        mseg = np.array([index[m["segment"]] for m in marks], dtype=int)
        local = np.array([_vector(m["local"], "a marker offset") for m in marks], dtype=float).reshape(-1, 3)
        rest = doc.get("rest_frame", 0)
        if isinstance(rest, bool) or not isinstance(rest, int) or rest < 0:
            raise ValueError(f"rest_frame is {str(rest)[:20]}, not a frame number")
        source = doc.get("source", "")
        if not isinstance(source, str):
            raise ValueError("source is not text")
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        what = f"missing {e}" if isinstance(e, KeyError) else str(e)
        raise InputError(f"damaged skeleton file ({what}) — {_FIX}", p) from None
    if (parent < 0).sum() != 1:
        raise InputError(f"damaged skeleton file ({(parent < 0).sum()} segments without a parent; one root is needed) — {_FIX}", p)
    # every segment must reach the root by its parents: a cycle (a segment its own parent or ancestor) never does
    cur = parent.copy()
    for _ in range(parent.size):
        live = cur >= 0
        if not live.any():
            break
        cur[live] = parent[cur[live]]
    if (cur >= 0).any():
        bad = names[int(np.flatnonzero(cur >= 0)[0])]
        raise InputError(f"damaged skeleton file (the parents of {bad!r} form a cycle) — {_FIX}", p)
    return Skeleton(
        names=names, parent=parent, origin=origin, marker_segment=mseg, marker_local=local, end_site=end_site,
        bone_length=bone, noise=noise, rest_frame=rest, labels=labels, joints=None,
        info={"source": source},
    )
