"""vtcal compare: same robot twice flags nothing; a changed robot flags what changed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.accuracy.compare import compare_runs, render_html
from pipeline.accuracy.evaluate import perturbed_chain, random_deviations, synthetic_touchups
from pipeline.cli import main
from pipeline.errors import BadInput
from pipeline.io.artefacts import read_artefact
from pipeline.kinematics.chain import Chain, load_chain
from pipeline.run.runner import write_fits
from pipeline.stages.crossval.stage import CrossvalConfig, cross_validate
from pipeline.stages.identify.stage import IdentifyConfig, identify

URDF = (Path(__file__).resolve().parent.parent / "pipeline/robots/lrmate.urdf").read_text()
PIN = np.array([0.01, -0.02, 0.2])
Q_CENTRE = [0.0, 0.3, -0.3, 0.0, -0.8, 0.0]


def make_run(out: Path, true: Chain, seed: int, *, crossval: bool = False) -> Path:
    """A run folder as `vtcal identify` leaves it (plus recording.json with the nominal URDF)."""
    rng = np.random.default_rng(seed)
    # 4 targets x 12 poses with a wide orientation spread: parameters to ~0.1 mrad / 0.02 mm
    tab, tg = synthetic_touchups(true, PIN, 4, 12, rng, noise_pin_m=3e-5, q_centre=Q_CENTRE,
                                 spread_rad=0.9, centre_spread_rad=0.9)  # fmt: skip
    cfg = IdentifyConfig(model="full", distances=[(0, 3, float(np.linalg.norm(tg[0] - tg[3])))])
    res = identify(tab, URDF, "base_link", "flange", cfg)
    write_fits(res, out)
    (out / "recording.json").write_text(json.dumps({"urdf": URDF}))
    if crossval:
        cv = cross_validate(tab, URDF, "base_link", "flange", cfg, CrossvalConfig(loto=False))
        s = json.loads((out / "identify.json").read_text())
        s["crossval"] = cv.summary
        (out / "identify.json").write_text(json.dumps(s))
    return out


@pytest.fixture(scope="module")
def robots() -> tuple[Chain, Chain, dict]:
    nominal = load_chain(URDF, "base_link", "flange")
    dev = random_deviations(nominal, np.random.default_rng(5))
    changed = json.loads(json.dumps(dev))
    changed["joint_4"]["dq0_rad"] += 2e-3  # the axis was re-mastered by 2 mrad
    changed["joint_3"]["dxyz_m"][0] += 0.4e-3  # and a link bent by 0.4 mm
    return perturbed_chain(nominal, dev), perturbed_chain(nominal, changed), changed


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory, robots: tuple) -> dict[str, Path]:
    a, b, _ = robots
    root = tmp_path_factory.mktemp("runs")
    return {
        "a1": make_run(root / "a1", a, 1, crossval=True),
        "a2": make_run(root / "a2", a, 2),
        "b": make_run(root / "b", b, 3),
    }


def test_same_robot_twice_flags_nothing(runs: dict[str, Path]) -> None:
    res = compare_runs([runs["a1"], runs["a2"]])
    assert res.summary["flags"] == [] and not res.table["moved"].any()
    # every identified kinematic parameter of the second run was compared
    second = res.table[(res.table["run"] == "a2") & (res.table["kind"] == "kinematic")]
    compared = second[second["identifiable"]]
    assert len(compared) > 10 and compared["delta_sigma"].notna().all()
    assert compared["delta_sigma"].max() < 3
    first = res.runs[res.runs["run"] == "a1"].iloc[0]
    assert np.isfinite(first["heldout_rms_mm"]) and first["heldout_rms_mm"] > 0
    assert first["cond"] > 1 and first["n_used"] == 48


def test_changed_robot_flags_the_parameters_that_changed(runs: dict[str, Path]) -> None:
    res = compare_runs([runs["a1"], runs["a2"], runs["b"]])
    moved = res.moved
    assert set(moved["run"]) == {"b"} and (moved["baseline_run"] == "a1").all()
    names = set(moved["parameter"])
    assert {"joint_4.dq0", "joint_3.dx"} <= names, names
    assert len(names) <= 4, names
    d = moved.set_index("parameter")["delta"]
    assert d["joint_4.dq0"] == pytest.approx(2e-3, abs=0.3e-3)
    assert d["joint_3.dx"] == pytest.approx(0.4e-3, abs=0.1e-3)
    assert len(res.summary["flags"]) == 1 and "joint_4.dq0" in res.summary["flags"][0]
    page = render_html(res)
    assert "joint_4.dq0" in page and "<script" not in page


def test_cli_writes_table_and_page(runs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "audit.parquet"
    main(["compare", str(runs["a1"]), str(runs["b"]), "--out", str(out)])
    table = read_artefact(out, "compare")
    assert set(table["run"]) == {"a1", "b"} and table["moved"].any()
    assert (tmp_path / "audit.html").read_text().startswith("<!DOCTYPE html>")
    with pytest.raises(SystemExit) as exc:
        main(["compare", str(runs["a1"]), str(runs["b"]), "--out", str(out), "--fail-on-drift"])
    assert exc.value.code == 5  # its own code: 1 is an unclassified error (README's table)
    main(["compare", str(runs["a1"]), str(runs["a2"]), "--out", str(out), "--fail-on-drift"])


def test_cli_writes_into_a_folder_of_its_own_by_default(
    runs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Not compare.parquet and compare.html loose in the current folder: compare/ holds
    them; --out DIR names another folder; a refused comparison makes no folder."""
    monkeypatch.chdir(tmp_path)
    main(["compare", str(runs["a1"]), str(runs["a2"])])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["compare"]
    assert sorted(p.name for p in (tmp_path / "compare").iterdir()) == [
        "compare.html", "compare.parquet",
    ]  # fmt: skip
    main(["compare", str(runs["a1"]), "--out", "cmp/a1"])
    assert (tmp_path / "cmp" / "a1" / "compare.parquet").is_file()
    with pytest.raises(SystemExit) as exc:
        main(["compare", str(tmp_path / "compare"), "--out", "refused"])
    assert exc.value.code == 2 and not (tmp_path / "refused").exists()


