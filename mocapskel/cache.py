"""The artifact cache: skip stages whose inputs and parameters have not changed.

Key = SHA-256 of a canonical JSON record {stage, stage VERSION, params,
upstream key}; the first key is the hash of the input file's bytes (and the
reader's options). Entries are ``<key>.npz`` files written atomically; an
entry that cannot be read is deleted, recomputed and reported.
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
        if self.folder is None:
            return None
        path = self.folder / f"{key}.npz"
        if not path.exists():
            return None
        try:
            return artifacts.load(path)
        except InputError:
            msg = f"{stage}: cache entry {path.name} was unreadable — deleted and recomputed"
            log.warning(msg)
            self.warnings.append(msg)
            try:
                path.unlink()
            except OSError:
                pass
            return None

    def put(self, key: str, obj: Any) -> None:
        if self.folder is None:
            return
        try:
            artifacts.save(obj, self.folder / f"{key}.npz")
        except OSError as e:
            msg = f"could not write cache entry ({e.strerror}) — continuing without it"
            log.warning(msg)
            self.warnings.append(msg)
