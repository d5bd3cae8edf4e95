"""Plots and figures a reader reads: the report's residual and targets plots, the audit's
change labels, numbers and angle units on the report, audit, compare and validate pages.

Each test reads the SVG or HTML the way a reader's eye would: where the marks are, what
the axes and legends say, whether labels cover each other (boxes from x, y, font size and
text length, as :func:`pipeline.report.svg.text_box` estimates them).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support.demo_run import make_demo_run

from pipeline.report import plots
from pipeline.report.data import load_run
from pipeline.report.html_sections import residual_section, targets_section

Box = tuple[float, float, float, float]


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_demo_run(tmp_path_factory.mktemp("run") / "run", seed=3)


# ------------------------------------------------------------------ SVG reading


def _axes_box(svg: str) -> Box:
    """The axes' data area: the axis line ``M L T V B H R`` of the (first) panel."""
    m = re.search(r'd="M([-\d.]+) ([-\d.]+)V([-\d.]+)H([-\d.]+)" stroke="#57606a"', svg)
    assert m, "no axes"
    left, top, bottom, right = map(float, m.groups())
    return left, top, right, bottom


def _legend_box(svg: str) -> Box:
    m = re.search(
        r'<rect x="([-\d.]+)" y="([-\d.]+)" width="([\d.]+)" height="([\d.]+)" fill="white"', svg
    )
    assert m, "no legend"
    x, y, w, h = map(float, m.groups())
    return x, y, x + w, y + h


def _meets(a: Box, b: Box) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _inside(x: float, y: float, box: Box) -> bool:
    return box[0] <= x <= box[2] and box[1] <= y <= box[3]


def _marks(svg: str, colour: str) -> list[str]:
    """The elements drawn in ``colour`` (paths stroked, rects filled), in drawing order."""
    return [
        e
        for e in re.findall(r"<(?:path|rect)\b[^>]*/>", svg)
        if f'stroke="{colour}"' in e or f'fill="{colour}"' in e
    ]


def _xs(element: str) -> list[float]:
    """x pixel coordinates of an element: a rect's centre, a path's absolute points."""
    if element.startswith("<rect"):
        x = float(re.search(r'x="([-\d.]+)"', element)[1])  # type: ignore[index]
        w = float(re.search(r'width="([-\d.]+)"', element)[1])  # type: ignore[index]
        return [x + w / 2]
    d = re.search(r'd="([^"]*)"', element)[1]  # type: ignore[index]
    return [float(x) for x in re.findall(r"[ML]([-\d.]+) [-\d.]+", d)]


def _off_legend(svg: str, colour: str) -> list[float]:
    """x of the marks of ``colour`` outside the legend's box."""
    lx0, ly0, lx1, ly1 = _legend_box(svg)
    out = []
    for e in _marks(svg, colour):
        ys = [float(y) for y in re.findall(r'(?:[ML][-\d.]+ |y=")([-\d.]+)', e)]
        if ys and all(ly0 <= y <= ly1 for y in ys) and all(lx0 <= x <= lx1 for x in _xs(e)):
            continue  # the legend's own swatch
        out += _xs(e)
    return out


# ------------------------------------------------------------ residual plot (a)


def test_the_residual_plot_tells_the_fitted_models_apart(demo_run: Path) -> None:
    """The nominal robot misses by 0.2-1.2 mm, two models by 0.02 and 0.05 mm: on the old
    histogram both models sat in its first bins (19 px apart), under a legend far above the
    axes. Their curves are now 64 px apart and the legend sits beside the axes."""
    data = load_run(demo_run)
    rng = np.random.default_rng(1)
    tid = np.repeat([0, 1, 2], 6)

    def group(norm_mm: np.ndarray) -> pd.DataFrame:
        return pd.DataFrame({"target_id": tid, "norm": norm_mm / 1e3})

    data.derived["residual_groups"] = {
        "nominal": group(rng.uniform(0.2, 1.2, 18)),
        "full": group(rng.uniform(0.015, 0.025, 18)),
        "elastic": group(rng.uniform(0.04, 0.06, 18)),
    }
    svg = residual_section(data)["hist_svg"]
    full = float(np.median(_off_legend(svg, plots.COLORS[0])))
    elastic = float(np.median(_off_legend(svg, plots.COLORS[1])))
    nominal = float(np.median(_off_legend(svg, plots.BEFORE)))
    assert elastic - full > 40, (full, elastic)  # a reader sees two curves
    assert nominal - elastic > 40, (elastic, nominal)
    axes, legend = _axes_box(svg), _legend_box(svg)
    assert not _meets(axes, legend), "the legend covers the data"
    beside = legend[1] < axes[3] and legend[3] > axes[1] and legend[0] >= axes[2]
    below = legend[1] >= axes[3] and legend[1] - axes[3] < 60
    assert beside or below, (axes, legend)
    assert "mm" in svg and "log" in svg


