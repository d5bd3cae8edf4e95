"""Kinematics core: SE(3) helpers, URDF reading and writing, serial chains."""

from pipeline.kinematics.chain import Chain, fk, fk_frames, jacobian, load_chain
from pipeline.kinematics.urdf import Joint, RobotDescription, parse_urdf

__all__ = [
    "Chain",
    "Joint",
    "RobotDescription",
    "fk",
    "fk_frames",
    "jacobian",
    "load_chain",
    "parse_urdf",
]
