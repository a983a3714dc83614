"""``mocapskel solve``: IK alone, with a subject skeleton fitted before."""
from __future__ import annotations

import logging

import click

from .. import pipeline
from ..io.atomic import AtomicOutputs
from ..io.bvh import write_bvh
from ..io.skeleton import read_skeleton
from .fit import check_osim_out, osim_model, raise_if_strict, write_markers_out, write_osim_out, write_report
from .main import cli, say_warnings
from .options import bvh_options, check_output, common, make_read, naming_options, read_options, strict_option

log = logging.getLogger("mocapskel")


@cli.command("solve")
@click.argument("input", type=click.Path(dir_okay=True))
@click.option("--skeleton", "skeleton_path", required=True, type=click.Path(), help="Subject skeleton (.skel) from 'fit --skeleton-out'.")
@click.option("-o", "--output", "output", required=True, type=click.Path(), help="BVH file to write.")
@bvh_options
@naming_options
@click.option("--report", "report_path", type=click.Path(), default=None, help="Also write a JSON report here.")
@click.option("--markers-out", "markers_out", type=click.Path(), default=None, help="Write the markers plus virtual joint markers (.c3d or .trc).")
@click.option("--osim-out", "osim_out", type=click.Path(), default=None,
              help="Also write an OpenSim model (.osim) and beside it its markers (.trc) and coordinates (.mot).")
@strict_option
@read_options
@common
def solve_cmd(input, skeleton_path, output, up, units, names, rest, report_path, markers_out, osim_out, strict, exclude, include):
    """Solve another take of a subject by IK alone, with the skeleton fitted on its calibration take.

    Markers are matched by label; missing ones are tolerated, unknown ones ignored
    with a warning; a take with too few known labels is refused (exit 4).

    \b
    Example:
        mocapskel fit rom.c3d -o rom.bvh --skeleton-out subject.skel
        mocapskel solve walk.c3d --skeleton subject.skel -o walk.bvh
    """
    check_output(output, input, suffixes=(".bvh",))
    if report_path:
        check_output(report_path, input, suffixes=(".json",))
    if markers_out:
        check_output(markers_out, input, suffixes=(".c3d", ".trc"))
    if osim_out:
        check_osim_out(osim_out, input)
    skel = read_skeleton(skeleton_path)
    params = pipeline.make_params(up=up, units=units, names=names, rest=rest)
    res = pipeline.solve(input, skel, params, read=make_read(exclude, include))
    raise_if_strict(strict, res.report, input)
    b = res.bvh
    model = osim_model(res, up) if osim_out else None  # before any output: a skeleton of one segment is an error
    if osim_out:
        res.report.setdefault("outputs", {})["osim"] = str(osim_out)
    with AtomicOutputs() as out:  # every output appears at the end, or none does
        write_bvh(out.stage(output), b.skeleton, b.root_pos, b.local_rot, b.frame_time)
        if report_path:
            write_report(out.stage(report_path), res.report)
        if markers_out:
            write_markers_out(out.stage(markers_out), res.motion, input, make_read(exclude, include), b)
        if osim_out:
            write_osim_out(out, osim_out, model, res.points, res.motion.rate, res.report["input"]["file"])
    say_warnings(res.report.get("warnings", []))
    log.info("wrote %s: %d frames, marker rms %.2f mm", output, b.root_pos.shape[0], res.report["ik"]["marker_rms_mm"] or float("nan"))
