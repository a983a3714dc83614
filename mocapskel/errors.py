"""Error types. Every error the user can cause maps to one documented exit code."""
from __future__ import annotations


class MocapskelError(Exception):
    """Root of every error mocapskel raises on purpose (exit code 1)."""

    exit_code = 1

    def __init__(self, message: str, path: str | None = None):
        self.path = path
        super().__init__(message)

    def __str__(self) -> str:  # "file: what is wrong — what to do"
        msg = super().__str__()
        return f"{self.path}: {msg}" if self.path else msg


class UsageError(MocapskelError):
    """Bad command-line usage (exit code 2)."""

    exit_code = 2


class InputError(MocapskelError):
    """Unreadable or invalid input file (exit code 3)."""

    exit_code = 3


class DataError(MocapskelError):
    """The data cannot support a skeleton: too few markers or frames, nothing moves (exit code 4)."""

    exit_code = 4


def interrupt_behind(e: BaseException) -> BaseException | None:
    """The interrupt an error wraps, if any: the first exception along its causes that is not an
    ``Exception`` (a Ctrl-C's KeyboardInterrupt, the exception a SIGTERM handler raises).

    Python 3.11 turns an exception raised while a class is created (a dataclass's field, during a lazy
    import) into a RuntimeError caused by it: a signal that lands then would otherwise pass for an
    unexpected error (exit 1, or a failed take in a batch) instead of stopping the run."""
    seen = set()
    while e is not None and id(e) not in seen:
        if not isinstance(e, Exception):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None
