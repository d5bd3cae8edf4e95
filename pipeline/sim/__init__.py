"""The recording simulator (``vtcal simulate``): a simulated touch-up cell with ground truth.

Modules: :mod:`~pipeline.sim.camera` (pinhole + radial distortion),
:mod:`~pipeline.sim.render` (area-coverage target rendering, exact projected
ellipse), :mod:`~pipeline.sim.detect` (the simulated controller's detection),
:mod:`~pipeline.sim.robot` (deviations, true URDFs, nominal IK),
:mod:`~pipeline.sim.scenario` (TOML scenarios), :mod:`~pipeline.sim.recorder`
(streaming ROS 2 MCAP writer) and :mod:`~pipeline.sim.simulator` (the session
and the truth file, whose layout follows the conformance sample's). See
``docs/simulator.md``.
"""