# -------------------------------------------------------------- targets plot (b)


def test_the_targets_plot_is_in_mm_and_its_marks_are_seen(demo_run: Path) -> None:
    """The plot was in metres beside a table in mm, its legend showed a line for crosses and
    the pins' 5 px dots hid under the crosses."""
    sec = targets_section(load_run(demo_run))
    svg = sec["svg"]
    assert any(h.startswith("x (mm)") for h in sec["headers"])
    assert ">x (mm)<" in svg and ">y (mm)<" in svg and "(m)<" not in svg
    axes = _axes_box(svg)
    x_ticks = [
        float(v)
        for y, v in re.findall(
            r'<text x="[-\d.]+" y="([-\d.]+)" text-anchor="middle">([-\d.]+)<', svg
        )
        if float(y) > axes[3]
    ]
    table_x = [float(r[sec["headers"].index("x (mm)")]) for r in sec["rows"]]
    assert x_ticks and min(x_ticks) < min(table_x) and max(table_x) < max(x_ticks), (
        x_ticks,
        table_x,
    )
    target, pin = plots.COLORS[0], plots.COLORS[1]
    legend = _legend_box(svg)
    assert not _meets(axes, legend), "the legend covers the data"
    swatches = {
        c: [e for e in _marks(svg, c) if _inside(*_first_point(e), legend)] for c in (target, pin)
    }
    t_key, p_key = swatches[target][0], swatches[pin][0]
    cross = r"M[-\d.]+ [-\d.]+l([\d.]+) \1M[-\d.]+ [-\d.]+l\1 -\1"
    assert re.search(cross, t_key), f"the targets' swatch is not a cross: {t_key}"
    drawn = [e for e in _marks(svg, target) + _marks(svg, pin) if e not in (t_key, p_key)]
    t_marks = [e for e in drawn if f'stroke="{target}"' in e]
    p_marks = [e for e in drawn if f'stroke="{pin}"' in e]
    assert t_marks and p_marks
    assert re.search(cross, t_marks[0])
    size = _mark_size(p_marks[0])
    assert size >= 10, f"pin marks {size} px across"
    assert _mark_size(p_key) >= 10 and _kind(p_key) == _kind(p_marks[0])
    order = svg.index(t_marks[0]), svg.index(p_marks[0])
    assert order[1] > order[0], "the pins are drawn under the targets' crosses"


def _first_point(element: str) -> tuple[float, float]:
    m = re.search(r'd="M([-\d.]+) ([-\d.]+)', element) or re.search(
        r'x="([-\d.]+)" y="([-\d.]+)"', element
    )
    assert m
    return float(m[1]), float(m[2])


def _kind(element: str) -> str:
    if re.search(r"a[\d.]+ [\d.]+ 0 1 0", element):
        return "ring"
    if "stroke-linecap" in element:
        return "dot"
    return "other"


def _mark_size(element: str) -> float:
    """Diameter (px) of a ring (its arc radius) or of a round dot (its stroke width)."""
    m = re.search(r"a([\d.]+) [\d.]+ 0 1 0", element)
    if m:
        return 2 * float(m[1])
    return float(re.search(r'stroke-width="([\d.]+)"', element)[1])  # type: ignore[index]


# ----------------------------------------------------------- audit labels (c)


def _audit_timeline() -> tuple[pd.DataFrame, pd.DataFrame]:
    """One robot's five recordings with three changes read: joint 3's zero, the camera
    remounted (three columns), the base moved (six columns), as ``vtcal audit`` tables them."""
    n = 5
    recs = pd.DataFrame(
        {
            "recording": [f"A-r0{i}" for i in range(n)],
            "stamp_ns": [int(1.79e18 + i * 30 * 86400e9) for i in range(n)],
            "drift_mm": [np.nan, 0.004, 0.039, 0.024, 0.9],
            "drift_raw_mm": [np.nan, 0.012, 0.045, 0.03, 0.91],
            "validated_mm": [np.nan, 0.011, 0.05, 0.03, 0.95],
            "fresh_mm": [0.008, 0.009, 0.008, 0.01, 0.009],
            "tolerance_mm": [0.1] * n,
        }
    )
    d = np.radians
    base = ["base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz"]
    changes = pd.DataFrame(
        [
            {"to_recording": "A-r01", "changed": False, "kind": "none", "cause": "",
             "columns": [], "size": [], "size_std": []},
            {"to_recording": "A-r02", "changed": True, "kind": "arm",
             "cause": "joint_3 zero offset", "columns": ["joint_3.dq0"], "size": [d(0.05)],
             "size_std": [d(0.004)]},
            {"to_recording": "A-r03", "changed": True, "kind": "camera",
             "cause": "camera / pin remounted", "columns": ["pin.x", "pin.y", "pin.z"],
             "size": [1e-4, -2e-5, 3e-5], "size_std": [5e-6] * 3},
            {"to_recording": "A-r04", "changed": True, "kind": "base",
             "cause": "base moved (the targets seen to move)", "columns": base,
             "size": [1e-3, 2e-5, -1e-5, d(0.001), d(-0.002), d(0.01)],
             "size_std": [1e-5] * 3 + [d(5e-4)] * 3},
        ]
    )  # fmt: skip
    return recs, changes


