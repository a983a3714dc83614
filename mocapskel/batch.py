"""Many takes at once: locally in worker processes or on a Dask cluster.

    run_batch(inputs, outdir, options)      fit every take, write <take>.bvh, <take>.json
                                            and summary.csv, identify subjects

Work is split so that it runs the same on one machine and on a cluster:

- the *workers* run :func:`fit_take`: they read the input take from its path
  (so on a cluster the inputs must be at the same path on every worker, e.g. a
  shared file system), use their own artifact cache, and send back the BVH
  text and the report;
- the *client* (this process) expands the inputs, skips takes whose outputs are
  up to date, writes every output atomically (:mod:`mocapskel.io.atomic`) and
  the summary. Outputs never need to be visible to the workers, and an
  interrupted batch leaves no partial file behind.

Subject identification (Kirk et al. 2005, §5: skeletons of one person have
the same proportions) compares the joint-to-joint bone lengths of fitted
skeletons that share a topology; see :func:`proportion_distance`,
:func:`compare_reports` and :func:`identify_subjects`.
"""
from __future__ import annotations

import contextlib
import csv
import dataclasses
import glob
import hashlib
import io
import json
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__, pipeline
from .errors import InputError, MocapskelError, UsageError, interrupt_behind
from .io.atomic import AtomicOutputs, atomic_open
from .pipeline import ReadOptions

log = logging.getLogger("mocapskel")

#: Extensions taken from folders and globs (explicitly named files are taken whatever they are).
TAKE_SUFFIXES: tuple[str, ...] = (".c3d", ".trc")
SUMMARY_NAME = "summary.csv"
#: Columns of ``summary.csv``, in order.
SUMMARY_COLUMNS: tuple[str, ...] = (
    "take", "input", "status", "exit_code", "error", "frames", "markers", "segments",
    "bone_lengths_mm", "ik_rms_mm", "warnings", "seconds", "subject",
)  # fmt: skip
#: Take statuses: fitted now, outputs already up to date (not re-run), failed.
STATUSES: tuple[str, ...] = ("ok", "skipped", "failed")

#: Two skeletons whose proportion distance (percent) is at most this are "likely" the same
#: subject; it is also the smallest distance at which automatic clustering separates subjects.
SAME_SUBJECT_PCT = 0.5
#: Automatic clustering: the distance between subjects must be at least this many times
#: the spread within them (the largest merge below the cut).
GAP_RATIO = 1.5
#: The spread within a subject is never taken below this (percent): measurement noise.
SPREAD_FLOOR_PCT = 0.25
#: With at least this many bones compared, the worst one is left out of the distance.
TRIM_MIN_BONES = 5


# --------------------------------------------------------------------------- inputs


def _is_glob(s: str) -> bool:
    return any(c in s for c in "*?[")


def _takes_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in TAKE_SUFFIXES)


def collect_inputs(patterns: Sequence[str | os.PathLike]) -> list[Path]:
    """Expand the command line's INPUTS into take files, in order, without repeats.

    Parameters
    ----------
    patterns : sequence of str or PathLike
        Files (taken whatever their extension: a file that is not a take fails
        as that take), folders (their ``.c3d`` and ``.trc`` files, not
        recursive) and glob patterns (``**`` recurses; the ``.c3d``/``.trc``
        files they match, and those of the folders they match).

    Returns
    -------
    list of Path
        Sorted within each pattern, in the order of the patterns; a file named
        twice is kept once (the first time).

    Raises
    ------
    UsageError
        A pattern that names nothing (no such file or folder, a glob matching
        no take), or no take at all.
    """
    out: list[Path] = []
    seen: set[str] = set()

    def add(p: Path) -> None:
        k = os.path.normcase(os.path.abspath(p))
        if k not in seen:
            seen.add(k)
            out.append(p)

    for pat in patterns:
        s = os.fspath(pat)
        p = Path(s)
        if p.is_dir():
            found = _takes_in(p)
            if not found:
                raise UsageError(f"folder {s} holds no .c3d or .trc file — give the takes or another folder")
        elif p.exists():
            found = [p]
        elif _is_glob(s):
            found = []
            for m in sorted(glob.glob(s, recursive=True)):
                q = Path(m)
                if q.is_dir():
                    found.extend(_takes_in(q))
                elif q.is_file() and q.suffix.lower() in TAKE_SUFFIXES:
                    found.append(q)
            if not found:
                raise UsageError(f"{s} matches no .c3d or .trc file — check the pattern")
        else:
            raise UsageError(f"{s}: no such file or folder — check the path")
        for q in found:
            add(q)
    if not out:
        raise UsageError("no takes given — name files, folders or globs")
    return out


