"""A Dask cluster started apart from vtcal: what it must share with the batch, checked first.

``vtcal batch --executor dask --scheduler ADDRESS`` sends one task per recording
to the workers of a running ``dask.distributed`` cluster. Each task writes its
artefacts itself, into ``OUT/<name>/``, so the batch only works when every
worker

- imports the same vtcal code as the batch process (else its artefacts would
  not be those a local run gives, and the run ledger would not vouch for them),
- sees the batch folder ``OUT`` at the same absolute path (one machine, or a
  shared filesystem mounted at the same place), and
- is there at all (a scheduler without workers would hold the tasks for ever).

:func:`preflight` checks the three before the first task is sent and turns a
failure into one :class:`~pipeline.errors.BadInput` line naming the scheduler,
the worker and what differs. Only the workers connected at that moment are
checked; workers joining later are trusted.

This module imports nothing heavy; ``distributed`` is imported by the caller.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path
from typing import Any

from pipeline.errors import BadInput

#: seconds to wait for the first worker of a cluster to connect
WORKER_WAIT_S = 30.0
#: name of the probe file written into the batch folder for the workers to find
PROBE_PREFIX = ".vtcal-cluster-probe-"


def worker_facts(out_dir: str, probe_name: str, token: str) -> dict[str, Any]:
    """Run on each worker: its vtcal code and whether it sees the batch folder's probe file.

    Parameters
    ----------
    out_dir : absolute path of the batch folder, as the batch process sees it
    probe_name, token : file the batch process wrote there, and its content

    Returns
    -------
    dict with ``version`` and ``code`` (:func:`pipeline.run.ledger.code_digest`)
    of the worker's vtcal, ``sees_out`` (the probe file is there with the token),
    ``host`` and ``pid``.
    """
    import socket

    from pipeline import __version__
    from pipeline.run.ledger import code_digest

    try:
        sees = (Path(out_dir) / probe_name).read_text() == token
    except OSError:
        sees = False
    return {
        "version": __version__,
        "code": code_digest(),
        "sees_out": sees,
        "host": socket.gethostname(),
        "pid": os.getpid(),
    }


def preflight(client: Any, scheduler: str, out_dir: Path, wait_s: float | None = None) -> int:
    """Check that a cluster's workers can run this batch; return how many there are.

    Waits up to ``wait_s`` (default :data:`WORKER_WAIT_S`) for a first worker, writes a probe file into
    ``out_dir`` (removed again before returning), and runs :func:`worker_facts`
    on every connected worker (``Client.run``).

    Raises
    ------
    BadInput
        One line: no worker connected within ``wait_s``; a worker that cannot
        run vtcal's code; a worker with other vtcal code (version or code
        digest); a worker that does not see ``out_dir`` (no shared filesystem).
    """
    from pipeline import __version__
    from pipeline.run.ledger import code_digest

    where = f"--scheduler {scheduler}"
    wait_s = WORKER_WAIT_S if wait_s is None else wait_s
    try:
        client.wait_for_workers(1, timeout=wait_s)
    except (TimeoutError, OSError) as exc:
        raise BadInput(f"{where}: no worker connected within {wait_s:.0f} s") from exc
    token = secrets.token_hex(16)
    probe = f"{PROBE_PREFIX}{token[:12]}"
    path = out_dir / probe
    path.write_text(token)
    try:
        facts = client.run(worker_facts, str(out_dir), probe, token)
    except Exception as exc:  # the worker could not import or run vtcal
        msg = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise BadInput(f"{where}: a worker cannot run vtcal: {msg}") from exc
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
    mine = (__version__, code_digest())
    for addr, f in sorted(facts.items()):
        theirs = (f.get("version"), f.get("code"))
        if theirs != mine:
            raise BadInput(
                f"{where}: worker {addr} runs vtcal {theirs[0]} code {theirs[1]}, this "
                f"process vtcal {mine[0]} code {mine[1]}: install the same vtcal on every worker"
            )
        if not f.get("sees_out"):
            raise BadInput(
                f"{where}: worker {addr} (host {f.get('host')}) does not see the batch folder "
                f"{out_dir}: --out must be on a filesystem every worker mounts at the same path"
            )
    return len(facts)
