"""The BLAS libraries on one thread each while the pipeline runs (its workers are the package's own)."""
from __future__ import annotations

from typing import Callable, TypeVar

R = TypeVar("R")


def one_blas_thread(fn: Callable[..., R]) -> Callable[..., R]:
    """``fn`` with the BLAS libraries on one thread each while it runs (the package sets the same
    through their variables, which act only where numpy was imported after it), unless the user set
    ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` or ``MKL_NUM_THREADS``. With BLAS threads of their
    own, the forked workers and threads of :mod:`mocapskel.solvers.parallel` (``run_forked``, ``Shares``, ``run_blocks``)
    spin against each other: a fit took twice as long."""
    import functools

    import mocapskel

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if mocapskel.BLAS_THREADS_CHOSEN:
            return fn(*args, **kwargs)
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
