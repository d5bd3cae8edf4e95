"""Compare calibration runs: held-out error, parameters, and drift between runs of a robot.

``compare_runs(run_dirs)`` reads what each run folder holds (``identify.json``,
``parameters.parquet``, and when present ``crossval`` figures inside
``identify.json``, ``inliers.parquet``, ``recording.json``) and lays every run
and every error model it fitted side by side in one long table
(``schemas/compare.json``): one row per (run, model, parameter) carrying the
run's figures (held-out RMS, training RMS, condition number, touch-ups used
and rejected, targets split after a knock) and the parameter's value and
standard error.

**Drift.** Runs of the same robot (same nominal URDF, compared by content hash,
and the same error model) are compared with the first such run in the order
given (the baseline). For every kinematic parameter identified in both::

    delta = x_run - x_base,   sigma = sqrt(std_run^2 + std_base^2)
    moved  <=>  |delta| > k sigma   (k = 3 by default)

``std`` is the identification's standard error (random error only). A moved
parameter means the robot changed between the runs by more than the two
calibrations can explain (a crash, a re-mastered axis, wear) -- the audit a
maintenance engineer wants. The virtual pin is reported but never flagged (a
re-mounted camera moves it legitimately).
"""

from __future__ import annotations

import hashlib
import html
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.io.numfmt import fmt, short
from pipeline.io.run_folder import RUN_FILES

#: columns of the compare table, in order (see ``schemas/compare.json``)
COLUMNS = [
    "run",
    "run_path",
    "robot",
    "nominal_hash",
    "model",
    "shipped",
    "heldout_rms_mm",
    "loto_rms_mm",
    "heldout_z_vs_shipped",
    "train_rms_mm",
    "predicted_rms_mm",
    "cond",
    "n_touchups",
    "n_used",
    "n_rejected",
    "n_split_targets",
    "parameter",
    "kind",
    "unit",
    "value",
    "std",
    "identifiable",
    "baseline_run",
    "delta",
    "delta_sigma",
    "moved",
]


@dataclass
class CompareResult:
    """Everything ``vtcal compare`` shows.

    Attributes
    ----------
    table : long table, one row per (run, model, parameter) (``schemas/compare.json``)
    runs : one row per (run, model): the run-level figures
    moved : the rows of ``table`` whose parameter moved beyond ``k`` sigma
    summary : JSON-able: runs, robots, and one sentence per flagged (run, model)
    """

    table: pd.DataFrame
    runs: pd.DataFrame
    moved: pd.DataFrame
    summary: dict[str, Any] = field(default_factory=dict)


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f


def _robot_name(urdf: str) -> str:
    m = re.search(r"<robot[^>]*\bname\s*=\s*[\"']([^\"']*)[\"']", urdf)
    return m.group(1) if m else ""


def _read_run(run: Path) -> dict[str, Any]:
    """The pieces of one run folder ``compare_runs`` needs."""
    if not run.is_dir():
        raise BadInput(f"{run}: not a run folder (no such directory)")
    ij = run / RUN_FILES["identify"]
    pp = run / RUN_FILES["parameters"]
    if not ij.exists() or not pp.exists():
        raise BadInput(
            f"{run}: not an identified run folder (needs {ij.name} and {pp.name}; "
            "run `vtcal run` or `vtcal identify` first)"
        )
    try:
        summary = json.loads(ij.read_text())
    except json.JSONDecodeError as exc:
        raise BadInput(f"{ij}: not valid JSON ({exc.msg} at line {exc.lineno})") from exc
    from pipeline.io.artefacts import read_artefact

    params = read_artefact(pp, "parameters")
    urdf = ""
    rec = run / RUN_FILES["recording"]
    if rec.exists():
        try:
            urdf = str(json.loads(rec.read_text()).get("urdf", ""))
        except json.JSONDecodeError as exc:
            raise BadInput(f"{rec}: not valid JSON ({exc.msg})") from exc
    if not urdf:
        cal = run / RUN_FILES["calibrated_urdf"]
        urdf = cal.read_text() if cal.exists() else ""
        # a calibrated URDF differs from the nominal one: hash its joint names only
        nominal_key = " ".join(re.findall(r"<joint[^>]*name=\"([^\"]+)\"", urdf))
    else:
        nominal_key = urdf
    inliers = None
    if (run / RUN_FILES["inliers"]).exists():
        inliers = read_artefact(run / RUN_FILES["inliers"], "inliers")
    return {
        "summary": summary,
        "params": params,
        "robot": _robot_name(urdf),
        "nominal_hash": hashlib.sha256(nominal_key.encode()).hexdigest()[:16],
        "inliers": inliers,
    }


