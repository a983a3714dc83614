"""C3D marker files: read the 3D points.

Reading is done in two steps:

1. :func:`read_layout` parses the 512-byte header and the parameter section
   with a small pure-Python parser that checks every record. ezc3d 1.7 crashes
   (segmentation fault) or loops forever on some damaged parameter sections,
   and silently returns fewer frames for a truncated file, so nothing reaches
   ezc3d before the header, the parameters and the size of the data block
   have been checked here. This parser also keeps the values ezc3d rewrites
   while reading (the header's frame range and rate, ``POINT:FRAMES``,
   ``POINT:LONG_FRAMES``, ``TRIAL:ACTUAL_*_FIELD``).
2. The points themselves come from a direct numpy read of the data block
   (``engine="numpy"``, the default) or from ezc3d (``engine="ezc3d"``).
   numpy reads the checked layout in about a fifteenth of ezc3d's time and
   with little more memory than the points themselves: ezc3d builds a C++
   object of about 150 bytes per point sample (a passive take of 450 labels
   over 60,000 frames would need some 4 GB), and on a 60,000-frame take of
   48 markers its read alone was a fifth of the whole fit. The two engines
   agree exactly on every file of the real-data collection
   (``tests/test_io_realdata.py``) and on integer, DEC and MIPS files built
   byte by byte (``tests/test_io_c3d.py``); ezc3d stays the reference they
   are checked against.

Timings (2-core machine, ezc3d 1.7.x, best of 10):

- ``cmu/135_02.c3d`` (5,202 frames x 41 markers, no analogs):
  ``ezc3d.c3d(path, extract_forceplat_data=False)["data"]["points"]`` 0.092 s;
  the SWIG object ``ezc3d.ezc3d.c3d(path)`` + ``get_points()`` +
  ``get_point_residuals()`` 0.088 s, of which parsing is 0.076 s. ezc3d 1.7
  has no option to skip analogs (``Options`` only has ``ignoreBadFormatting``
  and ``keepParametersTrailingSpaces``); going through the SWIG object skips
  the numpy copies of analogs, camera masks and rotations that the Python
  wrapper always makes (16 % faster on a synthetic take with 64 analog
  channels at 10x the point rate: 0.27 s against 0.32 s). The residuals are
  not fetched either: ezc3d has already set the points they mark as missing
  to NaN.
- ``engine="numpy"`` (a memory map of the data block, checked layout) reads
  the same file in 0.005 s.
- 60,000 frames x 48 markers, float, no analogs: SWIG path 1.3-1.8 s and
  about 590 MB peak (ezc3d keeps one C++ object per point and frame); the
  Python wrapper 2.6 s (1.6 s with ``extract_forceplat_data=False``);
  ``engine="numpy"`` 0.10-0.15 s and little more memory than the output array.

ezc3d 1.7 stores at most 65,535 frames in ``POINT:FRAMES`` when it writes and
reads at most that many back. When a file holds more frames than ezc3d
returned (declared by ``POINT:LONG_FRAMES`` or ``TRIAL:ACTUAL_END_FIELD``, or
found from the size of the data block when ``POINT:FRAMES`` is saturated),
the remaining frames are read from the data block with numpy.
"""
from __future__ import annotations

import re

import os
from typing import Literal

import numpy as np

from ..errors import InputError
from ..solvers.parallel import run_blocks
from .c3d_layout import _SATURATED, _TO_USER, C3DLayout, _decode_float32, read_layout
from .raw import RawTake, check_rate, unit_factor

__all__ = ["read_c3d"]


# --------------------------------------------------------------------------- point data