def take_names(paths: Sequence[Path]) -> list[str]:
    """Output base names, one per take: the file's stem, made unique.

    Stems that clash (``a/run.c3d`` and ``b/run.trc``, compared without case)
    get the extension appended (``run_c3d``) and then, if still clashing, a
    counter (``run_c3d_2``) in input order.
    """
    stems = [p.stem for p in paths]
    low = [s.lower() for s in stems]
    names = [s if low.count(s.lower()) == 1 else f"{s}_{p.suffix.lstrip('.').lower() or 'take'}"
             for s, p in zip(stems, paths)]
    taken: set[str] = set()
    out = []
    for n in names:
        cand, k = n, 2
        while cand.lower() in taken:
            cand, k = f"{n}_{k}", k + 1
        taken.add(cand.lower())
        out.append(cand)
    return out


# --------------------------------------------------------------------------- options and tasks


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


# --------------------------------------------------------------------------- one take (worker side)

_in_task = threading.local()


@contextlib.contextmanager
def _quiet_logging() -> Iterator[None]:
    """Keep a worker's per-stage log lines out of the batch's output (the report has the warnings)."""
    old = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(old)


def fit_take(task: TakeTask) -> TakeResult:
    """Fit one take: read it, run the pipeline, render the BVH; never raises for a bad take.

    Runs in a worker (a local process or a Dask worker): it reads
    ``task.input`` and the artifact cache but writes no output file.

    Parameters
    ----------
    task : TakeTask

    Returns
    -------
    TakeResult
        ``status="ok"`` with ``bvh`` (text) and ``report`` (with a ``batch``
        record: options hash, input path); or ``status="failed"`` with the
        one-line error and the exit code category (3 unreadable input, 4 the
        data cannot support a skeleton, 2 bad usage, 1 unexpected).
    """
    from .cache import Cache, default_dir
    from .io.bvh import bvh_text

    if getattr(_in_task, "interrupted", False):  # a worker told to stop takes nothing new
        raise KeyboardInterrupt
    t0 = time.perf_counter()
    opts = task.options
    _in_task.active = True
    try:
        with _quiet_logging():
            cache = Cache(opts.cache_dir or default_dir()) if opts.use_cache else Cache(None)
            res = pipeline.fit(task.input, opts.params, cache=cache, read=opts.read)
            if opts.strict and res.report.get("checks"):
                from .checks import Finding, strict_error

                raise strict_error([Finding(c["check"], c["name"], c["message"]) for c in res.report["checks"]], task.input)
            b = res.bvh
            text = bvh_text(b.skeleton, b.root_pos, b.local_rot, b.frame_time)
        report = dict(res.report)
        report["batch"] = {"options_hash": task.options_hash, "input": os.path.abspath(task.input), "take": task.name}
        json.dumps(report, allow_nan=False)  # fail here, in the worker, rather than when writing
        return TakeResult(task.name, "ok", time.perf_counter() - t0, report=report, bvh=text)
    except MocapskelError as e:
        msg = str(e) if e.path else f"{task.input}: {e}"
        return TakeResult(task.name, "failed", time.perf_counter() - t0, error=_one_line(msg), exit_code=e.exit_code)
    except OSError as e:  # the system refused a read (permissions, a vanished file …)
        where = e.filename or task.input
        return TakeResult(task.name, "failed", time.perf_counter() - t0, exit_code=1,
                          error=_one_line(f"{where}: {e.strerror or e} — check the file and its permissions"))
    except MemoryError:
        return TakeResult(task.name, "failed", time.perf_counter() - t0,
                          error=f"{task.input}: out of memory — try a shorter take or fewer markers", exit_code=1)
    except Exception as e:  # a bug: the take fails, the batch goes on
        if (stop := interrupt_behind(e)) is not None:
            raise stop from None  # a Ctrl-C or SIGTERM that Python wrapped: the batch stops, as it would unwrapped
        return TakeResult(task.name, "failed", time.perf_counter() - t0, exit_code=1,
                          error=_one_line(f"{task.input}: unexpected {type(e).__name__}: {e} — "
                                          "run 'mocapskel fit' on it with -v for details and report it"))
    finally:
        _in_task.active = False


