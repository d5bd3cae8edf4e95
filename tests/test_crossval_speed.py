"""Cross-validation's shortcuts: refit settings from the full fit, models in forked processes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.accuracy.evaluate import perturbed_chain, random_deviations
from pipeline.accuracy.evaluate import synthetic_touchups as synth
from pipeline.kinematics.chain import load_chain
from pipeline.stages.crossval.stage import CrossvalConfig, cross_validate, refit_config
from pipeline.stages.identify.stage import IdentifyConfig, IdentifyResult, identify
from pipeline.stages.parallel_map import parallel_map

URDF = (Path(__file__).resolve().parent.parent / "pipeline/robots/lrmate.urdf").read_text()
PIN = np.array([0.01, -0.02, 0.2])
Q_CENTRE = [0.0, 0.3, -0.3, 0.0, -0.8, 0.0]


def cell(seed: int, per_target: int = 8) -> tuple[pd.DataFrame, list[tuple[int, int, float]]]:
    chain = load_chain(URDF, "base_link", "flange")
    rng = np.random.default_rng(seed)
    true = perturbed_chain(chain, random_deviations(chain, rng))
    tab, tg = synth(true, PIN, 3, per_target, rng, noise_pin_m=3e-5, q_centre=Q_CENTRE)
    return tab, [(0, 2, float(np.linalg.norm(tg[0] - tg[2])))]


def fit(tab: pd.DataFrame, cfg: IdentifyConfig) -> IdentifyResult:
    res = identify(tab, URDF, "base_link", "flange", cfg)
    assert isinstance(res, IdentifyResult)
    return res


def test_refits_skip_a_print_shape_the_full_fit_did_not_find() -> None:
    tab, dist = cell(6)
    cfg = IdentifyConfig(model="full", distances=dist)
    full = fit(tab, cfg)
    assert full.summary.get("print_shape") is None  # no print-shape columns: nothing to test

    def with_shape(shape: object) -> dict[str, object]:
        return {**full.summary, "print_shape": shape}

    assert refit_config(cfg, full.summary).target_shape == "auto"
    assert (
        refit_config(cfg, with_shape({"fitted": False, "note": "p = 0.3"})).target_shape == "none"
    )
    whole = {"fitted": True, "parameters": "size and out-of-roundness"}
    assert refit_config(cfg, with_shape(whole)).target_shape == "auto"  # tested again
    assert not refit_config(cfg, full.summary).check_plausibility  # the full table passed them


def test_models_in_forked_processes_give_the_serial_results() -> None:
    tab, dist = cell(7, per_target=6)
    idc = IdentifyConfig(model="all", distances=dist)

    def run(workers: int) -> object:
        cfg = CrossvalConfig(models=["offsets", "full"], k=3, loto=False, workers=workers)
        return cross_validate(tab, URDF, "base_link", "flange", idc, cfg)

    one, two = run(1), run(2)
    pd.testing.assert_frame_equal(one.table, two.table)  # type: ignore[attr-defined]
    assert one.summary == two.summary  # type: ignore[attr-defined]
    offset = 10
    assert parallel_map(lambda t: t * t + offset, [3, 1, 2], workers=2) == [19, 11, 14]


def test_the_identify_stages_own_fits_stand_in_for_the_full_refits() -> None:
    tab, dist = cell(8, per_target=6)
    idc = IdentifyConfig(model="all", distances=dist)
    fits = identify(tab, URDF, "base_link", "flange", idc)
    assert isinstance(fits, dict)
    cfg = CrossvalConfig(models=["offsets", "full"], k=3, workers=1)
    fresh = cross_validate(tab, URDF, "base_link", "flange", idc, cfg)
    # the cross-validated models' own fits (every fit given, the choice sentence may also
    # name a fitted model that was not cross-validated: that alone differs)
    given = {m: fits[m].summary for m in cfg.models}
    reused = cross_validate(tab, URDF, "base_link", "flange", idc, cfg, full_fits=given)
    pd.testing.assert_frame_equal(fresh.table, reused.table)
    assert fresh.summary == reused.summary
    every = {m: r.summary for m, r in fits.items()}
    also = cross_validate(tab, URDF, "base_link", "flange", idc, cfg, full_fits=every)
    assert also.chosen_model == fresh.chosen_model
    pd.testing.assert_frame_equal(fresh.table, also.table)
    # the figures do come from what was given (not a refit)
    doctored = {**given, "full": {**given["full"], "rms_mm": 123.0}}
    odd = cross_validate(tab, URDF, "base_link", "flange", idc, cfg, full_fits=doctored)
    assert odd.summary["models"]["full"]["train_rms_mm"] == 123.0


def test_prediction_only_refits_predict_what_full_refits_do(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The folds' lean refits: the same held-out figures, without tables or URDF."""
    import dataclasses

    import pipeline.stages.crossval.stage as cv

    tab, dist = cell(9, per_target=6)
    idc = IdentifyConfig(model="all", distances=dist)
    cfg = CrossvalConfig(models=["offsets", "poe"], k=3, workers=1)
    assert refit_config(idc, {}).prediction_only
    lean = cross_validate(tab, URDF, "base_link", "flange", idc, cfg)
    original = cv.refit_config
    monkeypatch.setattr(
        cv, "refit_config", lambda c, f: dataclasses.replace(original(c, f), prediction_only=False)
    )
    full = cross_validate(tab, URDF, "base_link", "flange", idc, cfg)
    pd.testing.assert_frame_equal(lean.table, full.table)
    assert lean.summary == full.summary
    # a lean fit's own figures are those of the full fit
    one = dataclasses.replace(idc, model="poe")
    a = fit(tab, one)
    b = fit(tab, dataclasses.replace(one, prediction_only=True))
    assert b.calibrated_urdf == "" and b.parameters.empty and b.targets.empty
    for key in ("rms_mm", "sigma_mm", "n_identified"):
        assert abs(a.summary[key] - b.summary[key]) <= 1e-12 * max(1.0, abs(a.summary[key]))
    assert a.target_xyz.keys() == b.target_xyz.keys() == set(a.targets["target_id"])
    for t, xyz in a.target_xyz.items():
        np.testing.assert_array_equal(xyz, b.target_xyz[t])
        row = a.targets.loc[a.targets["target_id"] == t, ["x", "y", "z"]].to_numpy()[0]
        np.testing.assert_array_equal(xyz, row)


