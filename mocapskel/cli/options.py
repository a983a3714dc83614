"""Options shared by several commands, defined once."""
from __future__ import annotations

import functools
import os
from pathlib import Path

import click

from ..cache import Cache, default_dir
from ..errors import UsageError
from ..pipeline import ReadOptions
from .main import setup_logging

JOINT_METHODS = ("auto", "jmv", "mtb", "sphere", "score")
JOINT_MODELS = ("map",)


def verbosity(f):
    f = click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")(f)
    f = click.option("-v", "--verbose", count=True, help="More detail, and tracebacks on error.")(f)
    return f


def cache_options(f):
    f = click.option("--no-cache", is_flag=True, help="Neither read nor write the artifact cache.")(f)
    f = click.option(
        "--cache-dir",
        type=click.Path(),  # not file_okay=False: a cache folder that cannot be used means no cache and a warning
        default=None,
        help="Artifact cache folder [default: $XDG_CACHE_HOME/mocapskel or ~/.cache/mocapskel].",
    )(f)
    return f


def read_options(f):
    f = click.option("--include", multiple=True, metavar="PATTERN", help="Use only markers whose label matches (glob; repeatable).")(f)
    f = click.option("--exclude", multiple=True, metavar="PATTERN", help="Leave out markers whose label matches (glob; repeatable).")(f)
    return f


def fit_options(f):
    """Options that set stage parameters (segments, joints, rest frame)."""
    f = click.option("--rest-frame", type=click.IntRange(min=0), default=None, help="Frame whose pose is the rest pose [default: a well-visible frame near the start].")(f)
    f = click.option(
        "--joint-model", type=click.Choice(JOINT_MODELS), default="map", show_default=True,
        help="How the rigid stage places the joints: the model's MAP with explicit priors (the only model; the older rules were removed).",
    )(f)
    f = click.option(
        "--joint-method", type=click.Choice(JOINT_METHODS), default="auto", show_default=True, help="Joint-centre estimator."
    )(f)
    f = click.option("--segments", type=click.IntRange(min=2), default=None, help="Number of rigid segments [default: automatic].")(f)
    return f


def strict_option(f):
    """``--strict``: a failing output check (see mocapskel.checks) is an error, exit code 4."""
    return click.option("--strict", is_flag=True,
                        help="Fail (exit 4, nothing written) when an output check fails instead of warning.")(f)


def bvh_options(f):
    f = click.option("--units", type=click.Choice(["cm", "mm", "m"]), default="cm", show_default=True, help="BVH units.")(f)
    f = click.option("--up", type=click.Choice(["y", "z"]), default="y", show_default=True, help="BVH up axis (y: lab (x,y,z) → (x,z,−y)).")(f)
    return f


def naming_options(f):
    """--names and --rest (the BVH's joint names and rest pose)."""
    f = click.option(
        "--rest", type=click.Choice(["frame", "tpose", "apose"]), default="frame", show_default=True,
        help="Rest pose: the rest frame's pose, or for a person a T-pose or A-pose (joint positions unchanged).",
    )(f)
    f = click.option(
        "--names", type=click.Choice(["auto", "humanoid", "segments"]), default="auto", show_default=True,
        help="Joint names: humanoid (Hips, Spine, LeftUpLeg ...) when the skeleton is recognised as a person (auto), or the segment names.",
    )(f)
    return f


def common(f):
    """Logging set-up for every command (pops -v/-q from the kwargs)."""

    @functools.wraps(f)
    def wrapper(*args, verbose: int = 0, quiet: bool = False, **kw):
        setup_logging(verbose, quiet)
        return f(*args, **kw)

    return verbosity(wrapper)


def make_cache(cache_dir: str | None, no_cache: bool) -> Cache:
    if no_cache:
        return Cache(None)
    return Cache(cache_dir if cache_dir else default_dir())


def make_read(exclude: tuple[str, ...], include: tuple[str, ...]) -> ReadOptions:
    return ReadOptions(exclude=tuple(exclude), include=tuple(include))


def check_output(out: str, *inputs: str, suffixes: tuple[str, ...] | None = None) -> Path:
    """Refuse an output that is an input, a folder, or in a folder that does not exist or is not writable."""
    p = Path(out)
    for i in inputs:
        if i is not None and Path(i).exists() and p.exists() and os.path.samefile(p, i):
            raise UsageError(f"output {out} is the input — choose another output file")
        if i is not None and Path(os.path.abspath(i)) == Path(os.path.abspath(out)):
            raise UsageError(f"output {out} is the input — choose another output file")
    if p.is_dir():
        raise UsageError(f"output {out} is a folder — give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise UsageError(f"output folder {parent} does not exist — create it first")
    if not os.access(parent, os.W_OK):
        raise UsageError(f"output folder {parent} is not writable — choose another folder or fix its permissions")
    if suffixes and p.suffix.lower() not in suffixes:
        raise UsageError(f"output {out} should end in {' or '.join(suffixes)}")
    return p
