"""Marker files in and out: the ``read`` stage of the pipeline.

:func:`read_markers` turns a C3D or TRC file into :class:`~mocapskel.artifacts.Markers`:
points ``(F, M, 3)`` float64 in mm with NaN for gaps, unique clean labels, the
rate and the source units. Computed points that files often store next to
the markers (joint centres, Plug-in-Gait outputs, ``V*`` virtual points) are
dropped unless asked for. :func:`write_markers` writes C3D or TRC.
"""
from __future__ import annotations

import fnmatch
import logging
import os
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..artifacts import Markers
from ..errors import InputError, UsageError
from .c3d import read_c3d
from .c3d_write import write_c3d
from .raw import RawTake, check_rate
from .trc import read_trc, write_trc

__all__ = [
    "COMPUTED_POINT_PATTERNS",
    "COMPUTED_DESCRIPTION_PATTERNS",
    "computed_reason",
    "read_markers",
    "write_markers",
]


#: Coordinates beyond this (mm, 10 km) cannot come from a capture volume: the take is refused.
MAX_COORDINATE_MM = 1e7
log = logging.getLogger(__name__)

#: Labels of points that are computed by the capture software rather than seen
#: by the cameras, as ``(regular expression, reason)``. A label (without its
#: ``Subject:`` prefix, case-sensitive) that matches any of them is left out by
#: :func:`read_markers` unless an ``include`` pattern names it. The list is
#: deliberately conservative: a real marker must never match.
#:
#: - Vicon Plug-in-Gait model outputs stored as points: ``LHipAngles``,
#:   ``RKneeMoment``, ``LAnklePower``, ``LGroundReactionForce`` ...
#: - Plug-in-Gait bone points: segment code + O/A/L/P (origin, anterior,
#:   lateral, proximal): ``PELO PELA PELL PELP``, ``LFEO``, ``RTIA``,
#:   ``HEDO``, ``TRXL``, ``LHUP`` ...
#: - joint centres: ``LHJC``, ``RKJC``, ``L_AJC``, ``LHipJC`` (anything ending in JC);
#: - centre of mass: ``CentreOfMass``, ``CentreOfMassFloor``, ``CenterOfMass``;
#: - virtual points named ``V_...`` (Vicon, Motion Analysis Cortex);
#: - Motion Analysis / Helen Hayes virtual points ``VMID``, ``VPEL`` and
#:   ``V`` + side + two letters (``VRKN``, ``VLHI``, ``VRTO`` ...). ``VSAC``
#:   (the real sacral marker of the Helen Hayes set) does not match.
#:
#: Not computed (kept): unlabelled trajectories (``*12``, ``U3``, ``M001``),
#: OpenSim ``V.Sacral``.
COMPUTED_POINT_PATTERNS: tuple[tuple[str, str], ...] = (
    (r"^\w+(?:Angles?|Forces?|Moments?|Powers?)$", "model output (angle, force, moment or power)"),
    (r"^(?:PEL|HED|TRX|[LR](?:FE|TI|TIB|FO|TO|CL|HU|RA|HN))[OALP]$", "Plug-in-Gait bone point"),
    (r"JC$", "joint centre"),
    (r"^(?:Centre|Center)OfMass", "centre of mass"),
    (r"^V_", "virtual point (V_ prefix)"),
    (r"^V(?:MID|PEL|[LR][A-Z]{2})$", "Motion Analysis virtual point"),
)

#: Point descriptions (C3D ``POINT:DESCRIPTIONS``) that mark a computed point,
#: as ``(regular expression, reason)``: Motion Analysis Cortex describes its
#: virtual points as ``V_R.Knee_JC`` and the like.
COMPUTED_DESCRIPTION_PATTERNS: tuple[tuple[str, str], ...] = (
    (r"^V_", "virtual point (description starts with V_)"),
    (r"(?i)\bvirtual\b", "virtual point (description says so)"),
)

