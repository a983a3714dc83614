"""The Dask runner: takes fitted on a Dask cluster through a ``distributed`` client."""
from __future__ import annotations

import contextlib
import hashlib
import os
import time
from collections.abc import Sequence
from typing import Any

from ..errors import UsageError
from .tasks import TakeTask
from .worker import Done, _failed, _one_line, fit_take, warm_up


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
