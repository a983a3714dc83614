"""``mocapskel synth``: seeded generated takes with their ground truth."""
from __future__ import annotations

import logging
from pathlib import Path

import click

from ..synth.presets import KINDS, Recipe, make
from .main import cli
from .options import check_output, common

log = logging.getLogger("mocapskel")


#: Chains the generator can always build: markers per segment (they must stay 0.1 link lengths
#: apart around the bone) and segments.
MAX_CHAIN_MARKERS = 20
MAX_CHAIN_SEGMENTS = 50


def _counts(value: str) -> tuple[int, ...]:
    try:
        c = tuple(int(x) for x in value.replace(",", "-").split("-") if x)
    except ValueError:
        raise click.BadParameter(f"{value!r} is not like 4-3-3 — give markers per segment joined by '-'", param_hint="'--counts'") from None
    if len(c) < 2 or min(c) < 1:
        raise click.BadParameter("a chain needs at least 2 segments with at least 1 marker each — give e.g. 4-3-3",
                                 param_hint="'--counts'")
    if max(c) > MAX_CHAIN_MARKERS or len(c) > MAX_CHAIN_SEGMENTS:
        raise click.BadParameter(
            f"at most {MAX_CHAIN_MARKERS} markers per segment and {MAX_CHAIN_SEGMENTS} segments (got {value!r}) — use smaller counts",
            param_hint="'--counts'")
    return c


def _finite(lo: float, hi: float):
    """A click callback: a float from ``lo`` to ``hi`` (NaN and inf refused; click's FloatRange lets NaN through)."""

    def check(ctx, param, value):
        if value is not None and not (lo <= value <= hi):
            raise click.BadParameter(f"{value:g} is not from {lo:g} to {hi:g} — give a value in that range")
        return value

    return check


@cli.command("synth")
@click.argument("kind", type=click.Choice(KINDS))
@click.option("-o", "--output", "output", required=True, type=click.Path(), help="Take to write (.c3d or .trc).")
@click.option("--truth", "truth_path", type=click.Path(), default=None, help="Ground truth .npz [default: OUTPUT with .truth.npz].")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--frames", type=click.IntRange(min=2, max=1_000_000), default=7200, show_default=True)
@click.option("--rate", type=float, callback=_finite(1.0, 100_000.0), default=120.0, show_default=True, help="Frames per second (human, linkage; 1 to 100,000).")
@click.option("--motion", type=click.Choice(["rom", "walk", "run", "climb", "reach", "kick"]), default="rom", show_default=True,
              help="Human: what the subject does (run, climb, reach, kick: the realistic generator).")
@click.option("--markerset", type=click.Choice(["default", "cmu41", "gait", "cluster"]), default="default", show_default=True,
              help="Human: marker set (cmu41: CMU/Vicon 41-marker full body; gait: lower-body Plug-in-Gait; cluster: "
                   "4-marker plates + anatomical markers).")
@click.option("--skin", type=click.Choice(["none", "realistic"]), default="none", show_default=True,
              help="Human: skin motion driven by the joint angles (thigh 10-30 mm, shank 5-15, upper arm 5-20).")
@click.option("--wands/--no-wands", default=True, show_default=True, help="Human, gait set: thigh and shank markers on wands.")
@click.option("--counts", default="4-3-3", show_default=True, help="Chain: markers per segment.")
@click.option("--link-length", type=float, callback=_finite(1.0, 100_000.0), default=300.0, show_default=True, help="Chain: joint-to-joint length (mm, 1 to 100,000).")
@click.option("--markers-per-segment", type=click.IntRange(min=1), default=None, help="Human: markers on each segment [default: 48-marker set].")
@click.option("--scale", type=float, callback=_finite(0.1, 100.0), default=1.0, show_default=True, help="Human: body size factor.")
@click.option("--subject-seed", type=int, default=None, help="Human: fix the subject (several takes of one person).")
@click.option("--noise", "noise_mm", type=float, callback=_finite(0.0, 1000.0), default=0.0, show_default=True, help="Gaussian noise (mm).")
@click.option("--soft-tissue", "soft_tissue_mm", type=float, callback=_finite(0.0, 1000.0), default=0.0, show_default=True, help="Skin wobble rms (mm).")
@click.option("--gaps", "gaps", type=float, callback=_finite(0.0, 10_000.0), default=0.0, show_default=True, help="Occlusion gaps per marker per minute.")
@click.option("--jumps", type=click.IntRange(min=0), default=0, show_default=True, help="Sporadic jumps.")
@click.option("--ghosts", type=click.IntRange(min=0), default=0, show_default=True, help="Ghost markers.")
@click.option("--passive", is_flag=True, help="New label after every gap (passive system).")
@common
def synth_cmd(kind, output, truth_path, seed, frames, rate, motion, markerset, skin, wands, counts, link_length, markers_per_segment, scale,
              subject_seed, noise_mm, soft_tissue_mm, gaps, jumps, ghosts, passive):
    """Generate a take with ground truth (joint centres, topology, bone lengths).

    \b
    Examples:
        mocapskel synth human -o rom.c3d --noise 1 --soft-tissue 2 --gaps 4
        mocapskel synth human -o walk.c3d --markerset cmu41 --motion walk --skin realistic --noise 1 --frames 1200
        mocapskel synth linkage -o linkage.trc --noise 0.5 --frames 2400
        mocapskel synth chain --counts 3-2-2-2-2 -o chain.trc --frames 100
    """
    out = check_output(output, suffixes=(".c3d", ".trc"))
    truth_out = Path(truth_path) if truth_path else out.with_name(out.name[: -len(out.suffix)] + ".truth.npz")
    if truth_path:
        check_output(truth_path, suffixes=(".npz",))
    recipe = Recipe(
        kind=kind, seed=seed, frames=frames, rate=rate, motion=motion, counts=_counts(counts), link_length=link_length,
        markers_per_segment=markers_per_segment, scale=scale, subject_seed=subject_seed, noise_mm=noise_mm,
        soft_tissue_mm=soft_tissue_mm, gaps_per_marker_per_minute=gaps, jumps=jumps, ghosts=ghosts, passive=passive,
        markerset=markerset, skin=skin, wands=wands,
    )
    if markers_per_segment is not None and markerset != "default":
        raise click.BadParameter("applies to the default marker set only", param_hint="--markers-per-segment")
    take = make(recipe)
    from dataclasses import replace

    from ..io.atomic import AtomicOutputs
    from ..io.markers import write_markers

    markers = replace(take.markers, source=out.name)
    with AtomicOutputs() as staged:  # the take and its truth appear together, or neither does
        write_markers(staged.stage(out), markers)
        with open(staged.stage(truth_out), "wb") as f:
            take.truth.save(f)
    log.info("wrote %s (%d frames, %d labels) and %s", out, markers.n_frames, markers.n_markers, truth_out)
