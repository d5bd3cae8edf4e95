"""How well a fit's parameters are determined, said in words (the conditioning note)."""

from __future__ import annotations

#: condition number of the scaled, reduced identification Jacobian above which a run warns
COND_WARN = 1e4


def conditioning_note(not_excited: list[str], n_structural: int, cond: float) -> tuple[str, bool]:
    """What the identification's conditioning says, and whether it is a warning.

    The touch-ups' own pivoted QR (``data_tol``) holds the structurally
    identifiable parameters they fail to excite at nominal, so the fitted problem
    stays solvable; what those parameters do to the robot is then simply not
    calibrated. That, or a condition number above :data:`COND_WARN` (the
    sample's 18 touch-ups give 800-1,200), is worth a line.

    Parameters
    ----------
    not_excited : names of the structurally identifiable parameters held for lack of excitation
    n_structural : number of structurally identifiable parameters
    cond : condition number of the scaled identification Jacobian of the fitted parameters
    """
    if not not_excited and cond <= COND_WARN:
        return f"every identifiable parameter excited (cond {cond:.3g})", False
    parts = []
    if not_excited:
        names = ", ".join(not_excited[:6]) + (", ..." if len(not_excited) > 6 else "")
        parts.append(
            f"{len(not_excited)} of {n_structural} identifiable parameters are not excited by "
            f"these touch-ups and stay at nominal ({names})"
        )
    if cond > COND_WARN:
        parts.append(f"cond {cond:.3g} > {COND_WARN:.0e}")
    return (
        "; ".join(parts) + ": add touch-ups in more varied arm orientations (`vtcal plan` "
        "chooses well-conditioned poses)",
        True,
    )
