"""The touch-up measurement model, defined once, below every stage.

- :mod:`~pipeline.measurement.image`: the image side. A touch-up drives the target's
  image ``(u, v, s)`` (centre, long axis) to the designated ``(u0, v0, s0)``; its
  error ``e_T = (u - u0, v - v0, 1/s - 1/s0)``, the pinhole size/depth relation
  ``s = f D / z`` and its inversions, one image-Jacobian pair's change, and the
  camera, diameter and view geometry an image Jacobian implies.
- :mod:`~pipeline.measurement.pin`: the pin side, eq. (1) of the method paper,
  ``T_base_flange(q_i; x) (p_flange_pin + d_i) = p_base_target[k]``: its declared
  parameter layout ``[kinematic | pin | targets]``, its rows (any subset of
  touch-ups, any row weighting), its known-distance rows, the least-squares
  :class:`~pipeline.measurement.pin.Problem` and the one linear pin/target solve.
- :mod:`~pipeline.measurement.data`: the rows identification fits
  (:class:`~pipeline.measurement.data.FitData`).

Every stage, the live loop, the simulator, the planner, validate, evaluate and
the report take these from here (``docs/architecture.md`` lists the callers;
``tests/test_measurement_core.py`` fails on a second definition). The
simulator's truth (:mod:`pipeline.sim.target_geometry`: the exact projected
ellipse of a printed disc) stays apart: it is what the model approximates.
"""
