"""The held-out error of each error model (the choose stage, :mod:`pipeline.stages.choose`,
ships by it).

``stage`` (the crossval stage: k-fold and leave-one-target-out), ``refit`` (the refits
on subsets of one table), ``predict`` (held-out predictions).
``node`` (the stage's node: the function the runner calls, data in, data out).
"""