def test_not_a_run_folder_is_one_line_bad_input(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(BadInput) as exc:
        compare_runs([tmp_path / "empty"])
    assert "empty" in str(exc.value) and "\n" not in str(exc.value)


def test_a_model_that_was_not_shipped_is_not_a_verdict(runs: dict[str, Path], tmp_path) -> None:
    """Drift of a model a run did not ship is listed, not flagged (it flagged 7.5 sigma before)."""
    import shutil

    b = tmp_path / "b"
    shutil.copytree(runs["b"], b)
    s = json.loads((b / "identify.json").read_text())
    s["best_model"] = "mdh"  # b shipped another model than the one whose parameters moved
    (b / "identify.json").write_text(json.dumps(s))
    res = compare_runs([runs["a1"], b])
    assert res.summary["flags"] == []
    assert res.summary["not_shipped_moved"] and "not shipped" in res.summary["not_shipped_moved"][0]
    assert res.summary["verdict"].startswith("nothing compared")


def test_different_nominal_robots_compare_nothing_and_say_so(runs: dict[str, Path], tmp_path):
    """Every delta NaN (different nominal URDFs): not 'no parameter moved'."""
    import shutil

    other = tmp_path / "a2"
    shutil.copytree(runs["a2"], other)
    (other / "recording.json").write_text(json.dumps({"urdf": URDF.replace("lrmate", "lrmate_b")}))
    res = compare_runs([runs["a1"], other])
    assert res.summary["verdict"].startswith("nothing compared: the runs have different nominal")
    same = compare_runs([runs["a1"], runs["a2"]])
    assert same.summary["verdict"].startswith("no parameter moved")
    assert same.summary["n_compared"] > 10


def test_a_model_without_a_held_out_figure_says_so_everywhere() -> None:
    """Issue 35: elastic's missing held-out figure was ``nan`` in compare, ``-`` in batch."""
    import math

    from pipeline.accuracy.compare import NOT_CROSS_VALIDATED, heldout_text

    assert heldout_text(math.nan) == NOT_CROSS_VALIDATED == heldout_text(None)
    assert heldout_text(0.05861) == "0.0586 mm"


def test_the_compare_cli_prints_no_nan(runs: dict[str, Path], tmp_path: Path) -> None:
    from click.testing import CliRunner

    from pipeline.cli import cli

    out = tmp_path / "c.parquet"
    res = CliRunner().invoke(cli, ["compare", str(runs["a1"]), str(runs["a2"]), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "nan" not in res.output
    a2 = next(line for line in res.output.splitlines() if line.startswith("a2"))
    assert "held-out not cross-validated" in a2
    assert "nan" not in out.with_suffix(".html").read_text()