def test_identify_fits_its_models_in_forked_processes_as_in_one() -> None:
    tab, dist = cell(9, per_target=6)

    def run(workers: int) -> dict[str, IdentifyResult]:
        res = identify(
            tab,
            URDF,
            "base_link",
            "flange",
            IdentifyConfig(model="all", distances=dist, workers=workers),
        )
        assert isinstance(res, dict)
        return res

    one, two = run(1), run(2)
    assert list(one) == list(two)
    for m in one:
        for name in ("parameters", "residuals", "targets"):
            pd.testing.assert_frame_equal(getattr(one[m], name), getattr(two[m], name))
        assert one[m].calibrated_urdf == two[m].calibrated_urdf
        np.testing.assert_array_equal(one[m].x, two[m].x)


def test_a_result_the_children_cannot_send_back_is_made_here() -> None:
    class Local:  # defined in a function: instances cannot be pickled
        def __init__(self, v: int) -> None:
            self.v = v

    out = parallel_map(Local, [1, 2, 3], workers=2)
    assert [o.v for o in out] == [1, 2, 3]


def test_free_workers_count_a_core_free_when_half_of_it_is(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    from pipeline.stages import parallel_map as pm

    monkeypatch.setattr(pm.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(pm, "runnable_others", lambda: None)  # the load alone
    for load, want in ((0.2, 2), (1.01, 2), (1.49, 2), (1.51, 1), (3.0, 1)):
        monkeypatch.setattr(pm.os, "getloadavg", lambda load=load: (load, 0.0, 0.0))
        assert pm.free_workers() == want, load


def test_a_lagging_load_average_does_not_hide_an_idle_core(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Runs one after another leave the 1-minute load at 1.4-1.6 on an idle 2-core machine:
    nothing else runnable now, a core is free; another task runnable now, it is not."""
    from pipeline.stages import parallel_map as pm

    monkeypatch.setattr(pm.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(pm.os, "getloadavg", lambda: (1.6, 1.2, 1.0))
    monkeypatch.setattr(pm, "runnable_others", lambda: 0)
    assert pm.free_workers() == 2
    monkeypatch.setattr(pm, "runnable_others", lambda: 1)
    assert pm.free_workers() == 1
    monkeypatch.setattr(pm.os, "getloadavg", lambda: (0.3, 0.2, 0.1))
    assert pm.free_workers() == 2  # the load says free: as before


def test_runnable_others_reads_the_kernels_count(monkeypatch, tmp_path) -> None:  # type: ignore[no-untyped-def]
    import builtins

    from pipeline.stages import parallel_map as pm

    readings = iter(["0.50 0.40 0.30 3/120 999\n", "0.50 0.40 0.30 1/120 999\n"] * 2)
    real_open = builtins.open

    def fake_open(path, *a, **k):  # type: ignore[no-untyped-def]
        if str(path) == "/proc/loadavg":
            f = tmp_path / "loadavg"
            f.write_text(next(readings))
            return real_open(f, *a, **k)
        return real_open(path, *a, **k)

    monkeypatch.setattr(builtins, "open", fake_open)
    assert pm.runnable_others(samples=2, gap_s=0.0) == 2  # the largest reading, less this one

    def no_file(path, *a, **k):  # type: ignore[no-untyped-def]
        raise FileNotFoundError(path)

    monkeypatch.setattr(builtins, "open", no_file)
    assert pm.runnable_others() is None


def test_this_process_and_a_forked_one_share_the_tasks() -> None:
    """Two workers are this process and one fork taking tasks by a shared index: both
    take some (a fast one more), the results come back in the tasks' order, and a task's
    exception is raised here."""
    import os
    import time

    def where(t: int) -> tuple[int, int]:
        time.sleep(0.05)
        return t, os.getpid()

    out = parallel_map(where, list(range(8)), workers=2)
    assert [t for t, _ in out] == list(range(8))
    pids = {pid for _, pid in out}
    assert os.getpid() in pids and len(pids) == 2

    def boom(t: int) -> int:
        if t == 5:
            raise ValueError("task 5 failed")
        return t

    with pytest.raises(ValueError, match="task 5 failed"):
        parallel_map(boom, list(range(8)), workers=2)


def test_work_this_run_keeps_busy_is_not_a_free_core(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A registered probe's busy cores are left out of ``workers=0`` (identification),
    unless the map does not yield to them (cross-validation)."""
    import os
    import time

    from pipeline.stages import parallel_map as pm

    monkeypatch.setattr(pm.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(pm.os, "getloadavg", lambda: (0.1, 0.0, 0.0))
    monkeypatch.setattr(pm, "runnable_others", lambda: 0)
    busy = [1]

    def probe() -> int:
        return busy[0]

    def pid(_: int) -> int:
        time.sleep(0.05)  # long enough for the forked worker to take some
        return os.getpid()

    pm.register_busy(probe)
    try:
        assert pm.free_workers() == 1
        assert pm.free_workers(count_busy=False) == 2
        assert set(pm.parallel_map(pid, [1, 2, 3, 4], 0)) == {os.getpid()}
        assert len(set(pm.parallel_map(pid, [1, 2, 3, 4], 0, yield_to_busy=False))) == 2
        busy[0] = 0  # the other work is done: the core is free again
        assert pm.free_workers() == 2
    finally:
        pm.unregister_busy(probe)
    busy[0] = 1
    assert pm.free_workers() == 2  # unregistered
