"""Screenshots of the audit page (``vtcal audit``) on a small simulated fleet, at 900 and
1400 px: ``report_screenshots.py --pages audit``.

    python benchmarks/audit_screenshot.py [--out docs/img]

The fleet, the page and what is printed (the layout and token probes) are
``benchmarks/report_screenshots.py``'s; this writes ``audit-900.png`` and
``audit-1400.png`` (the fleet page, the first 1200 px of each) and ``audit-robot-1400.png``
(the page of the robot on top) without running the shipped sample.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv: list[str] | None = None) -> None:
    from report_screenshots import main as screenshots

    screenshots(["--pages", "audit", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    main()
