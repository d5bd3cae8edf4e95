"""Identification: from converged touch-ups to a calibrated robot.

``stage`` (the stage), ``types`` (its options, results and failure), ``data`` (the
touch-up table as the rows the fit takes), ``frame`` (step 0: the corrections in the
calibrated flange frame; ``first_fit``: its first fit, made once per process), ``shape`` and ``print_shape`` (the targets' printed size and
out-of-roundness), ``structure`` (structural identifiability, the planning Jacobian),
``tables`` (what one model's fit leaves), ``notes`` (the conditioning note).
``node`` (the stage's node: the function the runner calls, data in, data out).
"""
