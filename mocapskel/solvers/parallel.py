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
import signal
import sys
import warnings
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

__all__ = ["Shares", "WorkerLost", "defer_signal", "forking", "n_threads", "run_ahead", "run_blocks",
           "run_forked"]

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


def run_ahead(fn: Callable[[T], R], items: Iterable[T], ahead: int | None = None) -> Iterator[R]:
    """``fn(x)`` for every item, yielded in order, computed on threads at most ``ahead`` items
    (default: twice the threads) ahead of the consumer: results not yet taken are held, so that a
    long stream of large results (a long take's text, block by block) stays within a few blocks."""
    items = list(items)
    k = min(n_threads(), len(items))
    if k <= 1:
        yield from map(fn, items)
        return
    ahead = max(k, ahead or 2 * k)
    with ThreadPoolExecutor(max_workers=k, thread_name_prefix="mocapskel") as ex:
        pending = deque(ex.submit(fn, x) for x in items[:ahead])
        nxt = ahead
        while pending:
            out = pending.popleft().result()
            if nxt < len(items):
                pending.append(ex.submit(fn, items[nxt]))
                nxt += 1
            yield out


def run_forked(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[fn(x) for x in items]``, each item done in a forked child (``n_threads()`` children at a
    time, the next forked as one finishes), the children's results (or exceptions) sent back pickled.

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
            # this process only hands out the items: k children at a time, the next forked as soon as
            # one is done (tasks of unequal length: a child that finishes early never waits for a
            # long task of this process's own)
            while pending and len(running) < k:
                i = pending.pop(0)
                r, w = os.pipe()
                try:
                    pid = _fork()
                except OSError:  # no process to be had: the item is done here
                    os.close(r)
                    os.close(w)
                    out[i] = (True, fn(items[i]))
                    continue
                if pid == 0:
                    _child(fn, items[i], r, w)
                os.close(w)
                running[r] = (i, pid, bytearray())
                sel.register(r, selectors.EVENT_READ)
            if running:
                collect(None)
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


_FORKING = False  # inside os.fork(), its at-fork hooks included (see _fork)
_DEFERRED: list[int] = []  # signals that arrived then, sent again once the fork is done


def forking() -> bool:
    """Whether this process is inside :func:`os.fork` (its at-fork hooks included), where an exception
    raised by a signal handler is not raised but printed with its traceback and dropped."""
    return _FORKING


def defer_signal(signum: int) -> None:
    """Have the signal ``signum``, which arrived while :func:`forking`, sent again to this process once the
    fork is done (a handler that would raise calls this instead while forking)."""
    _DEFERRED.append(int(signum))


def _fork() -> int:
    """``os.fork()``. Python 3.12+ warns of fork in a process with threads; ours are numpy's BLAS
    threads, which their library quiesces across a fork, and none of our own.

    A signal whose handler raises (the command line's SIGTERM and SIGINT) may arrive while the fork runs
    Python's at-fork hooks (logging releases its lock there), where the exception would be printed and
    dropped: the handler defers it (:func:`defer_signal`), and once the fork is done the new child is
    ended and the signal sent again, to be raised here.
    """
    global _FORKING
    _FORKING = True
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*multi-threaded.*fork", category=DeprecationWarning)
            pid = os.fork()
    finally:
        _FORKING = False
    if pid == 0:
        _DEFERRED.clear()  # the parent's to deal with
        return pid
    if _DEFERRED:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        while _DEFERRED:
            signal.raise_signal(_DEFERRED.pop(0))
    return pid


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


class WorkerLost(RuntimeError):
    """A forked worker of :class:`Shares` ended without answering (killed, or out of memory)."""


class Shares:
    """Items of one long computation shared out between this process and forked children, each item
    always done by the same process, which keeps what it computed for it between calls.

    ``fn(j, msg)`` runs in item ``j``'s process and returns its reply; ``call([msg_0, msg_1, ...])``
    sends every item its message and returns the replies in item order. Item ``j`` belongs to
    process ``j % k`` (``k = n_threads()`` processes, this one the first): the rounds of an
    iterative solver over blocks of frames, whose every round holds the interpreter lock too much
    for threads to share the cores, and whose blocks' state (large) stays where it was made while
    the messages and replies (small) go between the processes. The children are forked when the
    object is made, so ``fn`` sees this process's memory as it was then; with one core, where fork
    is not there, or in a child of :func:`run_forked`, every item is done here. Use as a context
    manager (the children end with it). Raises :class:`WorkerLost` when a child is lost (the caller
    can start again with ``processes=1``: every item in this process).
    """

    def __init__(self, fn: Callable[[int, object], object], n_items: int, processes: int | None = None):
        self.fn = fn
        self.n = n_items
        k = min(n_threads() if processes is None else max(1, processes), n_items)
        if k <= 1 or not sys.platform.startswith("linux") or not hasattr(os, "fork"):
            k = 1
        self.k = k
        self.children: list[tuple[int, int, int]] = []  # (pid, write end to it, read end from it)
        global _FORCED
        prev = _FORCED
        try:
            _FORCED = 1  # the children's own run_blocks: one thread each
            for c in range(1, k):
                r1, w1 = os.pipe()
                r2, w2 = os.pipe()
                try:
                    pid = _fork()
                except OSError:  # no more processes: this one does the rest
                    for fd in (r1, w1, r2, w2):
                        os.close(fd)
                    self.k = c
                    break
                if pid == 0:
                    os.close(w1)
                    os.close(r2)
                    for _, w, r in self.children:
                        os.close(w)
                        os.close(r)
                    _serve(fn, r1, w2)
                os.close(r1)
                os.close(w2)
                self.children.append((pid, w1, r2))
        except BaseException:
            self.close()
            raise
        finally:
            _FORCED = prev

    def call(self, msgs: list) -> list:
        """Every item's reply to its message (``msgs[j]`` for item ``j``), in item order."""
        k = self.k
        for c, (_, w, _) in enumerate(self.children, start=1):
            _send(w, [(j, msgs[j]) for j in range(c, self.n, k)])
        out: list = [None] * self.n
        for j in range(0, self.n, k):
            out[j] = self.fn(j, msgs[j])
        for c, (_, _, r) in enumerate(self.children, start=1):
            got = _receive(r)
            if got is None:
                raise WorkerLost("a worker process ended unexpectedly")
            ok, replies = got
            if not ok:
                raise replies
            for j, rep in zip(range(c, self.n, k), replies):
                out[j] = rep
        return out

    def close(self) -> None:
        for pid, w, r in self.children:
            for fd in (w, r):
                try:
                    os.close(fd)
                except OSError:
                    pass
            try:
                os.kill(pid, 9)
                os.waitpid(pid, 0)
            except OSError:
                pass
        self.children = []

    def __enter__(self) -> "Shares":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _send(fd: int, obj) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(len(data).to_bytes(8, "little") + data)
    while view:
        view = view[os.write(fd, view):]


def _read_exactly(fd: int, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        chunk = os.read(fd, min(n - len(buf), 1 << 20))
        if not chunk:
            return None
        buf.extend(chunk)
    return bytes(buf)


def _receive(fd: int):
    head = _read_exactly(fd, 8)
    if head is None:
        return None
    data = _read_exactly(fd, int.from_bytes(head, "little"))
    return None if data is None else pickle.loads(data)


def _serve(fn, r: int, w: int) -> None:
    """In a forked child of :class:`Shares`: answer each batch of (item, message) with the items'
    replies (or the first exception) until the parent closes the pipe; leaves without exit handlers."""
    code = 0
    try:
        while True:
            batch = _receive(r)
            if batch is None:
                break
            try:
                reply = (True, [fn(j, msg) for j, msg in batch])
            except BaseException as exc:  # noqa: BLE001 - sent to the parent, raised there
                reply = (False, exc)
            try:
                _send(w, reply)
            except (pickle.PicklingError, TypeError, AttributeError):
                _send(w, (False, RuntimeError("a worker's reply would not pickle")))
    except BaseException:  # noqa: BLE001 - the parent is gone or interrupted: nothing to report to
        code = 1
    os._exit(code)
