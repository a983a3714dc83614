"""The data that flows between pipeline stages.

Every artifact is a frozen dataclass of numpy arrays (time first), plain
scalars, tuples of strings and JSON-able ``info`` dicts. Later artifacts hold
the earlier one they were computed from, so a saved ``Motion`` carries the
whole chain back to the markers. Artifacts are saved with ``np.savez`` and
loaded with ``allow_pickle=False``: no pickles ever.

Conventions
-----------
- Positions are float64 millimetres in the input's lab frame; NaN marks a gap.
- Segment frames: every segment has a rest orientation equal to the lab axes
  at the rest frame, so a segment rotation ``rot[f, s]`` is the rotation that
  carries the segment from its rest pose to its pose at frame ``f`` (global,
  not relative to the parent).
"""
from __future__ import annotations

import dataclasses
import io
import json
import re
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np

from .errors import InputError

SCHEMA = 1

#: Frame rates mocapskel accepts (Hz). Optical capture runs at tens to a few thousand
#: frames per second; a rate outside this range is a damaged or mislabelled header, and
#: the stages size their windows (half a second ...) by it.
MIN_RATE_HZ = 1.0
MAX_RATE_HZ = 100_000.0


@dataclass(frozen=True, eq=False)
class Markers:
    """Marker trajectories: the output of read, clean and merge-ids.

    points : (F, M, 3) float64 ndarray, mm, NaN where the marker is not seen.
    labels : M unique marker labels.
    rate   : frames per second.
    units  : the units of the source file (points are always mm).
    source : the input file's name (no folder).
    stage  : "read", "clean" or "merge-ids".
    info   : JSON-able notes of the stages so far (what was removed and why).
    """

    points: np.ndarray
    labels: tuple[str, ...]
    rate: float
    units: str = "mm"
    source: str = ""
    stage: str = "read"
    info: dict = field(default_factory=dict)
    kind: ClassVar[str] = "markers"

    @property
    def n_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.points.shape[1])


@dataclass(frozen=True, eq=False)
class Segments:
    """Markers grouped into rigid segments.

    group    : (M,) int, the segment of each marker; -1 for markers left out.
    dist_std : (M, M) std of pairwise marker distances on the chosen sampling.
    eigvals  : eigenvalues of the normalised affinity (largest first).
    """

    markers: Markers
    group: np.ndarray
    dist_std: np.ndarray
    eigvals: np.ndarray
    info: dict = field(default_factory=dict)
    kind: ClassVar[str] = "segments"

    @property
    def n_segments(self) -> int:
        return int(self.group.max()) + 1 if self.group.size and self.group.max() >= 0 else 0

    def members(self, s: int) -> np.ndarray:
        return np.flatnonzero(self.group == s)


@dataclass(frozen=True, eq=False)
class Topology:
    """The tree of segments.

    edges     : (E, 2) int, (parent, child) segment pairs, directed away from root.
    cost      : (E,) joint cost of each edge (mm^2).
    pair_cost : (S, S) cheap joint cost of every pair (inf where not computed).
    root      : the root segment (the tree's centre).
    """

    segments: Segments
    edges: np.ndarray
    cost: np.ndarray
    pair_cost: np.ndarray
    root: int
    info: dict = field(default_factory=dict)
    kind: ClassVar[str] = "topology"


