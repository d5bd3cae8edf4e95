"""Structural identifiability: one set of exact touch-ups per robot, shared by every model."""

from __future__ import annotations

import numpy as np

import pipeline.accuracy.evaluate as evaluate
from pipeline.kinematics import load_chain
from pipeline.models import model_names
from pipeline.robots import builtin_urdf
from pipeline.stages.identify import structure as ident
from pipeline.stages.identify.stage import IdentifyConfig, identify
from tests.test_identify import _case


def _fresh() -> None:
    ident.exact_touchups.cache_clear()
    ident.structure.cache_clear()


def test_every_model_is_rated_on_one_inverse_kinematics(monkeypatch):
    urdf = builtin_urdf("ur5e")
    _fresh()
    calls = []
    real = evaluate.synthetic_touchups

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(evaluate, "synthetic_touchups", counted)
    got = {
        (m, d): ident.structure(m, urdf, "base_link", "flange", d, 1e-6)
        for m in model_names(load_chain(urdf, "base_link", "flange"))
        for d in (True, False)
    }
    assert len(calls) == 1  # one robot: its exact touch-ups made once
    # the same ratings as each model making its own (the cache emptied before each)
    for (m, d), st in got.items():
        _fresh()
        alone = ident.structure(m, urdf, "base_link", "flange", d, 1e-6)
        assert np.array_equal(alone.kept, st.kept)
        assert alone.held == st.held
        assert (alone.gauge is None) == (st.gauge is None)
        if st.gauge is not None:
            assert np.array_equal(alone.gauge, st.gauge)
    assert len(calls) == 1 + len(got)


def test_identify_makes_them_before_the_fits_fork(monkeypatch):
    import pipeline.stages.identify.stage as stage

    urdf, _, _, table, _ = _case(seed=3)
    _fresh()
    made_before = []
    real = stage.parallel_map

    def spy(fn, items, workers):
        made_before.append(ident.exact_touchups.cache_info().currsize)
        return real(fn, items, workers)

    monkeypatch.setattr(stage, "parallel_map", spy)
    identify(table, urdf, "base_link", "flange", IdentifyConfig(model="all", workers=2))
    # made in this process before the workers fork, so they (and later stages' forks)
    # inherit them instead of each solving the inverse kinematics again
    assert made_before == [1]