def _text_box(x: float, y: float, s: str, size: float) -> Box:
    """A start-anchored text's box: 0.6 font sizes per character across, from one font size
    above the baseline to a fifth below (the estimate the placer uses)."""
    return x, y - size, x + 0.6 * size * len(s), y + 0.2 * size


def test_the_audit_change_labels_do_not_cover_each_other() -> None:
    """Ten labels (three changes read, one to six columns each) were set at two heights
    above their points: the camera's and the base's covered each other."""
    from pipeline.audit.page import timeline_svg

    svg = timeline_svg(*_audit_timeline())
    width = float(re.search(r'<svg[^>]* width="([\d.]+)"', svg)[1])  # type: ignore[index]
    texts = re.findall(r'<text x="([-\d.]+)" y="([-\d.]+)" font-size="8">([^<]*)</text>', svg)
    assert len(texts) == 10, texts  # one per column read
    boxes = [_text_box(float(x), float(y), s, 8) for x, y, s in texts]
    for i, a in enumerate(boxes):
        assert 0 <= a[0] and a[2] <= width, f"{texts[i][2]!r} runs off the figure"
        for j in range(i):
            assert not _meets(a, boxes[j]), f"{texts[i][2]!r} over {texts[j][2]!r}"


def test_labels_at_one_point_are_stacked_apart() -> None:
    """Twelve labels on one point (the worst crowd): every one placed, none over another,
    those moved off the point flagged for a leader line."""
    from pipeline.report.svg import place_labels, text_box

    assert text_box(10.0, 20.0, "abc", 8) == _text_box(10.0, 20.0, "abc", 8)
    texts = [f"label {i}: dq0 deg" for i in range(12)]
    got = place_labels([300.0] * 12, [200.0] * 12, texts, 8, (0.0, 0.0, 720.0, 400.0))
    boxes = [text_box(x, y, s, 8) for (x, y, _), s in zip(got, texts, strict=True)]
    for i, a in enumerate(boxes):
        for b in boxes[:i]:
            assert not _meets(a, b)
    assert sum(lead for _, _, lead in got) >= 8


# ------------------------------------------------------------ numbers (d)


def test_numbers_are_written_for_people() -> None:
    from pipeline.io.numfmt import fmt, sci, short

    assert fmt(40210926531.0, 1) == "4.02e10"
    assert fmt(40210926531.0, 4) == "4.02e10"
    assert fmt(0.0586, 4) == "0.0586" and fmt(12.5, 1) == "12.5"
    assert fmt(1.234e-5) == "1.23e-5" and fmt(-2e7) == "-2e7"
    assert fmt(None) == fmt(float("nan")) == "–" and fmt(True) == "yes" and fmt(12) == "12"
    assert fmt(np.float64(3.14159), 2) == "3.14" and fmt(np.int64(7)) == "7"
    assert short(0.1 + 0.2) == "0.3" and short(1e-5) == "1e-5" and short(0.05) == "0.05"
    assert sci(123456.0) == "1.23e5"


#: a float as Python prints it raw: 40210926531.0, 0.30000000000000004, 4.021e+10, 1e-05
RAW_FLOAT = re.compile(r"\b\d{7,}\.\d+\b|\b\d+\.\d{9,}\b|\d[eE]\+|\d[eE]-0\d")


def _visible_text(page: str) -> str:
    """The page as read: no style block, no SVG path data, no raw JSON dump."""
    page = re.sub(r"<style>.*?</style>", "", page, flags=re.S)
    page = re.sub(r"<details>.*?</details>", "", page, flags=re.S)
    page = re.sub(r"<[^>]*>", " ", page)
    return page


def _audit_result(chi2: float):  # type: ignore[no-untyped-def]
    from pipeline.audit.audit import AuditResult

    recs, changes = _audit_timeline()
    recs = recs.assign(
        robot_id="A", model="lrmate200id", n_touchups=24, passed=True, index=range(len(recs))
    )
    changes = changes.assign(
        comparison="history", robot_id="A", from_robot_id="A",
        from_recording=[f"A-r0{i}" for i in range(len(changes))],
        chi2=[3.1, 210.5, 1830.0, chi2], dof=12, p_value=[0.99, 1e-30, 0.0, 0.0],
        text="read",
    )  # fmt: skip
    models = pd.DataFrame(
        {"recording": ["A-r00", "A-r00"], "model": ["offsets", "full"],
         "heldout_mm": [0.0123, 0.0081], "rank": [2, 1]}
    )  # fmt: skip
    ranking = pd.DataFrame(
        {"model": ["full", "offsets"], "median_rank": [1.0, 2.0],
         "rms_heldout_mm": [0.0081, 0.0123], "n": [1, 1]}
    )  # fmt: skip
    return AuditResult(recs, changes, models, ranking)


