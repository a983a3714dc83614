"""The local runner: takes fitted in worker processes on this machine, interrupted cleanly on Ctrl-C."""
from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any

from .tasks import TakeTask
from .worker import Done, _failed, _in_task, fit_take, warm_up


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



def _on_sigint(signum: int, frame: Any) -> None:  # pragma: no cover - runs in worker processes
    _in_task.interrupted = True  # and the takes already queued to this worker will not start
    if getattr(_in_task, "active", False):
        raise KeyboardInterrupt



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
