"""The artifact cache: skip stages whose inputs and parameters have not changed.

Key = SHA-256 of a canonical JSON record {stage, stage VERSION, params,
upstream key}; the first key is the hash of the input file's bytes (and the
reader's options). Entries are ``<key>.npz`` files written atomically; an
entry holds its upstream artifact by reference (that artifact's key), so the
markers of a take are stored once, not once per stage. An entry that cannot be
read is deleted, recomputed and reported; one whose upstream entry is gone is
simply recomputed.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any

from . import artifacts
from .errors import InputError

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


def stage_key(stage: str, version: int, params: Any, upstream: str) -> str:
    p = dataclasses.asdict(params) if dataclasses.is_dataclass(params) else params
    rec = json.dumps({"stage": stage, "version": version, "params": p, "upstream": upstream}, sort_keys=True, default=str)
    return hashlib.sha256(rec.encode()).hexdigest()


class _MissingUpstream(LookupError):
    """A cache entry refers to an upstream entry that is gone."""


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

    def get(self, key: str, stage: str) -> Any | None:
        """The artifact stored under ``key`` (its upstream artifacts resolved by key), or None."""
        if self.folder is None:
            return None
        path = self.folder / f"{key}.npz"
        if not path.exists():
            return None
        try:
            return artifacts.load(path, resolve=lambda ref: self._upstream(ref, stage))
        except _MissingUpstream:
            return None
        except InputError:
            msg = f"{stage}: cache entry {path.name} was unreadable — deleted and recomputed"
            log.warning(msg)
            self.warnings.append(msg)
            try:
                path.unlink()
            except OSError:
                pass
            return None

    def _upstream(self, ref: str, stage: str) -> Any:
        obj = self.get(ref, stage)
        if obj is None:
            raise _MissingUpstream(ref)
        return obj

    def put(self, key: str, obj: Any, upstream: tuple[Any, str] | None = None) -> None:
        """Store ``obj`` under ``key``; ``upstream`` = (artifact nested in obj, its key) is stored by reference."""
        if self.folder is None:
            return
        refs = {id(upstream[0]): upstream[1]} if upstream is not None else None
        try:
            artifacts.save(obj, self.folder / f"{key}.npz", refs=refs)
        except OSError as e:
            msg = f"could not write cache entry ({e.strerror}) — continuing without it"
            log.warning(msg)
            self.warnings.append(msg)
