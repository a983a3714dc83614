"""One take, worker side (a local process or a Dask worker): read, fitted and rendered; no output written."""
from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator

from .. import pipeline
from ..errors import MocapskelError, interrupt_behind
from .tasks import TakeResult, TakeTask

log = logging.getLogger("mocapskel")

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
    from ..cache import Cache, default_dir
    from ..io.bvh import bvh_text

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
                from ..checks import Finding, strict_error

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


def warm_up() -> None:
    """Import every stage and the BVH writer (about 2 s in a fresh process) before the first take."""
    from ..io import bvh  # noqa: F401

    for s in (*pipeline.STAGES, "export"):
        pipeline.stage_module(s)


def _failed(task: TakeTask, message: str, seconds: float = 0.0) -> TakeResult:
    return TakeResult(task.name, "failed", seconds, error=_one_line(f"{task.input}: {message}"), exit_code=1)


Done = Callable[[TakeTask, TakeResult], None]
