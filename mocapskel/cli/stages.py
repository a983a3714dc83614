"""One command per stage (``mocapskel clean|merge-ids|segment|topology|joints|rigid|ik``) and ``export``."""
from __future__ import annotations

import logging

import click

from .. import pipeline
from ..io.atomic import AtomicOutputs
from ..io.markers import write_markers
from ..stages import export
from .main import cli
from .options import naming_options, bvh_options, cache_options, check_output, common, fit_options, make_cache, make_read, read_options
from ..io import artifact_files

log = logging.getLogger("mocapskel")

_HELP = {
    "clean": "Trim gap edges, turn sporadic jumps into gaps, drop short runs.",
    "merge-ids": "Merge labels that are one physical marker (passive systems).",
    "segment": "Group markers into rigid segments (spectral clustering).",
    "topology": "Connect the segments into a tree (joint costs, minimum spanning tree).",
    "joints": "Estimate every joint centre's trajectory.",
    "rigid": "Fit a rigid skeleton: constant offsets, bone lengths.",
    "ik": "Solve every frame by inverse kinematics.",
}


def _make(stage: str):
    @click.argument("input", type=click.Path(dir_okay=True))
    @click.option("-o", "--output", "output", required=True, type=click.Path(), help="Artifact (.npz) to write.")
    @fit_options
    @read_options
    @cache_options
    @common
    def cmd(input, output, segments, joint_method, joint_model, rest_frame, exclude, include, cache_dir, no_cache, write_c3d=None):
        check_output(output, input, suffixes=(".npz",))
        if write_c3d is not None:
            check_output(write_c3d, input, output, suffixes=(".c3d",))
        params = pipeline.make_params(segments=segments, joint_method=joint_method, joint_model=joint_model, rest_frame=rest_frame)
        run = pipeline.run_until(input, stage, params, cache=make_cache(cache_dir, no_cache), read=make_read(exclude, include))
        with AtomicOutputs() as out:  # the artifact and the C3D appear together, or neither does
            artifact_files.save(run.artifact, out.stage(output))
            if write_c3d is not None:
                write_markers(out.stage(write_c3d), run.artifact)
        log.info("wrote %s (%s artifact)", output, run.artifact.kind)
        if write_c3d is not None:
            log.info("wrote %s (%d merged labels)", write_c3d, run.artifact.n_markers)

    cmd.__doc__ = (
        f"{_HELP[stage]}\n\nINPUT is a take (.c3d, .trc) or the .npz artifact of an earlier stage;"
        f" the stages in between are run.\n\n\b\nExample:\n    mocapskel {stage} take.c3d -o {stage.replace('-', '_')}.npz"
    )
    if stage == "merge-ids":
        cmd.__doc__ += "\n    mocapskel merge-ids take.c3d -o merged.npz --write-c3d merged.c3d"
        cmd = click.option(
            "--write-c3d", "write_c3d", type=click.Path(), default=None, metavar="FILE.c3d",
            help="Also write the take with merged labels (one per physical marker) as C3D.",
        )(cmd)
    return cli.command(stage)(cmd)


for _s in pipeline.STAGES:
    _make(_s)


@cli.command("export")
@click.argument("input", type=click.Path(dir_okay=True))
@click.option("-o", "--output", "output", required=True, type=click.Path(), help="BVH file to write.")
@bvh_options
@naming_options
@fit_options
@read_options
@cache_options
@common
def export_cmd(input, output, up, units, names, rest, segments, joint_method, joint_model, rest_frame, exclude, include, cache_dir, no_cache):
    """Write BVH from an ik artifact (or from any earlier input, running what is missing).

    \b
    Example:
        mocapskel ik take.c3d -o take_ik.npz
        mocapskel export take_ik.npz -o take.bvh --up z --units mm
    """
    check_output(output, input, suffixes=(".bvh", ".glb", ".gltf"))
    params = pipeline.make_params(segments=segments, joint_method=joint_method, joint_model=joint_model, rest_frame=rest_frame, up=up, units=units,
                                  names=names, rest=rest)
    run = pipeline.run_until(input, "ik", params, cache=make_cache(cache_dir, no_cache), read=make_read(exclude, include))
    b = export.run(run.artifact, params["export"])
    from .fit import write_outputs

    with AtomicOutputs() as out:
        write_outputs(out, output, None, b)
    for n in b.notes:
        log.warning("warning: %s", n)
    log.info("wrote %s", output)
