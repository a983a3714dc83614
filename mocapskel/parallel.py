"""Threads for the kernels' independent blocks of frames.

numpy releases the interpreter lock inside its array operations, so blocks of
frames solved independently (IK, rigid fits) run side by side on the cores.
Every block writes its own frames only, so the result does not depend on the
number of threads or their timing.

``MOCAPSKEL_THREADS`` sets the number of threads (default: the cores this
process may use, at most 4; ``1`` turns threading off). ``batch`` gives each of
its worker processes its share of the cores.

Work that is many small array operations (a Levenberg–Marquardt iteration over a
few hundred frames) holds the interpreter lock most of the time, so threads run
it one after the other; :func:`run_forked` runs such independent tasks in forked
processes instead (on Linux; elsewhere, and with one core, as ``run_blocks``).
"""
from __future__ import annotations

import os
import pickle
import selectors
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, TypeVar

__all__ = ["n_threads", "run_blocks", "run_forked"]

T = TypeVar("T")
R = TypeVar("R")


_FORCED: int | None = None  # threads in a forked worker (see run_forked)


def n_threads() -> int:
    """Threads to use: ``MOCAPSKEL_THREADS`` if set (>= 1), else the usable cores, at most 4."""
    if _FORCED is not None:
        return _FORCED
    env = os.environ.get("MOCAPSKEL_THREADS", "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, min(cores, 4))


def run_blocks(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[fn(x) for x in items]``, on several threads when there is more than one item."""
    items = list(items)
    k = min(n_threads(), len(items))
    if k <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(max_workers=k, thread_name_prefix="mocapskel") as ex:
        return list(ex.map(fn, items))


def run_forked(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[fn(x) for x in items]``, the items shared out between this process and forked children
    (``n_threads()`` processes at a time), the children's results (or exceptions) sent back pickled.

    For independent tasks of a fraction of a second or more whose results are small; a child sees
    this process's memory as it was at its fork and changes nothing in it. In every process, the
    task's own ``run_blocks`` runs on one thread (the cores are shared out by the processes). Falls
    back to :func:`run_blocks` where fork is not safe or not there (not Linux), or with one core.
    """
    items = list(items)
    k = min(n_threads(), len(items))
    if k <= 1 or not sys.platform.startswith("linux") or not hasattr(os, "fork"):
        return run_blocks(fn, items)
    global _FORCED
    out: dict[int, tuple[bool, object]] = {}
    pending = list(range(len(items)))
    running: dict[int, tuple[int, int, bytearray]] = {}  # read end -> (item, pid, bytes so far)
    sel = selectors.DefaultSelector()
    prev = _FORCED

    def collect(timeout: float | None) -> None:
        # read what the children have sent; a child whose pipe is closed is done
        for key, _ in sel.select(timeout):
            r = key.fd
            chunk = os.read(r, 1 << 20)
            if chunk:
                running[r][2].extend(chunk)
                continue
            i, pid, data = running.pop(r)
            sel.unregister(r)
            os.close(r)
            os.waitpid(pid, 0)
            # a child that sent nothing (killed, or its result would not pickle): done here
            # instead, which gives its result or raises its error
            out[i] = pickle.loads(bytes(data)) if data else (True, fn(items[i]))

    try:
        _FORCED = 1
        while pending or running:
            if running:
                collect(0.0 if pending else None)
            while len(pending) > 1 and len(running) < k - 1:  # children take the later items
                i = pending.pop()
                r, w = os.pipe()
                with warnings.catch_warnings():
                    # Python 3.12+ warns of fork in a process with threads; ours are numpy's BLAS
                    # threads, which their library quiesces across a fork, and none of our own
                    warnings.filterwarnings("ignore", message=".*multi-threaded.*fork", category=DeprecationWarning)
                    pid = os.fork()
                if pid == 0:
                    _child(fn, items[i], r, w)
                os.close(w)
                running[r] = (i, pid, bytearray())
                sel.register(r, selectors.EVENT_READ)
            if pending:  # this process takes the next item itself
                i = pending.pop(0)
                out[i] = (True, fn(items[i]))
    finally:
        _FORCED = prev
        for r, (_, pid, _) in running.items():  # after an error: the others are not waited for
            try:
                os.kill(pid, 9)
                os.waitpid(pid, 0)
                os.close(r)
            except OSError:
                pass
        sel.close()
    results = []
    for i in range(len(items)):
        ok, value = out[i]
        if not ok:
            raise value
        results.append(value)
    return results


def _child(fn, item, r: int, w: int) -> None:
    """In a forked child: ``fn(item)`` (or its exception) pickled to ``w``; leaves without running exit
    handlers. Sends nothing when that will not pickle (the parent then does the item itself)."""
    code = 0
    try:
        os.close(r)
        try:
            result = (True, fn(item))
        except BaseException as exc:  # noqa: BLE001 - sent to the parent, raised there
            result = (False, exc)
        payload = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
        with os.fdopen(w, "wb") as f:
            f.write(payload)
    except BaseException:  # noqa: BLE001 - nothing left to report to: the parent redoes the item
        code = 1
    os._exit(code)
