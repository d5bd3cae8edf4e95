"""The declared pipeline (issue 20): one writer per file, stages reading only what came before.

The structural checks walk ``catalog.STAGES`` and a real run folder; the
behavioural one is the case the former two-writer layout got wrong: crossval
rewrote ``identify.json`` and ``calibrated.urdf`` after identify wrote them, so
when identify ran again and wrote byte-identical Parquet files, crossval stayed
cached and the held-out choice was lost (identify's training choice shipped).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.io.run_folder import ARTEFACTS, BY_KEY, RUN_FILES, writer
from pipeline.run import code_key
from pipeline.run.catalog import STAGE, STAGE_NAMES, STAGES
from pipeline.run.lazy import resolve
from pipeline.run.orchestrator import RunConfig, run_pipeline

SAMPLE = Path(__file__).resolve().parent.parent / "datasets" / "samples" / "sample_lrmate.mcap"


def test_every_file_has_exactly_one_writer_and_it_declares_it() -> None:
    files = [a.file for a in ARTEFACTS]
    assert len(files) == len(set(files)), "a file declared twice"
    for art in ARTEFACTS:
        declaring = [s.name for s in STAGES if art.key in s.outputs]
        if art.writer == "runner":
            assert declaring == [], art
        else:
            assert declaring == [art.writer], (art.key, declaring)
    for stage in STAGES:
        for key in stage.outputs:
            assert writer(key) == stage.name


def test_stages_read_only_what_an_earlier_stage_wrote() -> None:
    written: set[str] = set()
    for stage in STAGES:
        for key in (*stage.inputs, *stage.optional):
            assert key in written, f"{stage.name} reads {key} before it is written"
        written |= set(stage.outputs)


def test_every_declared_function_and_config_resolves() -> None:
    for stage in STAGES:
        assert callable(stage.fn), stage.name
        for entry in (*stage.code, *([stage.config] if stage.config else [])):
            assert callable(resolve(entry)), entry
    assert set(code_key.ENTRY_POINTS) == set(STAGE_NAMES)


def test_a_stage_takes_only_the_options_of_an_earlier_stage() -> None:
    """``Stage.uses_configs`` names earlier stages with options, each a keyword its function
    takes (crossval: identify's), so no node reads another stage's options from the
    run's context (issue 47)."""
    import inspect

    earlier: set[str] = set()
    for stage in STAGES:
        params = inspect.signature(stage.fn).parameters
        for other in stage.uses_configs:
            assert other in earlier and STAGE[other].config, (stage.name, other)
            assert params[other].kind is inspect.Parameter.KEYWORD_ONLY, (stage.name, other)
        earlier.add(stage.name)
    assert STAGE["crossval"].uses_configs == ("identify",)


def test_each_stages_node_is_in_its_stages_package() -> None:
    """The catalog holds each stage's function itself (no ``module:function`` string for a
    stage), defined in ``node.py`` of the package named as the stage (the report's code is
    ``pipeline/report/``) (issue 47)."""
    for stage in STAGES:
        package = "pipeline.report" if stage.name == "report" else f"pipeline.stages.{stage.name}"
        assert stage.fn.__module__ == f"{package}.node", stage.name
        assert stage.fn_name == f"{package}.node:{stage.name}"


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not SAMPLE.exists():
        pytest.skip(f"shipped sample missing: {SAMPLE}")
    out = tmp_path_factory.mktemp("catalog") / "run"
    run_pipeline(SAMPLE, out, RunConfig(report=False), until="crossval")
    return out


def test_every_file_of_a_run_is_declared(sample_run: Path) -> None:
    fits = json.loads((sample_run / RUN_FILES["models"]).read_text())
    declared = {f for k, f in RUN_FILES.items()}
    declared |= {BY_KEY["model_urdfs"].file.format(model=m) for m in fits["order"]}
    on_disk = {p.name for p in sample_run.iterdir()}
    assert on_disk <= declared, on_disk - declared
    assert len(fits["order"]) > 1  # the sample fits every model: the per-model files exist


def test_a_rerun_identify_keeps_the_held_out_choice(sample_run: Path, tmp_path: Path) -> None:
    import shutil

    out = tmp_path / "run"
    shutil.copytree(sample_run, out)
    # identify's own pick is full; on the sample full and mdh are one fit (held-out RMS
    # equal to 1e-8), so cross-validation is asked to leave full out: the held-out choice
    # then differs from identify's, or this test could not tell the layouts apart
    cfg = RunConfig(report=False, stage_options={"crossval": {"models": "mdh,poe,offsets"}})
    run_pipeline(SAMPLE, out, cfg, until="crossval")
    shipped = json.loads((out / "identify.json").read_text())
    cv = shipped["crossval"]
    assert cv["chosen_model"] in shipped["models"]
    assert shipped["best_model"] == cv["chosen_model"]
    assert json.loads((out / "models.json").read_text())["best_model"] != cv["chosen_model"]
    urdf = (out / "calibrated.urdf").read_text()
    # identify runs again (its options changed and changed back: same Parquet bytes)
    (out / "parameters.parquet").unlink()
    res = run_pipeline(SAMPLE, out, cfg, until="crossval")
    status = {s.stage: s.status for s in res.stages}
    assert status["identify"] == "ran" and status["crossval"] == "cached"
    after = json.loads((out / "identify.json").read_text())
    assert after["best_model"] == cv["chosen_model"]
    assert after["crossval"] == cv
    assert (out / "calibrated.urdf").read_text() == urdf


def test_the_runner_keys_no_stage_or_file_by_name() -> None:
    """How a stage is keyed, planned and written is declared (``Stage.cache``, ``source``,
    ``follows``, ``Artefact.per_model``), never looked up by a stage's or file's name
    (issue 37): the runner's loop names none, but its own ``run`` ledger, the source's
    cache label ``recording`` and the index's ``models`` field (``write_fits``, the
    library's identify-and-choose, aside)."""
    import ast

    import pipeline.run.runner as runner

    names = set(STAGE_NAMES) | set(BY_KEY)
    tree = ast.parse(Path(runner.__file__).read_text())
    skip = {
        id(n)
        for f in tree.body
        if isinstance(f, ast.FunctionDef) and f.name == "write_fits"
        for n in ast.walk(f)
    }
    named = {
        (n.lineno, n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and n.value in names and id(n) not in skip
    }
    assert {v for _, v in named} <= {"run", "recording", "models"}, sorted(named)


def test_identify_declares_the_touchups_it_reads_the_implied_diameter_from(
    sample_run: Path,
) -> None:
    """The image-implied target diameter reaches identify as a declared input (its key
    holds the touch-ups' hash), not through a config built from the disk (issue 37)."""
    from pipeline.io.artefacts import read_meta
    from pipeline.run.catalog import STAGE

    assert "touchups" in STAGE["identify"].optional
    inputs = json.loads(read_meta(sample_run / RUN_FILES["parameters"])["inputs"])
    assert set(inputs) == {"inliers", "touchups"}


def test_identify_and_choose_read_only_the_metadata_they_need(
    sample_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """identify takes the touch-ups' implied target size, choose their capture noise and the
    cross-validation summary, from the tables' metadata: neither table's rows are read
    and checked again (4.2 + 4.4 + 1.4 ms on the 72-touch-up cell)."""
    import shutil

    from pipeline.io import artefacts

    out = tmp_path / "run"
    shutil.copytree(sample_run, out)
    (out / "parameters.parquet").unlink()  # identify runs again, then choose
    read: list[str] = []
    real = artefacts.read_artefact

    def read_artefact(path, schema):  # type: ignore[no-untyped-def]
        read.append(Path(path).name)
        return real(path, schema)

    monkeypatch.setattr(artefacts, "read_artefact", read_artefact)
    res = run_pipeline(SAMPLE, out, RunConfig(report=False), until="crossval")
    status = {s.stage: s.status for s in res.stages}
    assert status["identify"] == "ran" and status["choose"] in ("ran", "cached")
    assert "inliers.parquet" in read  # identify's rows are read
    assert "touchups.parquet" not in read and "crossval.parquet" not in read
    shipped = json.loads((out / "identify.json").read_text())
    assert shipped["crossval"] == json.loads((sample_run / "identify.json").read_text())["crossval"]


def test_a_run_takes_the_tables_it_wrote_instead_of_reading_them_back(
    sample_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every Parquet input of a stage after ingest was written by this run: the stage takes
    the written table (the same frame) instead of decoding and checking the file again;
    a file changed since it was written is read."""
    import shutil

    from pipeline.io import artefacts
    from pipeline.run import runner

    out = tmp_path / "run"
    shutil.copytree(sample_run, out)
    read: list[str] = []
    real = artefacts.read_artefact

    def read_artefact(path, schema):  # type: ignore[no-untyped-def]
        read.append(Path(path).name)
        return real(path, schema)

    monkeypatch.setattr(artefacts, "read_artefact", read_artefact)
    run_pipeline(SAMPLE, out, RunConfig(report=False), until="crossval", force=True)
    assert read == []  # the old runner read frames, detections, touchups, inliers (twice), ...
    shipped, before = (json.loads((d / "identify.json").read_text()) for d in (out, sample_run))
    assert shipped["crossval"] == before["crossval"]  # the same results
    kept = {out / "inliers.parquet": ("0" * 16, None)}  # a hash the file does not have
    frame = runner.load_input("inliers", out, kept)
    assert read == ["inliers.parquet"] and len(frame) > 0


def hand_typed_files(text: str, files: set[str]) -> list[tuple[int, str]]:
    """``(line, name)`` of each string (docstrings aside) in ``text`` that is a run-folder
    file name, or a path ending in one."""
    import ast

    tree = ast.parse(text)
    docs = {
        id(n.body[0].value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Module | ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
        and n.body
        and isinstance(n.body[0], ast.Expr)
        and isinstance(n.body[0].value, ast.Constant)
    }
    return [
        (n.lineno, n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant)
        and isinstance(n.value, str)
        and id(n) not in docs
        and any(n.value == f or n.value.endswith("/" + f) for f in files)
    ]


def test_run_folder_file_names_come_only_from_the_catalog() -> None:
    """No module types a run-folder file name by hand (``RUN_FILES[key]`` instead, declared
    in ``pipeline/io/run_folder.py``), so a renamed file is renamed once (issue 37). Prose and docstrings may name them."""
    root = Path(__file__).resolve().parent.parent / "pipeline"
    files = set(RUN_FILES.values())
    typed = {
        f"{p.relative_to(root)}:{line} {name}"
        for p in root.rglob("*.py")
        if p.relative_to(root).as_posix() != "io/run_folder.py"
        for line, name in hand_typed_files(p.read_text(), files)
    }
    assert typed == set()
    # the check can fail
    sample = 'def f(out):\n    """Reads identify.json."""\n    return out / "identify.json"\n'
    assert hand_typed_files(sample, files) == [(3, "identify.json")]