def compare_runs(run_dirs: list[Path], *, k_sigma: float = 3.0) -> CompareResult:
    """Compare run folders: figures, parameters with standard errors, and drift.

    Parameters
    ----------
    run_dirs : run folders (``vtcal run`` or ``vtcal identify`` outputs), in the
        order to compare them (the first run of each robot and model is its baseline)
    k_sigma : a parameter moved when ``|delta| > k_sigma * sqrt(std1^2 + std2^2)``

    Returns
    -------
    CompareResult

    Raises
    ------
    BadInput
        A folder that is not an identified run (one line naming it).
    """
    if not run_dirs:
        raise BadInput("vtcal compare: give at least one run folder")
    runs = [Path(r) for r in run_dirs]
    names = _unique_names(runs)
    rows: list[dict[str, Any]] = []
    run_rows: list[dict[str, Any]] = []
    for name, path in zip(names, runs, strict=True):
        _run_rows(name, path, run_rows, rows)
    table = pd.DataFrame(rows, columns=COLUMNS)
    _drift(table, k_sigma)
    moved = table[table["moved"]].reset_index(drop=True)
    flags, others = _flags(moved, k_sigma)
    runs_df = pd.DataFrame(run_rows)
    compared = table[
        table["shipped"].astype(bool) & np.isfinite(table["delta_sigma"].astype(float))
    ]
    summary = {
        "runs": names,
        "k_sigma": k_sigma,
        "robots": sorted(set(table["robot"])) if len(table) else [],
        "flags": flags,
        "not_shipped_moved": others,
        "n_compared": int(len(compared)),
        "verdict": _verdict(table, flags, len(runs), len(compared)),
    }
    return CompareResult(table=table, runs=runs_df, moved=moved, summary=summary)


def _run_rows(
    name: str, path: Path, run_rows: list[dict[str, Any]], rows: list[dict[str, Any]]
) -> None:
    """Append run folder ``path``'s figures per model to ``run_rows`` and its parameters to ``rows``."""
    info = _read_run(path)
    s = info["summary"]
    cv = s.get("crossval") or {}
    cvm = cv.get("models") or {}
    shipped = str(s.get("best_model", s.get("model", "")))
    inl = info["inliers"]
    n_touchups = int(len(inl)) if inl is not None else int(s.get("n_rows", 0))
    n_rejected = int((~inl["inlier"].astype(bool)).sum()) if inl is not None else -1
    n_split = (
        int(inl.loc[inl["target_id"] != inl["source_target_id"], "target_id"].nunique())
        if inl is not None
        else 0
    )
    models = s.get("models") or {shipped: s}
    par = info["params"]
    for model, ms in models.items():
        figures = {
            "run": name,
            "run_path": str(path),
            "robot": info["robot"],
            "nominal_hash": info["nominal_hash"],
            "model": str(model),
            "shipped": str(model) == shipped,
            "heldout_rms_mm": _num((cvm.get(model) or {}).get("kfold_rms_mm")),
            "loto_rms_mm": _num((cvm.get(model) or {}).get("loto_rms_mm")),
            "heldout_z_vs_shipped": _num(((cv.get("paired") or {}).get(model) or {}).get("z")),
            "train_rms_mm": _num(ms.get("rms_mm")),
            "predicted_rms_mm": _num(
                ms.get("predicted_absolute_rms_mm", ms.get("predicted_rms_mm"))
            ),
            "cond": _num(ms.get("cond")),
            "n_touchups": n_touchups,
            "n_used": int(ms.get("n_used", -1)),
            "n_rejected": n_rejected,
            "n_split_targets": n_split,
        }
        run_rows.append(figures)
        pm = par[par["model"] == model]
        for r in pm.itertuples():
            rows.append(
                {
                    **figures,
                    "parameter": str(r.name),
                    "kind": str(r.kind),
                    "unit": str(r.unit),
                    "value": float(r.value),
                    "std": _num(r.std),
                    "identifiable": bool(r.identifiable),
                    "baseline_run": "",
                    "delta": math.nan,
                    "delta_sigma": math.nan,
                    "moved": False,
                }
            )


