"""The audit's fleet page, the one a maintenance engineer starts from: every robot in one
row, in the order of attention (failed, changed, overdue, the rest; worst first), each
robot's timeline one click away on its own page; with 500 robots it loads in under 2 s.

The audit's tables are built directly (no fit): :func:`synthetic_fleet` writes them as
``vtcal audit`` does (``pipeline.audit.audit.AuditResult``).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from support.browser import CHROMIUM, probe_pages

from pipeline.audit.attention import DAY_NS, fleet_status
from pipeline.audit.audit import CHANGE_COLUMNS, AuditResult
from pipeline.audit.page import render_page, robot_file, write_pages

#: the first recording's date (2026-01-05) and the audit's time, 400 days later
T0 = 1_767_600_000 * 10**9
NOW = T0 + 400 * DAY_NS
MODELS = ("offsets", "mdh", "full", "poe")


def _robot(
    rid: str,
    drift: tuple[float, ...] = (0.01, 0.012, 0.011),
    *,
    passed: bool = True,
    kind: str = "none",
    significance: str = "none",
    read_mm: float = math.nan,
    last_day: float = 390.0,
    step_days: float = 30.0,
    cross_text: str = "",
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """One robot's recordings (``len(drift) + 1``, the last on ``last_day`` after
    :data:`T0`) and history comparisons, the latest of which reads ``kind`` with
    ``significance``; its latest validation ``passed``."""
    n = len(drift) + 1
    stamps = [int(T0 + (last_day - (n - 1 - i) * step_days) * DAY_NS) for i in range(n)]
    names = [f"{rid}-r{i:02d}" for i in range(n)]
    recs = [
        {
            "robot_id": rid, "model": "lrmate200id", "recording": names[i],
            "stamp_ns": stamps[i], "index": i, "n_touchups": 36,
            "previous": names[i - 1] if i else "", "fresh_mm": 0.008,
            "validated_mm": drift[i - 1] + 0.004 if i else math.nan,
            "drift_mm": drift[i - 1] if i else math.nan,
            "drift_raw_mm": drift[i - 1] + 0.006 if i else math.nan, "tolerance_mm": 0.1,
            "passed": passed if i == n - 1 else True, "verdict": "",
        }
        for i in range(n)
    ]  # fmt: skip
    changes = []
    for i in range(1, n):
        last = i == n - 1
        k = kind if last else "none"
        changed = k != "none"
        cause = {"arm": "joint_3 zero offset", "camera": "camera / pin remounted"}.get(k, "")
        changes.append(
            {
                "comparison": "history", "robot_id": rid, "from_robot_id": rid,
                "from_recording": names[i - 1], "to_recording": names[i], "stamp_ns": stamps[i],
                "chi2": 480.2 if changed else 28.5, "dof": 30, "f_dof": 24.0,
                "p_value": 1e-12 if changed else 0.54, "alpha": 0.01, "changed": changed,
                "kind": k, "cause": cause,
                "columns": ["joint_3.dq0"] if k == "arm" else [],
                "size": [np.radians(0.05)] if k == "arm" else [],
                "size_std": [np.radians(0.004)] if k == "arm" else [],
                "residual_chi2": 25.0, "residual_dof": 29, "groups": [], "alternatives": [],
                "text": f"{cause}: +0.0500 +- 0.0040 deg" if changed else "no change: chi2 28.5 "
                "on 30 dof (p = 0.54 >= 0.01)",
                "read_drift_mm": read_mm if last else math.nan,
                "significance": significance if last else "none",
            }
        )  # fmt: skip
    return recs, changes


def _result(robots: list[tuple[list[dict], list[dict]]], cross: bool = True) -> AuditResult:
    """The audit's tables of ``robots`` (:func:`_robot`): each robot's first recording
    compared with the previous robot's (read as different robots), every model on every
    recording."""
    recs = [r for rr, _ in robots for r in rr]
    changes = [c for _, cc in robots for c in cc]
    firsts = [rr[0] for rr, _ in robots]
    for a, b in zip(firsts, firsts[1:], strict=False) if cross else ():
        changes.append(
            {
                "comparison": "robots", "robot_id": b["robot_id"],
                "from_robot_id": a["robot_id"], "from_recording": a["recording"],
                "to_recording": b["recording"], "stamp_ns": b["stamp_ns"], "chi2": 2.41e5,
                "dof": 30, "f_dof": 24.0, "p_value": 0.0, "alpha": 0.01, "changed": True,
                "kind": "different_robot", "cause": "", "columns": [], "size": [],
                "size_std": [], "residual_chi2": math.nan, "residual_dof": 0,
                "groups": ["joint_2", "joint_3", "joint_5", "pin"], "alternatives": [],
                "text": "different robots of one model (or an arm rebuilt): 4 of the parameter "
                "groups changed at once (joint_2, joint_3, joint_5, pin); no single cause "
                "explains it",
                "read_drift_mm": math.nan, "significance": "beyond_tolerance",
            }
        )  # fmt: skip
    rng = np.random.default_rng(1)
    models = pd.DataFrame(
        [
            {"recording": r["recording"], "model": m, "heldout_mm": h, "rank": k + 1}
            for r in recs
            for k, (m, h) in enumerate(
                zip(MODELS, sorted(rng.uniform(0.005, 0.05, 4)), strict=True)
            )
        ]
    )
    ranking = pd.DataFrame(
        {"model": list(MODELS), "median_rank": [1.0, 2.0, 3.0, 4.0],
         "rms_heldout_mm": [0.011, 0.02, 0.03, 0.04], "n": len(recs)}
    )  # fmt: skip
    return AuditResult(
        pd.DataFrame(recs), pd.DataFrame(changes, columns=CHANGE_COLUMNS), models, ranking
    )


def _order(html: str) -> list[str]:
    """The robots of the fleet table, top to bottom."""
    return re.findall(r'<tr class="st-\w+" id="robot-([^"]+)"', html)


def attention_fleet() -> AuditResult:
    """Robots of each class, several per class, listed in no particular order."""
    return _result(
        [
            _robot("fine", (0.01, 0.012, 0.02)),
            _robot("fine-old", (0.01, 0.012, 0.03), last_day=100),  # overdue at 90 days
            _robot(
                "within",
                (0.01, 0.03, 0.04),
                kind="arm",
                significance="within_tolerance",
                read_mm=0.039,
            ),  # fmt: skip
            _robot(
                "changed-small",
                (0.01, 0.01, 0.12),
                kind="camera",
                significance="beyond_tolerance",
                read_mm=0.12,
            ),  # fmt: skip
            _robot(
                "failed",
                (0.01, 0.02, 0.15),
                passed=False,
                kind="arm",
                significance="beyond_tolerance",
                read_mm=0.15,
            ),  # fmt: skip
            _robot("older", (0.01, 0.012, 0.01), last_day=20),
            _robot(
                "swapped",
                (0.01, 0.01, 0.8),
                kind="different_robot",
                significance="beyond_tolerance",
            ),  # fmt: skip
            _robot("failed-worse", (0.3, 0.2, 0.4), passed=False, last_day=10),
            _robot(
                "changed-big",
                (0.01, 0.02, 0.35),
                kind="arm",
                significance="beyond_tolerance",
                read_mm=0.35,
            ),  # fmt: skip
            _robot("new", ()),  # one recording: nothing validated yet
            _robot("worse-fine", (0.01, 0.05, 0.09)),
            _robot("was-changed", (0.2, 0.05, 0.01)),  # an old change: its latest is fine
        ]
    )


#: the order of :func:`attention_fleet` with a 90-day interval
EXPECTED = [
    "failed-worse", "failed",  # latest validation failed, larger drift first (overdue too)
    "swapped", "changed-big", "changed-small",  # different robot (no drift figure) first
    "older", "fine-old",  # overdue, older first
    "worse-fine", "within", "fine", "was-changed", "new",  # the rest, larger drift first
]  # fmt: skip


def test_the_fleet_table_lists_robots_in_the_order_of_attention() -> None:
    res = attention_fleet()
    html = render_page(res, now_ns=NOW, interval_days=90)
    assert _order(html) == EXPECTED
    rows = dict(re.findall(r'id="robot-([^"]+)"><td[^>]*>.*?</td><td class="st">(\w+)</td>', html))
    assert rows["within"] == "ok" and rows["failed"] == "failed" and rows["older"] == "overdue"
    # a change within tolerance is said in its row, and each robot's name opens its page
    assert "joint_3 zero offset, within tolerance (0.0390 mm)" in html
    assert "<td>drift beyond 0.1 mm; joint_3 zero offset</td>" in html  # the robot "failed"
    assert f'<a href="{robot_file("failed")}">failed</a>' in html
    assert "2 failed" in html and "3 changed" in html and "2 overdue" in html and "5 ok" in html
    # every row has a sparkline but the robot with one recording
    assert html.count('<svg class="spark"') == 11


def test_interval_days_makes_robots_overdue() -> None:
    res = attention_fleet()
    st = fleet_status(res.recordings, res.changes, now_ns=NOW)  # no interval: none overdue
    assert not st["overdue"].any() and "overdue" not in set(st["status"])
    st = fleet_status(res.recordings, res.changes, now_ns=NOW, interval_days=90).set_index(
        "robot_id"
    )
    assert st.loc["older", "age_days"] == pytest.approx(380)
    assert set(st.index[st["overdue"]]) == {"older", "fine-old", "failed-worse"}
    assert st.loc["failed-worse", "status"] == "failed"  # a failure stays first
    st = fleet_status(res.recordings, res.changes, now_ns=NOW, interval_days=5)
    assert st["overdue"].all()  # every last recording is 10 days old or more
    html = render_page(res, now_ns=NOW, interval_days=90)
    assert 'class="nowrap late">2026-01-25 (380 days)</td>' in html
    assert "no recording for more than 90 days" in html


def test_the_cli_takes_interval_days(tmp_path: Path) -> None:
    """``vtcal audit --interval-days``: the simulated recordings (2026-01-05) are older than
    a 30-day interval today, not than a 100-year one."""
    from pipeline.cli import main
    from pipeline.sim.history import make_history, write_history

    write_history(make_history("A", {}, seed=11, n_recordings=2, per_target=4), tmp_path / "runs")
    for days, status in (("30", "overdue"), ("36500", "ok")):
        out = tmp_path / days
        try:
            main(["audit", str(tmp_path / "runs"), "--out", str(out), "--models", "offsets",
                  "--workers", "1", "--interval-days", days])  # fmt: skip
        except SystemExit as exc:
            assert not exc.code, exc.code
        html = (out / "audit.html").read_text()
        assert re.search(rf'<td class="st">{status}</td>', html), (days, html[-3000:])
        assert (out / robot_file("A")).is_file()
    with pytest.raises(SystemExit) as exc:
        main(["audit", str(tmp_path / "runs"), "--out", str(out), "--interval-days", "0"])
    assert exc.value.code == 2


def test_robot_files_are_plain_and_unique() -> None:
    assert robot_file("cell-3") == "robots/cell-3.html"
    odd = [robot_file(r) for r in ("cell 3", "cell/3", "cell_3", "../x", "")]
    assert len(set(odd)) == len(odd)
    assert all(re.fullmatch(r"robots/[A-Za-z0-9_-]+\.html", f) for f in odd), odd


def synthetic_fleet(n: int = 500, n_recordings: int = 4, seed: int = 7) -> AuditResult:
    """``n`` robots of ``n_recordings`` each: a few failed, changed or overdue."""
    rng = np.random.default_rng(seed)
    robots = []
    for i in range(n):
        drift = tuple(rng.gamma(2.0, 0.012, n_recordings - 1))
        u = rng.uniform()
        kw: dict[str, Any] = {"last_day": float(rng.uniform(320, 399))}
        if u < 0.05:  # the drift the change read is the validated drift: beyond, failed
            d = float(rng.uniform(0.11, 0.6))
            kw.update(passed=False, kind="arm", significance="beyond_tolerance", read_mm=d)
            drift = (*drift[:-1], d)
        elif u < 0.12:  # no one cause: no drift figure, the calibrations' distance below
            kw.update(kind="several", significance="beyond_tolerance")
        elif u < 0.25:
            kw.update(kind="arm", significance="within_tolerance", read_mm=0.04)
        elif u < 0.35:
            kw["last_day"] = float(rng.uniform(0, 300))
        robots.append(_robot(f"cell-{i:03d}", drift, **kw))
    return _result(robots)


WIDTHS = (900, 1400)


@pytest.fixture(scope="module")
def fleet_pages(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("fleet")
    res = synthetic_fleet()
    page = write_pages(res, out, now_ns=NOW, interval_days=90)
    first = _order(page.read_text())[0]
    return {"fleet": page, "robot": out / "robots" / f"{first}.html"}


def test_the_fleet_page_is_small(fleet_pages: dict[str, Path]) -> None:
    """500 robots: one row each, no chart but the sparklines (no timeline, no heat map),
    every robot's page written beside it."""
    html = fleet_pages["fleet"].read_text()
    assert len(_order(html)) == 500
    assert len(html) < 400_000, len(html)
    assert "<rect" not in html and html.count("<svg") == 500
    assert len(list(fleet_pages["fleet"].parent.glob("robots/*.html"))) == 500


