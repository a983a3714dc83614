"""Marker-ID merging (Kirk et al. 2005, §4): which labels of a passive system are one physical marker.

- :mod:`mocapskel.solvers.merging.pairs`: the evidence, robust pairwise label distances and
  rigid partners (``pair_sums``, ``partners_of``);
- :mod:`mocapskel.solvers.merging.links`: track ends joined to track starts where common
  partners put them (``link_tracks``);
- :mod:`mocapskel.solvers.merging.cluster`: Kirk's pose distance and spectral clustering with
  repulsion (``pose_distance``, ``repulsion_spectral``);
- :mod:`mocapskel.solvers.merging.jumps`: samples that leave their rigid partners (sporadic
  jumps, bad gap edges: ``rigid_outliers``, ``rigid_steps``), which the clean stage also uses.

The stages :mod:`mocapskel.stages.clean` and :mod:`mocapskel.stages.merge_ids` put them together.
"""
