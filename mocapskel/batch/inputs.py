"""The takes of a batch: the command line's files, folders and globs expanded, and their output names."""
from __future__ import annotations

import glob
import os
from collections.abc import Sequence
from pathlib import Path

from ..errors import UsageError

#: Extensions taken from folders and globs (explicitly named files are taken whatever they are).
TAKE_SUFFIXES: tuple[str, ...] = (".c3d", ".trc")


def _is_glob(s: str) -> bool:
    return any(c in s for c in "*?[")


def _takes_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in TAKE_SUFFIXES)


def collect_inputs(patterns: Sequence[str | os.PathLike]) -> list[Path]:
    """Expand the command line's INPUTS into take files, in order, without repeats.

    Parameters
    ----------
    patterns : sequence of str or PathLike
        Files (taken whatever their extension: a file that is not a take fails
        as that take), folders (their ``.c3d`` and ``.trc`` files, not
        recursive) and glob patterns (``**`` recurses; the ``.c3d``/``.trc``
        files they match, and those of the folders they match).

    Returns
    -------
    list of Path
        Sorted within each pattern, in the order of the patterns; a file named
        twice is kept once (the first time).

    Raises
    ------
    UsageError
        A pattern that names nothing (no such file or folder, a glob matching
        no take), or no take at all.
    """
    out: list[Path] = []
    seen: set[str] = set()

    def add(p: Path) -> None:
        k = os.path.normcase(os.path.abspath(p))
        if k not in seen:
            seen.add(k)
            out.append(p)

    for pat in patterns:
        s = os.fspath(pat)
        p = Path(s)
        if p.is_dir():
            found = _takes_in(p)
            if not found:
                raise UsageError(f"folder {s} holds no .c3d or .trc file — give the takes or another folder")
        elif p.exists():
            found = [p]
        elif _is_glob(s):
            found = []
            for m in sorted(glob.glob(s, recursive=True)):
                q = Path(m)
                if q.is_dir():
                    found.extend(_takes_in(q))
                elif q.is_file() and q.suffix.lower() in TAKE_SUFFIXES:
                    found.append(q)
            if not found:
                raise UsageError(f"{s} matches no .c3d or .trc file — check the pattern")
        else:
            raise UsageError(f"{s}: no such file or folder — check the path")
        for q in found:
            add(q)
    if not out:
        raise UsageError("no takes given — name files, folders or globs")
    return out


def take_names(paths: Sequence[Path]) -> list[str]:
    """Output base names, one per take: the file's stem, made unique.

    Stems that clash (``a/run.c3d`` and ``b/run.trc``, compared without case)
    get the extension appended (``run_c3d``) and then, if still clashing, a
    counter (``run_c3d_2``) in input order.
    """
    stems = [p.stem for p in paths]
    low = [s.lower() for s in stems]
    names = [s if low.count(s.lower()) == 1 else f"{s}_{p.suffix.lstrip('.').lower() or 'take'}"
             for s, p in zip(stems, paths)]
    taken: set[str] = set()
    out = []
    for n in names:
        cand, k = n, 2
        while cand.lower() in taken:
            cand, k = f"{n}_{k}", k + 1
        taken.add(cand.lower())
        out.append(cand)
    return out
