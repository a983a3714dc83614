"""C3D marker files: read the 3D points, write a float C3D of markers.

Reading is done in two steps:

1. :func:`read_layout` parses the 512-byte header and the parameter section
   with a small pure-Python parser that checks every record. ezc3d 1.7 crashes
   (segmentation fault) or loops forever on some damaged parameter sections,
   and silently returns fewer frames for a truncated file, so nothing reaches
   ezc3d before the header, the parameters and the size of the data block
   have been checked here. This parser also keeps the values ezc3d rewrites
   while reading (the header's frame range and rate, ``POINT:FRAMES``,
   ``POINT:LONG_FRAMES``, ``TRIAL:ACTUAL_*_FIELD``).
2. The points themselves come from ezc3d (``engine="ezc3d"``) or from a
   direct numpy read of the data block (``engine="numpy"``). The default,
   ``engine="auto"``, is ezc3d, except for files of more than
   :data:`EZC3D_MAX_SAMPLES` point samples (points x frames): ezc3d keeps a
   C++ object of about 150 bytes per sample, so that a passive take of 450
   labels over 60,000 frames would need some 4 GB to be read; numpy reads it
   with little more memory than the points themselves.

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
  :func:`~mocapskel.io.markers.read_markers` as a whole about 0.98 times that
  plain ezc3d read (fresh processes, median of 5); ``engine="numpy"`` 0.10 s
  and little more memory than the output array. The two engines agree exactly on every file of the
  real-data collection (``tests/test_io_realdata.py``) and on integer, DEC
  and MIPS files built byte by byte (``tests/test_io_c3d.py``).

ezc3d 1.7 stores at most 65,535 frames in ``POINT:FRAMES`` when it writes and
reads at most that many back. When a file holds more frames than ezc3d
returned (declared by ``POINT:LONG_FRAMES`` or ``TRIAL:ACTUAL_END_FIELD``, or
found from the size of the data block when ``POINT:FRAMES`` is saturated),
the remaining frames are read from the data block with numpy.
"""
from __future__ import annotations

import contextlib
import os
import struct
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ..artifacts import Markers
from ..errors import InputError
from .atomic import atomic_path
from .markers import RawTake, check_rate, unit_factor

__all__ = ["C3DLayout", "read_layout", "read_c3d", "write_c3d"]

_PROCESSORS = {84: "intel", 85: "dec", 86: "mips"}
_SATURATED = 65535  # the largest frame count a 16-bit header word or POINT:FRAMES can hold
_TO_USER = "export the take again as C3D or TRC"


# --------------------------------------------------------------------------- layout


@dataclass
class C3DParameter:
    """One parameter as stored: type, dimensions and raw bytes, decoded on demand."""

    type: int  # -1 char, 1 byte, 2 int16, 4 float
    dims: tuple[int, ...]
    data: bytes
    processor: str

    def ints(self, unsigned: bool = False) -> np.ndarray:
        """Integer values (flattened, file order)."""
        if self.type == 1:
            return np.frombuffer(self.data, np.uint8 if unsigned else np.int8).astype(np.int64)
        if self.type == 2:
            dt = (">" if self.processor == "mips" else "<") + ("u2" if unsigned else "i2")
            return np.frombuffer(self.data, dt).astype(np.int64)
        if self.type == 4:
            return np.rint(self.floats()).astype(np.int64)
        return np.zeros(0, np.int64)

    def floats(self) -> np.ndarray:
        """Float values (flattened, file order); integer parameters are converted."""
        if self.type == 4:
            return _decode_float32(self.data, self.processor).astype(np.float64)
        if self.type in (1, 2):
            return self.ints().astype(np.float64)
        return np.zeros(0, np.float64)

    def strings(self) -> list[str]:
        """Character values: one string per column of the (length, n, ...) char matrix."""
        if self.type != -1:
            return []
        if not self.dims:
            return [_decode_text(self.data)]
        length = self.dims[0]
        if length == 0:
            return []
        n = len(self.data) // length
        return [_decode_text(self.data[i * length:(i + 1) * length]) for i in range(n)]


