"""Joint zero offsets only: ``origin_k' = origin_k @ Rot(axis_k, dq0_k)``.

The smallest model: one parameter per joint (the encoder zero), everything
else nominal. Jacobian column of ``dq0_k`` = the geometric Jacobian column of
joint ``k`` at the pin (a rotation about the axis at the joint frame).
"""

from __future__ import annotations

from pipeline.models.base import register
from pipeline.models.full import FullOriginModel


@register
class JointOffsetModel(FullOriginModel):
    """Zero offsets of every actuated joint."""

    name = "offsets"
    description = "joint zero offsets only"
    components = ("dq0",)
