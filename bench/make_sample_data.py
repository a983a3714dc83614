"""Regenerate sample_data/: small generated takes with their ground truth (seeded).

    python bench/make_sample_data.py
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from mocapskel.io.markers import write_markers
from mocapskel.synth.presets import Recipe, active_rom, make

OUT = Path(__file__).resolve().parents[1] / "sample_data"

SAMPLES = {
    # DESIGN's active human ROM take (1 mm noise, 2 mm soft tissue, gaps), 20 s at 120 Hz
    "human_rom.c3d": active_rom(seed=1, frames=2400),
    # Kirk's linkage, 0.5 mm noise, 10 s
    "linkage.trc": Recipe(kind="linkage", seed=2, frames=1200, noise_mm=0.5),
    # Hang's chain <4-3-3>, noise-free, 300 mm links
    "chain_4-3-3.trc": Recipe(kind="chain", seed=3, frames=300, counts=(4, 3, 3)),
}


def main() -> None:
    OUT.mkdir(exist_ok=True)
    for name, recipe in SAMPLES.items():
        take = make(recipe)
        path = OUT / name
        write_markers(path, replace(take.markers, source=name))
        take.truth.save(OUT / (path.stem + ".truth.npz"))
        print(f"wrote {path.name} ({take.markers.n_frames} frames, {take.markers.n_markers} markers)")


if __name__ == "__main__":
    main()
