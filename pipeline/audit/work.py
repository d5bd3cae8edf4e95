"""What an audit computes, what its cache already holds, and the tasks its engine runs.

One task per robot (:func:`robot_task`): its recordings not yet fitted are fitted
(:func:`pipeline.audit.fit.fit_item`), their missing held-out figures computed
(:func:`pipeline.audit.fit.heldout_mm`) and the consecutive pairs not yet compared
compared (:func:`pipeline.audit.pairs.compare_pair`), each recording's touch-ups read
once, in the worker (a fit the cache holds comes along pickled when a comparison needs
it). Then the first recordings of robots of one model are compared (one task each).
The engine (:mod:`pipeline.audit.engine`) runs the tasks; the cache
(:mod:`pipeline.audit.cache`) keeps every result as it comes back.
"""

from __future__ import annotations

import pickle
from collections.abc import Iterator, Mapping
from typing import Any, cast

from pipeline.audit.cache import Cache, Keys
from pipeline.audit.fit import CHANGE_MODEL, Estimate
from pipeline.audit.fleet import Crossval, heldout_tasks, run_crossval
from pipeline.audit.identity import AuditItem

#: robots per chunk of tasks at most (a robot of four touch-up-level recordings: ~1 s)
ROBOTS_PER_CHUNK = 2


def _dumps(est: Estimate) -> tuple[int, bytes]:
    return len(est.q), pickle.dumps(est, protocol=pickle.HIGHEST_PROTOCOL)


def robot_task(
    recs: list[tuple[AuditItem, bytes | None, bool, list[str]]],
    comps: list[tuple[int, int]],
    alpha: float,
    tolerance_mm: float,
) -> tuple[dict[int, tuple[int, bytes]], dict[tuple[int, str], Any], dict[tuple[int, int], Any]]:
    """One robot's work: ``recs`` its recordings ``(item, cached fit or None, fit it?,
    models to hold out)``, ``comps`` the pairs ``(earlier, later)`` to compare. Returns
    ``({i: (n_touchups, pickled Estimate)} of the fits made, {(i, model): (mm, note)},
    {(earlier, later): compare_pair's})``."""
    from pipeline.audit.fit import fit_item, heldout_mm
    from pipeline.audit.identity import with_table
    from pipeline.audit.pairs import compare_pair

    later = {b for _, b in comps}
    est: dict[int, Estimate] = {}
    fits, held = {}, {}
    items = [r[0] for r in recs]
    for i, (item, cached, fit, models) in enumerate(recs):
        if fit or models or i in later:
            items[i] = with_table(item)
        if fit:
            est[i] = fit_item(items[i])
            fits[i] = _dumps(est[i])
        elif cached is not None:
            est[i] = pickle.loads(cached)
        for m in models:
            held[(i, m)] = heldout_mm(items[i], m)
    out = {
        (a, b): compare_pair("history", items[a], items[b], est[a], est[b], alpha, tolerance_mm)
        for a, b in comps
    }
    return fits, held, out


def run_task(task: tuple[Any, ...]) -> Any:
    """One task of the audit's engine, wherever it runs: ``("robot", ...)`` ->
    :func:`robot_task`'s; ``("compare", a, b, pickled estimate of a, of b, alpha,
    tolerance_mm)`` -> :func:`pipeline.audit.pairs.compare_pair`'s for two robots."""
    if task[0] == "robot":
        return robot_task(*task[1:])
    from pipeline.audit.pairs import compare_pair

    _, a, b, ea, eb, alpha, tol = task
    return compare_pair("robots", a, b, pickle.loads(ea), pickle.loads(eb), alpha, tol)


class Estimates(Mapping[str, Estimate]):
    """The audit's fits by recording name, read from its cache when asked for."""

    def __init__(self, cache: Cache, keys: dict[str, str]) -> None:
        self._cache, self._keys = cache, keys

    def __getitem__(self, name: str) -> Estimate:
        raw = self._cache.get("fit", self._keys[name])
        if raw is None:
            raise KeyError(name)
        return cast(Estimate, pickle.loads(raw[1]))

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


Pair = tuple[str, AuditItem, AuditItem]


