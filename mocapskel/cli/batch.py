"""``mocapskel batch``: fit many takes, locally in worker processes or on a Dask cluster.

Exit codes: 0 every take fitted (or up to date), 1 one take or more failed
(each failed row of ``summary.csv`` has its error and the exit code ``fit``
would have given), 2 bad usage (no takes, bad output folder, Dask missing or
its scheduler unreachable), 130 interrupted (nothing partial written, no
``summary.csv``).
"""
from __future__ import annotations

import logging

import click

from .. import pipeline
from ..batch import BatchOptions, Take, TakeResult, run_batch
from .main import cli
from .options import bvh_options, cache_options, common, fit_options, make_read, naming_options, read_options, strict_option

log = logging.getLogger("mocapskel")


class BatchFailed(click.ClickException):
    """Some takes failed (exit code 1); the summary says which and why."""

    exit_code = 1


def _progress_printer(show: bool):
    def show_line(done: int, total: int, take: Take, r: TakeResult) -> None:
        if not show:
            return
        w = len(str(total))
        name = take.input.replace("\\", "/").rsplit("/", 1)[-1]
        if r.status == "ok":
            n_warn = len((r.report or {}).get("warnings", []))
            tail = f"ok {r.seconds:.1f} s" + (f", {n_warn} warning{'s' * (n_warn != 1)}" if n_warn else "")
        elif r.status == "skipped":
            tail = "skipped (up to date)"
        else:
            tail = f"FAILED (exit {r.exit_code}): {r.error}"
        click.echo(f"[{done:>{w}}/{total}] {name} {tail}", err=True)
        if r.report is not None and r.status == "ok" and log.isEnabledFor(logging.DEBUG):
            for warning in r.report.get("warnings", []):
                click.echo(f"    warning: {warning}", err=True)

    return show_line


@cli.command("batch")
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--output-dir", "outdir", required=True, type=click.Path(file_okay=False),
              help="Folder for <take>.bvh, <take>.json and summary.csv (created if missing).")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=None,
              help="Local worker processes [default: the number of cores].")
@click.option("--scheduler", metavar="ADDRESS", default=None,
              help="Run on a Dask cluster (tcp://HOST:PORT) instead of local processes; needs mocapskel[dask].")
@click.option("--force", is_flag=True, help="Fit every take again, even those whose outputs are up to date.")
@click.option("--subjects", "n_subjects", type=click.IntRange(min=1), default=None,
              help="Number of subjects among the takes [default: automatic].")
@fit_options
@bvh_options
@naming_options
@strict_option
@read_options
@cache_options
@common
def batch_cmd(inputs, outdir, jobs, scheduler, force, n_subjects, segments, joint_method, joint_model, rest_frame, up, units,
              names, rest, strict, exclude, include, cache_dir, no_cache):
    """Fit every take of INPUTS (files, folders of .c3d/.trc, globs) and summarise them.

    Writes OUTDIR/<take>.bvh, OUTDIR/<take>.json (the report) and
    OUTDIR/summary.csv (one row per take, with a subject column: takes whose
    skeletons share a topology are grouped by their bone proportions). A
    failed take does not stop the others. Takes whose outputs are newer than
    the input and were made with the same options are skipped (--force
    re-fits them). With --scheduler, the Dask workers read the inputs at the
    same paths, so these must be on a file system every worker sees; the
    outputs are written here. Exit code 1 when a take failed.

    \b
    Examples:
        mocapskel batch takes/ -o out/
        mocapskel batch 'session*/*.c3d' -o out/ --jobs 4 --up z --units mm
        mocapskel batch /shared/takes -o out/ --scheduler tcp://10.0.0.5:8786
    """
    params = pipeline.make_params(segments=segments, joint_method=joint_method, joint_model=joint_model, rest_frame=rest_frame, up=up, units=units,
                                  names=names, rest=rest)
    options = BatchOptions(params=params, read=make_read(exclude, include), cache_dir=cache_dir, use_cache=not no_cache,
                           strict=strict)
    if scheduler and jobs:
        log.warning("warning: --jobs is ignored with --scheduler (the cluster's workers do the work)")
    res = run_batch(inputs, outdir, options, jobs=jobs, scheduler=scheduler, force=force, subjects=n_subjects,
                    progress=_progress_printer(log.isEnabledFor(logging.INFO)))
    subj = res.subjects
    for w in subj.warnings if subj else []:
        log.warning("warning: %s", w)
    c = res.counts
    total = len(res.rows)
    n_subj = subj.n_subjects if subj else 0
    log.info("%d of %d takes fitted, %d up to date, %d failed; %d subject%s; summary: %s",
             c["ok"], total, c["skipped"], c["failed"], n_subj, "s" * (n_subj != 1), res.summary)
    if res.failed:
        raise BatchFailed(f"{res.failed} of {total} takes failed — see {res.summary} (column 'error')")

