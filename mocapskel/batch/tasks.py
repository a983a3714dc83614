"""What a batch is made of: its options, its takes, the task sent to a worker and what came of it."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__, pipeline
from ..errors import UsageError
from ..pipeline import ReadOptions
from .inputs import take_names

SUMMARY_NAME = "summary.csv"


@dataclass(frozen=True)
class BatchOptions:
    """What every take of a batch is fitted with.

    Attributes
    ----------
    params : dict
        Stage parameters, as :func:`mocapskel.pipeline.make_params` makes them.
    read : ReadOptions
        Marker include/exclude patterns.
    cache_dir : str, optional
        Artifact cache folder as the *workers* see it; None: each worker's
        default (``$XDG_CACHE_HOME/mocapskel`` or ``~/.cache/mocapskel``).
    use_cache : bool
        False: neither read nor write the artifact cache.
    strict : bool
        A take whose output checks fail (:mod:`mocapskel.checks`) fails with
        exit code 4 instead of being written with warnings.
    """

    params: dict[str, Any] = field(default_factory=pipeline.make_params)
    read: ReadOptions = ReadOptions()
    cache_dir: str | None = None
    use_cache: bool = True
    strict: bool = False


def options_hash(options: BatchOptions) -> str:
    """SHA-256 of everything that changes a take's outputs: version, stage versions, parameters, reader options.

    Stored in each report (``report["batch"]["options_hash"]``) so that a
    re-run knows whether the outputs there were made with the same options.
    The cache location is not part of it.
    """
    rec = {
        "mocapskel": __version__,
        "stages": {s: pipeline.stage_module(s).VERSION for s in (*pipeline.STAGES, "export")},
        "params": {k: dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
                   for k, v in sorted(options.params.items())},
        "read": dataclasses.asdict(options.read),
    }
    return hashlib.sha256(json.dumps(rec, sort_keys=True, default=str).encode()).hexdigest()


@dataclass(frozen=True)
class Take:
    """One take of a batch: its input and its outputs (paths as the client sees them)."""

    name: str
    input: str
    bvh: str
    report: str


@dataclass(frozen=True)
class TakeTask:
    """What a worker needs to fit one take (picklable; paths as the worker sees them)."""

    name: str
    input: str
    options: BatchOptions
    options_hash: str


@dataclass
class TakeResult:
    """What came of one take.

    Attributes
    ----------
    name : str
        The take's name.
    status : {"ok", "skipped", "failed"}
    seconds : float
        Wall time spent on the take (fit and BVH text; for a skipped take, the check).
    report : dict, optional
        The fit report (None when failed).
    bvh : str, optional
        The BVH text, from a worker, until the client has written it.
    error : str
        The one-line error of a failed take.
    exit_code : int
        The exit code ``mocapskel fit`` would have given for this take (0 when it worked).
    """

    name: str
    status: str
    seconds: float
    report: dict | None = None
    bvh: str | None = None
    error: str = ""
    exit_code: int = 0


def plan(inputs: Sequence[Path], outdir: str | os.PathLike) -> list[Take]:
    """The takes of a batch and their output paths ``OUTDIR/<name>.bvh`` and ``.json``.

    Raises
    ------
    UsageError
        An input that is one of the outputs.
    """
    out = Path(outdir)
    takes = [Take(n, os.fspath(p), os.fspath(out / f"{n}.bvh"), os.fspath(out / f"{n}.json"))
             for n, p in zip(take_names(inputs), inputs)]
    outputs = {os.path.normcase(os.path.abspath(p)) for t in takes for p in (t.bvh, t.report)}
    outputs.add(os.path.normcase(os.path.abspath(out / SUMMARY_NAME)))
    for t in takes:
        if os.path.normcase(os.path.abspath(t.input)) in outputs:
            raise UsageError(f"input {t.input} is also an output of the batch — choose another output folder")
    return takes
