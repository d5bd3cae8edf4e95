"""report.html: content from a synthetic run folder, and a headless-Chromium check that it
opens offline (no request leaves the file, no console error), with a screenshot.

Chromium is driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``:
NUL-separated JSON on file descriptors 3 and 4), so no port is opened and every
network request the page makes is seen as a ``Network.requestWillBeSent`` event.
"""

from __future__ import annotations

import base64
import json
import os
import re
import select
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.report.data import load_run, nominal_fit
from pipeline.report.demo import make_demo_run
from pipeline.report.html import build_report

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--remote-debugging-pipe",
]


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_demo_run(tmp_path_factory.mktemp("run") / "run", seed=3)


@pytest.fixture(scope="module")
def report(demo_run: Path) -> Path:
    return build_report(demo_run)


# ----------------------------------------------------------------- DevTools pipe


class Cdp:
    """Minimal DevTools-protocol client over Chromium's debugging pipe."""

    def __init__(self, user_data_dir: Path) -> None:
        assert CHROMIUM is not None
        to_r, self._to_w = os.pipe()  # we write, chromium reads on fd 3
        self._from_r, from_w = os.pipe()  # chromium writes on fd 4
        cmd = " ".join([CHROMIUM, *FLAGS, f"--user-data-dir={user_data_dir}", "about:blank"])
        self.proc = subprocess.Popen(
            ["bash", "-c", f"exec {cmd} 3<&{to_r} 4>&{from_w}"],
            pass_fds=(to_r, from_w),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        os.close(to_r)
        os.close(from_w)
        self._buf = b""
        self._id = 0
        self.events: list[dict[str, Any]] = []

    def _read_message(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no DevTools message from chromium")
            ready, _, _ = select.select([self._from_r], [], [], left)
            if ready:
                chunk = os.read(self._from_r, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed the DevTools pipe")
                self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        msg: dict[str, Any] = json.loads(raw)
        return msg

    def call(
        self, method: str, session: str | None = None, timeout: float = 20.0, **params: Any
    ) -> Any:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self._to_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            m = self._read_message(deadline)
            if m.get("id") == self._id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def wait_event(self, name: str, timeout: float = 20.0) -> dict[str, Any]:
        for e in self.events:
            if e.get("method") == name:
                return e
        deadline = time.monotonic() + timeout
        while True:
            m = self._read_message(deadline)
            self.events.append(m)
            if m.get("method") == name:
                return m

    def drain(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        try:
            while True:
                self.events.append(self._read_message(deadline))
        except TimeoutError:
            pass

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=5.0)
        except Exception:  # noqa: BLE001 - it may already be gone
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._to_w)
        os.close(self._from_r)


def open_in_chromium(html: Path, tmp: Path, screenshot: Path | None = None) -> dict[str, Any]:
    """Load a file in headless Chromium; return requests, console errors and exceptions."""
    cdp = Cdp(tmp / "profile")
    try:
        target = cdp.call("Target.createTarget", url="about:blank")["targetId"]
        sid = cdp.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Network", "Runtime", "Log", "Page"):
            cdp.call(f"{domain}.enable", session=sid)
        cdp.call(
            "Emulation.setDeviceMetricsOverride",
            session=sid,
            width=1280,
            height=2000,
            deviceScaleFactor=1,
            mobile=False,
        )
        cdp.call("Page.navigate", session=sid, url=html.resolve().as_uri())
        cdp.wait_event("Page.loadEventFired")
        cdp.drain(0.3)
        title = cdp.call("Runtime.evaluate", session=sid, expression="document.title")
        n_svg = cdp.call(
            "Runtime.evaluate", session=sid, expression="document.querySelectorAll('svg').length"
        )
        if screenshot is not None:
            shot = cdp.call("Page.captureScreenshot", session=sid, format="png")
            screenshot.write_bytes(base64.b64decode(shot["data"]))
    finally:
        cdp.close()
    ev = cdp.events
    requests = [
        e["params"]["request"]["url"] for e in ev if e.get("method") == "Network.requestWillBeSent"
    ]
    errors = [
        e["params"]["entry"]["text"]
        for e in ev
        if e.get("method") == "Log.entryAdded" and e["params"]["entry"]["level"] == "error"
    ]
    errors += [
        json.dumps(e["params"]["args"])[:300]
        for e in ev
        if e.get("method") == "Runtime.consoleAPICalled"
        and e["params"]["type"] in ("error", "assert")
    ]
    errors += [
        e["params"]["exceptionDetails"].get("text", "exception")
        for e in ev
        if e.get("method") == "Runtime.exceptionThrown"
    ]
    return {
        "requests": requests,
        "leaving": [u for u in requests if not u.startswith(("file:", "data:", "about:"))],
        "errors": errors,
        "title": title["result"].get("value"),
        "n_svg": n_svg["result"].get("value"),
    }


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
