"""The batch summary: one ``summary.csv`` row per take, written atomically and read back."""
from __future__ import annotations

import csv
import io
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..io.atomic import atomic_open
from .tasks import Take, TakeResult

#: Columns of ``summary.csv``, in order.
SUMMARY_COLUMNS: tuple[str, ...] = (
    "take", "input", "status", "exit_code", "error", "frames", "markers", "segments",
    "bone_lengths_mm", "ik_rms_mm", "warnings", "seconds", "subject",
)  # fmt: skip


def _fmt(x: Any, digits: int) -> str:
    if x is None:
        return ""
    x = float(x)
    return f"{x:.{digits}f}" if np.isfinite(x) else ""


def summary_row(take: Take, result: TakeResult, subject: str = "") -> dict[str, Any]:
    """One row of ``summary.csv`` (see :data:`SUMMARY_COLUMNS`)."""
    rep = result.report or {}
    inp = rep.get("input", {})
    bones = rep.get("bones", [])
    return {
        "take": take.name,
        "input": take.input,
        "status": result.status,
        "exit_code": result.exit_code,
        "error": result.error,
        "frames": inp.get("frames", ""),
        "markers": inp.get("markers", ""),
        "segments": len(rep["segments"]) if "segments" in rep else (len(bones) if bones else ""),
        "bone_lengths_mm": ";".join(f"{b['segment']}={_fmt(b.get('length_mm'), 2) or 'nan'}" for b in bones),
        "ik_rms_mm": _fmt(rep.get("ik", {}).get("marker_rms_mm"), 3),
        "warnings": len(rep.get("warnings", [])) if result.report is not None else "",
        "seconds": f"{result.seconds:.2f}",
        "subject": subject,
    }


def write_summary(path: str | os.PathLike, rows: Sequence[dict[str, Any]]) -> None:
    """Write ``summary.csv`` atomically: a header of :data:`SUMMARY_COLUMNS`, one row per take."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in SUMMARY_COLUMNS})
    with atomic_open(path, "w", encoding="utf-8", newline="") as f:
        f.write(buf.getvalue())


def read_summary(path: str | os.PathLike) -> list[dict[str, str]]:
    """The rows of a ``summary.csv`` (all values as strings)."""
    with open(path, encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))
