"""Typed errors that carry the context a user needs to fix the problem.

Every error the service or the CLI reports to a person derives from :class:`CompanionError`. Its
``str()`` is one line that names what was wrong (the file, the field path, the bad value), so the CLI
can print it as-is with exit code 2 and the daemon can put it in its health message.
"""

from __future__ import annotations

from typing import Any


class CompanionError(Exception):
    """Base class of every error this package raises on purpose.

    Args:
        message: One line saying what is wrong and, where it helps, how to fix it.
        **context: Extra facts (path, field, value, ...) kept for logs and health messages.
    """

    def __init__(self, message: str, **context: Any) -> None:
        super().__init__(message)
        self.message = message
        self.context = context

    def __str__(self) -> str:
        return self.message


class ConfigError(CompanionError):
    """A configuration file or patch is invalid (unknown key, wrong type, out of bounds)."""


class CalibrationError(CompanionError):
    """A calibration file is unreadable, inconsistent, or for another resolution than the frame's."""


class FrameError(CompanionError):
    """A camera frame is unusable: wrong shape or dtype, odd side-by-side width, left/right mismatch."""


class InputError(CompanionError):
    """A file given on the command line could not be read or decoded."""


class CameraError(CompanionError):
    """The camera could not be opened, or stopped delivering frames."""


class VehicleError(CompanionError):
    """The vehicle link failed: no autopilot, a rejected command, a lost connection."""


class BackendError(CompanionError):
    """A disparity backend cannot run here (e.g. ``cupy`` asked for on a machine without CUDA)."""


class ProtocolError(CompanionError):
    """A control-plane message is malformed or names an unknown command."""