def _one_line(s: str) -> str:
    return " ".join(s.split())


# --------------------------------------------------------------------------- outputs (client side)


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


# --------------------------------------------------------------------------- executors


def cpu_count() -> int:
    """Cores this process may use (its CPU affinity where the system says, else all)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not on every system
        return os.cpu_count() or 1


def _thread_env(jobs: int) -> dict[str, str]:
    """Thread counts for the numerical libraries of ``jobs`` worker processes sharing the cores."""
    n = str(max(1, cpu_count() // max(1, jobs)))
    return {k: n for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "MOCAPSKEL_THREADS")
            if k not in os.environ}


@contextlib.contextmanager
def _environ(extra: dict[str, str]) -> Iterator[None]:
    old = {k: os.environ.get(k) for k in extra}
    os.environ.update(extra)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _worker_init() -> None:
    """In a local worker process: Ctrl-C interrupts the take being fitted, never an idle worker;
    the pipeline's modules are imported now, so that a take's time is its own."""
    signal.signal(signal.SIGINT, _on_sigint)
    warm_up()


def warm_up() -> None:
    """Import every stage and the BVH writer (about 2 s in a fresh process) before the first take."""
    from .io import bvh  # noqa: F401

    for s in (*pipeline.STAGES, "export"):
        pipeline.stage_module(s)


def _on_sigint(signum: int, frame: Any) -> None:  # pragma: no cover - runs in worker processes
    _in_task.interrupted = True  # and the takes already queued to this worker will not start
    if getattr(_in_task, "active", False):
        raise KeyboardInterrupt


def _failed(task: TakeTask, message: str, seconds: float = 0.0) -> TakeResult:
    return TakeResult(task.name, "failed", seconds, error=_one_line(f"{task.input}: {message}"), exit_code=1)


Done = Callable[[TakeTask, TakeResult], None]


def run_local(tasks: Sequence[TakeTask], jobs: int, done: Done) -> None:
    """Fit ``tasks`` in ``jobs`` worker processes (spawned), calling ``done`` as each finishes.

    ``jobs == 1`` (or a single task) fits in this process. On Ctrl-C the
    pending takes are cancelled, the running ones interrupted, and
    KeyboardInterrupt is raised again.
    """
    if jobs <= 1 or len(tasks) <= 1:
        for t in tasks:
            done(t, fit_take(t))
        return
    n = min(jobs, len(tasks))
    with _environ(_thread_env(n)):
        ex = ProcessPoolExecutor(max_workers=n, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_worker_init)
        futures: dict[Future, TakeTask] = {}
        try:
            futures = {ex.submit(fit_take, t): t for t in tasks}
            pending = set(futures)
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in sorted(finished, key=lambda f: tasks.index(futures[f])):
                    t = futures[f]
                    try:
                        r = f.result()
                    except Exception as e:  # the worker died (killed, out of memory …)
                        r = _failed(t, f"the worker process died ({type(e).__name__}: {e}) — fit it alone with 'mocapskel fit'")
                    done(t, r)
        except BaseException:  # Ctrl-C, SIGTERM: stop the workers, then go
            for f in futures:
                f.cancel()
            _stop_workers(ex)
            raise
        ex.shutdown(wait=True)


def _stop_workers(ex: ProcessPoolExecutor, grace: float = 5.0) -> None:
    """Interrupt the takes being fitted (SIGINT: their temporary files are removed), let the workers
    exit, and terminate those still there after ``grace`` seconds."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(OSError, ValueError, AttributeError):
            if p.is_alive():
                os.kill(p.pid, signal.SIGINT)
    ex.shutdown(wait=False, cancel_futures=True)
    deadline = time.monotonic() + grace
    for p in procs:
        with contextlib.suppress(OSError, ValueError, AttributeError):
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.terminate()
                p.join(1.0)


