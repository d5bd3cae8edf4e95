"""The measuring-pose planner (``vtcal plan``; docs/planner.md).

:func:`pipeline.plan.planner.plan_poses` is the stage: candidate views of each
target solved by nominal IK (:mod:`~pipeline.plan.candidates`, :mod:`~pipeline.plan.ik`),
their identification Jacobian reduced to identifiable directions
(:mod:`~pipeline.plan.design`), DETMAX exchange selection by O1/O3/O4/A
(:mod:`~pipeline.plan.select`) and the visiting order (:mod:`~pipeline.plan.order`).
:mod:`~pipeline.plan.check` scores a pose set through the real identification.
"""
