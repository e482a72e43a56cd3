"""Error hierarchy. Library code raises these; only ``workflows.cli`` turns them into exit codes."""

from __future__ import annotations


class FleetcalError(Exception):
    """Base of every error fleetcal raises on purpose (exit code 1 in the CLI)."""


class InputError(FleetcalError):
    """The input (a log, a message, a file) is missing, malformed or unusable."""


class ReaderError(InputError):
    """A log container cannot be opened or read."""


class TruncatedLogError(ReaderError):
    """A log ends early; ``recovered_messages`` were read before ``lost_bytes`` of damage."""

    def __init__(self, message: str, recovered_messages: int = 0, lost_bytes: int = 0) -> None:
        super().__init__(message)
        self.recovered_messages = recovered_messages
        self.lost_bytes = lost_bytes


class DecodeError(InputError):
    """A message's bytes cannot be decoded into a frame."""


class UnsupportedEncodingError(DecodeError):
    """An image or point encoding that fleetcal does not support."""


class TransformError(InputError):
    """A transform is missing from the tf tree or is not a valid rigid transform."""


class ConfigError(FleetcalError):
    """A configuration value is invalid.

    Attributes:
        key: the ``section.key`` whose value was rejected (None when the error is not about one key).
        reason: why the value was rejected, without the key (e.g. ``must be >= 1``).
        source: where the rejected value came from (a file, ``command line``...); None for a range check
            of the effective value (after every source was applied).
    """

    def __init__(
        self, message: str, key: str | None = None, reason: str | None = None, source: str | None = None
    ) -> None:
        super().__init__(message)
        self.key = key
        self.reason = reason or message
        self.source = source


class ProcessingError(FleetcalError):
    """An algorithm could not produce a result from valid input (no overlap, no points in view...)."""


class UsageError(FleetcalError):
    """Wrong command-line arguments (exit code 2 in the CLI)."""