def dask_client(address: str, timeout: float = 20.0) -> Any:
    """A ``dask.distributed.Client`` connected to the scheduler at ``address``.

    Raises
    ------
    UsageError
        Dask is not installed ("install mocapskel[dask]"), or the scheduler
        cannot be reached.
    """
    try:
        from distributed import Client
    except ImportError:
        raise UsageError("--scheduler needs Dask: install mocapskel[dask] (pip install 'mocapskel[dask]')") from None
    try:
        return Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise UsageError(f"cannot reach the Dask scheduler at {address} ({_one_line(str(e)) or type(e).__name__}) "
                         "— check the address and that the scheduler is running") from None


def run_dask(tasks: Sequence[TakeTask], client: Any, done: Done) -> None:
    """Fit ``tasks`` on a Dask cluster through ``client``, calling ``done`` as each finishes.

    The workers must be able to import mocapskel and read every input at
    the path given. On Ctrl-C the takes not finished are cancelled and
    KeyboardInterrupt is raised again.
    """
    from distributed import as_completed

    token = hashlib.sha256(f"{os.getpid()}-{time.time_ns()}".encode()).hexdigest()[:12]
    futures = {}
    with contextlib.suppress(Exception):  # import the pipeline on every worker first (else the first take pays)
        client.run(warm_up)
    try:
        for i, t in enumerate(tasks):
            f = client.submit(fit_take, t, key=f"mocapskel-fit-{i}-{token}", pure=False)
            futures[f.key] = (f, t)
        for f in as_completed([f for f, _ in futures.values()], loop=client.loop):
            t = futures[f.key][1]
            try:
                r = f.result()
            except Exception as e:  # a worker died, or cannot import mocapskel
                r = _failed(t, f"failed on the Dask cluster ({type(e).__name__}: {_one_line(str(e))}) "
                               "— check that the workers have mocapskel and can read the input")
            done(t, r)
            f.release()
    except BaseException:
        with contextlib.suppress(Exception):
            client.cancel([f for f, _ in futures.values()], force=True)
        raise


# --------------------------------------------------------------------------- the batch


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


# --------------------------------------------------------------------------- summary


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


# --------------------------------------------------------------------------- skeletons and proportions


_REPORT_FIX = "give the JSON written by 'fit --report' or 'batch', unedited"


@dataclass(frozen=True)
class Bones:
    """A fitted skeleton's tree and bone lengths, from a report's ``bones`` (and ``segments``).

    Attributes
    ----------
    names : tuple of str
        Segment names.
    parent : (S,) int ndarray
        Parent segment, -1 for the root (the tree's centre, as the fit chose it).
    length : (S,) float ndarray
        Bone length in mm (NaN where the report has none).
    labels : tuple of frozenset of str
        Marker labels of each segment (empty when the report does not say).
    source : str
        Where the report came from (for messages).
    """

    names: tuple[str, ...]
    parent: np.ndarray
    length: np.ndarray
    labels: tuple[frozenset[str], ...]
    source: str = ""

    @classmethod
    def from_report(cls, report: dict, source: str = "") -> Bones:
        """Read ``report["bones"]`` (``segment``, ``parent``, ``length_mm``).

        Raises
        ------
        InputError
            Not a fit report, or its bones do not form one tree.
        """
        bones = report.get("bones") if isinstance(report, dict) else None
        if not isinstance(bones, list) or not bones:
            raise InputError("not a fit report (no 'bones') — give the JSON written by 'fit --report' or 'batch'", source or None)
        try:
            names = tuple(str(b["segment"]) for b in bones)
            parents = [b.get("parent") for b in bones]
            lengths = [b.get("length_mm") for b in bones]
        except (KeyError, TypeError, AttributeError):
            raise InputError("damaged report: every bone needs 'segment', 'parent' and 'length_mm' — " + _REPORT_FIX, source or None) from None
        index = {n: i for i, n in enumerate(names)}
        if len(index) != len(names):
            raise InputError("damaged report: repeated segment names in 'bones' — " + _REPORT_FIX, source or None)
        try:
            parent = np.array([-1 if p is None else index[str(p)] for p in parents], dtype=int)
        except (KeyError, TypeError) as e:
            raise InputError(f"damaged report: bone parent {str(e.args[0])[:40]!r} is not a segment — {_REPORT_FIX}", source or None) from None
        bad = [x for x in lengths if x is not None and (isinstance(x, bool) or not isinstance(x, (int, float))
                                                         or not 0 <= float(x) <= 1e7)]
        if bad:
            raise InputError(f"damaged report: bone length {str(bad[0])[:40]!r} is not a length in mm (0 to 1e7)"
                             f" — {_REPORT_FIX}", source or None)
        length = np.array([np.nan if x is None else float(x) for x in lengths], dtype=float)
        if np.count_nonzero(parent < 0) != 1 or not _is_tree(parent):
            raise InputError(f"damaged report: the bones do not form one tree — {_REPORT_FIX}", source or None)
        seg_labels = {}
        segments = report.get("segments")
        for s in segments if isinstance(segments, list) else []:
            if isinstance(s, dict) and "name" in s and isinstance(s.get("markers"), list):
                seg_labels[str(s["name"])] = frozenset(str(m) for m in s["markers"])
        labels = tuple(seg_labels.get(n, frozenset()) for n in names)
        return cls(names, parent, length, labels, source)

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent < 0)[0])

    def children(self) -> list[list[int]]:
        kids: list[list[int]] = [[] for _ in range(self.n)]
        for s, p in enumerate(self.parent.tolist()):
            if p >= 0:
                kids[p].append(s)
        return kids

    @property
    def inner(self) -> np.ndarray:
        """(S,) bool: segments with children, whose bone runs joint to joint (a leaf's runs to its End Site)."""
        m = np.zeros(self.n, dtype=bool)
        m[self.parent[self.parent >= 0]] = True
        return m

    def canonical(self) -> list[str]:
        """Canonical form of every rooted subtree (AHU encoding: equal strings ⇔ isomorphic subtrees)."""
        kids = self.children()
        out = [""] * self.n
        for s in _postorder(kids, self.root):
            out[s] = "(" + "".join(sorted(out[c] for c in kids[s])) + ")"
        return out

    @property
    def topology(self) -> str:
        """Canonical form of the whole tree, rooted where the fit rooted it."""
        return self.canonical()[self.root]


