"""(W1) of :mod:`pipeline.estimation.whitening`: the flange whitening's shape is paid for
in the variance factor's degrees of freedom."""

from __future__ import annotations

import numpy as np

from pipeline.audit.fit import fit_table
from pipeline.estimation.whitening import SHAPE_PARAMS, whitening_params
from pipeline.io.known_distances import parse_distances
from pipeline.robots import builtin_urdf
from pipeline.sim.history import make_history
from pipeline.stages.identify.stage import identify
from pipeline.stages.identify.types import IdentifyConfig


def test_whitening_params_counts_the_shape_only_when_whitened() -> None:
    assert whitening_params(None) == 0
    assert whitening_params(np.eye(3)) == SHAPE_PARAMS == 5


def test_whitened_fit_spends_five_degrees_of_freedom() -> None:
    rec = make_history("R1", {}, seed=7, n_recordings=1, per_target=12)[0]
    urdf, dist = builtin_urdf(rec.robot), parse_distances(rec.known_distances)
    flange = fit_table(rec.table, urdf, "base_link", "flange", "full", dist)
    cfg = IdentifyConfig(model="full", distances=list(dist), noise_model="isotropic")
    iso = identify(rec.table, urdf, "base_link", "flange", cfg)
    assert not isinstance(iso, dict)
    assert "whitened" in flange.summary["noise_model"]
    assert "whitened" not in iso.summary["noise_model"]
    assert iso.summary["dof"] - flange.summary["dof"] == SHAPE_PARAMS
    # the variance factor is the whitened residual over those degrees of freedom
    assert np.isfinite(flange.summary["sigma_mm"]) and flange.summary["sigma_mm"] > 0


def test_a_fitted_print_shape_is_paid_for_too() -> None:
    """(W2): the print shape's parameters, once fitted, leave the variance factor's dof."""
    from pipeline.stages.identify.shape import spent_unknowns

    fitted = {"fitted": True, "n_params": 8}
    assert spent_unknowns(None, None) == 0
    assert spent_unknowns(np.eye(3), {"fitted": False, "n_params": 8}) == SHAPE_PARAMS
    assert spent_unknowns(None, fitted) == 8
    assert spent_unknowns(np.eye(3), fitted) == SHAPE_PARAMS + 8
