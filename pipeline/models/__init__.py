"""Kinematic error models behind one interface (:class:`pipeline.models.base.ErrorModel`).

Every module of this package except ``base`` and ``observability`` defines a
model and registers it by name; importing the package imports them all, so a
new model is one new file. ``get_model(name)`` / ``model_names()`` look them up.
"""

from __future__ import annotations

import importlib
import pkgutil

from pipeline.kinematics.chain import Chain
from pipeline.models.base import REGISTRY, ErrorModel, register

_NOT_MODELS = {"base", "observability"}

for _info in pkgutil.iter_modules(__path__):
    if _info.name not in _NOT_MODELS and not _info.name.startswith("_"):
        importlib.import_module(f"{__name__}.{_info.name}")

__all__ = ["ErrorModel", "get_model", "make_model", "model_help", "model_names", "register"]


def model_names(chain: Chain | None = None) -> list[str]:
    """Registered model names, in registration order; with ``chain``, those that apply to it
    (:meth:`pipeline.models.base.ErrorModel.applies`)."""
    if chain is None:
        return list(REGISTRY)
    return [n for n, cls in REGISTRY.items() if cls.applies(chain)]


def get_model(name: str) -> type[ErrorModel]:
    """The model class registered as ``name``.

    Raises
    ------
    KeyError
        With the known names, if ``name`` is not registered.
    """
    if name not in REGISTRY:
        raise KeyError(f"unknown error model {name!r}; known: {', '.join(REGISTRY)}")
    return REGISTRY[name]


def make_model(name: str, chain: Chain) -> ErrorModel:
    """The error model ``name`` of ``chain``, its declared lists checked (:meth:`check_contract`)."""
    model = get_model(name)(chain)
    model.check_contract()
    return model


def model_help() -> str:
    """``name (description)`` of every registered model, for the CLI's ``--model`` help."""
    return ", ".join(f"{n} ({REGISTRY[n].description})" for n in REGISTRY)