def _is_tree(parent: np.ndarray) -> bool:
    n = parent.size
    for s in range(n):
        seen, p = 0, s
        while p >= 0:
            p = int(parent[p])
            seen += 1
            if seen > n:
                return False
    return True


def _postorder(kids: list[list[int]], root: int) -> list[int]:
    order, stack = [], [root]
    while stack:
        s = stack.pop()
        order.append(s)
        stack.extend(kids[s])
    return order[::-1]


def _proportions(b: Bones) -> np.ndarray:
    """Lengths of the inner bones over their total (NaN elsewhere); for the cost of a tree match."""
    ok = b.inner & np.isfinite(b.length) & (b.length > 0)
    p = np.full(b.n, np.nan)
    if ok.any():
        p[ok] = b.length[ok] / b.length[ok].sum()
    return p


def _label_match(a: Bones, b: Bones) -> np.ndarray | None:
    """b's segment for each of a's, by marker labels, if that is a tree isomorphism (same root)."""
    if a.n != b.n or not all(a.labels) or not all(b.labels):
        return None
    index = {lab: j for j, lab in enumerate(b.labels)}
    if len(index) != b.n or len(set(a.labels)) != a.n:
        return None
    try:
        m = np.array([index[lab] for lab in a.labels], dtype=int)
    except KeyError:
        return None
    for i, p in enumerate(a.parent.tolist()):
        q = int(b.parent[m[i]])
        if (p < 0) != (q < 0) or (p >= 0 and m[p] != q):
            return None
    return m


