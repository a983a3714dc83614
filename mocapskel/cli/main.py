"""Entry point: the ``mocapskel`` command group, logging and error handling.

Every error ends in one line ``mocapskel: error: …`` on stderr and a documented
exit code: 2 bad usage, 3 unreadable or invalid input, 4 the data cannot
support a skeleton, 1 anything unexpected, 130 interrupted. ``-v`` shows
tracebacks.
"""
from __future__ import annotations

import logging
import sys
import traceback

import click

from ..errors import MocapskelError

log = logging.getLogger("mocapskel")


class _State:
    verbose = 0


def setup_logging(verbose: int, quiet: bool) -> None:
    _State.verbose = verbose
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 0 else logging.INFO)
    log.setLevel(level)
    if not log.handlers:
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("mocapskel: %(message)s"))
        log.addHandler(h)
    log.propagate = False


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="mocapskel")
def cli() -> None:
    """Template-free skeletons from raw optical motion-capture markers.

    \b
    Example:
        mocapskel fit take.c3d -o skel.bvh --report skel.json
    """


def _register() -> None:
    from . import fit, inspect, stages, synth  # noqa: F401  (commands register themselves)


def main(argv: list[str] | None = None) -> None:
    """Run the command line; never lets a traceback through unless -v."""
    _register()
    args = sys.argv[1:] if argv is None else argv
    try:
        cli.main(args=args, prog_name="mocapskel", standalone_mode=False)
    except click.exceptions.Exit as e:
        sys.exit(e.exit_code)
    except click.exceptions.Abort:
        click.echo("mocapskel: error: interrupted — no output was written", err=True)
        sys.exit(130)
    except click.UsageError as e:
        click.echo(f"mocapskel: error: {e.format_message()} (see 'mocapskel {_cmd(args)}--help')", err=True)
        sys.exit(2)
    except click.ClickException as e:
        click.echo(f"mocapskel: error: {e.format_message()}", err=True)
        sys.exit(e.exit_code)
    except MocapskelError as e:
        if _State.verbose:
            traceback.print_exc()
        click.echo(f"mocapskel: error: {_one_line(str(e))}", err=True)
        sys.exit(e.exit_code)
    except KeyboardInterrupt:
        click.echo("mocapskel: error: interrupted — no output was written", err=True)
        sys.exit(130)
    except MemoryError:
        click.echo("mocapskel: error: out of memory — try a shorter take or fewer markers", err=True)
        sys.exit(1)
    except Exception as e:  # anything unexpected
        if _State.verbose:
            traceback.print_exc()
        click.echo(
            f"mocapskel: error: unexpected {type(e).__name__}: {_one_line(str(e))} — run with -v for details and report it",
            err=True,
        )
        sys.exit(1)


def _cmd(args: list[str]) -> str:
    return f"{args[0]} " if args and not args[0].startswith("-") else ""


def _one_line(s: str) -> str:
    return " ".join(s.split())