_LABEL_RES = tuple((re.compile(p), why) for p, why in COMPUTED_POINT_PATTERNS)
_DESC_RES = tuple((re.compile(p), why) for p, why in COMPUTED_DESCRIPTION_PATTERNS)
_READERS = (".c3d", ".trc")


def computed_reason(label: str, description: str = "") -> str | None:
    """Why a point looks computed rather than seen, or None for a real marker.

    Parameters
    ----------
    label : str
        The label without whitespace and without a ``Subject:`` prefix.
    description : str
        The C3D point description, if any.
    """
    for rx, why in _LABEL_RES:
        if rx.search(label):
            return why
    if description:
        for rx, why in _DESC_RES:
            if rx.search(description.strip()):
                return why
    return None


# --------------------------------------------------------------------------- labels


@dataclass
class _Labels:
    final: list[str]  # unique labels
    base: list[str]  # stripped, without namespace, before renaming
    original: list[str]  # stripped, as in the file (with namespace)
    renamed: dict[str, str]
    namespaces: list[str]
    warnings: list[str]


def _clean_labels(raw: Sequence[str]) -> _Labels:
    """Strip, remove ``Subject:`` prefixes, name empty labels, make labels unique."""
    original = [str(s).replace("\x00", "").strip() for s in raw]
    warnings: list[str] = []
    split = [s.split(":", 1) if ":" in s and s.split(":", 1)[1].strip() else None for s in original]
    prefixes = sorted({p[0].strip() for p in split if p is not None})
    base = original
    namespaces: list[str] = []
    if prefixes:
        stripped = [p[1].strip() if p is not None else s for s, p in zip(original, split)]
        dup_before = sum(c - 1 for c in Counter(s for s in original if s).values())
        dup_after = sum(c - 1 for c in Counter(s for s in stripped if s).values())
        if dup_after <= dup_before:
            base, namespaces = stripped, prefixes
        else:
            warnings.append(
                f"labels keep their prefixes {prefixes}: without them several subjects would share marker names"
            )
    final = list(base)
    renamed: dict[str, str] = {}
    taken = {s for s in base if s}
    for i, s in enumerate(base):
        if not s:
            name = f"M{i + 1:03d}"
            k = 2
            while name in taken:
                name = f"M{i + 1:03d}_{k}"
                k += 1
            taken.add(name)
            final[i] = name
            renamed[name] = ""
    seen: set[str] = set()
    for i, s in enumerate(final):
        if s in seen:
            k = 2
            while f"{s}_{k}" in taken:
                k += 1
            new = f"{s}_{k}"
            taken.add(new)
            renamed[new] = s
            final[i] = new
        seen.add(final[i])
    return _Labels(final, list(base), original, renamed, namespaces, warnings)


def _matches(patterns: Sequence[str], *names: str) -> bool:
    return any(fnmatch.fnmatchcase(n, p) for p in patterns for n in names if n)


# --------------------------------------------------------------------------- reading


def _check_input_path(path: str | os.PathLike) -> tuple[Path, str]:
    p = Path(path)
    spath = str(path)
    if not p.exists():
        raise InputError("no such file — check the path", spath)
    if p.is_dir():
        raise InputError("is a folder, not a marker file — give a .c3d or .trc file", spath)
    ext = p.suffix.lower()
    if ext not in _READERS:
        what = f"'{p.suffix}'" if p.suffix else "no extension"
        raise InputError(f"unknown marker file type ({what}) — give a .c3d or .trc file", spath)
    try:
        size = p.stat().st_size
    except OSError as e:  # pragma: no cover - races, permissions
        raise InputError(f"cannot read ({e.strerror or e}) — check the file's permissions", spath) from None
    if not p.is_file():
        raise InputError("not a regular file — give a .c3d or .trc file", spath)
    if size == 0:
        raise InputError(f"empty file — export the take again as {ext[1:].upper()} (or C3D/TRC)", spath)
    return p, ext


