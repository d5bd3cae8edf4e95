"""Stage cache keys include the stage's code (issue 15: no stale artefacts after a code change).

The central test changes what a stage computes in a copy of the package's
source, reruns into the same run folder in a fresh process, and checks that
exactly that stage and everything downstream ran again, while the stages
upstream stayed cached. Before stage keys held the code, every stage said
"cached" and the old artefacts stayed.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.run import code_key
from pipeline.run.orchestrator import RunConfig, run_pipeline

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"

#: appended to outliers.py in the copy: the stage now rejects one more touch-up
CHANGED_OUTLIERS = """

_flag_outliers_before = flag_outliers


def flag_outliers(table, info, config):  # noqa: F811  (a changed stage, for the test)
    out = _flag_outliers_before(table, info, config)
    first = out.index[out["inlier"]][0]
    out.loc[first, "inlier"] = False
    out.loc[first, "reason"] = "changed_code"
    return out
"""

RUN = """
import json, sys
from pipeline.run.orchestrator import RunConfig, run_pipeline
res = run_pipeline(sys.argv[1], sys.argv[2], RunConfig(report=False), until=sys.argv[3])
print(json.dumps({s.stage: s.status for s in res.stages}))
"""


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(recording, run folder) of the sample run up to crossval with this package."""
    if not SAMPLE.exists():
        pytest.skip(f"shipped sample missing: {SAMPLE}")
    d = tmp_path_factory.mktemp("codekey")
    out = d / "run"
    res = run_pipeline(SAMPLE, out, RunConfig(report=False), until="crossval")
    assert all(s.status == "ran" for s in res.stages)
    return SAMPLE, out


def _package_copy(root: Path) -> Path:
    """A copy of ``pipeline/`` and ``schemas/`` under ``root`` (sources only)."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc")
    shutil.copytree(REPO / "pipeline", root / "pipeline", ignore=ignore)
    shutil.copytree(REPO / "schemas", root / "schemas", ignore=ignore)
    return root


def _run_with(pkg_root: Path, rec: Path, out: Path, until: str) -> dict[str, str]:
    proc = subprocess.run(
        [sys.executable, "-c", RUN, str(rec), str(out), until],
        cwd=pkg_root,
        env={"PYTHONPATH": str(pkg_root), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_changed_stage_and_everything_downstream_rerun(sample_run, tmp_path) -> None:
    rec, first = sample_run
    out = tmp_path / "run"
    shutil.copytree(first, out)
    pkg = _package_copy(tmp_path / "src")
    assert _run_with(pkg, rec, out, "crossval") == dict.fromkeys(
        ["ingest", "touchups", "outliers", "identify", "crossval", "choose"], "cached"
    ), "an identical copy of the code must find every stage fresh"

    target = pkg / "pipeline" / "stages" / "outliers" / "stage.py"
    target.write_text(target.read_text() + CHANGED_OUTLIERS)
    status = _run_with(pkg, rec, out, "crossval")
    assert status == {
        "ingest": "cached",
        "touchups": "cached",
        "outliers": "ran",
        "identify": "ran",
        "crossval": "ran",
        "choose": "ran",
    }
    import pandas as pd

    inliers = pd.read_parquet(out / "inliers.parquet")
    assert (inliers["reason"] == "changed_code").sum() == 1, "the new code's artefact is on disk"


def test_a_change_outside_a_stages_code_leaves_it_cached(sample_run, tmp_path) -> None:
    rec, first = sample_run
    out = tmp_path / "run"
    shutil.copytree(first, out)
    pkg = _package_copy(tmp_path / "src")
    plots = pkg / "pipeline" / "report" / "plots.py"
    plots.write_text(plots.read_text() + "\n\nREPORT_ONLY_CHANGE = 1\n")
    status = _run_with(pkg, rec, out, "identify")
    assert status == {
        **dict.fromkeys(["ingest", "touchups", "outliers", "identify"], "cached"),
        # the provenance block's run id hashes every package file: calibrated.urdf is restamped
        "choose": "ran",
    }


def test_the_digest_sees_a_function_replaced_at_run_time(monkeypatch) -> None:
    before = {s: code_key.stage_code_digest(s) for s in code_key.ENTRY_POINTS}
    from pipeline.stages.outliers import stage as outliers

    original = outliers.flag_outliers

    def replaced(table, info, config):
        return original(table, info, config).iloc[:-1]

    monkeypatch.setattr(outliers, "flag_outliers", replaced)
    after = {s: code_key.stage_code_digest(s) for s in code_key.ENTRY_POINTS}
    assert after["outliers"] != before["outliers"]
    assert {s: d for s, d in after.items() if s != "outliers"} == {
        s: d for s, d in before.items() if s != "outliers"
    }


def test_the_closure_follows_imports_and_stops_at_the_stage() -> None:
    touchup = set(code_key.module_closure("pipeline.stages.touchups.stage"))
    assert {"pipeline.stages.touchups.stage", "pipeline.kinematics.chain", "pipeline"} <= touchup
    assert not any(m.startswith("pipeline.report") for m in touchup)
    identify = set(code_key.module_closure("pipeline.stages.identify.stage"))
    # the error models are imported by the registry at run time: every one is code of identify
    assert {"pipeline.models.full", "pipeline.models.offsets", "pipeline.models.base"} <= identify


@pytest.fixture
def fresh_import_cache(tmp_path, monkeypatch):
    """The import cache in a temporary user cache folder, nothing parsed in this process."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))

    def reset() -> None:
        monkeypatch.setattr(code_key, "_STORE", None)
        monkeypatch.setattr(code_key, "_STORE_NEW", set())
        monkeypatch.setattr(code_key, "_USED", set())
        code_key._imports.cache_clear()
        code_key.module_closure.cache_clear()
        code_key._module_path.cache_clear()

    reset()
    yield reset
    code_key._imports.cache_clear()
    code_key.module_closure.cache_clear()
    code_key._module_path.cache_clear()


