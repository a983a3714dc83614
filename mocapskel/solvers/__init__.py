"""Numerical kernels. They know no pipeline and do no I/O.

One folder per concern; the skeleton model first:

- :mod:`mocapskel.solvers.model`: the skeleton model of a take and its solver (the bundle
  adjustment, its MAP with priors, each joint's uncertainty, the refinement);
- :mod:`mocapskel.solvers.joints`: the joint-centre estimators that give the model its starts
  (SCoRE, JMV, MTB and Hang's hybrid, hinges);
- :mod:`mocapskel.solvers.spheres`: sphere fits (Knight & Semwal's closed forms, the geometric fit);
- :mod:`mocapskel.solvers.ik`: inverse kinematics of a fitted skeleton over a whole take;
- :mod:`mocapskel.solvers.grouping`: markers into rigid segments and the segments into a tree;
- :mod:`mocapskel.solvers.merging`: marker-ID merging of passive systems;
- :mod:`mocapskel.solvers.priors`: where the model's priors put a joint the data leave free (their means and planes).

The modules at this level are shared by several folders and by the rest of the package:
:mod:`~mocapskel.solvers.rotations` (rotation kernels), :mod:`~mocapskel.solvers.rigid` (Kabsch),
:mod:`~mocapskel.solvers.rigid_shape` (one rigid shape's poses over a take),
:mod:`~mocapskel.solvers.parallel` (threads and forked workers), :mod:`~mocapskel.solvers.rest_pose`
and :mod:`~mocapskel.solvers.joint_moves` (a fitted skeleton's rest pose and moved joints),
and for the outputs :mod:`~mocapskel.solvers.bvh_pose`,
:mod:`~mocapskel.solvers.euler_continuity` and :mod:`~mocapskel.solvers.osim_model`.
"""
