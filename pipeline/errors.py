"""Error types and the exit codes the CLI maps them to (see README, "Exit codes").

The ``EXIT_*`` constants are every status ``vtcal`` exits with; :data:`EXIT_CODES` says
what each means (``tests/test_exit_codes.py`` checks each is in README's table).
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_BAD_INPUT = 2
EXIT_FAILED = 3
EXIT_CELL_FAULT = 4
EXIT_CHANGED = 5
EXIT_INTERNAL = 70
EXIT_INTERRUPTED = 130

#: exit status -> what it means (README, "Exit codes")
EXIT_CODES: dict[int, str] = {
    EXIT_OK: "success",
    EXIT_ERROR: "a vtcal error not otherwise classified (`vtcal batch`: a recording did not "
    "finish)",
    EXIT_BAD_INPUT: "bad input (a file, message, option or value), named on one line",
    EXIT_FAILED: "the calibration ran but failed its checks, or a tolerance was not met",
    EXIT_CELL_FAULT: "`vtcal measure`/`calibrate`: a fault at the cell",
    EXIT_CHANGED: "a change found where asked to fail on one: `vtcal compare --fail-on-drift` "
    "(a parameter moved), `vtcal audit --fail-on-change` (a robot changed)",
    EXIT_INTERNAL: "internal error (a bug)",
    EXIT_INTERRUPTED: "interrupted",
}


class VtcalError(Exception):
    """Base of every error vtcal reports as one clear line."""

    exit_code = EXIT_ERROR


class BadInput(VtcalError):
    """Input (file, message, value) is not what the spec says. Exit code 2."""

    exit_code = EXIT_BAD_INPUT


class CalibrationFailed(VtcalError):
    """The calibration ran but cannot be trusted (too few touch-ups, ...). Exit code 3."""

    exit_code = EXIT_FAILED


class ExportRefused(VtcalError):
    """A calibration cannot be written in the asked format (wrong robot kind). Exit code 3."""

    exit_code = EXIT_FAILED


class CellFault(VtcalError):
    """The robot or camera failed during ``vtcal measure`` (lost connection, refused
    move, target not found, camera timeout); the recording so far is kept. Exit code 4."""

    exit_code = EXIT_CELL_FAULT