@pytest.fixture(scope="module")
def fleet_probed(
    fleet_pages: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
) -> dict[tuple[str, int], dict]:
    if CHROMIUM is None:
        pytest.skip("chromium not installed (.ci/run installs it)")
    return probe_pages(fleet_pages, tmp_path_factory.mktemp("chromium"), WIDTHS)


@pytest.mark.parametrize("width", WIDTHS)
def test_500_robots_load_fast_and_fit_the_window(fleet_probed: dict, width: int) -> None:
    """The fleet page of 500 robots x 4 recordings in headless Chromium: loaded and laid out
    in under 2 s, no console error, no table cell's token split, nothing wider than the
    window; the robot's page too."""
    for page in ("fleet", "robot"):
        got = fleet_probed[(page, width)]
        t, lay, tok = got["timing"], got["layout"], got["tokens"]
        print(f"{page} at {width} px: {t}")
        assert t["load_ms"] < 2000 and t["layout_ms"] < 2000, (page, width, t)
        assert not got["errors"], (page, width, got["errors"])
        assert tok["cells"] > (3000 if page == "fleet" else 10), (page, tok["cells"])
        assert not tok["broken"], (page, width, tok["broken"][:5])
        assert lay["page"] <= lay["viewport"], (page, width, lay)
        assert not lay["past"], (page, width, lay["past"][:5])
