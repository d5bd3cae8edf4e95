"""Code named now and imported on first use: the one lazy-import helper.

:class:`Ref` names a module's attribute (a function, a class) without importing
it; :meth:`Ref.load` imports it. The catalog holds its stages' option classes and
entry functions so (:mod:`pipeline.run.catalog`: their modules load numpy, pandas,
SciPy and the Rerun SDK, 1.8 s together, and the catalogue is read by ``vtcal run``'s
options and the run ledger's shortcut without them), the runner builds options from
the loaded classes and :mod:`pipeline.run.code_key` keys the loaded functions (their
modules taken from ``fn.__module__``). The CLI's command table names each command's
module so (:mod:`pipeline.cli`: ``vtcal --help`` imports no command).

Standard library only, and cheap: the CLI imports it before numpy loads.
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import Any, NamedTuple


class Ref(NamedTuple):
    """``module``'s attribute ``name``, imported by :meth:`load`."""

    module: str
    name: str

    def load(self) -> Any:
        """The attribute, its module imported now (once: Python keeps it)."""
        return getattr(importlib.import_module(self.module), self.name)

    def exists(self) -> bool:
        """Whether the module is there to import (without importing it)."""
        return importlib.util.find_spec(self.module) is not None

    def __str__(self) -> str:
        return f"{self.module}:{self.name}"


def resolve(obj: Any) -> Any:
    """``obj`` itself, or what it names when it is a :class:`Ref`."""
    return obj.load() if isinstance(obj, Ref) else obj