def _read_frames_numpy(path: str | os.PathLike, lay: C3DLayout, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``[start, stop)`` of the point block, read straight from the file in blocks of frames.

    Each block is decoded into the preallocated outputs, so that the memory
    needed is the outputs and one block (a memory map of a whole long take
    would add its pages to the process, and a full float32 copy its size).

    Returns
    -------
    xyz : (n, P, 3) float64 ndarray
        Coordinates in the file's units (integer data already multiplied by
        the scale factor).
    residual : (n, P) float32 ndarray
        The fourth word of every point; negative means "not seen".
    """
    n, P = stop - start, lay.n_points
    if n <= 0 or P == 0:
        return np.zeros((max(n, 0), P, 3)), np.zeros((max(n, 0), P), dtype=np.float32)
    words = lay.bytes_per_frame // (4 if lay.is_float else 2)
    offset = (lay.data_start - 1) * 512 + start * lay.bytes_per_frame
    big = lay.processor == "mips"
    if lay.is_float:
        dt = np.dtype(">f4" if big else "<f4") if lay.processor != "dec" else np.dtype("<u4")
    else:
        dt = np.dtype(">i2" if big else "<i2")
    xyz = np.empty((n, P, 3))
    residual = np.empty((n, P), dtype=np.float32)
    step = max(1, (4 << 20) // max(lay.bytes_per_frame, 1))  # about 4 MB of the file per block

    def read_block(lo: int) -> None:
        # blocks are read and decoded side by side on the cores, each from its own file handle into its
        # own frames; a short block raises as a read in order would (the first short one, in order)
        k = min(step, n - lo)
        with open(path, "rb") as f:
            f.seek(offset + lo * lay.bytes_per_frame)
            block = np.fromfile(f, dtype=dt, count=k * words)
        if block.size != k * words:
            raise OSError(f"the data block ends after {lo + block.size // words} of {n} frames")
        block = block.reshape(k, words)[:, : 4 * P]
        if lay.is_float and lay.processor == "dec":
            block = _decode_float32(np.ascontiguousarray(block).tobytes(), "dec").reshape(k, 4 * P)
        block = block.reshape(k, P, 4)
        with np.errstate(invalid="ignore"):  # a signalling NaN in float data: a coordinate not seen
            xyz[lo : lo + k] = block[..., :3]
        residual[lo : lo + k] = block[..., 3]

    run_blocks(read_block, range(0, n, step))
    if not lay.is_float:
        xyz *= abs(lay.scale)
    return xyz, residual


def _read_frames_ezc3d(path: str | os.PathLike) -> np.ndarray:
    """All frames ezc3d returns: ``(F, P, 3)`` coordinates, NaN where the residual is negative.

    ezc3d itself sets a point with a negative residual to NaN while it reads
    (``Point``'s constructor; missing markers have read as NaN since before
    1.5, the oldest version mocapskel accepts), so the residuals are not asked
    for: ``get_point_residuals`` would copy another (F, P) array out of
    ezc3d's per-point objects (about 5 % of the read of a long take). The
    tests check the two engines against each other on files with negative
    residuals.
    """
    from ezc3d import ezc3d as _swig  # the SWIG layer: skips analog/rotation/camera-mask copies

    c = _swig.c3d(str(path))
    raw = c.get_points()  # (4, P, F) float64, scale already applied
    del c
    return np.ascontiguousarray(raw[:3].transpose(2, 1, 0))


#: POINT parameters that list the labels of points a model computed (Vicon's typed groups: model outputs
#: stored as points), read whether or not ``POINT:TYPE_GROUPS`` names them.
TYPED_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")
#: Other POINT parameters whose name says their labels are virtual or modelled points.
_VIRTUAL_GROUP = re.compile(r"VIRTUAL|MODELL?ED")
#: POINT parameters that never list computed points, whatever ``POINT:TYPE_GROUPS`` says.
_NOT_TYPED = frozenset({"LABELS", "DESCRIPTIONS", "UNITS", "USED", "TYPE_GROUPS"})


def typed_groups(lay) -> list[str]:
    """The POINT parameters of the layout ``lay`` that list computed points' labels: the typed groups
    above, every string parameter that ``POINT:TYPE_GROUPS`` names (Vicon lists its type groups there, by
    name or as name/parameter pairs) but one of markers, and any named virtual or modelled."""
    have = lay.params.get("POINT", {})
    out = list(TYPED_GROUPS)
    named = [n.strip().upper() for n in lay.string_series("POINT", "TYPE_GROUPS")]
    for n in named + sorted(have):
        if n in out or n in _NOT_TYPED or n not in have or n[-1:].isdigit() and n.rstrip("0123456789") in have:
            continue
        if "MARKER" in n and not _VIRTUAL_GROUP.search(n):
            continue  # a group of markers is what the cameras saw
        if n in named or _VIRTUAL_GROUP.search(n):
            out.append(n)
    return out


def read_c3d(path: str | os.PathLike, *, engine: Literal["auto", "ezc3d", "numpy"] = "auto") -> RawTake:
    """Read the 3D points of a C3D file.

    Parameters
    ----------
    path : str or PathLike
        The C3D file.
    engine : {"auto", "ezc3d", "numpy"}
        Who reads the point block once the header and parameters have been
        checked: a numpy read of the data block, or ezc3d (about 15x slower,
        with a C++ object per point sample); "auto" (the default) is numpy.
        Files written by a MIPS (big-endian) processor, which ezc3d 1.7
        refuses, are always read with numpy.

    Returns
    -------
    RawTake
        ``points`` (F, M, 3) float64 in mm with NaN where the marker is not
        seen (negative residual, or exactly (0, 0, 0)); labels from
        ``POINT:LABELS``, ``LABELS2`` ...; descriptions; labels the file lists
        as computed (``POINT:ANGLES`` ...); rate; source units; warnings.

    Raises
    ------
    InputError
        Garbage, a damaged or truncated file, or one without points.
    """
    spath = str(path)
    lay = read_layout(path)
    warnings: list[str] = []

    # ----- rate, checked before anything is sized by it
    prate = lay.first_float("POINT", "RATE")
    hrate = lay.header_rate
    if prate is not None and (prate > 0 or not np.isfinite(prate)):
        rate = check_rate(prate, spath, "POINT:RATE", _TO_USER)
        if np.isfinite(hrate) and hrate > 0 and abs(hrate - prate) > 1e-4 * prate:
            warnings.append(f"header rate {hrate:g} Hz disagrees with POINT:RATE {prate:g} Hz; using POINT:RATE")
    elif hrate > 0 or not np.isfinite(hrate):
        rate = check_rate(hrate, spath, "the header's frame rate", _TO_USER)
        if prate is not None:
            warnings.append(f"POINT:RATE is {prate:g}; using the header rate {hrate:g} Hz")
    else:
        raise InputError(f"no frame rate (POINT:RATE and the header rate are 0) — {_TO_USER}", spath)

    P = lay.n_points
    declared, source, saturated = lay.declared_frames()
    if P == 0:
        raise InputError("no marker data (the C3D file has no 3D points) — export the take again with its marker trajectories", spath)
    if declared <= 0:
        raise InputError("no marker data (the C3D file declares 0 frames) — export the take again with its marker trajectories", spath)
    in_file = lay.frames_in_file
    if in_file == 0:
        raise InputError(f"truncated C3D file (it ends before its first frame; {declared} declared) — {_TO_USER}", spath)
    if saturated:  # 65535 in a 16-bit field: the data block says how many frames there are
        if in_file < _SATURATED:
            raise InputError(f"truncated C3D file ({in_file} of {declared} frames present) — {_TO_USER}", spath)
        if not lay.ends_on_frame():  # the count cannot say how many frames there were: a cut last frame shows the cut
            raise InputError(
                f"truncated C3D file (its data ends inside frame {in_file + 1}; the 16-bit frame count is saturated,"
                f" so the file cannot say how many frames it had) — {_TO_USER}", spath
            )
        target = in_file
    elif in_file < declared:
        if not lay.ends_on_frame():
            raise InputError(
                f"truncated C3D file ({in_file} of {declared} frames present, the last one cut) — {_TO_USER}", spath
            )
        target = in_file  # the file ends cleanly after its last frame: the frame count lies
    else:
        target = declared

    # ----- points
    if not np.isfinite(lay.scale):  # its sign says integer or float data; its size scales integer data
        raise InputError(f"damaged C3D file (POINT:SCALE is {lay.scale}, not a number a point can be scaled by)"
                         f" — {_TO_USER}", spath)
    if engine == "auto":
        engine = "numpy"
    if engine == "ezc3d" and lay.processor == "mips":
        engine = "numpy"  # ezc3d 1.7: "MIPS processor type not supported yet"
    residual: np.ndarray | None = None  # (F, P); None: negative residuals are NaN already (ezc3d)
    try:
        if engine == "ezc3d":
            xyz = _read_frames_ezc3d(path)
        elif engine == "numpy":
            xyz, residual = _read_frames_numpy(path, lay, 0, target)
        else:
            raise ValueError(f"unknown C3D engine {engine!r}")
    except (RuntimeError, OSError, IndexError, MemoryError) as e:
        raise InputError(f"unreadable C3D file ({str(e).splitlines()[0] if str(e) else type(e).__name__}) — {_TO_USER}", spath) from None
    except ValueError as e:
        if engine not in ("ezc3d", "numpy"):  # (auto is resolved above)
            raise
        raise InputError(f"unreadable C3D file ({e}) — {_TO_USER}", spath) from None
    if xyz.shape[1] != P:
        raise InputError(f"damaged C3D file (POINT:USED is {P} but {xyz.shape[1]} points were read) — {_TO_USER}", spath)
    if xyz.shape[0] > target:
        xyz = xyz[:target]
        residual = residual[:target] if residual is not None else None
    F = xyz.shape[0]
    if F < target:
        if F != _SATURATED:  # ezc3d and this parser disagree about the layout
            raise InputError(f"damaged C3D file ({F} frames read where {target} are declared) — {_TO_USER}", spath)
        txyz, tres = _read_frames_numpy(path, lay, F, target)  # ezc3d stops at 65535 frames
        xyz = np.concatenate([xyz, txyz])
        residual = np.concatenate([residual if residual is not None else np.zeros((F, P), dtype=np.float32), tres])
        del txyz, tres
    if saturated:  # trailing frames of zero bytes past frame 65535 are block padding, not frames
        past = ~(xyz[_SATURATED:] != 0).any(axis=(1, 2))  # a NaN (ezc3d's negative residual) is not padding
        if residual is not None:
            past &= ~(residual[_SATURATED:] != 0).any(axis=1)
        n_pad = int(np.argmin(past[::-1])) if not past.all() else len(past)
        if n_pad:
            xyz = xyz[: len(xyz) - n_pad]
            residual = residual[: len(residual) - n_pad] if residual is not None else None
    F = xyz.shape[0]
    if F > _SATURATED:
        how = "is saturated at 65535; the rest found from the size of the data block" if saturated else f"says {declared}"
        warnings.append(f"{F} frames, more than 16-bit frame counts hold ({source} {how})")
    claims = {}
    if not saturated and declared != F:
        claims[source] = declared
    if lay.header_frames and lay.header_frames != F and lay.header_last_frame != _SATURATED:
        claims["header frame range"] = lay.header_frames
    if claims:
        said = ", ".join(f"{k} {v}" for k, v in claims.items())
        warnings.append(f"the file declares a different frame count ({said}) than its data block holds ({F}); using the data")

    # ----- gaps: negative residual, or exactly (0, 0, 0)
    gap = (xyz[..., 0] == 0) & (xyz[..., 1] == 0) & (xyz[..., 2] == 0)
    if residual is not None:
        gap |= residual < 0
    np.copyto(xyz, np.nan, where=gap[..., None])  # (a boolean index would build index arrays as long as the gaps)

    # ----- units
    units_list = [u for u in lay.string_series("POINT", "UNITS") if u.strip()]
    if not units_list:
        units, factor = "mm", 1.0
        warnings.append("POINT:UNITS is missing or empty; assuming mm")
    else:
        names = {unit_factor(u)[0] for u in units_list}
        units, factor = unit_factor(units_list[0])
        if len(names) > 1:
            warnings.append(f"POINT:UNITS lists several units {sorted(names)}; using {units!r}")
        if factor is None:
            warnings.append(f"unknown POINT:UNITS {units!r}; assuming mm")
            factor = 1.0
    if factor != 1.0:
        xyz *= factor

    # ----- labels
    labels = lay.string_series("POINT", "LABELS")
    if len(labels) < P:
        if labels:
            warnings.append(f"POINT:LABELS has {len(labels)} labels for {P} points; the rest get generated names")
        labels = labels + [""] * (P - len(labels))
    labels = labels[:P]
    desc = lay.string_series("POINT", "DESCRIPTIONS")
    descriptions = desc[:P] if len(desc) >= P else desc + [""] * (P - len(desc))
    computed: dict[str, str] = {}
    for group in typed_groups(lay):
        for lab in lay.string_series("POINT", group):
            if lab.strip():
                computed.setdefault(lab.strip(), f"listed in POINT:{group}")

    return RawTake(
        points=xyz,
        labels=labels,
        rate=float(rate),
        units=units,
        descriptions=descriptions,
        computed=computed,
        warnings=warnings,
        info={"format": "c3d", "engine": engine, "processor": lay.processor,
              "storage": "float" if lay.is_float else "integer"},
    )