def _tree_match(a: Bones, b: Bones) -> np.ndarray | None:
    """b's segment for each of a's by the tree structure; among equivalent subtrees (left/right limbs),
    the assignment whose proportions differ least. None if the rooted trees differ."""
    from scipy.optimize import linear_sum_assignment

    ca, cb = a.canonical(), b.canonical()
    if ca[a.root] != cb[b.root]:
        return None
    pa, pb = _proportions(a), _proportions(b)
    ka, kb = a.children(), b.children()
    memo: dict[tuple[int, int], tuple[float, list[tuple[int, int]]]] = {}

    def cost(u: int, v: int) -> float:
        x, y = pa[u], pb[v]
        if not (np.isfinite(x) and np.isfinite(y)):
            return 0.0
        return float((x - y) ** 2 / max((x + y) / 2, 1e-12))

    def rec(u: int, v: int) -> tuple[float, list[tuple[int, int]]]:
        if (u, v) in memo:
            return memo[(u, v)]
        total, pairs = cost(u, v), [(u, v)]
        groups: dict[str, tuple[list[int], list[int]]] = {}
        for c in ka[u]:
            groups.setdefault(ca[c], ([], []))[0].append(c)
        for c in kb[v]:
            groups[cb[c]][1].append(c)
        for xs, ys in groups.values():
            if len(xs) == 1:
                sub = [rec(xs[0], ys[0])]
            else:
                C = np.array([[rec(x, y)[0] for y in ys] for x in xs])
                r, c = linear_sum_assignment(C)
                sub = [rec(xs[i], ys[j]) for i, j in zip(r, c)]
            for t, p in sub:
                total += t
                pairs += p
        memo[(u, v)] = (total, pairs)
        return memo[(u, v)]

    _, pairs = rec(a.root, b.root)
    m = np.full(a.n, -1, dtype=int)
    for u, v in pairs:
        m[u] = v
    return m


def match_bones(a: Bones, b: Bones) -> tuple[np.ndarray, str] | None:
    """Which segment of ``b`` is each segment of ``a``.

    By the segments' marker labels when both skeletons have the same label
    sets and these give the same tree; otherwise by the tree structure, rooted
    where each fit rooted it (subtrees matched by canonical form, equivalent
    siblings — left and right limbs — paired so that their proportions differ
    least).

    Returns
    -------
    (mapping, how) or None
        ``mapping`` (S,) int ndarray: ``b``'s index for each of ``a``'s
        segments; ``how`` is ``"labels"`` or ``"tree"``. None when the
        topologies differ.
    """
    m = _label_match(a, b)
    if m is not None:
        return m, "labels"
    m = _tree_match(a, b)
    return (m, "tree") if m is not None else None


@dataclass
class Comparison:
    """How alike two fitted skeletons are (see :func:`compare_bones`).

    Attributes
    ----------
    a, b : Bones
    mapping : (S,) int ndarray or None
        ``b``'s segment for each of ``a``'s; None when the topologies differ.
    matched_by : str
        ``"labels"``, ``"tree"`` or ``""``.
    used : (S,) bool ndarray
        Bones (of ``a``, matched) that enter the distance.
    relative_difference : (S,) float ndarray
        Per bone, (proportion in b − proportion in a) / their mean, NaN where unused.
    distance_pct : float
        Proportion distance in percent (NaN if it cannot be computed).
    scale : float
        Total length of the bones kept in ``b`` over that in ``a``.
    threshold_pct : float
        The same-subject threshold used for ``same_subject``.
    left_out : int
        The bone (of ``a``) left out of the distance as the worst, -1 if none.
    """

    a: Bones
    b: Bones
    mapping: np.ndarray | None
    matched_by: str
    used: np.ndarray
    relative_difference: np.ndarray
    distance_pct: float
    scale: float
    threshold_pct: float = SAME_SUBJECT_PCT
    left_out: int = -1

    @property
    def same_subject(self) -> bool:
        """True when the proportions agree within the threshold."""
        return bool(np.isfinite(self.distance_pct) and self.distance_pct <= self.threshold_pct)


def _weighted_rms(la: np.ndarray, lb: np.ndarray, keep: np.ndarray) -> tuple[float, np.ndarray]:
    pa, pb = la / la[keep].sum(), lb / lb[keep].sum()
    m = (pa + pb) / 2
    r = (pb - pa) / m
    return float(np.sqrt(np.sum(m[keep] * r[keep] ** 2) / np.sum(m[keep])) * 100.0), r