def _flags(moved: pd.DataFrame, k_sigma: float) -> tuple[list[str], list[str]]:
    """(flags, others): one line per shipped run/model with moved parameters; the rest listed."""
    flags = []
    others: list[str] = []  # models a run did not ship: listed, never the verdict
    for (run, model), g in moved.groupby(["run", "model"], sort=False):
        if not bool(g["shipped"].iloc[0]):
            others.append(f"{run} [{model}, not shipped]: {len(g)} parameter(s)")
            continue
        items = ", ".join(
            f"{p} ({_fmt_delta(_num(d), str(u))}, {_num(ds):.1f} sigma)"
            for p, d, u, ds in g[["parameter", "delta", "unit", "delta_sigma"]].itertuples(
                index=False
            )
        )
        flags.append(
            f"{run} [{model}] against {g['baseline_run'].iloc[0]}: {len(g)} parameter(s) moved "
            f"by more than {k_sigma:g} sigma: {items}"
        )
    return flags, others


def _verdict(table: pd.DataFrame, flags: list[str], n_runs: int, n_compared: int) -> str:
    """The comparison's one-line verdict."""
    if flags:
        return f"{len(flags)} run/model pair(s) with parameters that moved"
    if n_runs < 2 or not n_compared:
        hashes = set(table["nominal_hash"]) if len(table) else set()
        why = (
            "the runs have different nominal robots (URDFs), so each is its own baseline"
            if len(hashes) > 1
            else "no identifiable kinematic parameter of a shipped model has an uncertainty in "
            "two runs"
            if n_runs >= 2
            else "one run"
        )
        return f"nothing compared: {why}"
    return (
        f"no parameter moved beyond its uncertainty between runs of the same robot "
        f"({n_compared} shipped-model parameter(s) compared)"
    )


def _unique_names(runs: list[Path]) -> list[str]:
    names: list[str] = []
    for p in runs:
        base = p.resolve().name or str(p)
        n, i = base, 2
        while n in names:
            n, i = f"{base}#{i}", i + 1
        names.append(n)
    return names


def _fmt_delta(delta: float, unit: str) -> str:
    """A parameter's change in the report's units: mm and deg."""
    if unit == "rad":
        return f"{math.degrees(delta):+.4f} deg"
    if unit == "m":
        return f"{delta * 1e3:+.3f} mm"
    return f"{delta:+.3g} {unit}"


def _drift(table: pd.DataFrame, k_sigma: float) -> None:
    """Fill ``baseline_run, delta, delta_sigma, moved`` in place (module docstring)."""
    if not len(table):
        return
    firsts: dict[tuple[str, str], str] = {}
    for run, h, model in (
        table[["run", "nominal_hash", "model"]].drop_duplicates().itertuples(index=False)
    ):
        firsts.setdefault((h, model), run)
    lookup: dict[tuple[str, str, str], tuple[float, float, bool]] = {}
    for run, model, par, v, sd, ident in table[
        ["run", "model", "parameter", "value", "std", "identifiable"]
    ].itertuples(index=False):
        lookup.setdefault((str(run), str(model), str(par)), (_num(v), _num(sd), bool(ident)))
    for i in range(len(table)):
        run = str(table.at[i, "run"])
        model = str(table.at[i, "model"])
        base = firsts[(str(table.at[i, "nominal_hash"]), model)]
        if base == run:
            continue
        table.at[i, "baseline_run"] = base
        b = lookup.get((base, model, str(table.at[i, "parameter"])))
        if b is None:
            continue
        b_value, b_std, b_ident = b
        delta = _num(table.at[i, "value"]) - b_value
        table.at[i, "delta"] = delta
        sig = math.hypot(_num(table.at[i, "std"]), b_std)
        usable = (
            table.at[i, "kind"] == "kinematic"
            and bool(table.at[i, "identifiable"])
            and b_ident
            and np.isfinite(sig)
            and sig > 0
        )
        if usable:
            table.at[i, "delta_sigma"] = abs(delta) / sig
            table.at[i, "moved"] = bool(abs(delta) > k_sigma * sig)


