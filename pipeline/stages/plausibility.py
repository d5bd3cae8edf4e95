"""Guardrails: inputs that look right but cannot be, caught before identification.

A plausible-looking wrong input ends in a confident claim: identification fits
whatever it is given. Joint values in degrees still fit a (wrong) robot, and a
bar length typed in millimetres, or 3 % off, rescales every link. Each check
here compares an input with what the nominal robot itself says. It returns one
line naming the value, the bound and what to check. Identification refuses with
those lines (exit 3) unless told to accept them (``--accept-implausible``).

Checks:

* **joint values** against the URDF's limits. A value more than
  ``JOINT_MARGIN`` outside them is implausible. Where some value exceeds a full
  turn and every value of the joint read as degrees falls inside the limits,
  the line says they look like degrees.
* **known distances** against the nominal robot's own estimate. The pin and the
  targets are solved at nominal kinematics by linear least squares (the
  identification's start, eq. (1) with ``x = 0``), which places the targets to
  within the nominal robot's error. The declared distance ``D`` and the nominal
  one ``D_0`` may differ by at most

      tol = max(REL_TOL D_0, RESID_FACTOR rho_0, ABS_TOL_M)

  with ``rho_0`` the RMS residual of that nominal fit, the size of the
  nominal robot's error on these touch-ups. A distance in the wrong unit is off
  by a factor of 1000. A typo or the wrong bar is off by per cents. The line
  states the implied scale change in ppm.
"""

from __future__ import annotations

import numpy as np

from pipeline.evaluate import fit_pin_and_targets
from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64

#: rad (or m for a prismatic joint) beyond a URDF limit that counts as implausible
JOINT_MARGIN = 0.05
#: known distance vs the nominal robot's estimate: relative bound
REL_TOL = 0.01
#: ... in units of the nominal fit's RMS residual
RESID_FACTOR = 3.0
#: ... and never tighter than this (m)
ABS_TOL_M = 2e-3


def joint_values(q: F64, chain: Chain) -> list[str]:
    """One line per joint with values outside its URDF limits by more than ``JOINT_MARGIN``.

    Parameters
    ----------
    q : (N, n) joint values of the used touch-ups (rad / m)
    chain : the nominal chain (its actuated joints' limits)
    """
    out = []
    lo, hi = chain.lower, chain.upper
    for j, name in enumerate(chain.joint_names):
        if not (np.isfinite(lo[j]) and np.isfinite(hi[j])):
            continue
        v = q[:, j]
        bad = (v < lo[j] - JOINT_MARGIN) | (v > hi[j] + JOINT_MARGIN)
        if not bad.any():
            continue
        worst = float(v[np.argmax(np.abs(v))])
        line = (
            f"joint {name}: {int(bad.sum())} of {len(v)} values outside the URDF's limits "
            f"[{lo[j]:.3f}, {hi[j]:.3f}] (worst {worst:.4g})"
        )
        deg = np.deg2rad(v)
        beyond_turn = float(np.max(np.abs(v))) > 2.0 * np.pi  # no revolute reading in rad
        if beyond_turn and np.all((deg >= lo[j] - JOINT_MARGIN) & (deg <= hi[j] + JOINT_MARGIN)):
            line += ": these look like degrees; the touch-up table holds radians"
        else:
            line += ": check the joint columns (order, names, units) and the URDF"
        out.append(line)
    return out


def nominal_targets(
    chain: Chain, q: F64, d: F64, tk: np.ndarray, K: int, sw: F64
) -> tuple[F64, F64, float]:
    """Pin and targets at nominal kinematics and that fit's RMS residual (m).

    :func:`pipeline.evaluate.fit_pin_and_targets` with the nominal chain.

    Returns
    -------
    pin : (3,) ; targets : (K, 3) ; rms : m
    """
    pin, targets, r = fit_pin_and_targets(chain, q, d, tk, K, sw)
    return pin, targets, float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


def known_distances(
    chain: Chain,
    q: F64,
    d: F64,
    tk: np.ndarray,
    K: int,
    sw: F64,
    distances: list[tuple[int, int, float]],
    labels: list[str],
) -> list[str]:
    """One line per known distance the nominal robot contradicts beyond ``tol``.

    ``distances`` as ``(k_a, k_b, metres)`` over the used targets ``0..K-1``;
    ``labels`` their names.
    """
    if not distances or K < 2:
        return []
    _, tg, rho = nominal_targets(chain, q, d, tk, K, sw)
    out = []
    for a, b, metres in distances:
        d0 = float(np.linalg.norm(tg[a] - tg[b]))
        tol = max(REL_TOL * d0, RESID_FACTOR * rho, ABS_TOL_M)
        if abs(metres - d0) <= tol:
            continue
        ppm = 1e6 * (metres / d0 - 1.0) if d0 > 0 else float("inf")
        hint = (
            "in millimetres? distances are in metres"
            if 300.0 < metres / max(d0, 1e-12) < 3000.0
            else "a typo, or another bar's length?"
        )
        out.append(
            f"known distance {labels[a]}:{labels[b]} = {metres:.6g} m, but the nominal robot "
            f"puts these targets {d0:.4f} m apart: a scale change of {ppm:+.0f} ppm, beyond "
            f"the {1e6 * tol / max(d0, 1e-12):.0f} ppm the nominal robot's own error allows "
            f"(RMS {1e3 * rho:.2f} mm on these touch-ups): {hint}"
        )
    return out