def read_markers(
    path: str | os.PathLike,
    *,
    exclude: Sequence[str] = (),
    include: Sequence[str] = (),
) -> Markers:
    """Read a C3D or TRC marker file.

    Parameters
    ----------
    path : str or PathLike
        ``.c3d`` or ``.trc`` file (extension case-insensitive).
    exclude : sequence of str
        fnmatch patterns (case-sensitive); markers whose label matches are
        left out. A pattern is matched against the final label and against
        the label as written in the file (so ``"boite:*"`` works too).
        Exclusion wins over inclusion.
    include : sequence of str
        fnmatch patterns; when given, only markers that match are kept. A
        marker named by an include pattern is kept even when it looks
        computed (see :data:`COMPUTED_POINT_PATTERNS`).

    Returns
    -------
    Markers
        ``points`` (F, M, 3) float64 in mm, NaN for gaps (non-finite values,
        C3D negative residuals and exact (0, 0, 0) included); ``labels``
        unique (whitespace and a ``Subject:`` prefix removed, repeats
        suffixed ``_2``, ``_3``, empty labels named ``M001``...); ``rate``;
        ``units`` of the source; ``source`` the file name; ``stage="read"``.
        ``info`` holds ``file, format, frames, markers, markers_in_file,
        rate, units, gaps_fraction, nonfinite, excluded, excluded_why,
        renamed, namespace, never_seen, warnings``.

    Raises
    ------
    InputError
        Missing file, folder, unknown extension, empty, unreadable or damaged
        file, or no marker data left (0 frames, 0 markers, every coordinate
        missing).
    """
    p, ext = _check_input_path(path)
    spath = str(path)
    raw = read_c3d(path) if ext == ".c3d" else read_trc(path)
    exclude = (exclude,) if isinstance(exclude, str) else tuple(exclude)
    include = (include,) if isinstance(include, str) else tuple(include)
    return _finish(raw, p.name, spath, exclude=exclude, include=include)