# ----------------------------------------------------------------------------- HTML


_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
.table-wrap{max-width:100%;overflow-x:auto;margin:0.6em 0 1.6em}
table{border-collapse:collapse;font-size:0.86em}
th,td{border:1px solid #ccc;padding:0.2em 0.5em;text-align:right}
th{background:#f0f0f0} td.l,th.l{text-align:left} .w{white-space:nowrap}
tr.moved td{background:#fde2e2} .ok{color:#176b2c} .bad{color:#a11}
"""


#: what every table says for a model without a held-out figure (e.g. elastic, which the
#: run fits but does not cross-validate unless asked): never ``nan`` here and ``-`` there
NOT_CROSS_VALIDATED = "not cross-validated"


def told_apart_text(z: Any) -> str:
    """'' or "  (not told apart from the shipped model: z = +0.4)", (T1) of
    :mod:`pipeline.accuracy.told_apart`; '' where it was not made or told them apart."""
    from pipeline.accuracy.told_apart import Z_APART

    zf = _num(z)
    if not math.isfinite(zf) or abs(zf) >= Z_APART:
        return ""
    return f"  (not told apart from the shipped model: z = {zf:+.1f})"


def heldout_text(v: Any) -> str:
    """A held-out RMS as the console tables print it: ``0.0586 mm``, else
    :data:`NOT_CROSS_VALIDATED`."""
    if isinstance(v, (int, float, np.floating)) and np.isfinite(v):
        return f"{float(v):.4f} mm"
    return NOT_CROSS_VALIDATED


def _cell(v: Any, unit: str = "") -> str:
    """A table cell: SI lengths in mm and angles in deg (as the report shows them), every
    figure through :mod:`pipeline.io.numfmt`."""
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else ""
    if isinstance(v, (float, np.floating)):
        if not np.isfinite(v):
            return ""
        scale = {"rad": math.degrees(1.0), "m": 1e3}.get(unit)
        if scale is not None:
            return fmt(float(v) * scale, 4)
        return short(float(v), 4)
    return html.escape(str(v))


#: the page's runs table: (column of compare_runs' runs frame, heading)
RUN_HEADS = [
    ("run", "run"),
    ("robot", "robot"),
    ("n_touchups", "touch-ups"),
    ("n_rejected", "rejected"),
    ("n_split_targets", "knocked targets"),
]
#: the page's error-models table (a row per run and model)
MODEL_HEADS = [
    ("run", "run"),
    ("model", "model"),
    ("shipped", "shipped"),
    ("heldout_rms_mm", "held-out RMS mm"),
    ("loto_rms_mm", "leave-one-target-out mm"),
    ("train_rms_mm", "training RMS mm"),
    ("predicted_rms_mm", "predicted RMS mm"),
    ("cond", "condition"),
    ("n_used", "used"),
]


def _words(text: str) -> str:
    """Escaped cell text that wraps only between words: a hyphenated word (``touch-ups``,
    ``cross-validated``, ``1e-05``, a run's folder name) is kept on one line (a browser
    breaks after a hyphen)."""
    return " ".join(f"<span class='w'>{w}</span>" if "-" in w else w for w in text.split(" "))


def _table(rows: pd.DataFrame, heads: list[tuple[str, str]]) -> str:
    """An HTML table of ``rows``' columns ``heads`` (column, heading), in a sideways-scrolling
    wrapper; a missing held-out figure reads :data:`NOT_CROSS_VALIDATED`."""
    out = ["<div class='table-wrap'><table><tr>"]
    out.append("".join(f"<th class='l'>{_words(html.escape(h))}</th>" for _, h in heads))
    out.append("</tr>")
    for r in rows.to_dict("records"):
        cells = [
            NOT_CROSS_VALIDATED if c == "heldout_rms_mm" and not _cell(r[c]) else _cell(r[c])
            for c, _ in heads
        ]
        out.append("<tr>" + "".join(f"<td>{_words(v)}</td>" for v in cells) + "</tr>")
    out.append("</table></div>")
    return "\n".join(out)


def render_html(result: CompareResult) -> str:
    """A self-contained HTML page of a comparison (no scripts, no external resources)."""
    s = result.summary
    out = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta http-equiv='Content-Security-Policy' content=\"default-src 'none'; "
        "style-src 'unsafe-inline'\">",
        "<title>vtcal compare</title><style>",
        _CSS,
        "</style></head><body><h1>vtcal compare</h1>",
    ]
    cls = "ok" if not s.get("flags") else "bad"
    out.append(f"<p class='{cls}'><b>{html.escape(str(s.get('verdict', '')))}</b></p>")
    if s.get("flags"):
        out.append("<ul>" + "".join(f"<li>{html.escape(f)}</li>" for f in s["flags"]) + "</ul>")
    out.append(
        f"<p>A parameter <i>moved</i> when |delta| &gt; {s.get('k_sigma', 3):g} "
        "&times; sqrt(std<sub>1</sub><sup>2</sup> + std<sub>2</sub><sup>2</sup>) against the "
        "first run of the same robot and model (standard errors of identification: random "
        "error only). Lengths in mm, angles in deg. Held-out: k-fold cross-validation RMS.</p>"
    )
    # two tables, not one of 13 columns: each fits a 900 px window with its words whole
    out.append("<h2>Runs</h2>")
    out.append(_table(result.runs.drop_duplicates("run"), RUN_HEADS))
    out.append("<h2>Error models</h2>")
    out.append(_table(result.runs, MODEL_HEADS))
    kin = result.table[result.table["kind"] != "target"]
    for (robot, model), g in kin.groupby(["robot", "model"], sort=False):
        out.append(f"<h2>Parameters: {html.escape(str(robot))} [{html.escape(str(model))}]</h2>")
        runs = list(dict.fromkeys(g["run"]))
        out.append("<div class='table-wrap'><table><tr><th class='l'>parameter</th>")
        out.append("<th class='l'>unit</th>")
        out.append("".join(f"<th>{_words(html.escape(r))} value &plusmn; std</th>" for r in runs))
        out.append("<th>largest |delta|/sigma</th></tr>")
        for p, gp in g.groupby("parameter", sort=False):
            unit = str(gp["unit"].iloc[0])
            moved = bool(gp["moved"].any())
            cells = []
            for r in runs:
                x = gp[gp["run"] == r]
                if not len(x):
                    cells.append("<td></td>")
                    continue
                v, sd = float(x["value"].iloc[0]), float(x["std"].iloc[0])
                held = "" if bool(x["identifiable"].iloc[0]) else " (held)"
                txt = f"{_cell(v, unit)} &plusmn; {_cell(sd, unit)}{held}"
                cells.append(f"<td>{_words(txt)}</td>")
            ds = gp["delta_sigma"].max()
            shown = "deg" if unit == "rad" else ("mm" if unit == "m" else unit)
            name, sigmas = _words(html.escape(str(p))), _words(_cell(ds))
            out.append(
                f"<tr class='{'moved' if moved else ''}'><td class='l'>{name}</td>"
                f"<td class='l'>{html.escape(shown)}</td>{''.join(cells)}<td>{sigmas}</td></tr>"
            )
        out.append("</table></div>")
    out.append("</body></html>\n")
    return "\n".join(out)
