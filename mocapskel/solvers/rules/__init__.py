"""Hand-made placement rules, kept beside the skeleton model until it replaces them.

They move joints after a fit or choose between fits by tests, where the model
(:mod:`mocapskel.solvers.model`) says the same with a prior and a score. The rigid stage's
``joint_model="rules"``, no longer the default, applies them:

- :mod:`mocapskel.solvers.rules.mirror`: like limbs' first joints moved into their parent's plane
  of symmetry (``centre_mirrored_pairs``);
- :mod:`mocapskel.solvers.rules.deepen`: a hinge with a marker over its axis moved one limb
  half-width inside it (``deepen_joints``; the MAP takes this geometry as a prior's mean);
- :mod:`mocapskel.solvers.rules.leaf_hinges`: a hinge at the end of a limb moved along its axis to
  the end segment's markers (``centre_leaf_hinges``);
- :mod:`mocapskel.solvers.rules.plausible`: tests of a fitted skeleton's joints (off the body,
  collapsed, slid: ``implausible_joints``, ``slid_joints``), by which the refinement holds joints
  and the rigid stage picks its start; they decide, so they are rules, not output checks.
"""
