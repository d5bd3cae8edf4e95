"""Open an HTML file in headless Chromium and report what it did (for the report's tests).

Chromium (Debian package ``chromium``) is driven over the DevTools protocol on a
pipe (``--remote-debugging-pipe``: NUL-separated JSON messages, Chromium reads
file descriptor 3 and writes 4), so no port is opened and every request the
page makes is seen as a ``Network.requestWillBeSent`` event. Console errors,
log entries of level error and uncaught exceptions are collected too, and a
screenshot can be taken.
"""

from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

#: the browser executable, or None when it is not installed
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


#: JavaScript returning (as JSON) what does not fit the page's width: the page's own scroll
#: width against the viewport's, every table / figure / block whose right edge passes the
#: viewport, every table scrolling sideways inside itself, and the pairs of SVG text
#: boxes that overlap within one figure
LAYOUT_PROBE = """(() => {
  const W = document.documentElement.clientWidth;
  const out = {viewport: W, page: document.documentElement.scrollWidth, past: [], scrolls: [],
               overlaps: []};
  const name = el => el.tagName.toLowerCase() + ' "' + (el.textContent || '').trim().slice(0, 50) + '"';
  for (const el of document.querySelectorAll('main > *, section > *, table, svg, pre, img, dl')) {
    const r = el.getBoundingClientRect();
    if (r.width > 0 && r.right > W + 0.5) out.past.push(name(el) + ' right ' + Math.round(r.right));
  }
  for (const el of document.querySelectorAll('table')) {
    if (el.scrollWidth > el.clientWidth + 1) out.scrolls.push(name(el));
  }
  document.querySelectorAll('svg').forEach((svg, k) => {
    const boxes = [...svg.querySelectorAll('text')].map(t => [t, t.getBoundingClientRect()])
      .filter(([t, r]) => r.width > 0 && t.textContent.trim());
    for (let i = 0; i < boxes.length; i++) for (let j = i + 1; j < boxes.length; j++) {
      const a = boxes[i][1], b = boxes[j][1];
      const dx = Math.min(a.right, b.right) - Math.max(a.left, b.left);
      const dy = Math.min(a.bottom, b.bottom) - Math.max(a.top, b.top);
      if (dx > 1 && dy > 1) out.overlaps.push('svg ' + k + ': "' + boxes[i][0].textContent +
                                               '" / "' + boxes[j][0].textContent + '"');
    }
  });
  return JSON.stringify(out);
})()"""


def open_in_chromium(
    html: Path,
    tmp: Path,
    screenshot: Path | None = None,
    *,
    width: int = 1280,
    height: int = 2000,
    full_page: bool = False,
) -> dict[str, Any]:
    """Load a file in headless Chromium (``width`` x ``height`` viewport) and report what happened.

    Parameters
    ----------
    html : the file to open
    tmp : scratch folder (a fresh browser profile is made in it)
    screenshot : where to save a PNG of the viewport (the whole page with ``full_page``),
        optional
    width, height : the viewport, CSS px

    Returns
    -------
    dict with ``requests`` (every URL requested), ``leaving`` (those not ``file:``,
    ``data:`` or ``about:``), ``errors`` (console errors, error log entries,
    exceptions), ``title``, ``n_svg`` (inline SVG elements in the page) and ``layout``
    (:data:`LAYOUT_PROBE`'s findings at this width).
    """
    cdp = Cdp(tmp / "profile")
    try:
        target = cdp.call("Target.createTarget", url="about:blank")["targetId"]
        sid = cdp.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Network", "Runtime", "Log", "Page"):
            cdp.call(f"{domain}.enable", session=sid)
        cdp.call(
            "Emulation.setDeviceMetricsOverride",
            session=sid,
            width=width,
            height=height,
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
        layout = cdp.call("Runtime.evaluate", session=sid, expression=LAYOUT_PROBE)
        if screenshot is not None:
            extra: dict[str, Any] = {}
            if full_page:
                size = cdp.call("Page.getLayoutMetrics", session=sid)["cssContentSize"]
                extra = {
                    "clip": {"x": 0, "y": 0, "width": width, "height": size["height"], "scale": 1},
                    "captureBeyondViewport": True,
                }
            shot = cdp.call("Page.captureScreenshot", session=sid, format="png", **extra)
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
        "layout": json.loads(layout["result"].get("value") or "{}"),
    }
