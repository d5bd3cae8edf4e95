"""The report and the Rerun recording of real runs: the shipped sample and the independent
conformance recording (every fault), each run through identification by ``vtcal run``."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner
from support.browser import CHROMIUM, open_in_chromium

from pipeline.cli import cli
from pipeline.report.html import build_report
from pipeline.report.rrd import build_rrd

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
CONFORMANCE = REPO.parent / "shared" / "samples" / "conformance_lrmate_small.mcap"


def run_until_identify(rec: Path, out: Path, *extra: str) -> Path:
    res = CliRunner().invoke(
        cli, ["run", str(rec), "--out", str(out), "--until", "identify", "-q", *extra]
    )
    assert res.exit_code == 0, res.output
    return out


@pytest.mark.skipif(not SAMPLE.exists(), reason="shipped sample missing")
def test_sample_report_under_5_mb(tmp_path: Path) -> None:
    run = run_until_identify(SAMPLE, tmp_path / "run")
    html = build_report(run)
    rrd = build_rrd(run)
    size = html.stat().st_size
    print(
        f"report.html of the shipped sample: {size / 1e6:.2f} MB, run.rrd {rrd.stat().st_size / 1e6:.2f} MB"
    )
    assert size < 5_000_000
    text = html.read_text()
    assert "Verdict" in text and "not available" in text  # crossval not run: said so
    assert "fit residual, model" in text


@pytest.mark.skipif(not CONFORMANCE.exists(), reason="shared conformance sample missing")
def test_conformance_report_shows_rejections_with_thumbnails(tmp_path: Path) -> None:
    run = run_until_identify(CONFORMANCE, tmp_path / "run", "--model", "offsets")
    html = build_report(run)
    assert html.stat().st_size < 5_000_000
    text = html.read_text()
    assert "Rejected touch-ups" in text
    assert text.count("data:image/png;base64,") >= 1  # recording reachable: thumbnails
    assert "length scale was identified" in text  # the recording carries known_distances
    if CHROMIUM is not None:
        res = open_in_chromium(html, tmp_path, screenshot=run / "report.png")
        assert res["leaving"] == [] and res["errors"] == [], res
