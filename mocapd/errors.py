"""The one exception hierarchy of mocapd.

::

    MocapdError
    ├── InputError            a caller passed a mis-shaped or non-finite array (names the input and shape)
    ├── ConfigError           a configuration key or value is invalid (names the key, value and what is allowed)
    ├── CalibrationError      a calibration could not be computed or loaded
    ├── ModelError            a model (pose prior, detector) is missing, malformed or incompatible
    ├── ProtocolError         a wire protocol was violated in a way a parser cannot just count and skip
    ├── OutputError           an output path cannot be written (a missing folder, a directory, a device, an input
    │                         of the same command, an existing file without --force, a write that failed)
    ├── DeviceError           a camera, IMU or port failed (open, configure, stream)
    │   └── DeviceTimeout     a device did not answer in time
    ├── ToolError             an external program mocapd runs (Blender, for FBX) is missing or failed
    └── RateLimitError        a request came sooner than its rate limit allows (HTTP 429; a heading reset flood)

Parsers never raise on bad bytes: they count and resynchronise. Solvers never raise on numerical failure: they
report it in their summary and keep the previous pose. These exceptions are for callers that passed something
that cannot be used at all.
"""

from __future__ import annotations


class MocapdError(Exception):
    """Base class of every error raised by mocapd."""


class InputError(MocapdError, ValueError):
    """An array argument has the wrong shape, dtype or non-finite values."""


class ConfigError(MocapdError, ValueError):
    """A configuration key or value is invalid."""


class CalibrationError(MocapdError):
    """A calibration could not be computed or loaded."""


class ModelError(MocapdError):
    """A model file is missing, malformed or incompatible."""


class ProtocolError(MocapdError):
    """A wire protocol was violated beyond what a parser can count and skip."""


class OutputError(MocapdError):
    """An output path a command was given cannot be written (checked before the work starts)."""


class DeviceError(MocapdError):
    """A hardware device (camera, IMU, port) failed."""


class DeviceTimeout(DeviceError, TimeoutError):  # noqa: N818 (reads as a state, like TimeoutError)
    """A device did not answer within its time-out."""


class ToolError(MocapdError):
    """An external program mocapd runs (Blender, for the FBX export) is missing, failed or timed out."""


class RateLimitError(MocapdError):
    """A request came sooner than its rate limit allows (the status server answers 429 with ``Retry-After``)."""

    def __init__(self, message: str, retry_after_s: float) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s
