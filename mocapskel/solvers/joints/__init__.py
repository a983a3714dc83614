"""Joint-centre estimators: where two segments meet, from their markers; the skeleton model's starts.

- :mod:`mocapskel.solvers.joints.score`: SCoRE and SARA, the centre (or axis) fixed in both
  segments' frames, by linear least squares (``score``, ``score_from_markers``);
- :mod:`mocapskel.solvers.joints.jmv`: Kirk's joint-marker variance (``jmv_joint``,
  ``jmv_joint_long``), on the cost of :mod:`mocapskel.solvers.joints.cost` (``joint_cost``,
  ``JointFit``, the distance penalty's weights);
- :mod:`mocapskel.solvers.joints.mtb`: Hang's marker-trajectory bases (``mtb_basis``,
  ``mtb_joint``), and :mod:`mocapskel.solvers.joints.hybrid` his framework over a tree
  (``solve_tree``);
- :mod:`mocapskel.solvers.joints.centres`: centres from segment poses (a hinge's centre along its
  axis, the sphere fit of one segment's markers in the other's frame);
- :mod:`mocapskel.solvers.joints.hinges`: a fitted skeleton's hinge axes, from the relative
  rotations of a joint's two segments (used by the refinement and the placement rules).

The joints stage (:mod:`mocapskel.stages.joints`) picks among them per joint; the skeleton
model (:mod:`mocapskel.solvers.model`) starts from what it picks.
"""