def proportion_distance(la: np.ndarray, lb: np.ndarray, trim: bool = True) -> tuple[float, np.ndarray, int]:
    """Distance between the proportions of two sets of matched bone lengths.

    Each set is normalised by its total (``p = L / ΣL``); with ``m`` the mean
    of the two proportions and ``r = (p_b − p_a) / m`` the relative difference
    of each bone, the distance is the ``m``-weighted RMS of ``r``,
    ``sqrt(Σ m r² / Σ m)``, in percent: long bones weigh more, as their
    relative lengths are better determined, and overall size does not count.

    One badly fitted joint spoils two bones' lengths and, through the total,
    every proportion; so with ``trim`` and at least :data:`TRIM_MIN_BONES`
    bones, the bone with the largest contribution ``m r²`` is left out and the
    distance computed again over the others, normalised by their own total.

    Parameters
    ----------
    la, lb : (K,) array_like
        Matched bone lengths (mm), finite and positive, K ≥ 2.
    trim : bool
        Leave out the worst bone (see above).

    Returns
    -------
    distance_pct : float
    relative_difference : (K,) ndarray
        ``r`` per bone (a fraction), with the normalisation of the bones kept.
    left_out : int
        Index of the bone left out, -1 if none.
    """
    la, lb = np.asarray(la, float), np.asarray(lb, float)
    keep = np.ones(la.size, dtype=bool)
    d, r = _weighted_rms(la, lb, keep)
    if not trim or la.size < TRIM_MIN_BONES:
        return d, r, -1
    pa, pb = la / la.sum(), lb / lb.sum()
    worst = int(np.argmax((pa + pb) / 2 * r**2))
    keep[worst] = False
    d, r = _weighted_rms(la, lb, keep)
    return d, r, worst


def compare_bones(a: Bones, b: Bones, threshold_pct: float = SAME_SUBJECT_PCT) -> Comparison:
    """Compare two fitted skeletons' proportions.

    The bones compared are the joint-to-joint ones (segments with children)
    whose length is known in both skeletons: an End Site's length depends on
    where the markers were put, not on the subject. When fewer than two such
    bones match (a three-rod linkage), every matched bone with a length is used.
    """
    S = a.n
    nan = np.full(S, np.nan)
    mm = match_bones(a, b)
    if mm is None:
        return Comparison(a, b, None, "", np.zeros(S, bool), nan, float("nan"), float("nan"), threshold_pct)
    m, how = mm
    la, lb = a.length, b.length[m]
    known = np.isfinite(la) & np.isfinite(lb) & (la > 0) & (lb > 0)
    used = known & a.inner
    if used.sum() < 2:
        used = known
    rel = nan.copy()
    if used.sum() < 2:
        return Comparison(a, b, m, how, used, rel, float("nan"), float("nan"), threshold_pct)
    idx = np.flatnonzero(used)
    d, r, worst = proportion_distance(la[idx], lb[idx])
    rel[idx] = r
    left_out = int(idx[worst]) if worst >= 0 else -1
    kept = used.copy()
    if left_out >= 0:
        kept[left_out] = False
    return Comparison(a, b, m, how, used, rel, d, float(lb[kept].sum() / la[kept].sum()), threshold_pct, left_out)


def compare_reports(a: dict, b: dict, threshold_pct: float = SAME_SUBJECT_PCT, sources: tuple[str, str] = ("", "")) -> Comparison:
    """:func:`compare_bones` on two fit reports (dicts as read from their JSON)."""
    return compare_bones(Bones.from_report(a, sources[0]), Bones.from_report(b, sources[1]), threshold_pct)


# --------------------------------------------------------------------------- subjects


@dataclass
class SubjectResult:
    """Subjects found in a batch.

    Attributes
    ----------
    labels : list of str
        Per take, ``"S1"``, ``"S2"`` … (numbered in order of first take), or
        ``""`` for a take without a skeleton.
    groups : list of list of int
        Takes (indices) of each topology; subjects are only found within one.
    distances : list of (n, n) ndarray
        Proportion distance (percent) between the takes of each group.
    how : list of str
        How each group's count was chosen (``"given"``, ``"gap"``, ``"threshold"``, ``"single"``).
    warnings : list of str
    """

    labels: list[str]
    groups: list[list[int]] = field(default_factory=list)
    distances: list[np.ndarray] = field(default_factory=list)
    how: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def n_subjects(self) -> int:
        return len({s for s in self.labels if s})


