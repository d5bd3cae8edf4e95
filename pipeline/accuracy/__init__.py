"""How accurate a calibration is: figures against truth, on held-out data, and verdicts.

``evaluate`` (a model against the simulator's truth: registrations, workspace
poses, synthetic touch-ups), ``validate`` (``vtcal validate``: a calibration on
touch-ups it was not fitted on), ``verdict`` (the run's one-line verdict and its
validated figure), ``compare`` (runs and error models side by side),
``told_apart`` (the paired test of two models' held-out errors). Imported by the
stages, the planner, the simulator, the report and the commands; it imports
none of them.
"""