@dataclass
class C3DLayout:
    """What a C3D file declares, read without ezc3d.

    Every count is as written in the file (before ezc3d's corrections).
    """

    file_size: int
    processor: str
    header_points: int
    header_analog_words: int
    header_first_frame: int
    header_last_frame: int
    header_scale: float
    header_data_start: int
    header_rate: float
    params: dict[str, dict[str, C3DParameter]] = field(default_factory=dict)
    tail: bytes = b""  # the last 512 bytes of the file

    # ----------------------------------------------------------- parameter helpers
    def param(self, group: str, name: str) -> C3DParameter | None:
        return self.params.get(group, {}).get(name)

    def first_float(self, group: str, name: str) -> float | None:
        p = self.param(group, name)
        v = p.floats() if p is not None else np.zeros(0)
        return float(v[0]) if v.size else None

    def first_uint(self, group: str, name: str) -> int | None:
        p = self.param(group, name)
        v = p.ints(unsigned=True) if p is not None else np.zeros(0, np.int64)
        return int(v[0]) if v.size else None

    def string_series(self, group: str, base: str) -> list[str]:
        """Concatenate ``BASE``, ``BASE2``, ``BASE3`` ... (stops at the first missing one)."""
        out: list[str] = []
        p = self.param(group, base)
        if p is None:
            return out
        out.extend(p.strings())
        i = 2
        while (p := self.param(group, f"{base}{i}")) is not None:
            out.extend(p.strings())
            i += 1
        return out

    # ----------------------------------------------------------- derived values
    @property
    def n_points(self) -> int:
        used = self.first_uint("POINT", "USED")
        return used if used is not None else self.header_points

    @property
    def scale(self) -> float:
        s = self.first_float("POINT", "SCALE")
        return s if s is not None else self.header_scale

    @property
    def is_float(self) -> bool:
        return self.scale < 0

    @property
    def data_start(self) -> int:
        ds = self.first_uint("POINT", "DATA_START")
        return ds if ds else self.header_data_start

    @property
    def point_rate(self) -> float:
        r = self.first_float("POINT", "RATE")
        return r if r is not None and r > 0 else self.header_rate  # (read_c3d refuses absurd rates first)

    @property
    def analog_words(self) -> int:
        """Analog samples stored per point frame (channels x subframes)."""
        used = self.first_uint("ANALOG", "USED")
        if used is None:
            return self.header_analog_words
        if used == 0:
            return 0
        arate = self.first_float("ANALOG", "RATE")
        prate = self.point_rate
        ratio = arate / prate if arate and prate and arate > 0 and prate > 0 else float("nan")
        if np.isfinite(ratio) and ratio < 1e6:
            sub = int(round(ratio))
        elif self.header_points or self.header_analog_words:
            sub = self.header_analog_words // max(used, 1)
        else:
            sub = 1
        return used * max(sub, 1)

    @property
    def bytes_per_frame(self) -> int:
        return (4 * self.n_points + self.analog_words) * (4 if self.is_float else 2)

    @property
    def frames_in_file(self) -> int:
        """Complete frames the data block of the file can hold."""
        bpf = self.bytes_per_frame
        return max(self._data_bytes(), 0) // bpf if bpf > 0 else 0

    def _data_bytes(self) -> int:
        """Bytes from the start of the point block to the end of the file (or of the rotation block's start)."""
        end = self.file_size
        rot = self.first_uint("ROTATION", "DATA_START") if self.first_uint("ROTATION", "USED") else None
        if rot and rot > self.data_start:
            end = min(end, (rot - 1) * 512)
        return end - (self.data_start - 1) * 512

    def ends_on_frame(self) -> bool:
        """Whether the data block ends after a whole frame (or is padded with zeros to a 512-byte block)."""
        avail = self._data_bytes()
        bpf = self.bytes_per_frame
        rem = avail % bpf if bpf > 0 and avail > 0 else 0
        if rem == 0:
            return True
        return self.file_size % 512 == 0 and rem <= len(self.tail) and not any(self.tail[-rem:])

    @property
    def header_frames(self) -> int:
        return self.header_last_frame - self.header_first_frame + 1 if self.header_last_frame else 0

    def declared_frames(self) -> tuple[int, str, bool]:
        """Frame count the file declares, where it comes from, and whether it is saturated.

        ``POINT:LONG_FRAMES`` first, then ``TRIAL:ACTUAL_START/END_FIELD``
        (two 16-bit words each), then ``POINT:FRAMES`` (float or unsigned
        16-bit), then the header's frame range. Saturated means the count is
        65535 from a 16-bit field, so the file may hold more frames.
        """
        lf = self.first_float("POINT", "LONG_FRAMES")
        if lf is not None and lf > 0:
            return int(round(lf)), "POINT:LONG_FRAMES", False
        s = self.param("TRIAL", "ACTUAL_START_FIELD")
        e = self.param("TRIAL", "ACTUAL_END_FIELD")
        if s is not None and e is not None:
            sv, ev = s.ints(unsigned=True), e.ints(unsigned=True)
            if sv.size >= 2 and ev.size >= 2:
                start, end = int(sv[0] + (sv[1] << 16)), int(ev[0] + (ev[1] << 16))
                if end >= start > 0 and end - start + 1 > _SATURATED:
                    return end - start + 1, "TRIAL:ACTUAL_START_FIELD/ACTUAL_END_FIELD", False
        fp = self.param("POINT", "FRAMES")
        if fp is not None and fp.type == 4:
            v = fp.floats()
            if v.size:
                return int(round(v[0])), "POINT:FRAMES", False
        n = self.first_uint("POINT", "FRAMES")
        if n is not None and n > 0:
            return n, "POINT:FRAMES", n == _SATURATED
        return self.header_frames, "header", self.header_last_frame == _SATURATED


