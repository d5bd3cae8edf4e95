"""A built wheel carries what ``vtcal run`` reads besides the code: schemas, report templates, robots.

They live at the top of the repository (``schemas/``, ``reports/``); ``setup.py``
maps them into the wheel as ``pipeline/_data/...`` and :mod:`pipeline.resources`
finds them there when no checkout is beside the package. Before, a plain
``pip install .`` failed at the first artefact ("no schema declared").
"""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_the_wheel_carries_schemas_templates_and_robots(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(tmp_path), str(REPO)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = tmp_path.glob("*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for folder, inside in (
        ("schemas", "pipeline/_data/schemas"),
        ("reports", "pipeline/_data/reports"),
    ):
        for f in (REPO / folder).rglob("*"):
            if f.is_file():
                assert f"{inside}/{f.relative_to(REPO / folder).as_posix()}" in names, f
    assert {f"pipeline/robots/{p.name}" for p in (REPO / "pipeline/robots").glob("*.urdf")} <= names
    assert not any(n.startswith(("tests/", "benchmarks/", "datasets/")) for n in names)


def test_resources_fall_back_to_the_wheels_copy(tmp_path: Path, monkeypatch) -> None:
    from pipeline import resources

    assert resources.data_dir("schemas") == REPO / "schemas"
    fake_pkg = tmp_path / "site" / "pipeline"
    (fake_pkg / "_data" / "schemas").mkdir(parents=True)
    monkeypatch.setattr(resources, "PACKAGE_DIR", fake_pkg)
    assert resources.data_dir("schemas") == fake_pkg / "_data" / "schemas"