def _finish(raw: RawTake, name: str, spath: str, *, exclude: tuple[str, ...], include: tuple[str, ...]) -> Markers:
    pts = raw.points
    if pts.ndim != 3 or pts.shape[2] != 3:  # pragma: no cover - reader bug
        raise ValueError(f"reader returned points of shape {pts.shape}")
    F, M0 = pts.shape[:2]
    if F == 0:
        raise InputError("no marker data (0 frames) — export the take again with its marker trajectories", spath)
    if M0 == 0:
        raise InputError("no marker data (0 markers) — export the take again with its marker trajectories", spath)
    check_rate(raw.rate, spath)
    if pts.dtype != np.float64 or not pts.flags.writeable:
        pts = np.array(pts, dtype=np.float64)
    warnings = list(raw.warnings)

    # ----- gaps: any non-finite coordinate makes the whole sample a gap
    # (one pass per coordinate: reducing over a last axis of length 3 is several times slower)
    finite = np.isfinite(pts[..., 0]) & np.isfinite(pts[..., 1]) & np.isfinite(pts[..., 2])  # (F, M)
    nonfinite = 0
    if not finite.all():
        # in place and without index arrays (a passive take is mostly gaps)
        inf = np.isinf(pts[..., 0]) | np.isinf(pts[..., 1]) | np.isinf(pts[..., 2])
        nonfinite = int(np.count_nonzero(inf))
        np.copyto(pts, np.nan, where=~finite[..., None])
        del inf
    if nonfinite:
        warnings.append(f"{nonfinite} samples with infinite coordinates read as gaps")

    # ----- labels
    lab = _clean_labels(raw.labels)
    warnings.extend(lab.warnings)
    desc = raw.descriptions if raw.descriptions is not None and len(raw.descriptions) == M0 else [""] * M0
    declared = {k.split(":", 1)[-1].strip() if ":" in k else k: v for k, v in raw.computed.items()}
    declared.update(raw.computed)

    keep = np.ones(M0, dtype=bool)
    why: dict[str, str] = {}
    for i in range(M0):
        final, base, orig = lab.final[i], lab.base[i], lab.original[i]
        named = _matches(include, final, orig)
        if include and not named:
            keep[i], why[final] = False, "not matched by an include pattern"
            continue
        if exclude and _matches(exclude, final, orig):
            keep[i], why[final] = False, "matched by an exclude pattern"
            continue
        reason = declared.get(orig) or declared.get(base) or computed_reason(base, desc[i])
        if reason and not named:
            keep[i], why[final] = False, f"computed point: {reason}"
    for pat in include:
        if not any(_matches((pat,), lab.final[i], lab.original[i]) for i in range(M0)):
            warnings.append(f"include pattern {pat!r} matches no label")
    for pat in exclude:
        if not any(_matches((pat,), lab.final[i], lab.original[i]) for i in range(M0)):
            warnings.append(f"exclude pattern {pat!r} matches no label")

    labels = [s for s, k in zip(lab.final, keep) if k]
    if not labels:
        if include or exclude:
            raise InputError(
                f"no marker data left: the include/exclude patterns leave none of the {M0} labels — check the patterns",
                spath,
            )
        raise InputError(
            f"no marker data: all {M0} points look computed ({', '.join(list(why)[:5])}...) — "
            "name the ones to keep with an include pattern",
            spath,
        )
    if not keep.all():
        pts = pts[:, keep]
        finite = finite[:, keep]
    M = len(labels)
    seen_any = finite.any(axis=0)
    if not seen_any.any():
        raise InputError(
            f"no marker data: every coordinate of the {M} markers is missing — export the take again with its trajectories",
            spath,
        )
    biggest = float(max(np.fmax.reduce(pts, axis=None), -np.fmin.reduce(pts, axis=None)))  # gaps are NaN: skipped
    if biggest > MAX_COORDINATE_MM:
        raise InputError(
            f"coordinates up to {biggest:.3g} mm — beyond any capture volume ({MAX_COORDINATE_MM:g} mm);"
            " check the file's units (POINT:UNITS / Units) or export it again",
            spath,
        )
    excluded = [s for s, k in zip(lab.final, keep) if not k]
    never_seen = [s for s, v in zip(labels, seen_any) if not v]
    kept = set(labels)
    renamed = {k: v for k, v in lab.renamed.items() if k in kept}
    for w in warnings:
        log.warning("%s: %s", name, w)
    info = {
        "file": name,
        "format": raw.info.get("format", Path(name).suffix.lower().lstrip(".")),
        "frames": int(F),
        "markers": int(M),
        "markers_in_file": int(M0),
        "rate": float(raw.rate),
        "units": raw.units,
        "gaps_fraction": float(1.0 - np.count_nonzero(finite) / finite.size),
        "nonfinite": nonfinite,
        "excluded": excluded,
        "excluded_why": {k: why[k] for k in excluded},
        "renamed": renamed,
        "namespace": lab.namespaces,
        "never_seen": never_seen,
        "warnings": warnings,
        **{k: v for k, v in raw.info.items() if k != "format"},
    }
    return Markers(
        points=pts,
        labels=tuple(labels),
        rate=float(raw.rate),
        units=raw.units,
        source=name,
        stage="read",
        info=info,
    )


# --------------------------------------------------------------------------- writing


def write_markers(path: str | os.PathLike, markers: Markers) -> None:
    """Write markers as C3D or TRC (by extension, case-insensitive), atomically.

    Parameters
    ----------
    path : str or PathLike
        ``.c3d`` (float, mm) or ``.trc`` (tab-separated, mm, 6 decimals).
    markers : Markers
        ``points`` (F, M, 3) in mm, NaN for gaps.

    Raises
    ------
    UsageError
        Unknown extension, or the output folder does not exist.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in _READERS:
        what = f"'{p.suffix}'" if p.suffix else "no extension"
        raise UsageError(f"unknown marker file type ({what}) — name the output .c3d or .trc", str(path))
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise UsageError("the output folder does not exist — create it first", str(path))
    if p.is_dir():
        raise UsageError("is a folder — give a file name ending in .c3d or .trc", str(path))
    if ext == ".c3d":
        write_c3d(p, markers)
    else:
        write_trc(p, markers)
