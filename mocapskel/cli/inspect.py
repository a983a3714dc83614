"""``mocapskel inspect``: what a take, artifact or BVH file holds."""
from __future__ import annotations


import click
import numpy as np

from .. import artifacts
from .main import cli
from .options import common, read_options
from ..io import artifact_files


def describe_markers(m: artifacts.Markers) -> list[str]:
    vis = np.isfinite(m.points).all(-1)
    lines = [
        f"frames      {m.n_frames} ({m.n_frames / m.rate:.2f} s at {m.rate:g} Hz)" if m.rate else f"frames      {m.n_frames}",
        f"markers     {m.n_markers}",
        f"units       {m.units} in the file (held in mm)",
        f"visible     {100 * vis.mean():.1f} % of samples" if vis.size else "visible     -",
        f"stage       {m.stage}",
    ]
    if m.info.get("excluded"):
        lines.append(f"excluded    {', '.join(map(str, m.info['excluded']))}")
    for w in m.info.get("warnings", []) or []:
        lines.append(f"warning     {w}")
    per = vis.mean(0) if vis.size else np.zeros(m.n_markers)
    lines.append("labels      " + ", ".join(f"{l} ({100 * p:.0f}%)" for l, p in zip(m.labels, per)))
    return lines


def describe_artifact(obj) -> list[str]:
    lines = [f"artifact    {obj.kind}"]
    mk = artifacts.markers_of(obj) if obj.kind != "skeleton" or obj.joints is not None else None
    if obj.kind == "segments":
        lines.append(f"segments    {obj.n_segments}")
        for g, labels in enumerate(obj.info.get("groups", [])):
            lines.append(f"  {g:3d}  {' '.join(map(str, labels))}")
    elif obj.kind == "topology":
        lines.append(f"root        {obj.root}")
        lines += [f"  {a:3d} -> {b:3d}  cost {c:.3g}" for (a, b), c in zip(obj.edges.tolist(), obj.cost.tolist())]
    elif obj.kind == "joints":
        lines += [f"  joint {e:2d} {m:8s} residual {r:.3g} mm" for e, (m, r) in enumerate(zip(obj.method, obj.residual))]
    elif obj.kind in ("skeleton", "motion"):
        sk = obj if obj.kind == "skeleton" else obj.skeleton
        for s, (n, p) in enumerate(zip(sk.names, sk.parent.tolist())):
            lines.append(f"  {n:12s} parent {sk.names[p] if p >= 0 else '-':12s} bone {sk.bone_length[s]:.1f} mm")
        if obj.kind == "motion":
            lines.append(f"frames      {obj.root_pos.shape[0]}")
            if isinstance(obj.info.get("rms_mm"), (int, float)):
                lines.append(f"marker rms  {obj.info['rms_mm']:.2f} mm")
    if mk is not None:
        lines += ["-- markers --"] + describe_markers(mk)
    return lines


def describe_bvh(path: str) -> list[str]:
    from ..io.bvh_read import read_bvh

    skel, root_pos, local_rot, frame_time = read_bvh(path)
    lines = [
        f"BVH         {len(skel.names)} joints, {root_pos.shape[0]} frames, frame time {frame_time:g} s",
        f"order       {skel.order}",
    ]
    for n, p, o in zip(skel.names, skel.parent.tolist(), skel.offset):
        lines.append(f"  {n:12s} parent {skel.names[p] if p >= 0 else '-':12s} offset {o[0]:9.3f} {o[1]:9.3f} {o[2]:9.3f}")
    return lines


@cli.command("inspect")
@click.argument("file", type=click.Path(dir_okay=True))
@read_options
@common
def inspect_cmd(file, exclude, include):
    """Show what a C3D, TRC, .npz artifact or BVH file holds.

    \b
    Example:
        mocapskel inspect take.c3d
    """
    from ..io.paths import require_regular_file

    p = require_regular_file(file, "a .c3d, .trc, .npz or .bvh file")
    suf = p.suffix.lower()
    if suf == ".npz":
        lines = describe_artifact(artifact_files.load(p))
    elif suf == ".bvh":
        lines = describe_bvh(file)
    else:
        from ..io.markers import read_markers

        lines = describe_markers(read_markers(p, exclude=tuple(exclude), include=tuple(include)))
    click.echo(f"{p.name}")
    for line in lines:
        click.echo(f"  {line}")
