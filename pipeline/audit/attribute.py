"""One physical reading of a change: nested explanations compared.

A change found by :mod:`pipeline.audit.change` is a difference ``delta`` of the
estimated quantities. A physical cause ``c`` with ``k_c`` unknowns ``beta``
(e.g. joint 3's zero, one number) moves the *true* kinematics along columns of
the full error model; what it does to the *estimate* is the least-squares
response of the identified quantities, pin and targets to that motion of the
touch-up points (the columns held at nominal are absorbed by the identified
ones exactly as the fit absorbs them)::

    J_e = [J_x(identified), R_i (pin), -E_k (targets)],   J_c = the cause's columns
    A_c = first E rows of  J_e^+ J_c                                           (A1)

so the explanation is ``delta = A_c beta + noise``. Whitened with (C2)'s ``W``::

    beta = argmin |w - W A_c beta|^2,   R_c = |w - W A_c beta|^2 ~ chi2(r - k_c)  (A2)

The causes (full-model columns of each actuated joint ``j``):

=================  ============================================  =====
``joint_offset``   ``j.dq0``: the joint's zero                    1
``link``           ``j.dx, j.dy, j.dz``: the joint's origin moved 3
                   (the link before it: its length, or sideways)
``thermal``        every link offset grown by one factor          1
                   (``sum_j o_j . (j.dx, j.dy, j.dz)``, ``o_j`` the
                   nominal offsets; seen only with a known
                   distance: without, the scale is the gauge)
``camera``         ``pin.x, pin.y, pin.z``: camera/pin remounted  3
``base``           a rigid motion of every target centre (the     6
                   base moved against the cell; the kinematics
                   and the pin unchanged)
=================  ============================================  =====

A cause's columns that the estimate cannot see (``|A_c e_j| <`` :data:`VISIBLE`) are
dropped from it, and a cause that moves only the fitted targets (joint 1's zero
and origin, held at nominal and absorbed by the targets) is the base's motion
and left to the base cause. A bent
link (its origin turned about an axis normal to the joint's) is not a cause of
its own: to first order it is the neighbouring joint's zero offset plus an
origin shift, and the two cannot be told apart from touch-ups.

The reading is the cause with the smallest ``R_c + 2 k_c`` (Akaike's penalty:
a cause with more unknowns must fit better by more than chance; causes within
:data:`EQUALLY_WELL` of it are named beside it as not told apart) whose residual
is itself unremarkable: ``R_c <= chi2_isf(ALPHA_EXPLAINED, r - k_c) +
LINEAR_SHARE * T`` (:data:`ALPHA_EXPLAINED` is smaller than the change test's
``alpha``, and (A1) is a linearisation at the later fit: a change thousands of
chi-square units large leaves a small share of itself, :data:`LINEAR_SHARE`, in
the residual; seen on a 0.05 deg zero offset, T = 153,798 on 30 dof, read right
with R_c = 60.4 on 29 dof). When none is, no
single cause explains the change: the quantities are tested per group (each
joint's, the pin's; (C2) on the group, Bonferroni ``alpha / G``) and when
:data:`DIFFERENT_GROUPS` or more groups changed, and the whitened difference is
far beyond what a re-recording of one robot shows (``T >= DIFFERENT_MIN_RATIO r``,
an empirical null), the two calibrations are read
as **different robots of one model** (or an arm rebuilt), else as several
changes, named. A base that moved is not an arm change: it moves the fitted
targets together and leaves the kinematics and the pin alone. Joint 1's zero
and origin are held at nominal (the targets absorb them), so a turned joint 1
reads as the base turned about its axis: the two are one motion for touch-ups.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.audit.change import ALPHA, Difference, difference_test, isf, sf
from pipeline.audit.fit import Estimate, constraint_rows, point_columns
from pipeline.kinematics.se3 import F64
from pipeline.stages.identify.types import IdentifyConfig

#: a residual this unlikely under the cause read: no single cause explains the change
ALPHA_EXPLAINED = 1e-3
#: causes whose score is within this of the best are named beside it (Akaike: not told apart)
EQUALLY_WELL = 2.0
#: the share of the change's chi-square a first-order reading may leave unexplained
LINEAR_SHARE = 1e-3
#: a cause column whose response (A1) is below this norm is invisible to the estimate
VISIBLE = 1e-6
#: this many parameter groups changed at once: different robots, not one event
DIFFERENT_GROUPS = 3
#: and the whitened difference at least this many times its degrees of freedom: far beyond
#: what a re-recording of one robot shows (an empirical null, bench_audit_images.py
#: --histories 20: one robot, events included, chi2/dof up to 9.8e3; two robots of one
#: model from 3.6e6, median 3.9e7)
DIFFERENT_MIN_RATIO = 1e5
#: reading kind -> what it is (the table's ``kind`` column)
KINDS = {
    "none": "no change beyond the covariances",
    "arm": "an arm change (joint zero, link)",
    "camera": "the camera / pin remounted",
    "base": "the base (or every target) moved; the arm and pin did not change",
    "several": "several changes at once",
    "different_robot": "different robots of one model",
}


@dataclass
class Cause:
    """One candidate explanation: a name, its kind and the full-model columns it moves.

    With ``weights`` the cause is the one column ``sum_k weights[k] * columns[k]`` (its
    unit ``units[0]``): a thermal growth moves every link offset in proportion to it.
    """

    name: str
    kind: str
    columns: list[str]
    units: list[str]
    weights: list[float] | None = None


@dataclass
class Reading:
    """The reading of one comparison.

    Attributes
    ----------
    kind : a key of :data:`KINDS` ; cause : the cause's name ('' when none or several)
    text : one line for people
    beta, beta_std : (k,) the cause's size and its standard error (SI), with ``columns``
    residual, residual_dof, residual_p : (A2) of the cause read
    groups : the groups that changed (several / different robots)
    explained : (E,) ``A_c beta``, the change of every compared quantity the cause
        explains (``diff.names`` order; empty when no single cause does)
    alternatives : other causes whose score is within :data:`EQUALLY_WELL` of it: the
        touch-ups cannot tell them apart (e.g. joint 4's and joint 5's origins moved
        along joint 4's axis, which is one motion)
    """

    kind: str
    cause: str
    text: str
    columns: list[str] = field(default_factory=list)
    beta: list[float] = field(default_factory=list)
    beta_std: list[float] = field(default_factory=list)
    residual: float = float("nan")
    residual_dof: int = 0
    residual_p: float = float("nan")
    groups: list[str] = field(default_factory=list)
    explained: list[float] = field(default_factory=list)
    alternatives: list[str] = field(default_factory=list)


def causes(est: Estimate) -> list[Cause]:
    """The candidate causes for the model fitted in ``est`` (its joints and pin)."""
    model = est.result.error_model
    assert model is not None
    have = set(model.param_names)
    out = []
    for j in model.nominal.actuated:
        n = j.name
        if f"{n}.dq0" in have:
            out.append(Cause(f"{n} zero offset", "arm", [f"{n}.dq0"], ["rad"]))
        lin = [f"{n}.{c}" for c in ("dx", "dy", "dz") if f"{n}.{c}" in have]
        if lin:
            out.append(Cause(f"link before {n} (origin moved)", "arm", lin, ["m"] * len(lin)))
    grow = [(f"{j.name}.{c}", float(j.T_parent_joint[i, 3])) for j in model.nominal.actuated
            for i, c in enumerate(("dx", "dy", "dz")) if f"{j.name}.{c}" in have]  # fmt: skip
    grow = [(n, w) for n, w in grow if w != 0.0]
    if grow:
        out.append(
            Cause(
                "thermal growth (every link offset)",
                "arm",
                [n for n, _ in grow],
                ["1"],
                [w for _, w in grow],
            )  # fmt: skip
        )
    out.append(Cause("camera / pin remounted", "camera", ["pin.x", "pin.y", "pin.z"], ["m"] * 3))
    base = ["base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz"]
    out.append(
        Cause("base moved (the targets seen to move)", "base", base, ["m"] * 3 + ["rad"] * 3)
    )
    return out


def base_response(names: list[str], z: F64) -> F64:
    """The estimate's response to a rigid motion of the base (6 columns: translation x, y, z,
    rotation about x, y, z at the base origin): only the target centres move,
    ``dt_k = v + w x t_k``; the kinematics and the pin do not."""
    A = np.zeros((len(names), 6))
    at = {n: i for i, n in enumerate(names)}
    for n, i in at.items():
        if not n.startswith("target.") or not n.endswith(".x"):
            continue
        t = z[i : i + 3]
        A[i : i + 3, :3] = np.eye(3)
        A[i : i + 3, 3:] = -np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return A


def response(
    est: Estimate, names: list[str], cause_columns: list[str], weights: list[float] | None = None
) -> F64:
    """(A1): the estimate's response ``A_c`` (len(names), k) to a cause's columns (one
    combined column with ``weights``), under the fit's constraints (known distances, scale
    gauge: both estimates satisfy them)."""
    Jfull = point_columns(est, names)
    Jc = point_columns(est, cause_columns)
    if weights is not None:
        Jc = Jc @ np.asarray(weights, dtype=float)[:, None]
    G = constraint_rows(est, names, [])
    if len(G):
        Jfull = np.vstack([Jfull, IdentifyConfig().distance_weight * G])
        Jc = np.vstack([Jc, np.zeros((len(G), Jc.shape[1]))])
    scale = np.linalg.norm(Jfull, axis=0)
    scale[scale == 0] = 1.0
    sol = np.linalg.lstsq(Jfull / scale, Jc, rcond=1e-10)[0]
    return np.asarray(sol / scale[:, None])


def explain(diff: Difference, A: F64) -> tuple[F64, F64, float, int]:
    """(A2): ``beta``, its standard errors, the residual ``R_c`` and its dof."""
    B = diff.W @ A
    beta, *_ = np.linalg.lstsq(B, diff.w, rcond=1e-10)
    k = int(np.linalg.matrix_rank(B, tol=1e-8 * max(1.0, float(np.abs(B).max(initial=0)))))
    resid = float(np.sum((diff.w - B @ beta) ** 2))
    std = np.sqrt(np.clip(np.diag(np.linalg.pinv(B.T @ B)), 0, None))
    return np.asarray(beta), np.asarray(std), resid, diff.dof - k


def group_changes(diff: Difference, alpha: float = ALPHA) -> list[str]:
    """The groups (a joint's quantities, the pin's) whose own (C2) test fails at ``alpha / G``."""
    groups: dict[str, list[int]] = {}
    for i, n in enumerate(diff.names):
        groups.setdefault(n.split(".")[0], []).append(i)
    out = []
    for g, idx in groups.items():
        d = difference_test(
            np.zeros(len(idx)), np.zeros((len(idx),) * 2), diff.delta[idx],
            diff.cov[np.ix_(idx, idx)], [diff.names[i] for i in idx],
        )  # fmt: skip
        if d.dof and sf(d.T, d.dof, diff.f_dof) < alpha / len(groups):
            out.append(g)
    return out


def different_robots(diff: Difference, groups: list[str]) -> bool:
    """Read as different robots: :data:`DIFFERENT_GROUPS` or more groups changed and the
    whitened difference far beyond a re-recording's (``T >= DIFFERENT_MIN_RATIO r``)."""
    return len(groups) >= DIFFERENT_GROUPS and diff.T >= DIFFERENT_MIN_RATIO * max(diff.dof, 1)


