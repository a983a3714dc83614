"""The ``mocapskel`` command's first instructions: signals are handled before anything is imported.

Importing the command line (click, numpy, scipy …) takes most of a second. A
SIGTERM or Ctrl-C in that time must still end in the documented exit code
(143 or 130) and one line, not in Python's default (death by the signal, or a
KeyboardInterrupt traceback). Until the command group takes over (see
:mod:`mocapskel.cli.main`), a signal ends the process at once: nothing has
been written yet.
"""
import os
import signal

_MESSAGES = {
    signal.SIGINT: b"mocapskel: error: interrupted \xe2\x80\x94 no output was written\n",
    signal.SIGTERM: b"mocapskel: error: terminated \xe2\x80\x94 no output was written\n",
}


def _early_exit(signum, frame) -> None:  # pragma: no cover - runs in a real process only
    try:
        os.write(2, _MESSAGES.get(signum, b"mocapskel: error: stopped by a signal\n"))
    finally:
        os._exit(128 + signum)


def install_early_handlers() -> None:
    """SIGINT and SIGTERM end the process at once with 130 / 143 and one line (no clean-up needed yet)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:  # a batch system that ignores a signal keeps it ignored
            signal.signal(sig, _early_exit)


def main() -> None:
    """Console entry point (``mocapskel``) and ``python -m mocapskel``."""
    install_early_handlers()
    from .cli.main import main as cli_main

    cli_main()
