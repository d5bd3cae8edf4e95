"""Fuzz: mutated recordings and touch-up tables give success or a clean VtcalError, never more.

Bounded and derandomised (hypothesis, fixed seed, no example database), each
example under a wall-clock alarm so a hang fails the test instead of stalling CI.
The stages run in-process (as the orchestrator calls them) and every table a
stage returns is coerced to its declared schema: a stage writing an artefact
that breaks its own schema is a bug, so ``SchemaError`` from a stage's *output*
counts as a failure here, not as a clean error.

Mutants (>= 500 in all; the counts are printed, run with ``-s`` to see them):

- recordings: byte flips, truncation, dropped / duplicated / swapped chunks,
  zeroed spans and inserted garbage, on a tiny synthetic recording (two-joint
  arm, 64x48 images, uncompressed and zstd chunks) through ingest and touch-up
  extraction, and on a tiny simulated run (LR Mate, 160x128 PNG, 3 targets x 3
  poses) through ingest, touch-ups, outliers and identification;
- touch-up tables: cells set to NaN / inf / huge / text / None, dropped,
  renamed, retyped or extra columns, dropped / duplicated / shuffled rows, then
  identification and its output artefacts; and byte mutations of the CSV file
  read by ``vtcal identify``.
"""

from __future__ import annotations

import contextlib
import signal
import tempfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType
from test_robustness_data import chunk_spans, tiny_recording, touchup_table

from pipeline.errors import VtcalError
from pipeline.io.artefacts import SchemaError, load_schema

PER_EXAMPLE_S = 20.0
N_TINY = 260
N_SIM = 50
N_TABLE = 200
N_CSV = 60
OUTCOMES: Counter[str] = Counter()

