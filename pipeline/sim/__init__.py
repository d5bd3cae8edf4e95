"""The recording simulator (``vtcal simulate``): a simulated touch-up cell with ground truth.

Modules: :mod:`~pipeline.sim.camera` (pinhole + radial distortion),
:mod:`~pipeline.sim.render` (area-coverage target rendering),
:mod:`~pipeline.sim.image_finish` (the simple camera's optics and sensor),
:mod:`~pipeline.sim.target_geometry` (printed target shape, exact projected
ellipse), :mod:`~pipeline.sim.detect` (the simulated controller's detection),
:mod:`~pipeline.sim.robot` (deviations, true URDFs, nominal IK),
:mod:`~pipeline.sim.scenario` (TOML scenarios), :mod:`~pipeline.sim.cell` (the world of one seed),
:mod:`~pipeline.sim.poses` (planned poses), :mod:`~pipeline.sim.session` (clock,
motion, capture), :mod:`~pipeline.sim.cell_adapter` (the cell behind the
measurement protocols), :mod:`~pipeline.sim.link` (that cell as ``vtcal measure``'s
``sim:`` link), :mod:`~pipeline.sim.adapters` (``vtcal measure``'s adapter strings: a
live cell or the simulated one), :mod:`~pipeline.sim.faults`, :mod:`~pipeline.sim.truth`
(the truth file, whose layout follows the conformance sample's) and
:mod:`~pipeline.sim.simulator` (runs a session with the shared touch-up loop of
:mod:`pipeline.live.loop`). It writes with the project's streaming ROS 2 MCAP writer,
:mod:`pipeline.io.mcap_write` (shared with ``vtcal measure``). The simulator sits above
:mod:`pipeline.live` (it runs its loop), never below. See ``docs/simulator.md``.
"""
