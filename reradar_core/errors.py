"""Precise exceptions raised by the core; only the service maps them to HTTP status codes."""

__all__ = [
    "shorten_echo",
    "MAX_ECHOED_CHARS",
    "ReRadarError",
    "ScanFormatError",
    "ScanTooLargeError",
    "PoseFileError",
    "TimeUnitError",
    "ConfigError",
    "MapFormatError",
    "ModelMismatchError",
    "DatasetError",
]


class ReRadarError(Exception):
    """Base class for every error the core raises on bad input or state."""


class ScanFormatError(ReRadarError, ValueError):
    """A radar scan file or array is corrupt, has the wrong shape, or holds non-finite values."""


class ScanTooLargeError(ScanFormatError):
    """A scan whose header declares more pixels, azimuths or range bins than are accepted (the service's 413)."""


class PoseFileError(ReRadarError, ValueError):
    """A pose file is malformed; the message names the file and line."""


class TimeUnitError(PoseFileError):
    """A pose file's times are relative and no unit was given. ``problem`` says what was found without the
    command-line advice of the message, for callers (the HTTP API) that offer other ways to give the unit."""

    def __init__(self, message: str, problem: str) -> None:
        super().__init__(message)
        self.problem = problem


class ConfigError(ReRadarError, ValueError):
    """A configuration value is invalid (unknown preset, negative size, ...)."""


class MapFormatError(ReRadarError, ValueError):
    """A keyframe map file is unreadable or has an unsupported schema."""


class ModelMismatchError(ReRadarError, ValueError):
    """A map was built with a different model than the one running (descriptors are incomparable)."""


class DatasetError(ReRadarError, ValueError):
    """A dataset sequence folder is missing, has an unknown layout, or lacks scans or poses."""


#: the most characters of a user's own text (a field name, a preset name) echoed back in an error
MAX_ECHOED_CHARS = 64


def shorten_echo(text: str, limit: int = MAX_ECHOED_CHARS) -> str:
    """``text`` cut to ``limit`` characters (the cut marked with "..." and the full length), for echoing a user's
    text in an error without answering a long name with a longer message."""
    return text if len(text) <= limit else f"{text[:limit]}...({len(text):,} characters)"

