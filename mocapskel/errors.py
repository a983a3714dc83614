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
