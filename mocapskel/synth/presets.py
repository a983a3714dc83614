"""Named recipes for generated takes: one place for the CLI, the sample data,
the tests and the benchmarks to agree on what "an active human ROM take" is."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .truth import SynthTake

KINDS = ("human", "linkage", "chain")


@dataclass(frozen=True)
class Recipe:
    """What to generate and how to corrupt it (every field has a meaningful default)."""

    kind: str = "human"
    seed: int = 0
    frames: int = 7200
    rate: float = 120.0
    motion: str = "rom"
    counts: tuple[int, ...] = (4, 3, 3)
    """Markers per segment of a chain."""
    link_length: float = 300.0
    markers_per_segment: int | None = None
    """Human: markers on every segment (None: the default 48-marker set)."""
    scale: float = 1.0
    subject_seed: int | None = None
    noise_mm: float = 0.0
    soft_tissue_mm: float = 0.0
    gaps_per_marker_per_minute: float = 0.0
    jumps: int = 0
    ghosts: int = 0
    passive: bool = False
    markerset: str = "default"
    """Human: "default" (48 markers), "cmu41", "gait" or "cluster" (see synth.realistic)."""
    skin: str = "none"
    """Human: "none" or "realistic" (skin motion driven by the joint angles)."""
    wands: bool = True
    """Human, gait set: thigh and shank markers on wands."""

    @property
    def realistic(self) -> bool:
        """Whether the realistic generator makes this take (a real marker set, real skin or an everyday motion)."""
        return self.kind == "human" and (self.markerset != "default" or self.skin != "none"
                                         or self.motion not in ("rom", "walk"))


def active_rom(seed: int = 0, frames: int = 7200, **kw) -> Recipe:
    """DESIGN's active human ROM take: 1 mm noise, 2 mm soft tissue, gaps."""
    return Recipe(kind="human", seed=seed, frames=frames, noise_mm=1.0, soft_tissue_mm=2.0,
                  gaps_per_marker_per_minute=4.0, **kw)


def passive_rom(seed: int = 0, frames: int = 7200, **kw) -> Recipe:
    """The same take from a passive system: relabelled after every gap, 25 ghosts, a few jumps."""
    return Recipe(kind="human", seed=seed, frames=frames, noise_mm=1.0, soft_tissue_mm=2.0,
                  gaps_per_marker_per_minute=4.0, ghosts=25, jumps=10, passive=True, **kw)


def realistic(seed: int = 0, frames: int = 1200, motion: str = "walk", markerset: str = "cmu41", **kw) -> Recipe:
    """A take that looks like a real capture: a real marker set, skin motion driven by the joint angles,
    an everyday motion, 1 mm noise."""
    return Recipe(kind="human", seed=seed, frames=frames, motion=motion, markerset=markerset, skin="realistic",
                  noise_mm=1.0, **kw)


def make(recipe: Recipe) -> SynthTake:
    """Generate the take a recipe describes (deterministic for its seed)."""
    from . import corrupt
    from .chains import hang_chain, kirk_linkage
    from .human import human_take

    rng = np.random.default_rng(recipe.seed)
    if recipe.realistic:
        from .realistic import realistic_take

        kw = {} if recipe.markers_per_segment is None else {"markers_per_segment": recipe.markers_per_segment}
        take = realistic_take(
            rng=rng, n_frames=recipe.frames, rate=recipe.rate, markerset=recipe.markerset, motion=recipe.motion,
            skin=recipe.skin, noise_mm=recipe.noise_mm, scale=recipe.scale, subject_seed=recipe.subject_seed,
            wands=recipe.wands, soft_tissue_mm=recipe.soft_tissue_mm, **kw,
        )
    elif recipe.kind == "human":
        kw = {} if recipe.markers_per_segment is None else {"markers_per_segment": recipe.markers_per_segment}
        take = human_take(
            rng=rng, n_frames=recipe.frames, rate=recipe.rate, motion=recipe.motion, scale=recipe.scale,
            noise_mm=recipe.noise_mm, soft_tissue_mm=recipe.soft_tissue_mm, subject_seed=recipe.subject_seed, **kw,
        )
    elif recipe.kind == "linkage":
        take = kirk_linkage(recipe.frames, rng=rng, noise_mm=recipe.noise_mm, rate=recipe.rate)
    elif recipe.kind == "chain":
        take = hang_chain(recipe.counts, recipe.frames, rng=rng, link_length=recipe.link_length)
        if recipe.noise_mm:
            take = corrupt.add_noise(take, recipe.noise_mm, rng)
    else:
        raise ValueError(f"unknown kind {recipe.kind!r} (kinds: {', '.join(KINDS)})")
    if recipe.gaps_per_marker_per_minute > 0:
        take = corrupt.add_gaps(take, rng, gaps_per_marker_per_minute=recipe.gaps_per_marker_per_minute)
    if recipe.jumps > 0:
        take = corrupt.add_jumps(take, rng, n_jumps=recipe.jumps)
    if recipe.ghosts > 0:
        take = corrupt.add_ghosts(take, rng, n_ghosts=recipe.ghosts)
    if recipe.passive:
        take = corrupt.relabel_passive(take, rng)
    return take
