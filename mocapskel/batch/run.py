"""The batch itself: inputs planned, up-to-date takes skipped, the rest fitted, outputs and summary written."""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import UsageError
from .clustering import SubjectResult, identify_subjects
from .dask_runner import dask_client, run_dask
from .inputs import collect_inputs
from .local_runner import cpu_count, run_local
from .outputs import up_to_date, write_outputs
from .summary import summary_row, write_summary
from .tasks import SUMMARY_NAME, BatchOptions, Take, TakeResult, TakeTask, options_hash, plan

#: Take statuses: fitted now, outputs already up to date (not re-run), failed.
STATUSES: tuple[str, ...] = ("ok", "skipped", "failed")


@dataclass
class BatchResult:
    """What :func:`run_batch` did: one row per take (the summary) and the subject clustering."""

    rows: list[dict[str, Any]]
    summary: Path
    subjects: SubjectResult | None = None

    @property
    def failed(self) -> int:
        return sum(r["status"] == "failed" for r in self.rows)

    @property
    def counts(self) -> dict[str, int]:
        return {s: sum(r["status"] == s for r in self.rows) for s in STATUSES}


def prepare_outdir(outdir: str | os.PathLike) -> Path:
    """Create the output folder if missing; refuse a file or an unwritable folder (UsageError)."""
    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"output {outdir} is a file — give a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"cannot create output folder {outdir} ({e.strerror or e})") from None
    if not os.access(out, os.W_OK):
        raise UsageError(f"output folder {outdir} is not writable")
    return out


def run_batch(
    inputs: Sequence[str | os.PathLike],
    outdir: str | os.PathLike,
    options: BatchOptions | None = None,
    *,
    jobs: int | None = None,
    scheduler: str | None = None,
    force: bool = False,
    subjects: int | None = None,
    progress: Callable[[int, int, Take, TakeResult], None] | None = None,
) -> BatchResult:
    """Fit many takes; write ``OUTDIR/<take>.bvh``, ``<take>.json`` and ``summary.csv``.

    Parameters
    ----------
    inputs : sequence of str or PathLike
        Files, folders and globs (see :func:`collect_inputs`).
    outdir : str or PathLike
        Output folder, created if missing.
    options : BatchOptions, optional
        Stage parameters, reader options and cache for every take (default: ``BatchOptions()``).
    jobs : int, optional
        Local worker processes (default: the number of cores); ignored with ``scheduler``.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:port``): fit on that cluster instead.
    force : bool
        Re-fit takes whose outputs are up to date (see :func:`up_to_date`).
    subjects : int, optional
        Number of subjects (default: chosen automatically; see :func:`identify_subjects`).
    progress : callable, optional
        Called as ``progress(done, total, take, result)`` after every take.

    Returns
    -------
    BatchResult
        A failed take does not stop the others: it has ``status="failed"``
        and its error in its row.

    Raises
    ------
    UsageError
        No takes, bad output folder, Dask missing or its scheduler unreachable.
    KeyboardInterrupt
        Interrupted: the takes not finished are cancelled, no partial output
        is left and ``summary.csv`` is not written.
    """
    options = options if options is not None else BatchOptions()
    paths = collect_inputs(inputs)
    if scheduler:
        try:
            import distributed  # noqa: F401
        except ImportError:
            raise UsageError("--scheduler needs Dask: install mocapskel[dask] (pip install 'mocapskel[dask]')") from None
    out = prepare_outdir(outdir)
    takes = plan(paths, out)
    h = options_hash(options)
    by_name = {t.name: t for t in takes}
    results: dict[str, TakeResult] = {}
    total = len(takes)

    def finish(take: Take, r: TakeResult) -> None:
        if r.status == "ok":
            try:
                write_outputs(take, r)
            except OSError as e:
                r = TakeResult(r.name, "failed", r.seconds, error=f"{take.bvh}: cannot write ({e.strerror or e})",
                               exit_code=1)
            r.bvh = None  # written: do not hold every take's text
        results[take.name] = r
        if progress:
            progress(len(results), total, take, r)

    todo: list[TakeTask] = []
    for t in takes:
        t0 = time.perf_counter()
        rep = None if force else up_to_date(t, h)
        if rep is not None:
            finish(t, TakeResult(t.name, "skipped", time.perf_counter() - t0, report=rep))
        else:
            todo.append(TakeTask(t.name, t.input, options, h))

    def done(task: TakeTask, r: TakeResult) -> None:
        finish(by_name[task.name], r)

    if todo:
        if scheduler:
            client = dask_client(scheduler)
            try:
                run_dask(todo, client, done)
            finally:
                with contextlib.suppress(Exception):
                    client.close()
        else:
            run_local(todo, jobs or cpu_count(), done)

    ordered = [results[t.name] for t in takes]
    subj = identify_subjects([r.report for r in ordered], n_subjects=subjects)
    rows = [summary_row(t, r, s) for t, r, s in zip(takes, ordered, subj.labels)]
    summary = out / SUMMARY_NAME
    write_summary(summary, rows)
    return BatchResult(rows=rows, summary=summary, subjects=subj)
