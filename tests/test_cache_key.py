"""The cache key covers all the code that shapes a stage's output (issue 18).

A stage's entry is keyed by its own VERSION and by a digest of the source of its module and of every
module of the package it imports, directly or through others. A change to code a stage calls — a solver
shared with another stage, or a version number anywhere in that code — invalidates that stage's entry
and the entries after it, and nothing before.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from mocapskel import cache as cache_mod
from mocapskel import pipeline
from mocapskel.cache import Cache, code_digest, code_modules
from mocapskel.io.markers import write_markers
from mocapskel.synth.presets import Recipe, make

STAGES = ("clean", "merge-ids", "segment", "topology", "joints", "rigid", "ik")


def _stage(name: str) -> str:
    return pipeline.stage_module(name).__name__


@pytest.fixture()
def fresh_digests():
    cache_mod.code_digest.cache_clear()
    yield
    cache_mod.code_digest.cache_clear()


def _changed(monkeypatch: pytest.MonkeyPatch, module: str) -> None:
    """Make ``module``'s source read as if someone had edited it (a comment added)."""
    real = cache_mod.module_source

    def source(name: str) -> bytes | None:
        src = real(name)
        return src + b"\n# edited\n" if name == module and src is not None else src

    monkeypatch.setattr(cache_mod, "module_source", source)
    cache_mod.code_digest.cache_clear()


def _ik_solver() -> str:
    from mocapskel.solvers.ik.solve import solve_ik

    return solve_ik.__module__


def test_a_stage_s_code_includes_the_solvers_it_shares_with_other_stages() -> None:
    rigid, ik, segment = (code_modules(_stage(s)) for s in ("rigid", "ik", "segment"))
    assert _stage("rigid") in rigid and _stage("segment") in segment
    solver = _ik_solver()  # the rigid stage re-poses frames with the IK solver
    assert solver in rigid and solver in ik and solver not in segment
    assert "mocapskel.stages.ik" not in rigid  # a stage calls solvers, not another stage


def test_imports_are_read_however_they_are_written() -> None:
    """Relative and absolute, in parentheses over several lines with comments, inside functions, with
    ``as``: every module of the package named is found; names that are not modules are not."""
    src = b"""from __future__ import annotations
import numpy as np
import mocapskel.errors as err
from . import (
    pipeline,  # the stage order
    report,
)
from .io import atomic, paths as p


def f():
    from .model.tree import depth_first_order  # not a module: the module it comes from counts
    return depth_first_order
"""
    got = cache_mod._imported("mocapskel.cache", src, "mocapskel")
    assert got == {"mocapskel", "mocapskel.errors", "mocapskel.pipeline", "mocapskel.report", "mocapskel.io",
                   "mocapskel.io.atomic", "mocapskel.io.paths", "mocapskel.model.tree"}


def test_the_digest_changes_with_code_the_stage_calls_and_only_then(monkeypatch, fresh_digests) -> None:
    before = {s: code_digest(_stage(s)) for s in STAGES}
    assert before == {s: code_digest(_stage(s)) for s in STAGES}  # stable
    _changed(monkeypatch, _ik_solver())
    after = {s: code_digest(_stage(s)) for s in STAGES}
    changed = {s for s in STAGES if after[s] != before[s]}
    assert {"rigid", "ik"} <= changed
    assert not changed & {"clean", "merge-ids", "segment"}


def test_edited_shared_code_recomputes_the_stages_that_run_it(tmp_path: Path, monkeypatch, fresh_digests) -> None:
    take = tmp_path / "link.trc"
    write_markers(take, make(Recipe(kind="linkage", frames=300, noise_mm=0.5, seed=1)).markers)
    folder = tmp_path / "cache"
    first = pipeline.run_until(take, "ik", cache=Cache(folder))
    assert first.cached == []
    again = pipeline.run_until(take, "ik", cache=Cache(folder))
    assert again.cached == list(STAGES) and again.key == first.key
    _changed(monkeypatch, _ik_solver())
    edited = pipeline.run_until(take, "ik", cache=Cache(folder))
    assert edited.cached == ["clean", "merge-ids", "segment", "topology", "joints"]
    assert edited.key != first.key
    # a version number bumped in a module the stage imports counts the same as any other edit
    real = cache_mod.module_source
    monkeypatch.setattr(cache_mod, "module_source", real)
    cache_mod.code_digest.cache_clear()
    rigid_mod = _stage("rigid")

    def bumped(name: str) -> bytes | None:
        src = real(name)
        return src.replace(b"VERSION = ", b"VERSION = 1 + ", 1) if name == rigid_mod and src is not None else src

    monkeypatch.setattr(cache_mod, "module_source", bumped)
    cache_mod.code_digest.cache_clear()
    bump = pipeline.run_until(take, "ik", cache=Cache(folder))
    assert bump.cached == ["clean", "merge-ids", "segment", "topology", "joints"]


def test_without_a_cache_folder_no_code_is_digested(tmp_path: Path, monkeypatch) -> None:
    """Keys name the code only for entries that are stored: a run without a cache folder reads and hashes
    no source (a tenth of a second in a fresh process), one with a folder does."""
    take = tmp_path / "link.trc"
    write_markers(take, make(Recipe(kind="linkage", frames=300, noise_mm=0.5, seed=1)).markers)

    def no_digest(name: str) -> str:
        raise AssertionError(f"digested {name}")

    monkeypatch.setattr(pipeline, "code_digest", no_digest)
    run = pipeline.run_until(take, "segment", cache=Cache(None))
    assert run.artifact.n_segments >= 2
    with pytest.raises(AssertionError, match="digested mocapskel.stages.clean"):
        pipeline.run_until(take, "segment", cache=Cache(tmp_path / "cache"))


def test_a_module_moved_unchanged_recomputes_the_stages_that_import_it(tmp_path: Path, monkeypatch,
                                                                      fresh_digests) -> None:
    """A module's name is part of the digest, not only its source: entries written before a module moved to
    another folder (same source, other name) are a clean miss for the stages that import it, recomputed with no
    warning, and the stages before them still come from the cache."""
    take = tmp_path / "link.trc"
    write_markers(take, make(Recipe(kind="linkage", frames=300, noise_mm=0.5, seed=1)).markers)
    folder = tmp_path / "cache"
    first = pipeline.run_until(take, "ik", cache=Cache(folder))
    assert first.cached == []
    solver = _ik_solver()
    moved = solver + "_moved"
    real = cache_mod._code

    def renamed(name: str) -> dict[str, bytes | None]:
        return {(moved if m == solver else m): src for m, src in real(name).items()}

    for s in ("rigid", "ik"):  # the same sources in the same order: only the name tells them apart
        old, new = real(_stage(s)), renamed(_stage(s))
        assert [old[m] for m in sorted(old)] == [new[m] for m in sorted(new)] and moved in new

    monkeypatch.setattr(cache_mod, "_code", renamed)
    cache_mod.code_digest.cache_clear()
    cache = Cache(folder)
    again = pipeline.run_until(take, "ik", cache=cache)
    assert again.cached == ["clean", "merge-ids", "segment", "topology", "joints"]
    assert again.key != first.key and cache.warnings == []
