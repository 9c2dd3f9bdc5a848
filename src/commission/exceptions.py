"""The exception tree of drive-commission.

Every error the tool raises on purpose derives from :class:`CommissionError`;
lower-level errors (python-can, canopen, pyserial, pydantic, OS errors) are
re-raised as one of these with ``raise ... from err`` so the cause is kept::

    CommissionError
     +-- ConfigError                  invalid or unknown setting in a config file
     +-- RecordingError               a Recording that cannot be used (shape, NaN, timing)
     |    +-- LogFormatError          missing, empty, corrupt MCAP / CSV input
     +-- DriveError                   anything the drive or its link reports
     |    +-- DriveTimeout            (also TimeoutError) no answer in time
     |    +-- DriveFault              the drive entered its Fault state
     |    +-- DriveNotFound           (also FileNotFoundError) unknown or missing port
     +-- SafetyLimitExceeded          excitation or response outside the envelope
     +-- IdentificationError          the data cannot give a trustworthy model
     +-- OutputError                  an output file cannot be written
     +-- Aborted                      the user pressed Ctrl-C

The CLI prints ``str(err)`` as a single line and exits with ``err.exit_code``.
"""

from __future__ import annotations


class CommissionError(Exception):
    """Base class of every error raised by drive-commission on purpose."""

    exit_code: int = 1


class ConfigError(CommissionError):
    """A configuration file or option is invalid."""

    exit_code = 2


class RecordingError(CommissionError):
    """A Recording is malformed (length mismatch, NaN, non-uniform time…)."""

    exit_code = 3


class LogFormatError(RecordingError):
    """A log file (MCAP or CSV) is missing, empty, corrupt or incomplete."""


class DriveError(CommissionError):
    """The drive, or the link to it, reported an error."""

    exit_code = 4


class DriveTimeout(DriveError, TimeoutError):
    """The drive did not answer in time."""


class DriveFault(DriveError):
    """The drive is in its Fault state.

    :param code: the drive's error code (CiA 402 0x603F style), 0 if unknown.
    """

    def __init__(self, message: str, code: int = 0) -> None:
        super().__init__(message)
        self.code = code


class DriveNotFound(DriveError, FileNotFoundError):
    """The port does not exist or no backend serves it."""


class SafetyLimitExceeded(CommissionError):
    """The excitation, or the measured response, leaves the safety envelope."""

    exit_code = 5


class IdentificationError(CommissionError):
    """The data cannot give a trustworthy identification."""

    exit_code = 6


class OutputError(CommissionError):
    """An output file (log, result) cannot be written."""

    exit_code = 7


class Aborted(CommissionError):
    """The user interrupted the run (Ctrl-C, SIGTERM, SIGHUP)."""

    exit_code = 130
