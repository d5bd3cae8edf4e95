"""Artefact registry: validation on write and read, atomic writes, metadata stamps."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from pipeline.io import artefacts
from pipeline.io.artefacts import (
    SchemaError,
    load_schema,
    read_artefact,
    read_meta,
    write_artefact,
)

TEST_SCHEMA = {
    "name": "touchups",
    "doc": "a frozen copy of the spec's touch-up columns, so these tests do not follow the real one",
    "columns": [
        {"name": "touchup_id", "type": "int64"},
        {"name": "target_id", "type": "int64"},
        {"name": "dx_flange", "type": "float64", "unit": "m"},
        {"name": "dy_flange", "type": "float64", "unit": "m"},
        {"name": "dz_flange", "type": "float64", "unit": "m"},
        {"name": "weight", "type": "float64"},
        {"name": "converged", "type": "bool"},
        {"name": "stamp_ns", "type": "int64", "unit": "ns"},
    ],
    "extra_columns": {"type": "float64", "doc": "joints"},
}


@pytest.fixture(autouse=True)
def _frozen_schema(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch):
    folder = tmp_path_factory.mktemp("schemas")
    (folder / "touchups.json").write_text(json.dumps(TEST_SCHEMA))
    real = artefacts.SCHEMA_DIR
    monkeypatch.setattr(artefacts, "SCHEMA_DIR", folder)
    artefacts.load_schema.cache_clear()
    yield real
    artefacts.load_schema.cache_clear()


def _touchups(n: int = 3) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "touchup_id": range(n),
            "target_id": [0] * n,
            "dx_flange": [0.0] * n,
            "dy_flange": [0.0] * n,
            "dz_flange": [1e-5] * n,
            "weight": [1.0] * n,
            "converged": [True] * n,
            "stamp_ns": [10**18 + i for i in range(n)],
            "joint_1": [0.1 * i for i in range(n)],
        }
    )


def test_every_declared_schema_loads(_frozen_schema: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(artefacts, "SCHEMA_DIR", _frozen_schema)
    artefacts.load_schema.cache_clear()
    names = sorted(p.stem for p in artefacts.SCHEMA_DIR.glob("*.json"))
    assert {"touchups", "inliers", "frames", "detections"} <= set(names)
    for name in names:
        sch = load_schema(name)
        assert sch.name == name
        assert sch.columns, name
        sch.arrow_schema()


def test_round_trip_with_metadata(tmp_path: Path) -> None:
    df = _touchups()
    path = tmp_path / "touchups.parquet"
    write_artefact(
        path, df, "touchups", stage="touchup", config={"gain": 0.9}, inputs={"frames": "abc"}
    )
    back = read_artefact(path, "touchups")
    pd.testing.assert_frame_equal(back[df.columns], df, check_dtype=False)
    meta = read_meta(path)
    assert meta["stage"] == "touchup"
    assert meta["artefact"] == "touchups"
    assert json.loads(meta["inputs"]) == {"frames": "abc"}
    assert meta["config_hash"] == artefacts.config_hash({"gain": 0.9})
    assert meta["config_hash"] != artefacts.config_hash({"gain": 0.8})


def test_write_rejects_missing_and_mistyped_columns(tmp_path: Path) -> None:
    with pytest.raises(SchemaError, match="missing columns"):
        write_artefact(
            tmp_path / "x.parquet", _touchups().drop(columns="weight"), "touchups", stage="t"
        )
    bad = _touchups()
    bad["stamp_ns"] = ["soon"] * len(bad)
    with pytest.raises(SchemaError, match="stamp_ns"):
        write_artefact(tmp_path / "x.parquet", bad, "touchups", stage="t")
    assert not list(tmp_path.iterdir())


def test_read_rejects_foreign_parquet(tmp_path: Path) -> None:
    path = tmp_path / "other.parquet"
    pd.DataFrame({"a": [1]}).to_parquet(path)
    with pytest.raises(SchemaError, match="other.parquet: .*missing column"):
        read_artefact(path, "touchups")


def test_failed_write_keeps_previous_artefact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "touchups.parquet"
    write_artefact(path, _touchups(2), "touchups", stage="t")
    before = path.read_bytes()

    def boom(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(artefacts.os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        write_artefact(path, _touchups(5), "touchups", stage="t")
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["touchups.parquet"]


def test_writes_are_deterministic(tmp_path: Path) -> None:
    a = write_artefact(tmp_path / "a.parquet", _touchups(), "touchups", stage="t", config={"k": 1})
    b = write_artefact(tmp_path / "b.parquet", _touchups(), "touchups", stage="t", config={"k": 1})
    assert a == b
