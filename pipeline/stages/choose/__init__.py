"""Which fitted error model the run ships: ``stage`` (the choose stage: the shipped model,
its summary and the calibrated URDF's provenance block).
"""
