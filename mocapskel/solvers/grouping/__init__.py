"""Markers into rigid segments, and the segments into a tree (Kirk et al. 2005, §3.1 and §3.2).

- :mod:`mocapskel.solvers.grouping.distances`: the spread of pairwise marker distances over a
  take (``distance_std``), its affinity, the take's skin level and the rigid groups it gives;
- :mod:`mocapskel.solvers.grouping.spectral`: spectral clustering and the eigen-gap
  (``spectral_clustering``);
- :mod:`mocapskel.solvers.grouping.grouping`: the grouping rules (lone markers, pairs of skin,
  groups that do not move as one body: ``split_nonrigid``, ``reassign_by_frame``);
- :mod:`mocapskel.solvers.grouping.partition`: how far a group is from rigid (``rigid_rms``) and
  its best split in two;
- :mod:`mocapskel.solvers.grouping.pair_cost`: the cheap joint cost of two groups that the tree
  is chosen by (``pair_cost``, built on the joint estimators' costs).

The stages :mod:`mocapskel.stages.segment` and :mod:`mocapskel.stages.topology` put them together.
"""
