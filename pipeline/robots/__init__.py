"""Built-in nominal robot descriptions (URDF package data).

``lrmate`` (FANUC LR Mate 200iD-like, 6 axes, J2 parallel to J3, offset wrist),
``ur5e`` (UR5e-like, 6 axes, J2-J4 parallel) and ``iiwa7`` (LBR iiwa 7-like,
7 axes). Each has links ``base_link`` and ``flange`` (flange ``z`` along the
last joint axis).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from pipeline.errors import BadInput

BUILTIN = ("lrmate", "ur5e", "iiwa7")


def builtin_urdf(name: str) -> str:
    """URDF XML of a built-in robot (``lrmate``, ``ur5e``, ``iiwa7``)."""
    if name not in BUILTIN:
        raise BadInput(f"robot {name!r} is not built in (known: {', '.join(BUILTIN)})")
    return resources.files("pipeline.robots").joinpath(f"{name}.urdf").read_text()


def load_urdf(name_or_path: str, base_dir: Path | None = None) -> str:
    """URDF XML of a built-in robot by name, or of a file by path (relative to ``base_dir``)."""
    if name_or_path in BUILTIN:
        return builtin_urdf(name_or_path)
    p = Path(name_or_path)
    if not p.is_absolute() and base_dir is not None and not p.exists():
        p = base_dir / p
    if not p.exists():
        raise BadInput(
            f"robot {name_or_path!r}: neither built in ({', '.join(BUILTIN)}) nor a URDF file"
        )
    return p.read_text()
