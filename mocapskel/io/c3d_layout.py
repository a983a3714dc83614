"""C3D file layout: the header and the parameter section, parsed and checked without ezc3d."""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

__all__ = ["C3DParameter", "C3DLayout", "read_layout"]

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