@dataclass(frozen=True, eq=False)
class Joints:
    """Joint-centre trajectories, one per tree edge.

    centres  : (F, E, 3) mm, NaN where the joint cannot be placed.
    method   : E method names ("jmv", "mtb", "sphere", "score", ...).
    residual : (E,) rms distance variation of markers to the joint (mm).
    alt_centres : (F, E, 3) or None: a second start for the rigid stage, the
               same centres with the joints kept otherwise taken from Hang's
               framework instead (see the joints stage); None when every
               joint is SCoRE's or the framework's.
    """

    topology: Topology
    centres: np.ndarray
    method: tuple[str, ...]
    residual: np.ndarray
    info: dict = field(default_factory=dict)
    alt_centres: np.ndarray | None = None
    kind: ClassVar[str] = "joints"


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A rigid skeleton: constant offsets, in the rest pose (lab axes, mm).

    names        : S segment names (BVH joint names).
    parent       : (S,) int, parent segment, -1 for the root.
    origin       : (S, 3) segment origins at rest (a child's origin is its joint
                   with the parent; the root's is its own centre).
    marker_segment : (M,) int, the segment carrying each marker (-1: none).
    marker_local : (M, 3) marker position minus its segment's origin at rest.
    end_site     : (S, 3) End Site offset of leaves (zeros for inner segments).
    bone_length  : (S,) distance from a segment's origin to its child joints'
                   mean (leaves: to their end site); the root: 0.
    noise        : (S,) rms residual of the rigid fit per segment (mm).
    rest_frame   : the frame whose pose is the rest pose.
    labels       : M marker labels (so that a skeleton can solve other takes).
    pose_frames, pose_rot, pose_root : the take's poses at the frames the
                   skeleton was calibrated on ((K,), (K, S, 3, 3), (K, 3)), or
                   None; IK starts from them where markers alone cannot.
    """

    names: tuple[str, ...]
    parent: np.ndarray
    origin: np.ndarray
    marker_segment: np.ndarray
    marker_local: np.ndarray
    end_site: np.ndarray
    bone_length: np.ndarray
    noise: np.ndarray
    rest_frame: int
    labels: tuple[str, ...]
    joints: Joints | None = None
    info: dict = field(default_factory=dict)
    pose_frames: np.ndarray | None = None
    pose_rot: np.ndarray | None = None
    pose_root: np.ndarray | None = None
    kind: ClassVar[str] = "skeleton"

    @property
    def offset(self) -> np.ndarray:
        """(S, 3) BVH OFFSETs: origin minus the parent's origin (root: its origin)."""
        off = self.origin.copy()
        has = self.parent >= 0
        off[has] -= self.origin[self.parent[has]]
        return off


@dataclass(frozen=True, eq=False)
class Motion:
    """Per-frame pose of the skeleton (the output of IK).

    root_pos : (F, 3) root origin per frame (mm, lab frame).
    rot      : (F, S, 3, 3) global segment rotations relative to rest.
    residual : (F, M) distance of each marker from the skeleton's (mm), NaN when unseen.
    """

    skeleton: Skeleton
    root_pos: np.ndarray
    rot: np.ndarray
    residual: np.ndarray
    rate: float
    source: str = ""
    info: dict = field(default_factory=dict)
    kind: ClassVar[str] = "motion"


ARTIFACT_TYPES: dict[str, type] = {
    c.kind: c for c in (Markers, Segments, Topology, Joints, Skeleton, Motion)
}
#: Stage that produces each artifact kind (for "which stages remain").
PRODUCED_BY = {
    "segments": "segment",
    "topology": "topology",
    "joints": "joints",
    "skeleton": "rigid",
    "motion": "ik",
}


# --------------------------------------------------------------------------- save / load


def _flatten(obj: Any, prefix: str, out: dict[str, np.ndarray], refs: dict[int, str] | None = None) -> None:
    out[prefix + "__kind__"] = np.array(obj.kind)
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        key = prefix + f.name
        if v is None:
            out[key + "__none__"] = np.array(True)
        elif dataclasses.is_dataclass(v) and refs and id(v) in refs:
            out[key + "__ref__"] = np.array(refs[id(v)])
        elif dataclasses.is_dataclass(v):
            _flatten(v, key + "/", out, refs)
        elif isinstance(v, np.ndarray):
            out[key] = v
        elif isinstance(v, dict):
            out[key + "__json__"] = np.array(json.dumps(v, default=_json_default))
        elif isinstance(v, tuple):
            out[key + "__strs__"] = np.array(list(v), dtype=str) if v else np.zeros(0, dtype="<U1")
        elif isinstance(v, (bool, int, float, str, np.integer, np.floating)):
            out[key] = np.array(v)
        else:  # pragma: no cover - programming error
            raise TypeError(f"cannot save field {key} of type {type(v).__name__}")


def _unflatten(data: dict[str, np.ndarray], prefix: str, resolve: Callable[[str], Any] | None = None) -> Any:
    k = data[prefix + "__kind__"]
    kind = str(k) if k.shape == () and k.dtype.kind == "U" else None
    if kind not in ARTIFACT_TYPES:
        raise _Invalid(f"unknown artifact kind {str(k)[:40]!r}")
    cls = ARTIFACT_TYPES[kind]
    kwargs = {}
    for f in dataclasses.fields(cls):
        key = prefix + f.name
        if key + "__none__" in data:
            kwargs[f.name] = None
        elif key + "__ref__" in data:
            if resolve is None:
                raise KeyError(f"{key} refers to another artifact")
            kwargs[f.name] = resolve(str(data[key + "__ref__"]))
        elif key + "/__kind__" in data:
            kwargs[f.name] = _unflatten(data, key + "/", resolve)
        elif key + "__json__" in data:
            if data[key + "__json__"].shape != () or data[key + "__json__"].dtype.kind != "U":
                raise _Invalid(f"{key} is not JSON text")
            kwargs[f.name] = json.loads(str(data[key + "__json__"]))
        elif key + "__strs__" in data:
            a = data[key + "__strs__"]
            if a.ndim != 1 or a.dtype.kind != "U":
                raise _Invalid(f"{key} is not a list of text")
            kwargs[f.name] = tuple(str(s) for s in a)
        elif key in data:
            v = data[key]
            if v.ndim == 0:
                v = v.item()
                if isinstance(v, bytes):
                    raise _Invalid(f"{key} holds bytes")
            kwargs[f.name] = v
        # else: a field added later with a default
    return cls(**kwargs)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def to_arrays(obj: Any, refs: dict[int, str] | None = None) -> dict[str, np.ndarray]:
    """The arrays an artifact is saved as (see :func:`to_bytes`)."""
    out: dict[str, np.ndarray] = {"__schema__": np.array(SCHEMA)}
    _flatten(obj, "", out, refs)
    return out


def arrays_bytes(out: dict[str, np.ndarray]) -> bytes:
    """The bytes of an ``.npz`` file holding ``out``."""
    buf = io.BytesIO()
    np.savez(buf, **out)
    return buf.getvalue()


def to_bytes(obj: Any, refs: dict[int, str] | None = None) -> bytes:
    """Serialise an artifact to the bytes of an ``.npz`` file.

    ``refs`` maps ``id()`` of nested artifacts to a reference string stored in
    their place (the cache stores an upstream artifact once, by its key).
    """
    out = to_arrays(obj, refs)
    buf = io.BytesIO()
    np.savez(buf, **out)
    return buf.getvalue()


class Unresolved(LookupError):
    """Raised by a ``resolve`` callback that cannot give the artifact a reference names; passed through by
    :func:`from_arrays` (the caller decides what a missing upstream means)."""


def from_arrays(data: dict[str, np.ndarray], path: str = "", resolve: Callable[[str], Any] | None = None) -> Any:
    """The artifact held by the arrays of an ``.npz`` file, checked (types, shapes, ranges, consistency).

    Raises
    ------
    InputError
        Not a mocapskel artifact, another schema, or a damaged or inconsistent one.
    Unresolved
        ``resolve`` could not give an upstream artifact.
    """
    where = path or None
    if "__schema__" not in data or "__kind__" not in data:
        raise InputError("a .npz file but not a mocapskel artifact — give a take or a file written by mocapskel", where)
    sc = data["__schema__"]
    if sc.shape != () or sc.dtype.kind not in "iu":
        raise InputError(
            f"not a mocapskel artifact (its schema is a {sc.dtype} array of shape {sc.shape}, not a number)"
            " — give a take or a file written by mocapskel", where)
    if int(sc) != SCHEMA:
        raise InputError(f"artifact schema {int(sc)} is not this version's ({SCHEMA}) — re-run from the take", where)
    try:
        obj = _unflatten(data, "", resolve)
        validate(obj)
    except Unresolved:
        raise
    except _Invalid as e:
        raise InputError(f"damaged mocapskel artifact ({e}) — re-run the stage that wrote it", where) from None
    except RecursionError:
        raise InputError("damaged mocapskel artifact (its artifacts nest too deep) — re-run the stage that wrote it", where) from None
    except Exception as e:  # a crafted file: whatever the constructors choke on
        what = f"{type(e).__name__}: {str(e).splitlines()[0][:120]}" if str(e) else type(e).__name__
        raise InputError(f"damaged mocapskel artifact ({what}) — re-run the stage that wrote it", where) from None
    return obj


# --------------------------------------------------------------------------- checks


class _Invalid(ValueError):
    """What is wrong with an artifact's content."""


#: Positions beyond this (mm, 10 km) come from no capture volume (the readers' limit).
_MAX_MM = 1e7
_STAGES_OF_MARKERS = ("read", "clean", "merge-ids")


def _need(cond: bool, msg: str) -> None:
    if not cond:
        raise _Invalid(msg)


#: A valid BVH joint name (the whole name must match).
NAME_PATTERN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def name_problem(names) -> str | None:
    """What keeps ``names`` from being BVH joint names, or None when they are.

    Valid: each matches ``[A-Za-z_][A-Za-z0-9_]*``, all unique, none a prefix
    of another (importers that match bones by prefix confuse such names).
    A skeleton's segment names are such names (the pipeline makes them so, and
    ``--names segments`` writes them as they are).
    """
    bad = [n for n in names if not NAME_PATTERN.match(n)]
    if bad:
        return f"invalid BVH joint names {bad[:5]!r}: use [A-Za-z_][A-Za-z0-9_]*"
    srt = sorted(names)
    for a, b in zip(srt, srt[1:]):
        if a == b:
            return f"duplicate BVH joint name {a!r}"
        if b.startswith(a):
            return f"BVH joint name {a!r} is a prefix of {b!r}"
    return None


def check_names(names) -> None:
    """Raise ValueError unless ``names`` are valid BVH joint names (:func:`name_problem`)."""
    problem = name_problem(names)
    if problem:
        raise ValueError(f"{problem} (see sanitize_names)")


def _array(obj: Any, name: str, shape: tuple, kinds: str = "f", *, finite: bool = False, limit: float | None = None,
           inf_ok: bool = False) -> np.ndarray:
    """Check field ``name``: an ndarray of dtype kind in ``kinds`` and ``shape`` (None: any length).

    Float fields may hold NaN (gaps), never inf; ``finite``: no NaN either; ``limit``: largest magnitude.
    """
    a = getattr(obj, name)
    what = f"{obj.kind}.{name}"
    _need(isinstance(a, np.ndarray), f"{what} is not an array")
    _need(a.dtype.kind in kinds, f"{what} holds {a.dtype} values")
    _need(a.ndim == len(shape) and all(n is None or n == m for n, m in zip(shape, a.shape)),
          f"{what} has shape {a.shape}, expected {tuple('any' if n is None else n for n in shape)}")
    if a.dtype.kind == "f" and a.size:
        _need(inf_ok or not np.isinf(a).any(), f"{what} holds infinite values")
        if finite:
            _need(not np.isnan(a).any(), f"{what} holds NaN")
        if limit is not None:
            big = np.fmax.reduce(np.abs(a), axis=None)
            _need(not big > limit, f"{what} holds values up to {big:.3g}, beyond {limit:g}")
    return a


def _scalar(obj: Any, name: str, types: tuple) -> Any:
    v = getattr(obj, name)
    _need(isinstance(v, types) and not isinstance(v, (bool, np.bool_)),
          f"{obj.kind}.{name} is a {type(v).__name__}, not a {'/'.join(t.__name__ for t in types)}")
    return v


def _strings(obj: Any, name: str, n: int | None, unique: bool = False) -> tuple:
    v = getattr(obj, name)
    _need(isinstance(v, tuple) and all(isinstance(x, str) for x in v), f"{obj.kind}.{name} is not a list of text")
    _need(n is None or len(v) == n, f"{obj.kind}.{name} has {len(v)} entries for {n}")
    _need(not unique or len(set(v)) == len(v), f"{obj.kind}.{name} repeats names")
    return v


def _nested(obj: Any, name: str, cls: type, optional: bool = False) -> Any:
    v = getattr(obj, name)
    if v is None and optional:
        return v
    _need(isinstance(v, cls), f"{obj.kind}.{name} is not a {cls.kind} artifact")
    return v


def _info(obj: Any) -> None:
    info = obj.info
    _need(isinstance(info, dict), f"{obj.kind}.info is not a JSON object")
    lists = {"warnings": str, "excluded": str, "left_out": str, "groups": list, "split": list, "per_joint": dict}
    for key, t in lists.items():
        if key in info:
            v = info[key]
            _need(isinstance(v, list) and all(isinstance(x, t) for x in v), f"{obj.kind}.info['{key}'] is not a list of {t.__name__}")
    for key in ("rms_mm", "filled_fraction"):
        if info.get(key) is not None:
            _need(isinstance(info[key], (int, float)) and not isinstance(info[key], bool), f"{obj.kind}.info['{key}'] is not a number")
    for key in ("rms_mm_per_segment", "refined", "clean", "merge_ids", "excluded_why", "renamed", "out_of_view_frames"):
        if info.get(key) is not None:
            _need(isinstance(info[key], dict), f"{obj.kind}.info['{key}'] is not a JSON object")


def _tree(parent: np.ndarray, what: str) -> None:
    """One root (-1), every other entry a valid index, and no cycle."""
    S = parent.size
    _need(np.count_nonzero(parent < 0) == 1 and (parent >= -1).all() and (parent < S).all(),
          f"{what} is not a tree (one root, parents among the segments)")
    depth = np.zeros(S, dtype=np.int64)
    cur = parent.copy()
    for _ in range(S):  # after S steps up, every walk has reached the root (-1) unless it loops
        live = cur >= 0
        if not live.any():
            return
        depth[live] += 1
        cur[live] = parent[cur[live]]
    _need(not (cur >= 0).any(), f"{what} has a cycle (a segment is its own ancestor)")


def validate(obj: Any) -> None:
    """Check an artifact and every artifact it holds: types, shapes, ranges and their consistency.

    Raises ``ValueError`` (an internal subclass) naming the first field that is wrong.
    """
    def rate_ok(o: Any) -> None:
        r = _scalar(o, "rate", (int, float, np.integer, np.floating))
        _need(MIN_RATE_HZ <= float(r) <= MAX_RATE_HZ, f"{o.kind}.rate {float(r):g} Hz is not a capture rate")

    _need(type(obj) in ARTIFACT_TYPES.values(), f"not an artifact ({type(obj).__name__})")
    chain = []
    o = obj
    while o is not None:  # the artifact and those it was computed from, last first
        chain.append(o)
        o = {"markers": None, "segments": "markers", "topology": "segments", "joints": "topology",
             "skeleton": "joints", "motion": "skeleton"}[o.kind]
        o = getattr(chain[-1], o) if o else None
        _need(o is None or type(o) in ARTIFACT_TYPES.values(), f"{chain[-1].kind} holds something that is not an artifact")
    _need(chain[-1].kind == "markers", f"the {chain[-1].kind} artifact does not carry the markers it was computed from")
    F = M = S = E = None
    for o in reversed(chain):
        _info(o)
        if o.kind == "markers":
            pts = _array(o, "points", (None, None, 3), limit=_MAX_MM)
            F, M = pts.shape[:2]
            _need(F >= 1 and M >= 1, f"markers.points has shape {pts.shape}: no frames or no markers")
            _strings(o, "labels", M, unique=True)
            rate_ok(o)
            for name in ("units", "source", "stage"):
                _scalar(o, name, (str,))
            _need(o.stage in _STAGES_OF_MARKERS, f"markers.stage {o.stage!r} is none of {', '.join(_STAGES_OF_MARKERS)}")
        elif o.kind == "segments":
            _nested(o, "markers", Markers)
            g = _array(o, "group", (M,), "iu")
            _need(bool((g >= -1).all()), "segments.group holds values below -1")
            S = o.n_segments
            _need(set(np.unique(g[g >= 0]).tolist()) == set(range(S)), "segments.group skips segment numbers")
            _array(o, "dist_std", (M, M))
            _array(o, "eigvals", (None,))
        elif o.kind == "topology":
            _nested(o, "segments", Segments)
            _need(S >= 2, f"topology of {S} segment(s)")
            edges = _array(o, "edges", (S - 1, 2), "iu")
            _array(o, "cost", (S - 1,))
            _array(o, "pair_cost", (S, S), inf_ok=True)
            root = _scalar(o, "root", (int, np.integer))
            _need(0 <= root < S, f"topology.root {root} is not a segment")
            _need(bool((edges >= 0).all() and (edges < S).all()), "topology.edges name segments that do not exist")
            parent = np.full(S, -1, dtype=np.int64)
            _need(np.unique(edges[:, 1]).size == S - 1 and root not in edges[:, 1].tolist(),
                  "topology.edges do not give every segment but the root one parent")
            parent[edges[:, 1]] = edges[:, 0]
            _tree(parent, "topology.edges")
            E = S - 1
        elif o.kind == "joints":
            _nested(o, "topology", Topology)
            shape = (F, E, 3)
            _array(o, "centres", shape, limit=_MAX_MM)
            _strings(o, "method", E)
            _array(o, "residual", (E,))
            if o.alt_centres is not None:
                _array(o, "alt_centres", shape, limit=_MAX_MM)
        elif o.kind == "skeleton":
            has_joints = _nested(o, "joints", Joints, optional=True) is not None
            names = _strings(o, "names", S if has_joints else None, unique=True)
            S = len(names)
            _need(S >= 1, "skeleton without segments")
            problem = name_problem(names)
            _need(problem is None, f"skeleton.names: {problem}")
            parent = _array(o, "parent", (S,), "iu")
            _tree(parent.astype(np.int64), "skeleton.parent")
            _array(o, "origin", (S, 3), finite=True, limit=_MAX_MM)
            _array(o, "end_site", (S, 3), finite=True, limit=_MAX_MM)
            _array(o, "bone_length", (S,), limit=_MAX_MM)
            _array(o, "noise", (S,), limit=_MAX_MM)
            labels = _strings(o, "labels", M if has_joints else None, unique=True)
            M = len(labels)
            ms = _array(o, "marker_segment", (M,), "iu")
            _need(bool(((ms >= -1) & (ms < S)).all()), "skeleton.marker_segment names segments that do not exist")
            _array(o, "marker_local", (M, 3), limit=_MAX_MM)
            rest = _scalar(o, "rest_frame", (int, np.integer))
            _need(rest >= 0 and (F is None or rest < F), f"skeleton.rest_frame {rest} is outside the take")
            poses = (o.pose_frames, o.pose_rot, o.pose_root)
            _need(all(p is None for p in poses) or all(p is not None for p in poses), "skeleton poses are incomplete")
            if o.pose_frames is not None:
                pf = _array(o, "pose_frames", (None,), "iu")
                K = pf.size
                _need(F is None or bool(((pf >= 0) & (pf < F)).all()), "skeleton.pose_frames are outside the take")
                _array(o, "pose_rot", (K, S, 3, 3), limit=1.0 + 1e-6)
                _array(o, "pose_root", (K, 3), limit=_MAX_MM)
        elif o.kind == "motion":
            _nested(o, "skeleton", Skeleton)
            rp = _array(o, "root_pos", (None, 3), limit=_MAX_MM)
            _need(rp.shape[0] >= 1 and (F is None or rp.shape[0] == F), f"motion of {rp.shape[0]} frames for a take of {F}")
            Fm = rp.shape[0]
            _array(o, "rot", (Fm, S, 3, 3), limit=1.0 + 1e-6)
            _array(o, "residual", (Fm, M))
            rate_ok(o)
            _scalar(o, "source", (str,))


def markers_of(obj: Any) -> Markers:
    """The Markers an artifact was computed from."""
    while not isinstance(obj, Markers):
        obj = {
            "segments": lambda o: o.markers,
            "topology": lambda o: o.segments,
            "joints": lambda o: o.topology,
            "skeleton": lambda o: o.joints,
            "motion": lambda o: o.skeleton,
        }[obj.kind](obj)
        if obj is None:
            raise ValueError("artifact carries no markers")
    return obj
