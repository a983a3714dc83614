"""Entry point: the ``mocapskel`` command group, logging and error handling.

Every error ends in one line ``mocapskel: error: …`` on stderr and a documented
exit code: 2 bad usage, 3 unreadable or invalid input, 4 the data cannot
support a skeleton, 1 anything unexpected, 130 interrupted (SIGINT), 143
terminated (SIGTERM). ``-v`` shows tracebacks. Signals are handled from the
command's first instruction (see :mod:`mocapskel._entry`).
"""
from __future__ import annotations

import logging
import signal
import sys
import threading
import traceback

import click

from ..solvers import parallel
from ..errors import MocapskelError, interrupt_behind

log = logging.getLogger("mocapskel")


class _State:
    verbose = 0
    said: list[str] = []  # messages already written to stderr in this run
    pending: int | None = None  # a signal that arrived in this run (see raise_pending)


def setup_logging(verbose: int, quiet: bool) -> None:
    _State.verbose = verbose
    _State.said = []
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 0 else logging.INFO)
    log.setLevel(level)
    if not any(isinstance(h, _StderrHandler) for h in log.handlers):
        h = _StderrHandler()
        h.setFormatter(logging.Formatter("mocapskel: %(message)s"))
        log.addHandler(h)
    log.propagate = False


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (so test runners capture it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass

    def emit(self, record: logging.LogRecord) -> None:
        _State.said.append(record.getMessage())
        super().emit(record)


def say_warnings(warnings: list[str]) -> None:
    """Log a run's warnings at its end, leaving out those already shown when they happened."""
    for w in warnings:
        if not any(w in m for m in _State.said):
            log.warning("warning: %s", w)


class Terminated(BaseException):
    """SIGTERM arrived. Raised from the signal handler, like KeyboardInterrupt for Ctrl-C,
    so that temporary outputs are removed on the way out (exit code 143)."""


class Interrupted(BaseException):
    """Ctrl-C during a command: KeyboardInterrupt under another name, so that click does not
    print its blank line before our one-line message (exit code 130)."""


def _raise_now(sig: int) -> bool:
    """Note that ``sig`` arrived; whether its handler raises now. Not inside a fork: raised in an at-fork
    hook, the exception would be printed and dropped, so the fork sends the signal again once done."""
    _State.pending = sig
    if parallel.forking():
        parallel.defer_signal(sig)
        return False
    return True


def _on_sigterm(signum, frame) -> None:
    if _raise_now(signal.SIGTERM):
        raise Terminated()


def _on_sigint(signum, frame) -> None:
    # not KeyboardInterrupt itself: CPython 3.11 kills itself with SIGINT at exit (exit status -2, not 130)
    # when a KeyboardInterrupt went through exec() of a string on its way (a dataclass being created by a
    # lazy import, say), whatever sys.exit said
    if _raise_now(signal.SIGINT):
        raise Interrupted()


def raise_pending() -> None:
    """Raise again a signal that arrived in this run: one whose exception a library swallowed (a bare
    ``except:`` in a module being imported when it came: a SIGTERM 0.3 s into a fit once let the fit run to
    its end and exit 0). Called before any output is put in place and when the command returns."""
    if _State.pending == signal.SIGTERM:
        raise Terminated()
    if _State.pending == signal.SIGINT:
        raise Interrupted()


class MocapskelGroup(click.Group):
    """A click group whose ``main`` turns every error into one line and an exit code.

    Both the console script and click's CliRunner go through here.
    """

    def invoke(self, ctx):  # noqa: D102
        try:
            raise_pending()
            out = super().invoke(ctx)
            raise_pending()
            return out
        except KeyboardInterrupt:
            raise Interrupted() from None

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):  # noqa: D102
        main_thread = threading.current_thread() is threading.main_thread()
        old: dict[int, object] = {}
        args = list(sys.argv[1:] if args is None else args)
        _State.pending = None
        try:
            if main_thread:  # from here on a signal cleans up (temporary files) and ends in 130 / 143
                for sig, handler in ((signal.SIGTERM, _on_sigterm), (signal.SIGINT, _on_sigint)):
                    current = signal.getsignal(sig)
                    if current is not signal.SIG_IGN:
                        old[sig] = current
                        signal.signal(sig, handler)
            _register()
            super().main(args=args, prog_name=prog_name or "mocapskel", standalone_mode=False, **extra)
        except click.exceptions.Exit as e:
            sys.exit(e.exit_code)
        except click.exceptions.Abort:
            _fail("interrupted — no output was written", 130)
        except click.UsageError as e:
            _fail(f"{e.format_message()} (see 'mocapskel {_cmd(args)}--help')", 2)
        except click.ClickException as e:
            _fail(e.format_message(), e.exit_code)
        except MocapskelError as e:
            if _State.verbose:
                traceback.print_exc()
            _fail(str(e), e.exit_code)
        except (KeyboardInterrupt, Interrupted):
            _fail("interrupted — no output was written", 130)
        except Terminated:
            _fail("terminated — no output was written", 128 + signal.SIGTERM)
        except MemoryError:
            _fail("out of memory — try a shorter take or fewer markers", 1)
        except OSError as e:  # the system refused a read or a write (disk full, permissions ...)
            if _State.verbose:
                traceback.print_exc()
            where = f"{e.filename}: " if e.filename else ""
            _fail(f"{where}{e.strerror or e} — check free space and permissions (-v shows where it happened)", 1)
        except Exception as e:  # anything unexpected
            stop = interrupt_behind(e)
            if isinstance(stop, Terminated):
                _fail("terminated — no output was written", 128 + signal.SIGTERM)
            elif isinstance(stop, (KeyboardInterrupt, Interrupted)):
                _fail("interrupted — no output was written", 130)
            if _State.verbose:
                traceback.print_exc()
            _fail(f"unexpected {type(e).__name__}: {e} — run with -v for details and report it", 1)
        finally:
            _State.pending = None  # the run is over: nothing is held against the next (tests run many in one process)
            for sig, handler in old.items():  # (the console entry's handlers: a signal now exits at once)
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        sys.exit(0)


def _fail(message: str, code: int) -> None:
    if threading.current_thread() is threading.main_thread():  # a second signal must not cut the message short
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
    click.echo(f"mocapskel: error: {_one_line(message)}", err=True)
    sys.exit(code)


@click.group(cls=MocapskelGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="mocapskel")
def cli() -> None:
    """Template-free skeletons from raw optical motion-capture markers.

    \b
    Example:
        mocapskel fit take.c3d -o skel.bvh --report skel.json
    """


#: Modules under mocapskel.cli whose commands register themselves on import.
COMMAND_MODULES = ("fit", "stages", "inspect", "synth", "solve", "batch", "report", "compare")


def _register() -> None:
    import importlib

    from ..io import atomic

    if raise_pending not in atomic.before_commit:
        atomic.before_commit.append(raise_pending)  # no output is put in place after a signal
    for name in COMMAND_MODULES:
        importlib.import_module(f"{__package__}.{name}")


def main() -> None:
    """Console entry point."""
    cli.main()


def _cmd(args: list[str]) -> str:
    return f"{args[0]} " if args and not args[0].startswith("-") else ""


def _one_line(s: str) -> str:
    return " ".join(s.split())
