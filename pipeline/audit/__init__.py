"""Auditing a fleet over time (``vtcal audit``, docs/audit.md).

This package owns what is said about robots *across* recordings: which runs
are one robot's history (:mod:`~pipeline.audit.identity`), each recording's
own calibration and its figures (:mod:`~pipeline.audit.fit`), how far the
previous calibration has drifted on a new recording (:mod:`~pipeline.audit.drift`),
whether two consecutive calibrations differ beyond their covariances
(:mod:`~pipeline.audit.change`), the one physical cause that explains a change
(:mod:`~pipeline.audit.attribute`), the error models ranked across the fleet
(:mod:`~pipeline.audit.fleet`), the audit as one pure function from run folders
to tables (:mod:`~pipeline.audit.audit`), its HTML page
(:mod:`~pipeline.audit.page`) and its Rerun timeline (:mod:`~pipeline.audit.rrd`). Reading and writing files is the command's
(:mod:`pipeline.commands.audit`); the simulated histories are
:mod:`pipeline.sim.history`'s.
"""
