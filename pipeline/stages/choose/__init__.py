"""Which fitted error model the run ships: ``stage`` (the choose stage: the shipped model,
its summary and the calibrated URDF's provenance block).
``node`` (the stage's node: the function the runner calls, data in, data out).
"""
