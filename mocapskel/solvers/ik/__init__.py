"""Inverse kinematics: the segment rotations and root position of a fitted skeleton in every frame.

- :mod:`mocapskel.solvers.ik.motion`: IK of a whole take (``solve``), gaps and limbs out of
  view held, residuals and warnings: what the IK stage calls;
- :mod:`mocapskel.solvers.ik.solve`: the batched Gauss-Newton solver (``solve_ik``, ``IKResult``),
  on :mod:`~mocapskel.solvers.ik.problem` (the tree and marker model with its kernels) and
  :mod:`~mocapskel.solvers.ik.planes` (3-vector and 3x3 kernels over all frames at once);
- :mod:`mocapskel.solvers.ik.start`, :mod:`mocapskel.solvers.ik.segment_poses`: the starting
  pose, each segment's rigid fit to its markers;
- :mod:`mocapskel.solvers.ik.track`, :mod:`mocapskel.solvers.ik.unflip`: continuity in time,
  coarse to fine from key frames (``track``) and short flips solved again (``unflip``).

The skeleton model's fits (:mod:`mocapskel.solvers.model`) pose their frames with ``solve_ik``.
"""
