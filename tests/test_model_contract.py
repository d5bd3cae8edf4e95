"""The error-model contract: a new model is one class, and the pipeline takes it from there.

A throw-away model is defined here (as a new file in ``pipeline/models/`` would
define it: subclass, ``@register``), and ``vtcal identify --model all`` fits it,
cross-validates it and writes it back (its parameter rows, its held-out errors,
its own calibrated URDF) with no other edit anywhere. The declared per-parameter
lists are checked when a model is made, and ``pin_and_jacobian`` checks the
shapes it is given.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_identify import _case

from pipeline.cli import main
from pipeline.models import make_model, model_names
from pipeline.models.base import REGISTRY, register
from pipeline.models.full import FullOriginModel

NAME = "throwaway_zero_and_length"


@pytest.fixture
def throwaway() -> Iterator[str]:
    @register
    class ZeroAndLengthModel(FullOriginModel):
        """Joint zero offsets and joint-origin offsets along z: a model nobody ships."""

        name = NAME
        description = "zero offsets and z offsets (test only)"
        components = ("dz", "dq0")

    try:
        yield NAME
    finally:
        REGISTRY.pop(NAME, None)


def test_a_model_defined_in_one_place_is_fitted_crossvalidated_and_written(
    throwaway: str, tmp_path: Path
) -> None:
    assert throwaway in model_names()
    urdf, _, _, table, targets = _case(seed=5, per_target=10, noise_pin=10e-6)
    csv, urdf_path, out = tmp_path / "t.csv", tmp_path / "r.urdf", tmp_path / "out"
    table.to_csv(csv, index=False)
    urdf_path.write_text(urdf)
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    try:
        main(["identify", str(csv), "--urdf", str(urdf_path), "--out", str(out),
              "--base-link", "base_link", "--flange-link", "flange", "--model", "all",
              "--distance", f"0:2={d02:.9f}", "--no-report"])  # fmt: skip
    except SystemExit as exc:
        assert exc.code in (0, None)
    params = pd.read_parquet(out / "parameters.parquet")
    mine = params[(params["model"] == throwaway) & (params["kind"] == "kinematic")]
    assert len(mine) == 2 * 6 and mine["identifiable"].any()
    cv = pd.read_parquet(out / "crossval.parquet")
    assert cv[cv["model"] == throwaway]["error_mm"].notna().any()
    summary = json.loads((out / "identify.json").read_text())
    assert throwaway in summary["models"] and throwaway in summary["crossval"]["models"]
    assert (out / f"calibrated_{throwaway}.urdf").exists()


def test_the_declared_lists_are_checked_when_a_model_is_made(throwaway: str) -> None:
    from pipeline.kinematics import load_chain
    from pipeline.robots import builtin_urdf

    chain = load_chain(builtin_urdf("lrmate"), "base_link", "flange")
    model = make_model(throwaway, chain)
    assert model.param_priority.shape == (model.n_params,)
    assert np.all(model.param_nominal == 0.0)
    model.param_units.pop()
    with pytest.raises(ValueError, match="param_units"):
        model.check_contract()


def test_pin_and_jacobian_names_a_wrong_shape() -> None:
    from pipeline.kinematics import load_chain
    from pipeline.robots import builtin_urdf

    chain = load_chain(builtin_urdf("lrmate"), "base_link", "flange")
    for name in model_names(chain):
        m = make_model(name, chain)
        x, q = m.zero(), np.zeros((4, 6))
        p, R, J = m.pin_and_jacobian(x, q, np.zeros(3))
        assert p.shape == (4, 3) and J is not None and J.shape == (4, 3, m.n_params)
        with pytest.raises(ValueError, match=r"x has shape"):
            m.pin_and_jacobian(np.zeros(m.n_params + 1), q, np.zeros(3))
        with pytest.raises(ValueError, match=r"q has shape"):
            m.pin_and_jacobian(x, np.zeros((4, 5)), np.zeros(3))
        with pytest.raises(ValueError, match=r"p_flange has shape"):
            m.pin_and_jacobian(x, q, np.zeros((3, 3)))


def test_mdh_writes_its_nominal_dh_values() -> None:
    urdf, _, _, table, targets = _case(seed=5, per_target=10)
    from pipeline.stages.identify.stage import IdentifyConfig, identify

    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    res = identify(table, urdf, "base_link", "flange", IdentifyConfig(model="mdh", distances=[(0, 2, d02)]))  # fmt: skip
    kin = res.parameters[res.parameters["kind"] == "kinematic"].set_index("name")
    # the LR Mate-like arm: joint_2 -> joint_3 is a 0.44 m link along the DH a (or d) axis
    lengths = kin.loc[[n for n in kin.index if n.endswith((".a", ".d"))], "nominal"]
    assert lengths.abs().max() > 0.3, lengths
