"""Sphere fits: the centre and radius of points that keep a constant distance from one point.

- :mod:`mocapskel.solvers.spheres.sphere`: the closed forms of Knight & Semwal 2009 (``gdke``,
  ``ugdk``, ``mgdk``, the incremental ``IGDK``) and the algebraic ``sphere_lls``;
- :mod:`mocapskel.solvers.spheres.mle`: the geometric maximum-likelihood fit and its Cramér–Rao bound;
- :mod:`mocapskel.solvers.spheres.moments`, :mod:`mocapskel.solvers.spheres.solve`: the moments and
  the solve the closed forms share.

The joint-centre estimators and the grouping of markers use them.
"""
