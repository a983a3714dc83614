"""A take's outputs on the client side: whether they are up to date, and writing them atomically."""
from __future__ import annotations

import json
import os

from ..io.atomic import AtomicOutputs
from .tasks import Take, TakeResult


def up_to_date(take: Take, opt_hash: str) -> dict | None:
    """The report of a take whose outputs need no re-run, else None.

    Up to date: ``<take>.bvh`` and ``<take>.json`` exist, neither is older
    than the input, the report reads, and it was made from the same input
    path with the same options (``report["batch"]``).
    """
    try:
        src = os.stat(take.input).st_mtime_ns
        if os.stat(take.bvh).st_mtime_ns < src or os.stat(take.report).st_mtime_ns < src:
            return None
        with open(take.report, encoding="utf-8") as f:
            rep = json.load(f)
    except (OSError, ValueError):
        return None
    rec = rep.get("batch") if isinstance(rep, dict) else None
    if not isinstance(rec, dict) or rec.get("options_hash") != opt_hash:
        return None
    if rec.get("input") != os.path.abspath(take.input):
        return None
    return rep


def write_outputs(take: Take, result: TakeResult) -> None:
    """Write a fitted take's BVH and report: both appear together, or neither (:class:`AtomicOutputs`)."""
    assert result.bvh is not None and result.report is not None
    with AtomicOutputs() as out:
        with open(out.stage(take.bvh), "w", encoding="ascii", newline="\n") as f:
            f.write(result.bvh)
        with open(out.stage(take.report), "w", encoding="utf-8") as f:
            json.dump(result.report, f, indent=2, allow_nan=False)
            f.write("\n")