def test_the_audit_page_writes_a_huge_chi_square_for_people() -> None:
    """A different robot's chi-square printed as 40210926531.0."""
    from pipeline.audit.page import render_page, render_robot_page

    res = _audit_result(40210926531.0)
    text = _visible_text(render_robot_page(res, "A"))  # the robot's page has its changes
    assert "4.02e10 / 12" in text
    assert not RAW_FLOAT.search(text), RAW_FLOAT.search(text)
    text = _visible_text(render_page(res))  # and the fleet page its drifts
    assert "0.9000" in text and not RAW_FLOAT.search(text), RAW_FLOAT.search(text)


def test_the_report_writes_no_raw_float(demo_run: Path, tmp_path: Path) -> None:
    import shutil

    from pipeline.report.html import build_report

    run = tmp_path / "run"
    shutil.copytree(demo_run, run)
    idf = json.loads((run / "identify.json").read_text())
    idf["cond"] = 40210926531.0  # a nearly singular identification
    (run / "identify.json").write_text(json.dumps(idf))
    text = _visible_text(build_report(run).read_text())
    assert "4.02e10" in text
    assert not RAW_FLOAT.search(text), RAW_FLOAT.search(text)


def test_the_validate_page_writes_no_raw_float(lrmate_run: Path, tmp_path: Path) -> None:
    from pipeline.cli import main

    out = tmp_path / "val"
    table = tmp_path / "other.csv"  # the same touch-ups in another order: not the fitted file
    rows = (lrmate_run.parent / "table.csv").read_text().splitlines()
    table.write_text("\n".join([rows[0], *rows[:0:-1]]) + "\n")
    try:
        main(["validate", str(lrmate_run / "calibrated.urdf"), str(table),
              "--urdf", str(lrmate_run.parent / "nominal.urdf"), "--out", str(out),
              "--tolerance-mm", "0.00001"])  # fmt: skip
    except SystemExit as exc:
        assert exc.code == 3, exc.code  # nothing is that consistent: FAIL
    text = _visible_text((out / "validate.html").read_text())
    assert "tolerance of 1e-5 mm" in text
    assert not RAW_FLOAT.search(text), RAW_FLOAT.search(text)


# ---------------------------------------------------- compare's units (d, e)


def _compare_result():  # type: ignore[no-untyped-def]
    from pipeline.accuracy.compare import CompareResult

    runs = pd.DataFrame(
        {"run": ["a", "b"], "robot": "lrmate", "model": "full", "shipped": True,
         "heldout_rms_mm": [0.0586, 0.0612], "loto_rms_mm": [0.071, np.nan],
         "train_rms_mm": [0.041, 0.043], "predicted_rms_mm": [0.05, 0.05],
         "cond": [412.5, 40210926531.0], "n_touchups": 48, "n_used": 48, "n_rejected": 0,
         "n_split_targets": 0}
    )  # fmt: skip
    table = pd.DataFrame(
        {"run": ["a", "b", "a", "b"], "robot": "lrmate", "model": "full",
         "parameter": ["joint_4.dq0", "joint_4.dq0", "joint_3.dx", "joint_3.dx"],
         "kind": "kinematic", "unit": ["rad", "rad", "m", "m"],
         "value": [1e-4, 2.1e-3, 1e-5, 4.1e-4], "std": [1e-4, 1e-4, 2e-5, 2e-5],
         "identifiable": True, "delta_sigma": [np.nan, 14.1, np.nan, 14.1],
         "moved": [False, True, False, True]}
    )  # fmt: skip
    summary = {"verdict": "1 run/model pair(s) with parameters that moved", "k_sigma": 3,
               "flags": []}  # fmt: skip
    return CompareResult(table, runs, table[table["moved"]], summary)


def test_compare_shows_angles_in_degrees_as_the_report() -> None:
    """The report shows angles in deg, compare showed mrad: one unit on every page."""
    from pipeline.accuracy.compare import render_html

    page = render_html(_compare_result())
    text = _visible_text(page)
    assert "mrad" not in text and "angles in deg" in text
    row = page[page.index("joint_4.dq0") :].split("</tr>", 1)[0]
    assert ">deg<" in row
    assert f"{np.degrees(2.1e-3):.4f}" in row  # 0.1203 deg, not 2.1000 mrad
    assert "4.02e10" in text
    assert not RAW_FLOAT.search(text), RAW_FLOAT.search(text)
