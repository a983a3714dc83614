"""Atomic file output: write a temporary file beside the target, then rename."""
from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO


#: Bytes a file name may have on the usual file systems (ext4, XFS, APFS, NTFS in UTF-16 units).
NAME_MAX = 255
#: Bytes kept free beside the target's name in a temporary name: the dots, mkstemp's 8 random
#: characters, ``.part`` and a suffix a writer may add (ezc3d appends ``.c3d``), with room to spare.
_ROOM = 40


def short_name(name: str, room: int = _ROOM) -> str:
    """``name`` cut (at a character boundary) so that ``room`` more bytes still fit in a file name."""
    raw = os.fsencode(name)
    limit = NAME_MAX - room
    if len(raw) <= limit:
        return name
    cut = raw[:limit]
    for k in range(4):  # never split a UTF-8 character
        try:
            return cut[: len(cut) - k].decode("utf-8")
        except UnicodeDecodeError:
            continue
    return os.fsdecode(cut)  # pragma: no cover - not UTF-8 at all


#: Called with no argument just before an output is put in place; may raise to keep it out (the command
#: line raises there a signal whose exception a library swallowed while the run went on).
before_commit: list = []


def _before_commit() -> None:
    for check in before_commit:
        check()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``.

    On any exception (KeyboardInterrupt included) the temporary file is removed
    and ``path`` is left as it was. The temporary name is ``.NAME.XXXXXXXX.part``
    with NAME cut short enough that it (and a suffix a writer may add) fits
    the file system's 255-byte name limit whatever the target's name.
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{short_name(target.name)}.", suffix=".part", dir=target.parent or ".")
    os.close(fd)
    try:
        yield tmp
        _before_commit()
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual mode
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kw) -> Iterator[IO]:
    """Open a temporary file for writing that replaces ``path`` when closed without error."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kw) as f:
            yield f


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_open(path, "wb") as f:
        f.write(data)


class AtomicOutputs:
    """Several output files that appear together when a ``with`` block ends without error, or not at all.

    ``stage(path)`` returns the path to write instead of ``path``: a file of the
    same name (same suffix, for writers that check it) in a hidden folder
    ``.<name>.*.part`` beside ``path``, so on the same file system. When the
    block ends without error every staged file is renamed onto its target
    (Ctrl-C and SIGTERM held back for those few renames); on any exception,
    KeyboardInterrupt included, the staged files are removed and every target
    keeps what it held before.

    Example::

        with AtomicOutputs() as out:
            write_bvh(out.stage("take.bvh"), ...)
            write_report(out.stage("take.json"), report)
    """

    def __init__(self) -> None:
        self._staged: list[tuple[Path, Path]] = []

    def __enter__(self) -> "AtomicOutputs":
        return self

    def stage(self, path: str | os.PathLike) -> Path:
        target = Path(path)
        folder = tempfile.mkdtemp(prefix=f".{short_name(target.name)}.", suffix=".part", dir=target.parent)
        tmp = Path(folder) / target.name
        self._staged.append((tmp, target))
        return tmp

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            if exc_type is None:
                _before_commit()
                held = _hold_signals()
                try:
                    for tmp, target in self._staged:
                        if tmp.exists():
                            os.replace(tmp, target)
                finally:
                    _release_signals(held)
        finally:
            for tmp, _ in self._staged:
                shutil.rmtree(tmp.parent, ignore_errors=True)
        return False


def _hold_signals():
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - Windows
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


def _release_signals(held) -> None:
    if held is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
