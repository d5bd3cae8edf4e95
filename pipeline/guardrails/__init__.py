"""Guardrails: inputs that look right but cannot be, caught before identification.

``plausibility`` (joint values against the URDF's limits, the scale a known
distance implies, the pin against the nominal robot, joints off the chain).
Below the stages (``ingest`` and ``identify`` apply them) and ``vtcal validate``
(:mod:`pipeline.accuracy.validate`); it imports only the kinematics and the
measurement model.
"""
