"""What the data and the fit can be trusted with; nothing is deleted, only flagged.

``stage`` (the outliers stage: touch-ups identification must not trust),
``adequacy`` (whether the run's accuracy figure can be trusted: the
model-adequacy test). The guardrails on the input (inputs that look right but
cannot be, caught before identification) are :mod:`pipeline.guardrails.plausibility`,
below identification, which applies them.
``node`` (the stage's node: the function the runner calls, data in, data out).
"""
