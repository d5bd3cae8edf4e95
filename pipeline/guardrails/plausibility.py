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
* **the nominal robot's own fit** of these touch-ups: the RMS residual ``rho_0``
  above may be a few millimetres (10.7 mm on the worst real Panda placement,
  ``bench_real.py``) but not ``NOMINAL_RMS_MAX``. Beyond it the joint columns
  and the robot do not belong together: a joint's sign or zero flipped, two
  columns swapped within their limits, touch-ups labelled with the wrong target,
  another robot's URDF (25-100 mm on a simulated LR Mate, see
  ``docs/robustness.md``).
* **joints outside the chain that move**: a revolute or prismatic joint above
  the base link, or a revolute joint below the flange link, whose values in the
  touch-ups span more than ``JOINT_MOVE``. The camera is fixed to the flange and
  the targets stand still, so such a joint means the base or flange link is
  wrong (a flange link one joint short drops that joint's motion silently).
* **the printed target diameter** against the one the image Jacobian implies.
  Near the optical axis a flange translation moves the image by ``g = f / z``
  pixels per metre, and the long axis at the designated size is
  ``s_0 = f D / z``, so ``D_img = s_0 / g``
  (:func:`pipeline.measurement.image.diameter_from_jacobian`). ``D_img`` agrees
  with the print to 0.3-1 % on the shipped and conformance samples; a declared
  diameter more than ``DIAMETER_REL_TOL`` off is a typo, a unit slip or another
  target set (the diameter states print errors in micrometres and scales the
  targets drawn in run.rrd).
"""

from __future__ import annotations

import numpy as np

from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64
from pipeline.kinematics.urdf import Joint, RobotDescription
from pipeline.measurement.pin import fit_pin_and_targets

#: rad (or m for a prismatic joint) beyond a URDF limit that counts as implausible
JOINT_MARGIN = 0.05
#: known distance vs the nominal robot's estimate: relative bound. 1 % refused a right bar
#: on a simulated 6-touch-up cell (bench_fleet seed 56: the nominal fit put the targets
#: 1.07 % apart from the bar with 1.2 mm RMS residual); no robot is 2 % off in scale
REL_TOL = 0.02
#: ... in units of the nominal fit's RMS residual
RESID_FACTOR = 3.0
#: ... and never tighter than this (m)
ABS_TOL_M = 2e-3
#: RMS residual (m) of the nominal fit beyond which joints and robot do not belong together
NOMINAL_RMS_MAX = 0.025
#: span (rad, or m for prismatic) above which a joint outside the chain counts as moving
JOINT_MOVE = 0.05
#: relative difference between the declared and the image-implied target diameter
DIAMETER_REL_TOL = 0.10


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

    :func:`pipeline.measurement.pin.fit_pin_and_targets` with the nominal chain.

    Returns
    -------
    pin : (3,) ; targets : (K, 3) ; rms : m
    """
    pin, targets, r = fit_pin_and_targets(chain, q, d, tk, K, sw)
    return pin, targets, float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


def known_distances(
    tg: F64, rho: float, distances: list[tuple[int, int, float]], labels: list[str]
) -> list[str]:
    """One line per known distance the nominal robot contradicts beyond ``tol``.

    Parameters
    ----------
    tg : (K, 3) targets and ``rho`` the RMS residual (m) of the nominal fit
        (:func:`nominal_targets`)
    distances : ``(k_a, k_b, metres)`` over the used targets ``0..K-1``
    labels : the targets' names
    """
    if not distances or len(tg) < 2:
        return []
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


def nominal_fit(rho: float) -> list[str]:
    """One line if the nominal robot fits these touch-ups worse than ``NOMINAL_RMS_MAX``.

    Parameters
    ----------
    rho : RMS residual (m) of the nominal fit (:func:`nominal_targets`)
    """
    if rho <= NOMINAL_RMS_MAX:
        return []
    return [
        f"the nominal robot fits these touch-ups to {1e3 * rho:.1f} mm RMS (pin and targets "
        f"solved at nominal kinematics), beyond the {1e3 * NOMINAL_RMS_MAX:.0f} mm an "
        "uncalibrated robot is off: check the joint columns (order, signs, zeros), the "
        "target labels and that the URDF is this robot's (if its mastering is known to be "
        "lost, this is expected)"
    ]


def _parent_joints(robot: RobotDescription) -> dict[str, Joint]:
    return {j.child: j for j in robot.joints.values()}


def _above(robot: RobotDescription, link: str) -> list[Joint]:
    """Joints between the URDF's root and ``link``."""
    parent_of, out = _parent_joints(robot), []
    while link in parent_of:
        out.append(parent_of[link])
        link = parent_of[link].parent
    return out


def _below(robot: RobotDescription, link: str) -> list[Joint]:
    """Joints of the subtree under ``link``."""
    out, todo = [], [link]
    while todo:
        here = todo.pop()
        for j in robot.joints.values():
            if j.parent == here:
                out.append(j)
                todo.append(j.child)
    return out


def joints_outside_chain(
    values: dict[str, F64],
    robot: RobotDescription,
    base_link: str,
    flange_link: str,
    over: str = "the touch-ups",
) -> list[str]:
    """One line per joint outside base -> flange whose touch-up values span > ``JOINT_MOVE``.

    Parameters
    ----------
    values : joint name -> (N,) values over the used touch-ups, for every column the
        table holds (joints of the chain and others)
    robot : the parsed URDF
    base_link, flange_link : the chain's ends
    over : what the values span, for the line ("the touch-ups", "the recording")
    """
    suspects = [(j, f"above the base link {base_link!r}") for j in _above(robot, base_link)]
    suspects += [
        (j, f"after the flange link {flange_link!r}")
        for j in _below(robot, flange_link)
        if j.type in ("revolute", "continuous")
    ]
    out = []
    for j, where in suspects:
        v = values.get(j.name)
        if v is None or not j.actuated:
            continue
        v = v[np.isfinite(v)]
        span = float(np.ptp(v)) if len(v) else 0.0
        if span > JOINT_MOVE:
            unit = "m" if j.type == "prismatic" else "rad"
            out.append(
                f"joint {j.name} moves (span {span:.3g} {unit} over {over}) but lies "
                f"{where}: the camera is fixed to the flange and the targets stand still, "
                "so check --base-link / --flange-link"
            )
    return out


def target_diameter(declared_m: float | None, implied_m: float | None) -> list[str]:
    """One line if the declared target diameter is ``DIAMETER_REL_TOL`` off the image's.

    Parameters
    ----------
    declared_m : ``target_diameter_m`` of the recording (or None)
    implied_m : ``s_0 / g`` from the image Jacobian (or None when unknown)
    """
    if declared_m is None or implied_m is None:
        return []
    if not (np.isfinite(declared_m) and np.isfinite(implied_m) and implied_m > 0):
        return []
    rel = declared_m / implied_m - 1.0
    if abs(rel) <= DIAMETER_REL_TOL:
        return []
    hint = (
        "in millimetres? the diameter is in metres"
        if 300.0 < declared_m / implied_m < 3000.0
        else "a typo, or another target set?"
    )
    return [
        f"target_diameter_m = {declared_m:.6g} m, but the image Jacobian implies "
        f"{implied_m:.4g} m ({100 * rel:+.0f} %, beyond {100 * DIAMETER_REL_TOL:.0f} %): {hint}"
    ]
