"""Stage order, running up to a stage with the artifact cache, and ``fit``.

    read ─ clean ─ merge-ids ─ segment ─ topology ─ joints ─ rigid ─ ik ─ export

Files are read here (the input take or artifact) and cache entries are written
here; the stages themselves touch no files.
"""
from __future__ import annotations

import dataclasses
import importlib
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from . import artifacts
from .artifacts import Markers
from .cache import Cache, code_digest, file_key, stage_key
from .errors import DataError, InputError, UsageError
from .blas import one_blas_thread
from .io import artifact_files

log = logging.getLogger("mocapskel")

STAGES: tuple[str, ...] = ("clean", "merge-ids", "segment", "topology", "joints", "rigid", "ik")
_MODULES = {
    "clean": "clean",
    "merge-ids": "merge_ids",
    "segment": "segment",
    "topology": "topology",
    "joints": "joints",
    "rigid": "rigid",
    "ik": "ik",
    "export": "export",
}
ARTIFACT_SUFFIX = ".npz"


def stage_module(stage: str):
    """The module implementing ``stage`` (it has VERSION, Params and run)."""
    return importlib.import_module(f"mocapskel.stages.{_MODULES[stage]}")


def stage_of(obj: Any) -> str:
    """The last stage an artifact went through ("read" for raw markers)."""
    if isinstance(obj, Markers):
        return obj.stage
    return artifacts.PRODUCED_BY[obj.kind]


def _index(stage: str) -> int:
    return -1 if stage == "read" else STAGES.index(stage)


@dataclass(frozen=True)
class ReadOptions:
    exclude: tuple[str, ...] = ()
    include: tuple[str, ...] = ()


@dataclass
class Run:
    """What :func:`run_until` did."""

    artifact: Any
    key: str
    seconds: dict[str, float] = field(default_factory=dict)
    cached: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def read_input(path: str | os.PathLike, read: ReadOptions = ReadOptions(), *, hash_content: bool = True) -> tuple[Any, str]:
    """Read a take (C3D/TRC) or a saved artifact. Returns (artifact, cache key of its content).

    ``hash_content=False``: the key names the file (path, size, modification
    time) instead of hashing its content, for callers without a cache (a
    long take's hash costs as much as a tenth of its ezc3d read).
    """
    p = Path(path)
    if not p.exists():
        raise InputError("no such file — check the path", str(path))
    if p.is_dir():
        raise InputError("is a folder, not a take — give a .c3d or .trc file", str(path))
    if not p.is_file():  # a FIFO or a device: hashing it would block or never end
        raise InputError("not a regular file — give a .c3d or .trc file", str(path))
    if hash_content:
        key = file_key(p, dataclasses.asdict(read))
    else:
        st = p.stat()
        key = stage_key("read", 0, dataclasses.asdict(read), f"file:{p.resolve()}:{st.st_size}:{st.st_mtime_ns}")
    if p.suffix.lower() == ARTIFACT_SUFFIX:
        return artifact_files.load(p), key
    from .io.markers import read_markers

    return read_markers(p, exclude=read.exclude, include=read.include), key


