"""Where the project's data folders are: ``schemas/``, ``reports/`` (templates) and
``spec/`` (the file contracts: ``recording.md``, ``touchups.md``, ``outputs.md``).

They live at the top of the repository (the brief's layout), beside ``pipeline/``.
An editable install or a checkout finds them there; a built wheel carries copies
inside the package as ``pipeline/_data/schemas``, ``pipeline/_data/reports`` and
``pipeline/_data/spec`` (``setup.py`` maps them), so a plain ``pip install .`` runs too.
"""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent.parent


def data_dir(name: str) -> Path:
    """The folder ``name`` (``"schemas"``, ``"reports"`` or ``"spec"``): the checkout's, else
    the wheel's."""
    checkout = PACKAGE_DIR.parent / name
    if checkout.is_dir():
        return checkout
    return PACKAGE_DIR / "_data" / name


SCHEMA_DIR = data_dir("schemas")
TEMPLATE_DIR = data_dir("reports")
SPEC_DIR = data_dir("spec")


def user_cache_dir(name: str) -> Path:
    """A folder of vtcal's user cache: ``$XDG_CACHE_HOME/vtcal/NAME`` (``~/.cache`` by default).

    Only things that are recomputed when missing live there (compiled report
    templates, the import lists of the code key); the folder is not created here.
    """
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "vtcal" / name
