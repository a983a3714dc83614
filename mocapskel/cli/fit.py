"""``mocapskel fit``: the whole pipeline, from a take to BVH."""
from __future__ import annotations

import json
import logging

import click

from .. import pipeline
from ..io.atomic import AtomicOutputs, atomic_open
from ..io.bvh import write_bvh
from .main import cli, say_warnings
from .options import bvh_options, cache_options, check_output, common, fit_options, make_cache, make_read, read_options, strict_option

log = logging.getLogger("mocapskel")


def write_markers_out(path, motion, input_path, read) -> None:
    """The take's markers (as read) plus one virtual marker per joint centre, as C3D or TRC."""
    from ..io.markers import write_markers
    from ..kinematics import with_joint_markers

    markers, _ = pipeline.read_input(input_path, read)
    markers = pipeline.artifacts.markers_of(markers)
    if markers.n_frames != motion.root_pos.shape[0]:  # pragma: no cover - same take
        raise ValueError("markers and motion differ in frame count")
    # keep only the labels the fit used, so that gaps and cleaning are as solved
    write_markers(path, with_joint_markers(markers, motion))


def raise_if_strict(strict: bool, report: dict, source: str) -> None:
    """With ``--strict``, a failing output check is an error (exit code 4) before anything is written."""
    from ..checks import Finding, strict_error

    if strict and report.get("checks"):
        err = strict_error([Finding(c["check"], c["name"], c["message"]) for c in report["checks"]], str(source))
        raise err


def write_report(path, report: dict) -> None:
    with atomic_open(path, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2, allow_nan=False)
        f.write("\n")


@cli.command("fit")
@click.argument("input", type=click.Path(dir_okay=True))
@click.option("-o", "--output", "output", required=True, type=click.Path(), help="BVH file to write.")
@fit_options
@bvh_options
@click.option("--report", "report_path", type=click.Path(), default=None, help="Also write the JSON report here.")
@click.option("--skeleton-out", "skeleton_out", type=click.Path(), default=None, help="Also write the subject skeleton (.skel) for 'mocapskel solve'.")
@click.option("--markers-out", "markers_out", type=click.Path(), default=None, help="Also write the markers plus virtual joint markers (.c3d or .trc).")
@click.option("--html", "html_path", type=click.Path(), default=None, help="Also write the HTML report (plots, 3-D view) here; needs mocapskel[report].")
@strict_option
@read_options
@cache_options
@common
def fit_cmd(input, output, segments, joint_method, rest_frame, up, units, report_path, skeleton_out, markers_out, html_path, strict, exclude, include, cache_dir, no_cache):
    """Fit a skeleton to a take (C3D or TRC) and write its motion as BVH.

    \b
    Examples:
        mocapskel fit take.c3d -o take.bvh
        mocapskel fit take.trc -o take.bvh --up z --units mm --report take.json
    """
    check_output(output, input, suffixes=(".bvh",))
    if report_path:
        check_output(report_path, input, suffixes=(".json",))
    if skeleton_out:
        check_output(skeleton_out, input, suffixes=(".skel",))
    if markers_out:
        check_output(markers_out, input, suffixes=(".c3d", ".trc"))
    if html_path:
        from ..html_report import require_matplotlib
        from .report import HTML_SUFFIXES

        check_output(html_path, input, suffixes=HTML_SUFFIXES)
        require_matplotlib()
    params = pipeline.make_params(segments=segments, joint_method=joint_method, rest_frame=rest_frame, up=up, units=units)
    res = pipeline.fit(input, params, cache=make_cache(cache_dir, no_cache), read=make_read(exclude, include))
    raise_if_strict(strict, res.report, input)
    b = res.bvh
    with AtomicOutputs() as out:  # every output appears at the end, or none does
        write_bvh(out.stage(output), b.skeleton, b.root_pos, b.local_rot, b.frame_time)
        if report_path:
            write_report(out.stage(report_path), res.report)
        if skeleton_out:
            from ..io.skeleton import write_skeleton

            write_skeleton(out.stage(skeleton_out), res.motion.skeleton, source=res.report["input"]["file"])
        if markers_out:
            write_markers_out(out.stage(markers_out), res.motion, input, make_read(exclude, include))
        if html_path:
            from .report import write_html_report

            write_html_report(out.stage(html_path), res)
    ik = res.report["ik"]
    rms = ik.get("marker_rms_mm")
    log.info(
        "wrote %s: %d segments, %d frames, marker rms %s mm (%.1f s)",
        output, len(b.skeleton.names), b.root_pos.shape[0],
        f"{rms:.2f}" if rms is not None else "n/a", res.run.seconds.get("total", 0.0),
    )
    say_warnings(res.report.get("warnings", []))