def choose_clusters(heights: np.ndarray, threshold_pct: float = SAME_SUBJECT_PCT, gap_ratio: float = GAP_RATIO,
                    floor_pct: float = SPREAD_FLOOR_PCT) -> tuple[int | None, str]:
    """The number of subjects from the merge heights of an average-linkage dendrogram.

    Cutting the dendrogram into ``k`` clusters leaves a *spread* (the highest
    merge below the cut, at least ``floor_pct``: the measurement noise) and a
    *separation* (the lowest merge above it). A cut is acceptable when the
    separation exceeds ``threshold_pct`` and is at least ``gap_ratio`` times
    the spread; the acceptable cut with the largest ratio wins (``"gap"``).
    Without one, the dendrogram is cut at ``threshold_pct`` (returns None,
    ``"threshold"``).

    Parameters
    ----------
    heights : (n-1,) ndarray
        Merge distances (percent), ascending.

    Returns
    -------
    k : int or None
    how : str
    """
    h = np.sort(np.asarray(heights, float))
    n = h.size + 1
    best, best_k = 0.0, None
    for k in range(2, n + 1):
        sep = h[n - k]
        spread = h[n - k - 1] if k < n else 0.0
        ratio = sep / max(spread, floor_pct)
        if sep > threshold_pct and ratio >= gap_ratio and ratio > best:
            best, best_k = ratio, k
    return (best_k, "gap") if best_k is not None else (None, "threshold")


def identify_subjects(
    reports: Sequence[dict | None],
    n_subjects: int | None = None,
    *,
    threshold_pct: float = SAME_SUBJECT_PCT,
) -> SubjectResult:
    """Group takes by subject from their skeletons' proportions (Kirk et al. 2005, §5).

    Takes are grouped by topology first (rooted tree); within a group the
    proportion distance (:func:`compare_bones`) of every pair is clustered by
    average linkage. ``n_subjects`` fixes the count when every take shares
    one topology (with several topologies it is ignored, with a warning);
    otherwise the count is chosen by :func:`choose_clusters`.

    Parameters
    ----------
    reports : sequence of dict or None
        Fit reports, None for a take that failed.
    n_subjects : int, optional
    threshold_pct : float
        Same-subject threshold (percent).

    Returns
    -------
    SubjectResult
    """
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    n = len(reports)
    bones: list[Bones | None] = []
    warnings: list[str] = []
    for i, rep in enumerate(reports):
        if rep is None:
            bones.append(None)
            continue
        try:
            bones.append(Bones.from_report(rep, f"take {i + 1}"))
        except InputError as e:
            bones.append(None)
            warnings.append(f"no subject for take {i + 1}: {e}")
    groups: dict[str, list[int]] = {}
    for i, b in enumerate(bones):
        if b is not None:
            groups.setdefault(b.topology, []).append(i)
    glist = sorted(groups.values(), key=lambda g: g[0])
    if n_subjects is not None and len(glist) > 1:
        warnings.append(f"--subjects {n_subjects} ignored: the takes have {len(glist)} different topologies "
                        "(subjects are chosen automatically within each)")
    cluster_of: dict[int, tuple[int, int]] = {}
    dists, hows = [], []
    for gi, g in enumerate(glist):
        m = len(g)
        D = np.zeros((m, m))
        for x in range(m):
            for y in range(x + 1, m):
                c = compare_bones(bones[g[x]], bones[g[y]], threshold_pct)  # type: ignore[arg-type]
                d = c.distance_pct if np.isfinite(c.distance_pct) else 0.0
                D[x, y] = D[y, x] = d
        dists.append(D)
        if m == 1:
            lab, how = np.array([1]), "single"
        else:
            Z = linkage(squareform(D, checks=False), method="average")
            if n_subjects is not None and len(glist) == 1:
                k, how = min(n_subjects, m), "given"
            else:
                k, how = choose_clusters(Z[:, 2], threshold_pct)
            if k is None:
                lab = fcluster(Z, t=threshold_pct, criterion="distance")
            else:
                lab = fcluster(Z, t=k, criterion="maxclust")
        hows.append(how)
        for x, i in enumerate(g):
            cluster_of[i] = (gi, int(lab[x]))
    names: dict[tuple[int, int], str] = {}
    labels = []
    for i in range(n):
        if i not in cluster_of:
            labels.append("")
            continue
        key = cluster_of[i]
        if key not in names:
            names[key] = f"S{len(names) + 1}"
        labels.append(names[key])
    return SubjectResult(labels, glist, dists, hows, warnings)
