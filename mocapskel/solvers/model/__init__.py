"""The skeleton model of a take and its solver: start here.

Markers are points fixed on rigid segments, the segments meet at fixed joint centres, and what
is left is noise at the take's own level (DESIGN, "One model, not rules").

- :mod:`mocapskel.solvers.model.calibrate`: the whole-skeleton bundle adjustment, every pose and
  every constant offset fitted together (``refine_skeleton``); :mod:`mocapskel.solvers.model.ties` its linear ties
  between joints (like bones, a plane of symmetry, a limb's middle joint in line);
- :mod:`mocapskel.solvers.model.joint_map`: its MAP with explicit Gaussian priors where the
  markers do not fix a joint (``map_refine``, ``noise_sigma``), the rigid stage's
  ``joint_model="map"``;
- :mod:`mocapskel.solvers.model.links`: two joints with a link of no markers between them, where one joint
  cannot fit (a robot arm's unmarked link), the model's score choosing;
- :mod:`mocapskel.solvers.model.uncertainty`: each joint's uncertainty, the Laplace approximation
  at a fitted skeleton (``skeleton_uncertainty``);
- :mod:`mocapskel.solvers.model.effective` and :mod:`mocapskel.solvers.model.worth`: what the frames are worth,
  from the residuals' correlation in time and from the spread of the joints' estimates they show
  (``joint_overdispersion``, the data term's weight);
- :mod:`mocapskel.solvers.model.skin`: how much of the residual follows the joint angles
  (``skin_motion``), the part of the skin's motion the model's noise does not describe;
- :mod:`mocapskel.solvers.model.slack`: how far the joints wander about their fixed places (``slack_sigma``), the
  soft joints' sigma where the residual is noise;
- :mod:`mocapskel.solvers.model.refinement`: the frames the fits use (``refinement_frames``, ``pick_frames``).

The rigid stage (:mod:`mocapskel.stages.rigid`) calls them; the joints stage gives the starts
(:mod:`mocapskel.solvers.joints`), and every frame is posed by :mod:`mocapskel.solvers.ik`.
"""