@one_blas_thread
def run_until(
    source: str | os.PathLike | Any,
    target: str,
    params: dict[str, Any] | None = None,
    *,
    cache: Cache | None = None,
    read: ReadOptions = ReadOptions(),
    key: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> Run:
    """Run the pipeline from ``source`` (path or artifact) up to and including ``target``.

    ``params`` maps a stage name to its Params (defaults for stages not named).
    Stages already done by the source are skipped; stages found in ``cache`` are
    loaded instead of recomputed.
    """
    params = params or {}
    cache = cache or Cache(None)
    for name in params:
        if name not in _MODULES:
            raise UsageError(f"unknown stage {name!r}")
    if target not in STAGES:
        raise UsageError(f"unknown stage {target!r} (stages: {', '.join(STAGES)})")
    t0 = time.perf_counter()
    seconds: dict[str, float] = {}
    if isinstance(source, (str, os.PathLike)):
        obj, key = read_input(source, read, hash_content=cache.folder is not None)
        seconds["read"] = time.perf_counter() - t0
    else:
        obj = source
        key = key or "memory"
    have = stage_of(obj)
    if _index(have) > _index(target):
        raise UsageError(f"the input is already past stage {target!r} (it is a {have!r} artifact)")
    run = Run(artifact=obj, key=key, seconds=seconds, warnings=list(cache.warnings))
    # a take read here from a file is this run's alone: the first stage may reuse its arrays
    # (clean does, so that a long passive take is not held twice), and it is not kept after
    owned = isinstance(source, (str, os.PathLike)) and have == "read"
    del obj
    for stage in STAGES[_index(have) + 1 : _index(target) + 1]:
        mod = stage_module(stage)
        p = params.get(stage) or mod.Params()
        # the code's digest names the code in a stored entry's key; without a cache folder nothing is stored
        # (in a fresh process the digests read and hash the package's sources: a tenth of a second)
        k = stage_key(stage, mod.VERSION, p, run.key, code_digest(mod.__name__) if cache.folder is not None else "")
        t = time.perf_counter()
        # the upstream artifact is the one in hand: an entry's reference is checked against its key, never followed
        hit = cache.get(k, stage, upstream=(run.key, run.artifact)) if key != "memory" else None
        if hit is not None:
            run.artifact = hit
            run.cached.append(stage)
            log.info("%-9s cached — skipping", stage)
        else:
            if progress:
                progress(stage)
            before, before_key = run.artifact, run.key
            if owned and stage == "clean":
                run.artifact = None
                run.artifact = mod.run(before, p, consume=True)
            else:
                try:
                    run.artifact = mod.run(before, p)
                except DataError as e:
                    if stage not in ("segment", "topology"):
                        raise
                    from .diagnose import explain

                    raise explain(before, e) from None  # what is wrong with the take, not its consequence
            if key != "memory":
                # the upstream artifact is stored by reference when it is itself a cache entry
                up = (before, before_key) if stage != STAGES[_index(have) + 1] else None
                cache.put(k, run.artifact, upstream=up)
            del before
            log.info("%-9s done in %.2f s", stage, time.perf_counter() - t)
        run.seconds[stage] = time.perf_counter() - t
        run.key = k
    run.warnings.extend(w for w in cache.warnings if w not in run.warnings)
    return run


def make_params(
    *,
    segments: int | None = None,
    joint_method: str = "auto",
    joint_model: str = "map",
    rest_frame: int | None = None,
    up: str = "y",
    units: str = "cm",
    names: str = "auto",
    rest: str = "frame",
) -> dict[str, Any]:
    """Stage parameters from the command line's options."""
    from .stages import export, joints, rigid, segment

    return {
        "segment": segment.Params(n_segments=segments),
        "joints": joints.Params(method=joint_method),
        "rigid": rigid.Params(rest_frame=rest_frame, joint_model=joint_model),
        "export": export.Params(up=up, units=units, names=names, rest=rest,
                                rest_frame="auto" if rest_frame is None else rest_frame),
    }


@dataclass
class FitResult:
    """The outcome of :func:`fit`: the solved motion, its BVH form and the report.

    ``subjects``: when the take holds several subjects, one FitResult per subject (this
    one is the first); empty for a take of one subject. ``points``: from :func:`solve`, the
    (F, M, 3) markers it solved, one column per skeleton label (a fit's are its markers').
    """

    motion: Any
    bvh: Any
    report: dict
    run: Run
    subjects: list["FitResult"] = field(default_factory=list)
    points: Any = None


def _chain(a: Run, b: Run) -> Run:
    """Run ``b`` continued from run ``a`` (its seconds, cached stages and warnings first)."""
    return Run(artifact=b.artifact, key=b.key, seconds={**a.seconds, **b.seconds}, cached=a.cached + b.cached,
               warnings=a.warnings + [w for w in b.warnings if w not in a.warnings])


def _early(source: Any) -> bool:
    """Whether ``source`` (an artifact) is still before the segment stage."""
    return stage_of(source) in ("read", "clean", "merge-ids")


def fit(
    source: str | os.PathLike | Any,
    params: dict[str, Any] | None = None,
    *,
    cache: Cache | None = None,
    read: ReadOptions = ReadOptions(),
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit a skeleton to a take and solve every frame: read → … → ik → export.

    Between merge-ids and segment, the markers are split into subjects when the
    take holds several (see :mod:`mocapskel.subjects`); each is then fitted on
    its own and ``result.subjects`` holds one result per subject.

    Nothing is written: the caller writes ``result.bvh`` (see
    :func:`mocapskel.io.bvh.write_bvh`) and ``result.report`` as it likes.
    """
    from .report import build_report
    from .subjects import split_subjects

    params = dict(params or {})
    cache = cache or Cache(None)
    t = time.perf_counter()
    key = None
    if isinstance(source, (str, os.PathLike)) and Path(source).suffix.lower() == ARTIFACT_SUFFIX:
        source, key = read_input(source, read, hash_content=cache.folder is not None)
    groups = None
    if isinstance(source, (str, os.PathLike)) or _early(source):
        first = run_until(source, "merge-ids", params, cache=cache, read=read, key=key, progress=progress)
        groups = split_subjects(first.artifact)
        if groups is None:
            rest = run_until(first.artifact, "ik", params, cache=cache, key=None if first.key == "memory" else first.key,
                             progress=progress)
            run = _chain(first, rest)
    else:
        run = run_until(source, "ik", params, cache=cache, read=read, key=key, progress=progress)
    if groups is not None:
        return _fit_subjects(first, groups, params, cache, progress, t)
    bvh, checked = _export_and_check(run, params)
    run.seconds["total"] = time.perf_counter() - t
    report = build_report(run, params)
    _finish_report(report, run, bvh, checked)
    return FitResult(motion=run.artifact, bvh=bvh, report=report, run=run)


def _export_and_check(run: Run, params: dict[str, Any]) -> tuple[Any, tuple[list, float]]:
    """The BVH motion of ``run``'s solved motion, and the checks of that motion with their time (s).

    The two read the motion only and neither needs the other, so they run side by side (on two
    threads unless ``MOCAPSKEL_THREADS=1``); the export's time goes into ``run.seconds``."""
    from . import checks
    from .solvers.parallel import run_blocks
    from .stages import export

    motion = run.artifact

    def do_export() -> Any:
        t = time.perf_counter()
        out = export.run(motion, params.get("export") or export.Params())
        run.seconds["export"] = time.perf_counter() - t
        return out

    def do_checks() -> tuple[list, float]:
        t = time.perf_counter()
        found = checks.run_checks(motion, artifacts.markers_of(motion).points, joint_notes=checks.joint_notes(motion))
        return found, time.perf_counter() - t

    bvh, checked = run_blocks(lambda job: job(), [do_export, do_checks])
    return bvh, checked


def _finish_report(report: dict, run: Run, bvh: Any, checked: tuple[list, float]) -> None:
    """The export's naming and notes, the joints' uncertainty, and the checks of the solved motion (findings, seconds), into ``report``."""
    from . import checks
    from .report import add_uncertainty

    report["export"] = bvh.report()
    if bvh.rest_frame is not None:
        report["rest_frame"] = bvh.rest_frame  # the BVH's rest pose (the skeleton's may be another frame's)
    report["warnings"].extend(bvh.notes)
    add_uncertainty(report, run.artifact.skeleton, bvh.naming)
    findings, secs = checked
    checks.add_to_report(report, findings)
    report["seconds"]["checks"] = round(secs, 4)


def _fit_subjects(first: Run, groups: list, params: dict[str, Any], cache: Cache,
                  progress: Callable[[str], None] | None, t0: float) -> FitResult:
    """Fit every subject's markers on their own, from the segment stage on."""
    from .errors import MocapskelError
    from .report import build_report
    from .subjects import subset

    K = len(groups)
    mk_all = first.artifact
    log.info("%d subjects in the take (%s markers): fitted one by one", K, ", ".join(str(len(g)) for g in groups))
    results: list[FitResult] = []
    for i, idx in enumerate(groups, 1):
        t = time.perf_counter()
        mk = subset(mk_all, idx, i, K)
        key = None if first.key == "memory" else stage_key("subject", 1, {"index": i, "of": K, "labels": list(mk.labels)}, first.key)
        try:
            rest = run_until(mk, "ik", params, cache=cache, key=key, progress=progress)
        except MocapskelError as e:
            e.args = (f"subject {i} of {K} ({len(idx)} markers, {mk.labels[0]} …): {e.args[0]}",) + e.args[1:]
            raise
        run = _chain(first, rest)
        bvh, checked = _export_and_check(run, params)
        run.seconds["subject_total"] = time.perf_counter() - t
        run.seconds["total"] = time.perf_counter() - t0
        run.warnings.append(f"the take holds {K} subjects; this fit is subject {i} ({len(idx)} markers)")
        report = build_report(run, params)
        _finish_report(report, run, bvh, checked)
        results.append(FitResult(motion=run.artifact, bvh=bvh, report=report, run=run))
    listing = [
        {"index": i, "markers": [mk_all.labels[j] for j in g], "segments": len(r.bvh.skeleton.names),
         "marker_rms_mm": r.report.get("ik", {}).get("marker_rms_mm")}
        for i, (g, r) in enumerate(zip(groups, results), 1)
    ]
    for i, r in enumerate(results, 1):
        r.report["subject"] = {"index": i, "of": K}
        r.report["subjects"] = listing
    main = results[0]
    main.subjects = results
    return main


@one_blas_thread
def solve(
    source: str | os.PathLike | Any,
    skeleton: Any,
    params: dict[str, Any] | None = None,
    *,
    read: ReadOptions = ReadOptions(),
) -> FitResult:
    """Solve a take by IK alone with a subject skeleton fitted before (calibrate once, solve many).

    Markers are matched by label: the skeleton's markers missing from the take
    are tolerated (gaps), labels the skeleton does not know are ignored with a
    warning, and a take with too few known labels is refused (DataError).
    """
    import numpy as np

    from . import __version__
    from .errors import DataError
    from .solvers.ik.motion import solve as solve_motion
    from .stages import clean, export, ik

    params = dict(params or {})
    t0 = time.perf_counter()
    seconds: dict[str, float] = {}
    obj = read_input(source, read, hash_content=False)[0] if isinstance(source, (str, os.PathLike)) else source
    mk = artifacts.markers_of(obj)
    seconds["read"] = time.perf_counter() - t0
    t = time.perf_counter()
    if mk.stage == "read":
        mk = clean.run(mk, params.get("clean") or clean.Params())
    seconds["clean"] = time.perf_counter() - t
    where = {l: i for i, l in enumerate(mk.labels)}
    known = [l for l in skeleton.labels if l in where]
    unknown = [l for l in mk.labels if l not in set(skeleton.labels)]
    missing = [l for l in skeleton.labels if l not in where]
    need = max(3, int(np.ceil(0.3 * len(skeleton.labels))))
    if len(known) < need:
        raise DataError(
            f"only {len(known)} of the skeleton's {len(skeleton.labels)} marker labels are in this take (at least {need} needed)"
            " — is it the same subject and marker set?",
            mk.source or None,
        )
    pts = np.full((mk.n_frames, len(skeleton.labels), 3), np.nan)
    for j, l in enumerate(skeleton.labels):
        if l in where:
            pts[:, j] = mk.points[:, where[l]]
    t = time.perf_counter()
    motion = solve_motion(skeleton, pts, None, iterations=(params.get("ik") or ik.Params()).iterations, rate=mk.rate, source=mk.source,
                          version=ik.VERSION)
    seconds["ik"] = time.perf_counter() - t
    t = time.perf_counter()
    # the skeleton's own rest pose: one skeleton, the same OFFSETs, in every take it solves
    bvh = export.run(motion, dataclasses.replace(params.get("export") or export.Params(), rest_frame="skeleton"))
    seconds["export"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t0
    warnings = []
    if unknown:
        warnings.append(f"{len(unknown)} labels not in the skeleton were ignored: {', '.join(unknown[:20])}" + (" …" if len(unknown) > 20 else ""))
    if missing:
        warnings.append(f"{len(missing)} skeleton markers are missing from the take: {', '.join(missing[:20])}" + (" …" if len(missing) > 20 else ""))
    report = {
        "tool": {"name": "mocapskel", "version": __version__},
        "input": {"file": mk.source, "frames": mk.n_frames, "markers": mk.n_markers, "rate_hz": mk.rate},
        "skeleton": {"segments": len(skeleton.names), "markers": len(skeleton.labels), "source": skeleton.info.get("source", "")},
        "labels": {"matched": len(known), "missing": missing, "ignored": unknown},
        "clean": mk.info.get("clean", {}),
        "ik": {
            "marker_rms_mm": motion.info.get("rms_mm"),
            "marker_rms_mm_per_segment": motion.info.get("rms_mm_per_segment", {}),
            "filled_fraction": motion.info.get("filled_fraction"),
            "out_of_view_frames": motion.info.get("out_of_view_frames", {}),
        },
        "export": bvh.report(),
        "seconds": {k: round(v, 4) for k, v in seconds.items()},
        "warnings": warnings + [w for w in motion.info.get("warnings", []) if w not in warnings] + list(bvh.notes),
    }
    from . import checks

    t = time.perf_counter()
    checks.add_to_report(report, checks.run_checks(motion, pts))
    report["seconds"]["checks"] = round(time.perf_counter() - t, 4)
    return FitResult(motion=motion, bvh=bvh, report=report, run=Run(artifact=motion, key="solve", seconds=seconds, warnings=warnings),
                     points=pts)