def _decode_text(b: bytes) -> str:
    b = b.split(b"\x00", 1)[0]
    try:
        s = b.decode("utf-8")
    except UnicodeDecodeError:
        s = b.decode("latin-1")
    return s.rstrip()


def _decode_float32(raw: bytes | np.ndarray, processor: str) -> np.ndarray:
    """Float32 values stored by an Intel, MIPS (big-endian) or DEC processor."""
    if processor == "intel":
        return np.frombuffer(raw, "<f4")
    if processor == "mips":
        return np.frombuffer(raw, ">f4").astype(np.float32)
    # DEC F-float: 16-bit words swapped, exponent bias 2 larger than IEEE
    w = np.frombuffer(raw, "<u2").reshape(-1, 2).astype(np.uint32)
    return ((w[:, 0] << 16) | w[:, 1]).view(np.float32) / np.float32(4.0)


def _bad(msg: str, path: str) -> InputError:
    return InputError(msg, path)


def _parse_parameters(buf: bytes, processor: str, path: str) -> dict[str, dict[str, C3DParameter]]:
    """Parse and check every record of a parameter section (bytes after its 4-byte header)."""
    i16 = ">h" if processor == "mips" else "<h"
    groups: dict[int, str] = {}
    pending: list[tuple[int, str, C3DParameter]] = []
    pos, n = 0, len(buf)
    damaged = "damaged C3D parameter section ({}) — " + _TO_USER
    while pos + 2 <= n:
        nchars = struct.unpack_from("b", buf, pos)[0]
        gid = struct.unpack_from("b", buf, pos + 1)[0]
        if nchars == 0:
            break
        ln = abs(nchars)
        p = pos + 2 + ln
        if p + 2 > n:
            raise _bad(damaged.format(f"record at byte {pos} runs past the section"), path)
        name = buf[pos + 2:p].decode("latin-1").strip().upper()
        offset = struct.unpack_from(i16, buf, p)[0]
        body = p + 2
        if gid == 0:
            raise _bad(damaged.format(f"record {name!r} has group id 0"), path)
        if gid < 0:  # group
            if body + 1 > n:
                raise _bad(damaged.format(f"group {name!r} runs past the section"), path)
            end = body + 1 + buf[body]
            groups[-gid] = name
        else:
            if body + 2 > n:
                raise _bad(damaged.format(f"parameter {name!r} runs past the section"), path)
            ptype = struct.unpack_from("b", buf, body)[0]
            ndims = buf[body + 1]
            if ptype not in (-1, 1, 2, 4):
                raise _bad(damaged.format(f"parameter {name!r} has unknown type {ptype}"), path)
            if ndims > 7 or body + 2 + ndims > n:
                raise _bad(damaged.format(f"parameter {name!r} has {ndims} dimensions"), path)
            dims = tuple(buf[body + 2:body + 2 + ndims])
            count = int(np.prod(dims)) if dims else 1
            dstart = body + 2 + ndims
            dend = dstart + count * abs(ptype)
            if dend + 1 > n:
                raise _bad(damaged.format(f"parameter {name!r} runs past the section"), path)
            end = dend + 1 + buf[dend]
            pending.append((gid, name, C3DParameter(ptype, dims, bytes(buf[dstart:dend]), processor)))
        if end > n:
            raise _bad(damaged.format(f"description of {name!r} runs past the section"), path)
        if offset == 0:
            break
        nxt = p + offset
        if offset < 0 or nxt < end or nxt > n:
            raise _bad(damaged.format(f"record {name!r} points to byte {nxt}"), path)
        pos = nxt
    params: dict[str, dict[str, C3DParameter]] = {g: {} for g in groups.values()}
    for gid, name, prm in pending:
        gname = groups.get(gid)
        if gname is None:
            continue  # a parameter of a group that is not declared: ignored, as ezc3d does
        params[gname].setdefault(name, prm)
    return params


