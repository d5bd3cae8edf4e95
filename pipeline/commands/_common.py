"""Options, progress bars and the end-of-run summary shared by the CLI commands."""

from __future__ import annotations

import contextlib
import difflib
from collections.abc import Callable, Iterator
from typing import Any

import click


def _parse_set(
    ctx: click.Context, param: click.Parameter, value: tuple[str, ...]
) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in value:
        key, sep, val = item.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"{item!r}: expected KEY=VALUE")
        out[key.strip()] = val.strip()
    for key in out:
        _check_set_key(key)
    return out


def _check_set_key(key: str) -> None:
    """Refuse a ``--set`` key vtcal does not use, listing the ones it does (a typo is not
    silently ignored)."""
    from pipeline.stages.ingest.types import METADATA_KEYS, OTHER_METADATA_KEYS

    stage, dot, opt = key.partition(".")
    if dot:
        if stage not in stage_option_prefixes() or not opt:
            raise click.BadParameter(
                f"{key!r}: no stage {stage!r}; STAGE.OPTION takes a stage of "
                f"{stage_option_prefixes()}"
            )
        return  # the option name is checked against the stage's own options when it runs
    keys = [*METADATA_KEYS, *OTHER_METADATA_KEYS]
    if key not in keys:
        near = difflib.get_close_matches(key, keys, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise click.BadParameter(
            f"{key!r} is not a touchup metadata key{hint}: the keys are {sorted(keys)}, "
            f"or STAGE.OPTION with a stage of {stage_option_prefixes()}"
        )


def set_option(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``--set KEY=VALUE`` (repeatable): override a key of the ``touchup`` metadata."""
    return click.option(
        "--set",
        "overrides",
        multiple=True,
        callback=_parse_set,
        metavar="KEY=VALUE",
        help="Override a key of the recording's `touchup` metadata "
        "(target_diameter_m, designated_u, polarity, threshold_px, camera_response, ...), or "
        "set a stage option as STAGE.OPTION=VALUE (e.g. identify.target_shape=none, "
        "detect.clip_correction=false; stages: ingest, detect, touchups, outliers, identify, "
        "crossval). Repeatable.",
    )(fn)


def stage_option_prefixes() -> list[str]:
    """The names ``--set STAGE.OPTION=VALUE`` reaches (the catalog's option groups)."""
    from pipeline.run.catalog import option_groups

    return option_groups()


def _option_value(text: str) -> Any:
    """``true``/``false`` -> bool, an int or float literal -> number, else the text."""
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def split_stage_options(
    overrides: dict[str, str],
) -> tuple[dict[str, str], dict[str, dict[str, Any]]]:
    """``--set`` items: (metadata overrides, ``{stage: {option: value}}``)."""
    meta: dict[str, str] = {}
    stages: dict[str, dict[str, Any]] = {}
    for key, val in overrides.items():
        stage, dot, opt = key.partition(".")
        if dot and stage in stage_option_prefixes() and opt:
            stages.setdefault(stage, {})[opt] = _option_value(val)
        else:
            meta[key] = val
    return meta, stages


def distance_option(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``--distance A:B=METRES`` (repeatable): a known distance between two targets."""
    return click.option(
        "--distance",
        multiple=True,
        metavar="A:B=METRES",
        help="Known centre distance between targets A and B (labels in first-touch order). "
        "Makes the length scale identifiable. Repeatable; replaces the metadata's known_distances.",
    )(fn)


@contextlib.contextmanager
def progress_bars(enabled: bool = True) -> Iterator[Callable[[str, int, int | None], None] | None]:
    """A rich progress display; yields the callback the orchestrator calls (or None)."""
    if not enabled:
        yield None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
    )

    bars = Progress(
        TextColumn("[bold]{task.description:<10}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        transient=False,
    )
    tasks: dict[str, Any] = {}

    def update(stage: str, done: int, total: int | None) -> None:
        if not tasks:  # started at the first bar: a command failing before any prints nothing
            bars.start()
        if stage not in tasks:
            if stage == "compile":  # the orchestrator's first-run detector compilation
                bars.console.print("vtcal: first run: compiling the detector once (~10-20 s)")
            tasks[stage] = bars.add_task(stage, total=total)
        bars.update(tasks[stage], completed=done, total=total)

    try:
        yield update
    finally:
        if tasks:
            bars.stop()


def echo_summary(result: Any, tolerance_mm: float | None = None) -> dict[str, Any] | None:
    """Print what each stage did, where its files are and the verdict; return the verdict."""
    click.echo(f"run folder: {result.out_dir}")
    for rec in result.stages:
        took = f"{rec.seconds:6.1f} s" if rec.status == "ran" else "      -"
        click.echo(f"  {rec.stage:<9} {rec.status:<7} {took}  {', '.join(rec.outputs)}")
    s = result.summary
    if s:
        for line in s.get("headline", []):
            click.echo(f"  {line}")
        return echo_verdict(s, tolerance_mm, indent="  ")
    return None


def echo_verdict(
    summary: dict[str, Any], tolerance_mm: float | None, indent: str = ""
) -> dict[str, Any] | None:
    """Print the verdict line (when there is a validated error or a tolerance); return it."""
    from pipeline.accuracy.verdict import verdict

    v = verdict(summary, tolerance_mm)
    for w in v["warnings"] if v is not None else []:  # assumptions, the adequacy test
        click.echo(f"vtcal: warning: {w}", err=True)
    if v is not None and (v["validated_mm"] is not None or tolerance_mm is not None):
        click.echo(f"{indent}{v['line']}")
    return v


class PositiveFloat(click.types.FloatParamType):
    """A finite number > 0 (a tolerance, a length): anything else refused in one line
    before any work (``click.FloatRange(min=0, min_open=True)`` lets ``nan`` through)."""

    name = "float"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float:
        import math

        if isinstance(value, float):
            x = value
        else:
            try:
                x = float(value)
            except (TypeError, ValueError):
                self.fail(f"{value!r} is not a number", param, ctx)
        if not (math.isfinite(x) and x > 0):
            self.fail(f"{value}: must be a positive number", param, ctx)
        return x


#: the type of every ``--tolerance-mm``
POSITIVE = PositiveFloat()


def tolerance_option(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``--tolerance-mm T``: PASS / FAIL of the validated error, exit 3 on FAIL."""
    return click.option(
        "--tolerance-mm",
        type=POSITIVE,
        default=None,
        help="Accuracy the calibration must reach: PASS when the shipped model's validated "
        "(held-out) RMS is at most this and it improved on the nominal robot, else FAIL and "
        "exit 3. Default: the recording's tolerance_mm metadata key, if any.",
    )(fn)


def accept_implausible_option(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``--accept-implausible``: identify despite the guardrails (:mod:`pipeline.guardrails.plausibility`)."""
    return click.option(
        "--accept-implausible",
        is_flag=True,
        help="Identify even where an input contradicts the nominal robot (joint values outside "
        "the URDF's limits, a nominal fit worse than 25 mm, a moving joint outside the chain, "
        "a known distance or target diameter the nominal robot or the images contradict); the "
        "lines are kept in identify.json as 'implausible'.",
    )(fn)


def fail_on_verdict(v: dict[str, Any] | None) -> None:
    """Raise :class:`CalibrationFailed` (exit 3) when a tolerance was given and not met."""
    from pipeline.errors import CalibrationFailed

    if v is not None and v.get("passed") is False:
        raise CalibrationFailed("verdict FAIL: " + v["line"].split(" | FAIL ", 1)[-1].strip("()"))