def display_unit(column: str) -> tuple[float, str]:
    """How a cause's column is shown: ``(factor from SI, unit)``: deg, ppm or mm."""
    if column.endswith(("dq0", ".rx", ".ry", ".rz")):
        return float(np.degrees(1.0)), "deg"
    if column == "growth":
        return 1e6, "ppm"
    return 1e3, "mm"


def _fmt(beta: F64, std: F64, units: list[str]) -> str:
    parts = []
    for b, s, u in zip(beta, std, units, strict=True):
        if u == "rad":
            parts.append(f"{np.degrees(b):+.4f} +- {np.degrees(s):.4f} deg")
        elif u == "1":
            parts.append(f"{b * 1e6:+.1f} +- {s * 1e6:.1f} ppm")
        else:
            parts.append(f"{b * 1e3:+.4f} +- {s * 1e3:.4f} mm")
    return ", ".join(parts)


def attribute(diff: Difference, est: Estimate, alpha: float = ALPHA) -> Reading:
    """The reading of a comparison whose test (C2) failed (see the module docstring).

    Parameters
    ----------
    diff : :func:`pipeline.audit.change.compare_estimates` of the two calibrations
    est : the later recording's estimate (its poses linearise (A1))
    """
    best: tuple[float, Cause, F64, F64, float, int, F64] | None = None
    scores: list[tuple[float, str]] = []
    for c0 in causes(est):
        if c0.kind == "base":
            A = base_response(diff.names, est.z[[est.index()[n] for n in diff.names]])
        else:
            A = response(est, diff.names, c0.columns, c0.weights)
        if c0.weights is not None:
            c0 = Cause(c0.name, c0.kind, ["growth"], c0.units)
        seen = np.linalg.norm(A, axis=0) >= VISIBLE
        arm_rows = [i for i, n in enumerate(diff.names) if not n.startswith("target.")]
        if c0.kind != "base" and np.linalg.norm(A[arm_rows]) < VISIBLE:
            continue  # it moves the targets only: a motion of the base (read as such)
        if not seen.any():
            continue
        cols = [n for n, v in zip(c0.columns, seen, strict=True) if v]
        units = [u for u, v in zip(c0.units, seen, strict=True) if v]
        c, A = Cause(c0.name, c0.kind, cols, units), A[:, seen]
        beta, std, resid, dof = explain(diff, A)
        score = resid + 2 * (diff.dof - dof)
        scores.append((score, c.name))
        if best is None or score < best[0]:
            best = (score, c, beta, std, resid, dof, A @ beta)
    if best is not None:
        _, c, beta, std, resid, dof, explained = best
        p = sf(resid, dof, diff.f_dof)
        bound = isf(ALPHA_EXPLAINED, dof, diff.f_dof) + LINEAR_SHARE * diff.T
        if resid <= bound:
            alts = [n for sc, n in scores if n != c.name and sc - best[0] < EQUALLY_WELL]
            also = f"; as well explained by: {', '.join(alts)}" if alts else ""
            return Reading(
                c.kind, c.name, f"{c.name}: {_fmt(beta, std, c.units)} (one cause explains it: "
                f"residual chi2 {resid:.1f} on {dof} dof{also})", c.columns,
                [float(v) for v in beta], [float(v) for v in std], resid, dof, p,
                explained=[float(v) for v in explained], alternatives=alts,
            )  # fmt: skip
    groups = group_changes(diff, alpha)
    if different_robots(diff, groups):
        return Reading(
            "different_robot", "",
            f"different robots of one model (or an arm rebuilt): {len(groups)} of the parameter "
            f"groups changed at once ({', '.join(groups)}); no single cause explains it",
            groups=groups,
        )  # fmt: skip
    named = ", ".join(groups) if groups else "no group alone"
    return Reading(
        "several", "", f"several changes at once ({named}); no single cause explains it",
        groups=groups,
    )  # fmt: skip
