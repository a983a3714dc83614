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
import os
import zipfile
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np

from .errors import InputError

SCHEMA = 1


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
               same centres with the JMV-placed joints taken from Hang's
               framework instead (see the joints stage); None when no joint
               was placed by JMV.
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
    kind = str(data[prefix + "__kind__"])
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
            kwargs[f.name] = json.loads(str(data[key + "__json__"]))
        elif key + "__strs__" in data:
            kwargs[f.name] = tuple(str(s) for s in data[key + "__strs__"])
        elif key in data:
            v = data[key]
            if v.ndim == 0:
                v = v.item()
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


def to_bytes(obj: Any, refs: dict[int, str] | None = None) -> bytes:
    """Serialise an artifact to the bytes of an ``.npz`` file.

    ``refs`` maps ``id()`` of nested artifacts to a reference string stored in
    their place (the cache stores an upstream artifact once, by its key).
    """
    out: dict[str, np.ndarray] = {"__schema__": np.array(SCHEMA)}
    _flatten(obj, "", out, refs)
    buf = io.BytesIO()
    np.savez(buf, **out)
    return buf.getvalue()


def save(obj: Any, path: str | os.PathLike, refs: dict[int, str] | None = None) -> None:
    """Save an artifact to ``path`` atomically (temporary file, then rename)."""
    from .io.atomic import atomic_write_bytes

    atomic_write_bytes(path, to_bytes(obj, refs))


def load(path: str | os.PathLike, resolve: Callable[[str], Any] | None = None) -> Any:
    """Load an artifact saved by :func:`save`. Raises InputError when it is not one.

    ``resolve`` turns a stored reference back into the artifact (see :func:`to_bytes`).
    """
    try:  # open the file here: np.load leaks its own handle when the zip is damaged (ResourceWarning)
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(f"not a readable mocapskel artifact ({e}) — re-run the stage that wrote it", str(path)) from None
    if "__schema__" not in data or "__kind__" not in data:
        raise InputError("a .npz file but not a mocapskel artifact — give a take or a file written by mocapskel", str(path))
    if int(data["__schema__"]) != SCHEMA:
        raise InputError(
            f"artifact schema {int(data['__schema__'])} is not this version's ({SCHEMA}) — re-run from the take", str(path)
        )
    try:
        return _unflatten(data, "", resolve)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"damaged mocapskel artifact ({e}) — re-run the stage that wrote it", str(path)) from None


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
