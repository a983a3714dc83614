"""The pipeline's entry points: the BLAS libraries on one thread each while they run (the workers are the
package's own), and the C allocator set to keep a long take's large arrays (:mod:`mocapskel.solvers.allocator`)."""
from __future__ import annotations

from typing import Callable, TypeVar

R = TypeVar("R")


def one_blas_thread(fn: Callable[..., R]) -> Callable[..., R]:
    """``fn`` with the BLAS libraries on one thread each while it runs (the package sets the same
    through their variables, which act only where numpy was imported after it), unless the user set
    ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` or ``MKL_NUM_THREADS``. With BLAS threads of their
    own, the forked workers and threads of :mod:`mocapskel.solvers.parallel` (``run_forked``, ``Shares``, ``run_blocks``)
    spin against each other: a fit took twice as long. The allocator is set on the first call
    (:func:`~mocapskel.solvers.allocator.keep_large_blocks`)."""
    import functools

    import mocapskel
    from .solvers.allocator import keep_large_blocks

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        keep_large_blocks()
        if mocapskel.BLAS_THREADS_CHOSEN:
            return fn(*args, **kwargs)
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
