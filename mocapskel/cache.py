"""The artifact cache: skip stages whose inputs and parameters have not changed.

Key = SHA-256 of a canonical JSON record {stage, stage VERSION, the digest
of the stage's code, params, upstream key, cache format}; the first key is the
hash of the input file's bytes (and the reader's options). The code digest
covers the stage's module and every module of the package it imports, directly
or through others (function-level imports included): a change to a solver that
two stages call changes both stages' keys, so an entry never outlives the code
that made it. Entries are ``<key>.npz`` files written
atomically; an entry holds its upstream artifact by reference (that artifact's
key), so the markers of a take are stored once, not once per stage.

Every entry also holds its own key (``__cache_key__``) and a SHA-256 of its
arrays (``__cache_digest__``), both checked when it is read: an entry that
cannot be read, that holds another key (entries swapped or copied over each
other) or whose arrays do not match the digest (truncated, edited, a flipped
bit) is deleted, recomputed and reported. An entry whose upstream entry is
gone is simply recomputed. Upstream references are followed in a loop, never
by recursion, and a chain that comes back to an entry already seen is damage.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from . import artifacts
from .errors import InputError
from .io import artifact_files
from .io.atomic import atomic_write_bytes

log = logging.getLogger("mocapskel")


def default_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mocapskel"


def file_key(path: str | os.PathLike, extra: Any = None) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    if extra is not None:
        h.update(json.dumps(extra, sort_keys=True, default=str).encode())
    return h.hexdigest()


#: Layout of cache entries; part of every key, so that entries of another layout are never read.
CACHE_FORMAT = 2
#: Longest chain of upstream references an entry may have (one per stage, with room to spare).
_MAX_CHAIN = 32


def stage_key(stage: str, version: int, params: Any, upstream: str, code: str = "") -> str:
    """The key of a stage's entry. ``code``: :func:`code_digest` of the stage's module ("" for keys that
    name no code: the read and subject keys)."""
    p = dataclasses.asdict(params) if dataclasses.is_dataclass(params) else params
    rec = {"stage": stage, "version": version, "params": p, "upstream": upstream, "cache": CACHE_FORMAT}
    if code:
        rec["code"] = code
    return hashlib.sha256(json.dumps(rec, sort_keys=True, default=str).encode()).hexdigest()


#: The folder of the package's modules (this module's own folder).
_PACKAGE_DIR = Path(__file__).resolve().parent


def _module_file(name: str) -> Path | None:
    """The source file of the package module ``name`` (``mocapskel.x.y`` -> x/y.py or x/y/__init__.py)."""
    parts = name.split(".")[1:]
    base = _PACKAGE_DIR.joinpath(*parts)
    for f in (base / "__init__.py", base.with_suffix(".py") if parts else None):
        if f is not None and f.is_file():
            return f
    return None


def module_source(name: str) -> bytes | None:
    """The source of the package module ``name`` (``None`` when it has no source file)."""
    f = _module_file(name)
    return f.read_bytes() if f is not None else None


#: ``from X import names`` (names in parentheses may span lines) and ``import X, Y``, at any indentation
#: (function-level imports too). Read from the text rather than parsed: faster, and a match inside a docstring
#: only adds a module to the digest.
_FROM = re.compile(rb"^[ \t]*from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]*)", re.M)
_IMPORT = re.compile(rb"^[ \t]*import[ \t]+([^\n#;]*)", re.M)


@functools.lru_cache(maxsize=None)
def _imported(name: str, source: bytes, package: str) -> frozenset[str]:
    """The modules of ``package`` that the module ``name`` imports, wherever in it (function-level too)."""
    f = _module_file(name)
    here = name if f is not None and f.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for m in _IMPORT.finditer(source):
        out.update(w.split()[0] for w in m.group(1).decode().split(",") if w.strip())
    for m in _FROM.finditer(source):
        mod = m.group(1).decode()
        level = len(mod) - len(mod.lstrip("."))
        if level:
            base = here.split(".")[: len(here.split(".")) - level + 1]
            target = ".".join(base + ([mod[level:]] if mod[level:] else []))
        else:
            target = mod
        out.add(target)
        for w in re.sub(r"#[^\n]*", "", m.group(2).decode()).strip("()").replace("\n", " ").split(","):
            if w.strip():
                out.add(f"{target}.{w.split()[0]}")  # ``from . import x``: x may be a module
    return frozenset(m for m in out if (m == package or m.startswith(package + ".")) and _module_file(m) is not None)


def _code(name: str) -> dict[str, bytes | None]:
    """Module ``name`` and every module of its package it imports, directly or through others, with their
    sources (each read once)."""
    package = name.partition(".")[0]
    seen: dict[str, bytes | None] = {}
    todo = [name]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen[m] = src = module_source(m)
        if src is not None:
            todo.extend(_imported(m, src, package) - seen.keys())
    return seen


def code_modules(name: str) -> list[str]:
    """Module ``name`` and every module of its package it imports, directly or through others (sorted)."""
    return sorted(_code(name))


@functools.lru_cache(maxsize=None)
def code_digest(name: str) -> str:
    """SHA-256 over the source of module ``name`` and of every module of its package it imports, directly or
    through others (:func:`code_modules`): what shapes a stage's output besides its parameters and input."""
    h = hashlib.sha256()
    code = _code(name)
    for m in sorted(code):
        src = code[m] or b""
        h.update(f"{m}\0{len(src)}\0".encode())
        h.update(src)
    return h.hexdigest()


def digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 of an entry's arrays (names, dtypes, shapes and bytes), leaving out the ``__cache_*`` ones."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name.startswith("__cache_"):
            continue
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.reshape(-1).view(np.uint8) if a.size else b"")
    return h.hexdigest()


class Cache:
    """A folder of artifacts by key. ``Cache(None)`` caches nothing."""

    def __init__(self, folder: str | os.PathLike | None):
        self.folder: Path | None = None
        self.warnings: list[str] = []
        if folder is not None:
            folder = Path(folder)
            try:
                folder.mkdir(parents=True, exist_ok=True)
                probe = folder / f".probe-{os.getpid()}"
                probe.write_bytes(b"")
                probe.unlink()
                self.folder = folder
            except OSError as e:
                msg = f"cache folder {folder} is not writable ({e.strerror}) — running without cache"
                log.warning(msg)
                self.warnings.append(msg)

    def get(self, key: str, stage: str, upstream: tuple[str, Any] | None = None) -> Any | None:
        """The artifact stored under ``key``, or None (not there, or damaged: then deleted, with a warning).

        ``upstream`` = (key, artifact) of the artifact the entry was computed from, when the caller
        has it: the entry's reference must name that key, and the artifact is used as is. Otherwise
        the chain of references is read from the cache, entry by entry.
        """
        if self.folder is None:
            return None
        chain: list[tuple[str, dict]] = []
        base = None
        k = key
        while True:
            data = self._read(k, stage)
            if data is None:
                return None
            chain.append((k, data))
            refs = [n for n in data if n.endswith("__ref__")]
            if not refs:
                break
            ref = data[refs[0]]
            ref = str(ref) if len(refs) == 1 and ref.shape == () and ref.dtype.kind == "U" else ""
            if upstream is not None and k == key:
                if ref != upstream[0]:
                    self._discard(k, stage, "refers to another upstream artifact than its key says")
                    return None
                base = upstream[1]
                break
            if not ref or ref in {c[0] for c in chain} or len(chain) > _MAX_CHAIN:
                self._discard(k, stage, "refers back to itself through its upstream entries")
                return None
            k = ref
        obj = base
        for k, data in reversed(chain):
            try:
                obj = artifacts.from_arrays(data, str(self.folder / f"{k}.npz"), resolve=lambda ref, up=obj: up)
            except InputError:
                self._discard(k, stage, "was unreadable")
                return None
        return obj

    def _read(self, key: str, stage: str) -> dict | None:
        """The checked arrays of entry ``key``; None when it is missing or damaged (then deleted)."""
        path = self.folder / f"{key}.npz"
        if not path.is_file():
            return None
        try:
            data = artifact_files.read_arrays(path)
        except InputError:
            self._discard(key, stage, "was unreadable")
            return None
        stored, dig = data.get("__cache_key__"), data.get("__cache_digest__")
        if stored is None or dig is None or stored.shape != () or str(stored) != key:
            self._discard(key, stage, "does not hold the artifact its name says (swapped, copied or from another version)")
            return None
        if dig.shape != () or str(dig) != digest(data):
            self._discard(key, stage, "does not match its checksum (edited or damaged)")
            return None
        return data

    def _discard(self, key: str, stage: str, why: str) -> None:
        msg = f"{stage}: cache entry {key}.npz {why} — deleted and recomputed"
        log.warning(msg)
        self.warnings.append(msg)
        try:
            (self.folder / f"{key}.npz").unlink()
        except OSError:
            pass

    def put(self, key: str, obj: Any, upstream: tuple[Any, str] | None = None) -> None:
        """Store ``obj`` under ``key``; ``upstream`` = (artifact nested in obj, its key) is stored by reference."""
        if self.folder is None:
            return
        refs = {id(upstream[0]): upstream[1]} if upstream is not None else None
        try:
            arrays = artifacts.to_arrays(obj, refs)
            arrays["__cache_key__"] = np.array(key)
            arrays["__cache_digest__"] = np.array(digest(arrays))
            atomic_write_bytes(self.folder / f"{key}.npz", artifacts.arrays_bytes(arrays))
        except OSError as e:
            msg = f"could not write cache entry ({e.strerror}) — continuing without it"
            log.warning(msg)
            self.warnings.append(msg)
