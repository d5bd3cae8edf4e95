"""report.html: content from a synthetic run folder, and a headless-Chromium check that it
opens offline (no request leaves the file, no console error), with a screenshot
(:mod:`support.browser`: DevTools protocol over a pipe).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from support.browser import CHROMIUM, open_in_chromium
from support.demo_run import make_demo_run

from pipeline.report.data import load_run
from pipeline.report.figures import nominal_fit
from pipeline.report.html import build_report


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_demo_run(tmp_path_factory.mktemp("run") / "run", seed=3)


@pytest.fixture(scope="module")
def report(demo_run: Path) -> Path:
    return build_report(demo_run)


# ------------------------------------------------------------------------ tests

needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="chromium not installed (.ci/run installs it)"
)


@needs_chromium
def test_report_opens_offline_without_errors(report: Path, tmp_path: Path) -> None:
    shot = report.parent / "report.png"
    res = open_in_chromium(report, tmp_path, screenshot=shot)
    assert res["leaving"] == [], res["leaving"]
    assert res["errors"] == [], res["errors"]
    assert "vtcal report" in res["title"]
    assert res["n_svg"] >= 5  # histogram, per target, targets, convergence, cross-validation, ...
    png = shot.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


@needs_chromium
def test_checker_sees_a_request_leaving(report: Path, tmp_path: Path) -> None:
    """Negative control: a page that fetches from outside is caught (request or CSP error)."""
    html = report.read_text()
    bad = tmp_path / "bad.html"
    bad.write_text(html.replace("</main>", '<img src="http://127.0.0.1:9/x.png"></main>'))
    res = open_in_chromium(bad, tmp_path)
    assert res["leaving"] or res["errors"]
    # and without our CSP the request itself is seen
    bare = tmp_path / "bare.html"
    bare.write_text('<html><body><img src="http://127.0.0.1:9/x.png"></body></html>')
    res = open_in_chromium(bare, tmp_path)
    assert any("127.0.0.1:9" in u for u in res["leaving"])


def test_report_content(report: Path) -> None:
    html = report.read_text()
    # verdict at the top, before any section below it
    assert html.index("Verdict") < html.index('id="residuals"')
    for text in (
        "lrmate200id_like",
        "recording.mcap",
        "2026-09-21",  # date from the recording stamps
        "NOT identifiable",  # scale held, said plainly
        "captured while moving",
        "not converged",
        "data:image/png;base64,",  # thumbnails: the recording is reachable
        "Touch-up convergence",
        "Cross-validation",
        "predicted shape accuracy",
        "not reachable: no known distance",  # absolute accuracy needs a known distance
        "held at their nominal value",
        "along the base frame&#39;s z: not observable",  # why joint_1.z was held
        "inferred by the pipeline",  # what the metadata did not say, at the top
        "dark_on_light (automatic",
    ):
        assert text in html, text
    # nothing that would fetch: no external src/href/url(), no script
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:|//|file:)""", html)
    assert not re.search(r"url\(\s*[\"']?\s*(https?:|//)", html)
    assert "<script" not in html
    assert "Content-Security-Policy" in html


def test_report_is_deterministic_and_small(demo_run: Path, report: Path, tmp_path: Path) -> None:
    a = report.read_bytes()
    b = build_report(demo_run, tmp_path / "b.html").read_bytes()
    assert a == b
    assert len(a) < 5_000_000


def test_report_without_recording_or_identification(tmp_path: Path) -> None:
    """Missing artefacts and an unreachable recording give 'not available', not a crash."""
    run = make_demo_run(tmp_path / "run", seed=1, with_recording=False)
    for f in ("parameters.parquet", "residuals.parquet", "crossval.parquet", "identify.json"):
        (run / f).unlink()
    html = build_report(run).read_text()
    assert "not available" in html
    assert "data:image/png" not in html
    assert "not reachable" in html


def test_nominal_fit_recovers_exact_pin_and_targets(tmp_path: Path) -> None:
    """With the true robot as 'nominal', the linear pin/target fit leaves ~zero residual."""
    run = make_demo_run(tmp_path / "run", seed=2, with_recording=False)
    data = load_run(run)
    # replace the nominal URDF by the calibrated (true) one without the pin link
    assert data.recording is not None and data.calibrated_urdf is not None
    data.recording["urdf"] = data.calibrated_urdf
    res = nominal_fit(data)
    assert res is not None and len(res) >= 6
    assert float(np.max(res["norm"])) < 1e-9
    # the real nominal robot leaves a clearly larger residual
    res_nom = nominal_fit(load_run(run))
    assert res_nom is not None and float(np.sqrt(np.mean(res_nom["norm"] ** 2))) > 1e-5


def test_report_of_an_identify_only_folder(tmp_path: Path) -> None:
    """What `vtcal identify` leaves (no recording.json, no touch-up tables) still reports."""
    run = make_demo_run(tmp_path / "run", seed=4, with_recording=False)
    for f in (
        "recording.json",
        "touchups.parquet",
        "inliers.parquet",
        "frames.parquet",
        "detections.parquet",
        "run.json",
    ):
        (run / f).unlink()
    data = load_run(run)
    assert data.base_link == "base_link" and data.flange_link == "flange"  # from calibrated.urdf
    html = build_report(run).read_text()
    assert "fit residual, model full" in html
    assert "Touch-ups not available" in html


def test_report_with_a_known_distance_says_the_scale_was_identified(tmp_path: Path) -> None:
    run = make_demo_run(tmp_path / "run", seed=6, with_recording=False, known_distance=True)
    html = build_report(run).read_text()
    assert "length scale was identified" in html
    assert "NOT identifiable" not in html
    assert "not reachable: no known distance" not in html


def test_thumbnails_stay_within_their_byte_budget(
    demo_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import pipeline.report.html as report_html

    monkeypatch.setattr(report_html, "THUMB_BUDGET", 1)
    html = build_report(demo_run, tmp_path / "r.html").read_text()
    assert "data:image/png" not in html
    assert "left out to keep the file small" in html
