"""Threads for the kernels' independent blocks of frames.

numpy releases the interpreter lock inside its array operations, so blocks of
frames solved independently (IK, rigid fits) run side by side on the cores.
Every block writes its own frames only, so the result does not depend on the
number of threads or their timing.

``MOCAPSKEL_THREADS`` sets the number of threads (default: the cores this
process may use, at most 4; ``1`` turns threading off). ``batch`` gives each of
its worker processes its share of the cores.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, TypeVar

__all__ = ["n_threads", "run_blocks"]

T = TypeVar("T")
R = TypeVar("R")


def n_threads() -> int:
    """Threads to use: ``MOCAPSKEL_THREADS`` if set (>= 1), else the usable cores, at most 4."""
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