def test_import_parses_are_kept_by_source_and_used_again(fresh_import_cache) -> None:
    """A module's parsed imports are written to the user cache and read back by the next
    process; an entry is found by the module's bytes, so the cache is what answers."""
    mod = "pipeline.stages.crossval.stage"
    closure = code_key.module_closure(mod)
    assert "pipeline.stages.identify.stage" in closure
    code_key.save_import_cache()
    path = code_key.import_cache_path()
    entries = json.loads(path.read_text())["entries"]
    assert len(entries) >= len(closure) - 3  # every parsed module (packages included)

    fresh_import_cache()  # a "new process": the file is all it has
    assert code_key.module_closure(mod) == closure
    key = code_key._import_key(mod, code_key._module_path(mod).read_bytes())
    assert key in entries
    # the cache is what answers: a planted entry for crossval's bytes is believed
    entries[key] = ["pipeline.stages.outliers.stage"]
    path.write_text(json.dumps({"format": 1, "entries": entries}))
    fresh_import_cache()
    assert code_key._imports(mod) == frozenset({"pipeline.stages.outliers.stage"})
    # other bytes (an edited module) are another key: parsed afresh
    assert code_key._import_key(mod, b"import pipeline.io.jsonio\n") != key


def test_a_damaged_import_cache_only_means_parsing(fresh_import_cache) -> None:
    expected = code_key.module_closure("pipeline.stages.outliers.stage")
    digest = code_key.stage_code_digest("outliers")
    for damage in ("{not json", json.dumps({"format": 1, "entries": {"x": 3}}), "[]"):
        path = code_key.import_cache_path()
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(damage)
        fresh_import_cache()
        assert code_key.module_closure("pipeline.stages.outliers.stage") == expected
        assert code_key.stage_code_digest("outliers") == digest
        assert json.loads(path.read_text())["format"] == 1  # rewritten whole


def test_the_reports_code_key_does_not_load_the_rerun_sdk() -> None:
    """The report's key imports its entry modules; the Rerun SDK (0.25 s) is left to the
    report itself, where it loads while the frames are read (pipeline.report.outputs).
    Before, the key loaded it outside the report's timed span."""
    code = (
        "import sys\n"
        "from pipeline.run.code_key import stage_code_digest\n"
        "stage_code_digest('report')\n"
        "import pipeline.report.rrd, pipeline.report.outputs\n"
        "print('rerun' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_the_stages_digests_look_each_module_file_up_once(fresh_import_cache, monkeypatch) -> None:
    """The stages after ingest share most of their closures: a module's file is looked up
    once per process, not once per stage and import (1474 lookups for these four stages,
    of 405 paths, before: 5 ms of the outliers stage alone)."""
    import pathlib

    checked: list[str] = []
    real = pathlib.Path.is_file

    def is_file(self: pathlib.Path) -> bool:
        if self.suffix == ".py":
            checked.append(str(self))
        return real(self)

    monkeypatch.setattr(pathlib.Path, "is_file", is_file)
    for stage in ("touchups", "outliers", "identify", "crossval"):
        code_key.stage_code_digest(stage)
    assert checked and len(checked) == len(set(checked))