def read_layout(path: str | os.PathLike) -> C3DLayout:
    """Read and check a C3D file's header and parameter section (no data).

    Parameters
    ----------
    path : str or PathLike
        The C3D file.

    Returns
    -------
    C3DLayout

    Raises
    ------
    InputError
        Not a C3D file, damaged parameters, or a file that ends before its
        parameter section.
    """
    spath = str(path)
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            head = f.read(512)
            if len(head) < 512:
                raise _bad(f"not a C3D file (only {len(head)} bytes, shorter than a C3D header) — {_TO_USER}", spath)
            pblock, key = head[0], head[1]
            if key != 0x50 or pblock < 2:
                raise _bad(f"not a C3D file (bad header) — {_TO_USER}", spath)
            pstart = (pblock - 1) * 512
            if pstart + 4 > size:
                raise _bad(f"truncated C3D file (ends before its parameter section) — {_TO_USER}", spath)
            f.seek(pstart)
            phead = f.read(4)
            nblocks, ptype = phead[2], phead[3]
            processor = _PROCESSORS.get(ptype)
            if processor is None:
                raise _bad(f"not a C3D file (unknown processor type {ptype}) — {_TO_USER}", spath)
            if nblocks == 0:
                raise _bad(f"damaged C3D parameter section (0 blocks) — {_TO_USER}", spath)
            pbuf = f.read(nblocks * 512 - 4)
            if len(pbuf) < nblocks * 512 - 4:
                raise _bad(f"truncated C3D file (ends inside its parameter section) — {_TO_USER}", spath)
            f.seek(max(size - 512, 0))
            tail = f.read(512)
    except OSError as e:
        raise InputError(f"cannot read ({e.strerror or e}) — check the path and the file's permissions", spath) from None
    u16 = ">H" if processor == "mips" else "<H"
    words = struct.unpack_from(u16[0] + "6H", head, 2)
    scale = float(_decode_float32(head[12:16], processor)[0])
    data_start = struct.unpack_from(u16, head, 16)[0]
    rate = float(_decode_float32(head[20:24], processor)[0])
    params = _parse_parameters(pbuf, processor, spath)
    if "POINT" not in params:
        raise _bad(f"not a marker C3D file (no POINT parameter group) — {_TO_USER}", spath)
    return C3DLayout(
        file_size=size,
        processor=processor,
        header_points=words[0],
        header_analog_words=words[1],
        header_first_frame=words[2],
        header_last_frame=words[3],
        header_scale=scale,
        header_data_start=data_start,
        header_rate=rate,
        params=params,
        tail=tail,
    )


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
    step = max(1, (8 << 20) // max(lay.bytes_per_frame, 1))  # about 8 MB of the file per block
    with open(path, "rb") as f:
        f.seek(offset)
        for lo in range(0, n, step):
            k = min(step, n - lo)
            block = np.fromfile(f, dtype=dt, count=k * words)
            if block.size != k * words:
                raise OSError(f"the data block ends after {lo + block.size // words} of {n} frames")
            block = block.reshape(k, words)[:, : 4 * P]
            if lay.is_float and lay.processor == "dec":
                block = _decode_float32(np.ascontiguousarray(block).tobytes(), "dec").reshape(k, 4 * P)
            block = block.reshape(k, P, 4)
            xyz[lo : lo + k] = block[..., :3]
            residual[lo : lo + k] = block[..., 3]
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


#: Point samples (points x frames) above which ``engine="auto"`` reads with numpy: ezc3d's
#: per-sample objects would take more than about 750 MB (60,000 frames of 48 markers are
#: 2.9 million samples).
EZC3D_MAX_SAMPLES = 5_000_000


def read_c3d(path: str | os.PathLike, *, engine: Literal["auto", "ezc3d", "numpy"] = "auto") -> RawTake:
    """Read the 3D points of a C3D file.

    Parameters
    ----------
    path : str or PathLike
        The C3D file.
    engine : {"auto", "ezc3d", "numpy"}
        Who reads the point block once the header and parameters have been
        checked: ezc3d, or a memory map of the data block (about 15x faster
        and without ezc3d's per-point objects); "auto" (the default): ezc3d
        up to :data:`EZC3D_MAX_SAMPLES` point samples, numpy above. Files
        written by a MIPS (big-endian) processor, which ezc3d 1.7 refuses,
        are always read with numpy.

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
    if engine == "auto":
        engine = "numpy" if P * target > EZC3D_MAX_SAMPLES else "ezc3d"
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
    for group in ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS"):
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


# --------------------------------------------------------------------------- writer


def write_c3d(path: str | os.PathLike, markers: Markers) -> None:
    """Write markers as a float C3D file (mm) through ezc3d, atomically.

    Parameters
    ----------
    path : str or PathLike
        Output file; it is replaced only once the new file is complete.
    markers : Markers
        ``points`` (F, M, 3) in mm, NaN for gaps (written as residual -1 with
        zero coordinates); ``labels`` (LABELS, LABELS2 ... beyond 255 labels);
        ``rate``. Takes longer than 65535 frames also get ``POINT:LONG_FRAMES``
        and ``TRIAL:ACTUAL_START_FIELD``/``ACTUAL_END_FIELD``.
    """
    import ezc3d
    from ezc3d import ezc3d as _swig

    pts = np.asarray(markers.points, dtype=np.float64)
    F, M = pts.shape[:2]
    seen = np.isfinite(pts).all(axis=2)  # (F, M)
    data = np.zeros((4, M, F))
    data[:3] = np.where(seen[..., None], pts, 0.0).transpose(2, 1, 0)
    data[3] = 1.0
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(markers.rate)]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(markers.labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = np.where(seen.T, 0.0, -1.0)[None]
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, M, F), dtype=bool)
    if F > _SATURATED:
        c.add_parameter("POINT", "LONG_FRAMES", np.array([float(F)]), "number of frames (more than 65535)")
        params = c["parameters"]
        params.create_group_if_needed("TRIAL")
        for name, words in (("ACTUAL_START_FIELD", [1, 0]), ("ACTUAL_END_FIELD", [F & 0xFFFF, F >> 16])):
            params["TRIAL"][name] = {  # 16-bit integer words (low, high), as the C3D manual has them
                "type": _swig.INT, "value": np.array(words), "description": "frame number (low, high word)", "is_locked": False
            }
    write_ezc3d(c, path)


def write_ezc3d(c, path: str | os.PathLike) -> None:
    """Write the ezc3d object ``c`` to ``path`` atomically (temporary file, then rename)."""
    with atomic_path(path) as tmp:
        tmp_c3d = tmp + ".c3d"  # ezc3d's Python writer appends .c3d to any other name
        try:
            c.write(tmp_c3d)
            os.replace(tmp_c3d, tmp)
        finally:
            with contextlib.suppress(OSError):
                os.unlink(tmp_c3d)

