"""Seeded synthetic takes with ground truth (chains, linkage, human; corruptions)."""
from .truth import SynthTake, Truth

__all__ = ["SynthTake", "Truth"]
