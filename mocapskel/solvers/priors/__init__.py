"""Where the model's priors put a joint the data leave free: geometry from the take's own markers, used as the
means and planes of :mod:`mocapskel.solvers.model.joint_map`'s prior factors, never as moves after the fit.

- :mod:`mocapskel.solvers.priors.deepen`: a hinge with a marker over its axis, one limb half-width inside that
  marker (``deepen_joints``): a surface marker sits outside the bone;
- :mod:`mocapskel.solvers.priors.leaf_hinges`: a hinge at the end of a limb at the end segment's markers' middle
  along its axis (``centre_leaf_hinges``);
- :mod:`mocapskel.solvers.priors.mirror`: like limbs' parent's plane of symmetry (``mirror_planes``), where the
  mean of their first joints lies.
"""
