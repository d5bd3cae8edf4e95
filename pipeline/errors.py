"""Error types and the exit codes the CLI maps them to (see README, "Exit codes")."""

from __future__ import annotations


class VtcalError(Exception):
    """Base of every error vtcal reports as one clear line."""

    exit_code = 1


class BadInput(VtcalError):
    """Input (file, message, value) is not what the spec says. Exit code 2."""

    exit_code = 2


class CalibrationFailed(VtcalError):
    """The calibration ran but cannot be trusted (too few touch-ups, ...). Exit code 3."""

    exit_code = 3


class ExportRefused(VtcalError):
    """A calibration cannot be written in the asked format (wrong robot kind). Exit code 3."""

    exit_code = 3


class CellFault(VtcalError):
    """The robot or camera failed during ``vtcal measure`` (lost connection, refused
    move, target not found, camera timeout); the recording so far is kept. Exit code 4."""

    exit_code = 4
