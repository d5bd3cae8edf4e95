"""The choose stage: which fitted error model the run ships, and its summary.

Identify fits every error model asked for and writes each model's calibrated
URDF (``calibrated_MODEL.urdf``) and summary (``models.json``). Cross-validation
scores them on held-out touch-ups (``crossval.parquet``, whose metadata holds
its summary). This stage decides which one becomes ``calibrated.urdf`` and
writes the run's ``identify.json``; it is the only writer of both:

1. without cross-validation, the model identify preferred on training figures
   (``models.json`` ``best_model``: the default model if fitted, else the
   least residual RMS);
2. with it, the model with the least held-out error
   (:func:`pipeline.stages.crossval.stage.cross_validate`); a rule asked for by
   name ('auto') ships under the one model it fitted;
3. ``identify.json`` is the shipped model's summary at the top, every model's
   under ``models``, cross-validation's under ``crossval``, and a headline that
   says what was shipped and why (:func:`shipped_summary`);
4. the shipped URDF gets its provenance block (:mod:`pipeline.export.provenance`) from
   that summary and the run's source.

Pure: text and dicts in, text and a dict out.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pipeline import __version__


def shipped_summary(models: Mapping[str, dict[str, Any]], shipped: str) -> dict[str, Any]:
    """identify.json: the shipped model's own summary at the top, every model under ``models``.

    Every top-level figure (residual, conditioning, predicted accuracy, counts) is
    the shipped model's; other models' figures appear only under their names.
    The headline: each model's first line, the shipped model, then the shipped
    model's last line.
    """
    models = dict(models)
    out = dict(models[shipped])
    out["models"] = models
    out["best_model"] = shipped
    if len(models) > 1:
        out["headline"] = [
            line for m in models.values() for line in list(m.get("headline", []))[:1]
        ] + [
            f"calibrated.urdf from model {shipped}",
            *list(models[shipped].get("headline", []))[-1:],
        ]
    return out


def choose_model(
    fits: Mapping[str, Any],
    model_urdfs: Mapping[str, str],
    crossval: Mapping[str, Any] | None,
    source: Any = None,
) -> tuple[str, dict[str, Any]]:
    """The shipped ``calibrated.urdf`` text and ``identify.json`` (steps 1-4 of the module).

    Parameters
    ----------
    fits : ``models.json``: ``{"models": {model: summary}, "order": [model, ...],
        "best_model": name}`` (``order``: the order fitted, which the headline follows)
    model_urdfs : ``{model: calibrated URDF text}`` of every fitted model
    crossval : cross-validation's summary (``chosen_model``, ``choice``, ...), or
        None when it did not run
    source : :class:`pipeline.export.provenance.Source` of the run, or None (no provenance block)

    Returns
    -------
    (calibrated.urdf text, identify.json dict)
    """
    models = {m: fits["models"][m] for m in fits.get("order", fits["models"])}
    best = str(fits["best_model"])
    summary = shipped_summary(models, best)
    shipped = best
    if crossval is not None:
        chosen = crossval.get("chosen_model")
        choice = str(crossval.get("choice") or "")
        if chosen and chosen not in models and len(models) == 1:
            # one model asked for by a rule ('auto'): ship under the model it fitted
            rule, chosen = chosen, next(iter(models))
            choice = choice.replace(f": {rule},", f": {rule} (which fitted {chosen}),", 1)
        if chosen and chosen in models:
            # every top-level figure becomes the shipped model's (not the first-fitted one's)
            summary = shipped_summary(models, chosen)
            shipped = chosen
        summary["crossval"] = dict(crossval)
        if choice:
            lines = [
                line
                for line in summary.get("headline", [])
                if not line.startswith("calibrated.urdf from model")
            ]
            if chosen:
                lines.append(f"calibrated.urdf from model {chosen}")
            summary["headline"] = [*lines, choice]
    urdf = model_urdfs[shipped]
    if source is not None:
        from pipeline.export.provenance import provenance_lines, stamp_urdf

        urdf = stamp_urdf(urdf, provenance_lines(summary, source, __version__))
    return urdf, summary