class AuditWork:
    """An audit's fits, held-out figures and comparisons: cached or computed, and counted.

    After :meth:`run`: ``n_touchups`` per recording, ``runs`` (each recording's own
    k-fold, :func:`pipeline.audit.fleet.run_crossval`), ``heldout`` ``{(index in flat,
    model): (mm, note)}``, ``compared`` ``{(from, to): (change row, validation)}``,
    ``counts`` ``{"fits" | "held-out" | "comparisons": (computed, cached)}``.
    """

    def __init__(self, cache: Cache, alpha: float, tolerance_mm: float) -> None:
        self.cache, self.keys, self.alpha, self.tol = cache, Keys(), alpha, tolerance_mm
        self.fit_keys: dict[str, str] = {}
        self.n_touchups: dict[str, int] = {}
        self.runs: list[Crossval] = []
        self.heldout: dict[tuple[int, str], tuple[float, str]] = {}
        self.compared: dict[tuple[str, str], Any] = {}
        self.counts: dict[str, tuple[int, int]] = {}

    def run(
        self,
        hist: dict[str, list[AuditItem]],
        models: tuple[str, ...],
        pairs: list[Pair],
        engine: Any,
    ) -> None:
        flat = [it for runs in hist.values() for it in runs]
        at = {it.name: i for i, it in enumerate(flat)}
        inputs = {it.name: self.keys.inputs(it) for it in flat}
        self.fit_keys = {n: self.keys.fit(d, CHANGE_MODEL) for n, d in inputs.items()}
        ckeys, todo = {}, []
        for kind, a, b in pairs:
            fa, fb = self.fit_keys[a.name], self.fit_keys[b.name]
            key = ckeys[(a.name, b.name)] = self.keys.compare(
                kind, a, b, fa, fb, self.alpha, self.tol
            )
            got = self.cache.get("compare", key)
            if got is None:
                todo.append((kind, a, b))
            else:
                self.compared[(a.name, b.name)] = got
        need = {x.name for _, a, b in todo for x in (a, b)}
        need_cross = {x.name for k, a, b in todo if k == "robots" for x in (a, b)}
        cached: dict[str, bytes] = {}
        for it in flat:
            got = self.cache.get("fit", self.fit_keys[it.name])
            if got is not None:
                self.n_touchups[it.name] = got[0]
                if it.name in need:
                    cached[it.name] = got[1]
        self.runs = [run_crossval(it) for it in flat]
        hkeys: dict[tuple[int, str], str] = {}
        hold: dict[str, list[str]] = {}
        for i, m in heldout_tasks(self.runs, models):
            hkeys[(i, m)] = self.keys.heldout(inputs[flat[i].name], m)
            got = self.cache.get("heldout", hkeys[(i, m)])
            if got is None:
                hold.setdefault(flat[i].name, []).append(m)
            else:
                self.heldout[(i, m)] = got
        n_fits = len(flat) - len(self.n_touchups)
        n_held = sum(len(v) for v in hold.values())
        tasks = []
        for runs in hist.values():
            idx = {it.name: j for j, it in enumerate(runs)}
            comps = [
                (idx[a.name], idx[b.name]) for k, a, b in todo if k == "history" and b.name in idx
            ]
            recs = [
                (it, cached.get(it.name), it.name not in self.n_touchups, hold.get(it.name, []))
                for it in runs
            ]
            if comps or any(r[2] or r[3] for r in recs):
                tasks.append(("robot", recs, comps, self.alpha, self.tol))
        for j, (fits, held, comps) in engine.imap(run_task, tasks, ROBOTS_PER_CHUNK):
            recs = tasks[j][1]
            for i, res in fits.items():
                name = recs[i][0].name
                self.cache.put("fit", self.fit_keys[name], res)
                self.n_touchups[name] = res[0]
                if name in need_cross:
                    cached[name] = res[1]
            for (i, m), res in held.items():
                k = (at[recs[i][0].name], m)
                self.cache.put("heldout", hkeys[k], res)
                self.heldout[k] = res
            for (a, b), res in comps.items():
                names = (recs[a][0].name, recs[b][0].name)
                self.cache.put("compare", ckeys[names], res)
                self.compared[names] = res
        cross = [
            ("compare", a, b, cached[a.name], cached[b.name], self.alpha, self.tol)
            for k, a, b in todo
            if k == "robots"
        ]
        for j, res in engine.imap(run_task, cross):
            names = (cross[j][1].name, cross[j][2].name)
            self.cache.put("compare", ckeys[names], res)
            self.compared[names] = res
        self.counts = {
            "fits": (n_fits, len(flat) - n_fits),
            "held-out": (n_held, len(hkeys) - n_held),
            "comparisons": (len(todo), len(pairs) - len(todo)),
        }

    def estimates(self) -> Estimates:
        return Estimates(self.cache, self.fit_keys)

    def comparison(self, a: AuditItem, b: AuditItem, kind: str) -> tuple[dict[str, Any], Any]:
        """The change row (its identity columns this audit's own) and the validation."""
        c, v = self.compared[(a.name, b.name)]
        c = dict(c, comparison=kind, robot_id=b.robot_id, from_robot_id=a.robot_id,
                 from_recording=a.name, to_recording=b.name, stamp_ns=b.stamp_ns)  # fmt: skip
        return c, v


def work_line(counts: dict[str, tuple[int, int]]) -> str:
    """``fits: 3 new, 2000 cached; held-out: 12 new, 8000 cached; comparisons: ...``"""
    return "; ".join(f"{k}: {n} new, {c} cached" for k, (n, c) in counts.items())