FUZZ = settings(
    deadline=None,  # wall time is bounded by the alarm below instead
    derandomize=True,
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


class Hang(Exception):
    pass


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    def fire(signum: int, frame: Any) -> None:
        raise Hang(f"example took longer than {seconds} s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def outcome(kind: str, fn: Any) -> None:
    """Run ``fn``; record success or the clean error class; let anything else fail the test."""
    with time_limit(PER_EXAMPLE_S):
        try:
            fn()
        except SchemaError:
            raise  # a stage's output breaking its own schema is a bug (inputs are read elsewhere)
        except VtcalError as exc:
            OUTCOMES[f"{kind}: {type(exc).__name__}"] += 1
            msg = str(exc)
            assert msg and "\n" not in msg, msg  # one line
            return
    OUTCOMES[f"{kind}: ok"] += 1


class Blob(bytes):
    """Bytes with a short repr (hypothesis prints the test's arguments on failure)."""

    def __repr__(self) -> str:
        return f"<{len(self)} bytes>"


def conform(df: pd.DataFrame, schema: str) -> None:
    load_schema(schema).to_table(df)


# --------------------------------------------------------------------------- mutations

_mutation = st.one_of(
    st.tuples(st.just("flip"), st.floats(0, 1, exclude_max=True), st.integers(1, 255)),
    st.tuples(st.just("truncate"), st.floats(0, 1, exclude_max=True), st.just(0)),
    st.tuples(st.just("drop_chunk"), st.integers(0, 63), st.just(0)),
    st.tuples(st.just("dup_chunk"), st.integers(0, 63), st.just(0)),
    st.tuples(st.just("swap_chunks"), st.integers(0, 63), st.integers(0, 63)),
    st.tuples(st.just("zero"), st.floats(0, 1, exclude_max=True), st.integers(1, 400)),
    st.tuples(st.just("insert"), st.floats(0, 1, exclude_max=True), st.integers(1, 64)),
)


def mutate(data: bytes, muts: list[tuple[str, Any, Any]]) -> bytes:
    b = bytearray(data)
    for kind, a, c in muts:
        n = len(b)
        if n == 0:
            break
        pos = int(a * n) if isinstance(a, float) else 0
        spans = chunk_spans(bytes(b))
        if kind == "flip":
            b[pos] ^= c
        elif kind == "truncate":
            del b[pos:]
        elif kind == "zero":
            b[pos : pos + c] = bytes(len(b[pos : pos + c]))
        elif kind == "insert":
            b[pos:pos] = bytes((pos * 31 + i * 17) % 256 for i in range(c))
        elif spans and kind == "drop_chunk":
            s, e = spans[a % len(spans)]
            del b[s:e]
        elif spans and kind == "dup_chunk":
            s, e = spans[a % len(spans)]
            b[e:e] = b[s:e]
        elif spans and kind == "swap_chunks":
            (s1, e1), (s2, e2) = sorted([spans[a % len(spans)], spans[c % len(spans)]])
            if s1 != s2:
                b = b[:s1] + b[s2:e2] + b[e1:s2] + b[s1:e1] + b[e2:]
    return bytes(b)


def stages(path: Path, deep: bool) -> None:
    """Ingest and touch-up extraction; with ``deep`` also outliers and identification."""
    from pipeline.io.known_distances import parse_distances
    from pipeline.stages.detect.detector import DetectConfig
    from pipeline.stages.identify import stage as identify
    from pipeline.stages.ingest.stage import IngestConfig, ingest_recording
    from pipeline.stages.outliers import stage as outliers
    from pipeline.stages.touchups import stage as touchup

    frames, dets, info = ingest_recording(path, IngestConfig(), DetectConfig())
    conform(frames, "frames")
    conform(dets, "detections")
    tu = touchup.extract_touchups(frames, dets, info, touchup.TouchupConfig())
    conform(tu, "touchups")
    if not deep:
        return
    inl = outliers.flag_outliers(tu, info, outliers.OutlierConfig())
    conform(inl, "inliers")
    cfg = identify.IdentifyConfig(
        model="offsets",
        distances=parse_distances(info.metadata.get("known_distances", "")),
        strict_distances=False,
        n_workspace=20,
    )
    res = identify.identify(inl, info.urdf, info.base_link, info.flange_link, cfg)
    assert isinstance(res, identify.IdentifyResult)
    conform(res.parameters, "parameters")
    conform(res.residuals, "residuals")
    conform(res.targets, "targets")


@pytest.fixture(scope="module")
def work() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="vtcal_fuzz_") as d:
        yield Path(d)


@pytest.fixture(scope="module")
def tiny_bases(work: Path) -> list[Blob]:
    out = []
    for comp in (CompressionType.NONE, CompressionType.ZSTD):
        p = tiny_recording(work / f"base_{comp.name}.mcap", n_img=4, n_js=60, compression=comp,
                           chunk_size=2500)  # fmt: skip
        out.append(Blob(p.read_bytes()))
    return out


TINY_TOML = """
name = "fuzz_tiny"
[robot]
name = "lrmate"
[camera]
width = 160
height = 128
f_px = 300.0
subsamples = 4
[targets]
count = 3
[poses]
per_target = 3
[timing]
joint_rate_hz = 50.0
chunk_size = 65536
"""


@pytest.fixture(scope="module")
def sim_base(work: Path) -> Blob:
    """A tiny simulated recording that calibrates (checked once, unmutated)."""
    from pipeline.sim.scenario import load_scenario
    from pipeline.sim.simulator import simulate

    toml = work / "tiny.toml"
    toml.write_text(TINY_TOML)
    out = work / "sim.mcap"
    simulate(load_scenario(toml), seed=3, out=out)
    stages(out, deep=True)  # the base itself must go all the way
    return Blob(out.read_bytes())


@given(base=st.integers(0, 1), muts=st.lists(_mutation, min_size=1, max_size=3))
@settings(FUZZ, max_examples=N_TINY)
def test_fuzz_tiny_recordings(work, tiny_bases, base, muts):
    p = work / "mut_tiny.mcap"
    p.write_bytes(mutate(tiny_bases[base], muts))
    outcome("tiny recording", lambda: stages(p, deep=False))


@given(muts=st.lists(_mutation, min_size=1, max_size=2))
@settings(FUZZ, max_examples=N_SIM)
def test_fuzz_simulated_recording(work, sim_base, muts):
    p = work / "mut_sim.mcap"
    p.write_bytes(mutate(sim_base, muts))
    outcome("simulated recording", lambda: stages(p, deep=True))


# --------------------------------------------------------------------------- tables

_BAD_VALUES = [np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0, -1.0, 1e-300, "abc", None, True, ""]
_table_op = st.one_of(
    st.tuples(st.just("cell"), st.integers(0, 99), st.integers(0, 99), st.sampled_from(_BAD_VALUES)),
    st.tuples(st.just("column"), st.integers(0, 99), st.sampled_from(_BAD_VALUES), st.just(0)),
    st.tuples(st.just("drop_col"), st.integers(0, 99), st.just(0), st.just(0)),
    st.tuples(st.just("rename_col"), st.integers(0, 99), st.sampled_from(["x", "joint_9", "touchup_id"]), st.just(0)),
    st.tuples(st.just("as_str"), st.integers(0, 99), st.just(0), st.just(0)),
    st.tuples(st.just("as_int"), st.integers(0, 99), st.just(0), st.just(0)),
    st.tuples(st.just("keep_rows"), st.integers(0, 30), st.just(0), st.just(0)),
    st.tuples(st.just("dup_row"), st.integers(0, 99), st.just(0), st.just(0)),
    st.tuples(st.just("shuffle"), st.integers(0, 2**31), st.just(0), st.just(0)),
    st.tuples(st.just("extra_col"), st.sampled_from(_BAD_VALUES), st.just(0), st.just(0)),
)  # fmt: skip


def mutate_table(t: pd.DataFrame, ops: list[tuple[Any, ...]]) -> pd.DataFrame:
    t = t.copy()
    for op, a, b, c in ops:
        if t.shape[1] == 0 or len(t) == 0:
            break
        col = t.columns[a % t.shape[1]] if isinstance(a, int) else None
        if op == "cell":
            t[t.columns[b % t.shape[1]]] = t[t.columns[b % t.shape[1]]].astype(object)
            t.iloc[a % len(t), b % t.shape[1]] = c
        elif op == "column":
            t[col] = [b] * len(t)
        elif op == "drop_col":
            t = t.drop(columns=[col])
        elif op == "rename_col":
            t = t.rename(columns={col: b})
        elif op == "as_str":
            t[col] = t[col].astype(str)
        elif op == "as_int":
            with contextlib.suppress(ValueError, TypeError, OverflowError):
                t[col] = pd.to_numeric(t[col], errors="coerce").fillna(0).astype(np.int64)
        elif op == "keep_rows":
            t = t.head(a)
        elif op == "dup_row":
            t = pd.concat([t, t.iloc[[a % len(t)]]], ignore_index=True)
        elif op == "shuffle":
            t = t.sample(frac=1.0, random_state=a % (2**31)).reset_index(drop=True)
        elif op == "extra_col":
            t["extra"] = [a] * len(t)
    return t


class Case(tuple):  # type: ignore[type-arg]
    """``(table, urdf)`` with a short repr."""

    def __repr__(self) -> str:
        return f"<touch-up table {self[0].shape}, URDF>"


@pytest.fixture(scope="module")
def base_table() -> Case:
    return Case(touchup_table(seed=5, per_target=4))


def identify_and_write(df: pd.DataFrame, urdf: str, out: Path) -> None:
    from pipeline.run.runner import write_fits
    from pipeline.stages.identify.stage import IdentifyConfig, identify

    res = identify(df, urdf, "base_link", "flange", IdentifyConfig(model="offsets", n_workspace=20))
    write_fits(res, out)


@given(ops=st.lists(_table_op, min_size=1, max_size=4))
@settings(FUZZ, max_examples=N_TABLE)
def test_fuzz_touchup_tables(work, base_table, ops):
    table, urdf = base_table
    df = mutate_table(table, ops)
    outcome("table", lambda: identify_and_write(df, urdf, work / "table_out"))


@given(muts=st.lists(_mutation, min_size=1, max_size=3), utf16=st.booleans())
@settings(FUZZ, max_examples=N_CSV)
def test_fuzz_touchup_csv_bytes(work, base_table, muts, utf16):
    from pipeline.io.tables import read_table

    table, urdf = base_table
    text = table.to_csv(index=False)
    p = work / "mut.csv"
    p.write_bytes(mutate(text.encode("utf-16" if utf16 else "utf-8"), muts))

    def go() -> None:
        identify_and_write(read_table(p), urdf, work / "csv_out")

    outcome("csv bytes", go)


def test_fuzz_count_report() -> None:
    """Runs last in this file: prints what the fuzz tests above saw."""
    total = sum(OUTCOMES.values())
    if total == 0:
        pytest.skip("run with the fuzz tests")
    lines = [f"fuzz: {total} mutated inputs, 0 uncaught exceptions"]
    lines += [f"  {k}: {v}" for k, v in sorted(OUTCOMES.items())]
    print("\n".join(lines))
    want = N_TINY + N_SIM + N_TABLE + N_CSV
    assert want >= 500
    if total == want:  # the whole file ran: every example was a clean outcome
        assert sum(v for k, v in OUTCOMES.items() if k.endswith(": ok")) > 0
