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

    def new_page(self, domains: tuple[str, ...]) -> str:
        """A blank page attached with ``domains`` enabled; its session id."""
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        sid: str = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in domains:
            self.call(f"{domain}.enable", session=sid)
        return sid

    def window(self, sid: str, width: int, height: int) -> None:
        """The page's viewport: ``width`` x ``height`` CSS px at scale 1, desktop."""
        self.call(
            "Emulation.setDeviceMetricsOverride",
            session=sid,
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

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
#: viewport, every table scrolling sideways inside itself or its ``.table-wrap``, and the
#: pairs of SVG text boxes that overlap within one figure
LAYOUT_PROBE = """(() => {
  const W = document.documentElement.clientWidth;
  const out = {viewport: W, page: document.documentElement.scrollWidth, past: [], scrolls: [],
               overlaps: []};
  const name = el => el.tagName.toLowerCase() + ' "' + (el.textContent || '').trim().slice(0, 50) + '"';
  for (const el of document.querySelectorAll('main > *, section > *, table, svg, pre, img, dl')) {
    const r = el.getBoundingClientRect();
    if (r.width > 0 && r.right > W + 0.5) out.past.push(name(el) + ' right ' + Math.round(r.right));
  }
  for (const el of document.querySelectorAll('table, .table-wrap')) {
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


#: JavaScript returning (as JSON) every table cell's token that the browser broke over two
#: lines: every ``<details>`` is opened first so that each table is laid out, then for each
#: ``th`` / ``td`` each whitespace-free run of its text (a token: ``832.00``, ``18/42``,
#: ``model``) is covered by a Range; its client rects are grouped into lines (rects that
#: overlap vertically are one line, so ``x<sub>1</sub>`` stays one) and more than one line
#: means the token was split. ``cells`` is how many cells were measured, ``tokens`` how many
#: tokens, ``broken`` a list of ``{token, lines, cell}``.
TOKEN_PROBE = """(() => {
  document.querySelectorAll('details').forEach(d => { d.open = true; });
  const out = {cells: 0, tokens: 0, broken: []};
  for (const cell of document.querySelectorAll('th, td')) {
    const walker = document.createTreeWalker(cell, NodeFilter.SHOW_TEXT);
    const nodes = [];
    let text = '';
    for (let n = walker.nextNode(); n; n = walker.nextNode()) {
      nodes.push([n, text.length]);
      text += n.data;
    }
    if (!text.trim()) continue;
    out.cells++;
    const at = pos => {
      let k = nodes.length - 1;
      while (k > 0 && nodes[k][1] > pos) k--;
      return [nodes[k][0], pos - nodes[k][1]];
    };
    for (const m of text.matchAll(/\\S+/g)) {
      out.tokens++;
      const range = document.createRange();
      range.setStart(...at(m.index));
      const end = at(m.index + m[0].length - 1);
      range.setEnd(end[0], end[1] + 1);
      const rects = [...range.getClientRects()].filter(r => r.width > 0 && r.height > 0)
        .sort((a, b) => a.top - b.top);
      let lines = 0, bottom = -Infinity;
      for (const r of rects) {
        if (r.top >= bottom - 0.5) { lines++; bottom = r.bottom; }
        else bottom = Math.max(bottom, r.bottom);
      }
      if (lines > 1) out.broken.push({token: m[0], lines: lines,
                                      cell: cell.tagName.toLowerCase() + ' "' + text.trim().slice(0, 60) + '"'});
    }
  }
  return JSON.stringify(out);
})()"""


#: JavaScript returning (as JSON) the page's navigation timing, ms from the navigation's
#: start: ``dom_ms`` (DOMContentLoaded handled), ``load_ms`` (the load event), and
#: ``layout_ms`` (the page laid out: reading its height forces the layout)
TIMING_PROBE = """(() => {
  const h = document.documentElement.scrollHeight;
  const n = performance.getEntriesByType('navigation')[0];
  return JSON.stringify({dom_ms: n.domContentLoadedEventEnd, load_ms: n.loadEventEnd || n.loadEventStart,
                         layout_ms: performance.now(), height: h});
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
    exceptions), ``title``, ``n_svg`` (inline SVG elements in the page), ``layout``
    (:data:`LAYOUT_PROBE`'s findings at this width) and ``tokens`` (:data:`TOKEN_PROBE`'s:
    the table cells' tokens broken over two lines; measured after the screenshot, as it
    opens every ``<details>``).
    """
    cdp = Cdp(tmp / "profile")
    try:
        sid = cdp.new_page(("Network", "Runtime", "Log", "Page"))
        cdp.window(sid, width, height)
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
        tokens = cdp.call("Runtime.evaluate", session=sid, expression=TOKEN_PROBE)
    finally:
        cdp.close()
    ev = cdp.events
    requests = [
        e["params"]["request"]["url"] for e in ev if e.get("method") == "Network.requestWillBeSent"
    ]
    errors = console_errors(ev)
    return {
        "requests": requests,
        "leaving": [u for u in requests if not u.startswith(("file:", "data:", "about:"))],
        "errors": errors,
        "title": title["result"].get("value"),
        "n_svg": n_svg["result"].get("value"),
        "layout": json.loads(layout["result"].get("value") or "{}"),
        "tokens": json.loads(tokens["result"].get("value") or "{}"),
    }


def console_errors(ev: list[dict[str, Any]]) -> list[str]:
    """Console errors, error log entries (a blocked resource, a policy violation) and
    uncaught exceptions among DevTools events."""
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
    return errors


def probe_pages(
    pages: dict[str, Path], tmp: Path, widths: tuple[int, ...] = (900, 1400), height: int = 1200
) -> dict[tuple[str, int], dict[str, Any]]:
    """Each page at each width in one browser: ``{(name, width): {"layout", "tokens",
    "errors", "timing"}}`` (:data:`LAYOUT_PROBE`'s and :data:`TOKEN_PROBE`'s findings, the
    page's console errors, :func:`console_errors`, :data:`TIMING_PROBE`'s load times and
    ``wall_ms``: from the navigation's request to the page laid out, as this process saw
    it), faster than :func:`open_in_chromium` per page when only the probes are wanted."""
    out: dict[tuple[str, int], dict[str, Any]] = {}
    cdp = Cdp(tmp / "profile")
    try:
        sid = cdp.new_page(("Runtime", "Log", "Page"))
        for width in widths:
            cdp.window(sid, width, height)
            for name, html in pages.items():
                cdp.events.clear()  # a load event of the page before is not this one's
                t0 = time.monotonic()
                cdp.call("Page.navigate", session=sid, url=html.resolve().as_uri())
                cdp.wait_event("Page.loadEventFired")
                res = cdp.call("Runtime.evaluate", session=sid, expression=TIMING_PROBE)
                found: dict[str, Any] = {"timing": json.loads(res["result"].get("value") or "{}")}
                found["timing"]["wall_ms"] = 1e3 * (time.monotonic() - t0)
                for key, probe in (("layout", LAYOUT_PROBE), ("tokens", TOKEN_PROBE)):
                    res = cdp.call("Runtime.evaluate", session=sid, expression=probe)
                    found[key] = json.loads(res["result"].get("value") or "{}")
                cdp.drain(0.2)  # log entries that arrive after the load event
                found["errors"] = console_errors(cdp.events)
                out[(name, width)] = found
    finally:
        cdp.close()
    return out
