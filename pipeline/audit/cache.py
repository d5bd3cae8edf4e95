"""The audit folder as a cache: each recording's fit, its held-out figures and each comparison.

``vtcal audit ... --out DIR`` keeps what it computed under ``DIR/cache/KIND/KEY[:2]/KEY.pkl``,
one file per entry (``KIND``: ``fit``, ``heldout``, ``compare``), so that an audit run
again over the same run folders and more fits only the recordings it has not seen.
An entry's key is a digest of everything that computes it:

* **fit** (:func:`pipeline.audit.fit.fit_item`): the recording's inputs (:meth:`Keys.inputs`:
  the bytes of its ``inliers.parquet`` and ``recording.json``, or the touch-up table's
  content when the caller read it, the nominal chain, the known distances and the
  touch-up stage's measured noise of ``touchups.parquet``), the error model the change
  test compares, and the code (:func:`pipeline.run.code_key.code_digest`: the function and
  its modules' import closure);
* **heldout** (:func:`pipeline.audit.fit.heldout_mm`): the inputs, the error model, the code;
* **compare** (:func:`pipeline.audit.pairs.compare_pair`): both fits' keys, the two
  recordings' names, the kind of comparison, ``alpha``, the tolerance, the code.

The robot identity, the date and the run's own k-fold figures (``identify.json``) are
read afresh each time; they key nothing.

An entry is ``MAGIC``, the SHA-256 of its payload, and the payload (a pickle). It is
written through a temporary sibling and ``os.replace`` (never half there), without
``fsync``: an entry a crash loses is computed again, and one that is truncated, altered
or unreadable fails its digest and is computed again too. Pickles are code: the cache
is the audit's own folder, read only by the audit that wrote it.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
from pathlib import Path
from typing import Any

from pipeline.audit.identity import INLIERS, RECORDING, AuditItem
from pipeline.run.lazy import Ref

#: the first bytes of every entry (a format change is a new magic: old entries are recomputed)
MAGIC = b"vtcal-audit-cache 1\n"
_DIGEST = 32

#: the function whose code keys each kind of entry
ENTRIES = {
    "fit": Ref("pipeline.audit.fit", "fit_item"),
    "heldout": Ref("pipeline.audit.fit", "heldout_mm"),
    "compare": Ref("pipeline.audit.pairs", "compare_pair"),
}


class Cache:
    """Entries by kind and key under ``folder/cache`` (in memory when ``folder`` is None)."""

    def __init__(self, folder: Path | None) -> None:
        self.root = None if folder is None else Path(folder) / "cache"
        self._mem: dict[tuple[str, str], bytes] = {}

    def path(self, kind: str, key: str) -> Path:
        assert self.root is not None
        return self.root / kind / key[:2] / f"{key}.pkl"

    def get_bytes(self, kind: str, key: str) -> bytes | None:
        """The payload of an entry; None when missing, unreadable or damaged."""
        if self.root is None:
            return self._mem.get((kind, key))
        try:
            blob = self.path(kind, key).read_bytes()
        except OSError:
            return None
        n = len(MAGIC)
        payload = blob[n + _DIGEST :]
        if blob[:n] != MAGIC or hashlib.sha256(payload).digest() != blob[n : n + _DIGEST]:
            return None
        return payload

    def get(self, kind: str, key: str) -> Any | None:
        """The value of an entry; None when missing, unreadable or damaged."""
        raw = self.get_bytes(kind, key)
        if raw is None:
            return None
        try:
            return pickle.loads(raw)
        except Exception:  # a payload of an older class layout, say: computed again
            return None

    def put(self, kind: str, key: str, value: Any) -> None:
        """Keep ``value`` (a disk that refuses it only means computing it again next time)."""
        payload = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        if self.root is None:
            self._mem[(kind, key)] = payload
            return
        path = self.path(kind, key)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(MAGIC + hashlib.sha256(payload).digest() + payload)
            os.replace(tmp, path)
        except OSError:
            tmp.unlink(missing_ok=True)


class Keys:
    """The cache keys of an audit's entries (the code digests taken once)."""

    def __init__(self) -> None:
        from pipeline.run.code_key import code_digest

        self.code = {kind: code_digest((entry,)) for kind, entry in ENTRIES.items()}

    @staticmethod
    def inputs(item: AuditItem) -> str:
        """Digest of what a fit of ``item`` reads (see the module docstring)."""
        h = hashlib.sha256()
        files = [RECORDING] + ([] if item.table_read else [INLIERS])
        for name in files:
            path = item.path / name
            if path.is_file():
                h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
        if item.table_read:
            import pandas as pd

            t = item.table
            h.update(repr([(str(c), str(t[c].dtype)) for c in t.columns]).encode())
            h.update(pd.util.hash_pandas_object(t, index=False).to_numpy().tobytes())
        chain = [item.urdf, item.base_link, item.flange_link, repr(item.distances)]
        h.update(json.dumps([chain, item.noise], sort_keys=True, default=str).encode())
        return h.hexdigest()

    def _key(self, kind: str, *parts: Any) -> str:
        text = json.dumps([kind, self.code[kind], *parts], default=str)
        return hashlib.sha256(text.encode()).hexdigest()

    def fit(self, inputs: str, model: str) -> str:
        return self._key("fit", inputs, model)

    def heldout(self, inputs: str, model: str) -> str:
        return self._key("heldout", inputs, model)

    def compare(
        self, kind: str, a: AuditItem, b: AuditItem, fa: str, fb: str, alpha: float, tol: float
    ) -> str:
        return self._key("compare", kind, a.name, b.name, fa, fb, repr(alpha), repr(tol))
