"""Guardrails: inputs that look right but cannot be, caught before identification.

``plausibility`` (joint values against the URDF's limits, the scale a known
distance implies, the pin against the nominal robot, joints off the chain).
Below ``identify`` (which applies them) and ``ingest``; ``trust`` (outliers,
adequacy) sits above identify.
"""
