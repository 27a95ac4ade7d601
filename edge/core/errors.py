"""The project's exception hierarchy.

Everything the project raises on purpose derives from :class:`EdgeError`. Subclasses also
inherit the matching builtin, so callers that already catch ``TimeoutError`` or
``ValueError`` keep working.
"""

from __future__ import annotations


class EdgeError(Exception):
    """Root of every error raised on purpose by vtzero."""


class ConfigError(EdgeError, ValueError):
    """A configuration file or value is invalid; the message names the field."""


class RecordingError(EdgeError, ValueError):
    """A press recording is malformed, truncated or of an unknown schema."""


class PreprocessError(EdgeError, ValueError):
    """Tactile data cannot be turned into model input (e.g. the crop leaves the stream)."""


class DeviceError(EdgeError, OSError):
    """A hardware device (or its emulator) failed or answered wrongly."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """A device did not answer within its named timeout."""


class SensorError(DeviceError):
    """The tactile sensor stream is broken (bad frame, wrong layout)."""


class StaleSensorError(SensorError, TimeoutError):
    """No fresh tactile frame arrived within the stale timeout: never press on it."""


class MotorError(DeviceError):
    """A Dynamixel motor reported an error or did not answer."""

    def __init__(self, message: str, motor_id: int | None = None,
                 transient: bool = False) -> None:
        super().__init__(message)
        self.motor_id = motor_id
        # A lost or garbled reply (worth one more try), not a refusal by the motor.
        self.transient = transient


class ModelError(EdgeError, ValueError):
    """The encoder or reference database is missing, corrupt or inconsistent."""


class VLMError(EdgeError):
    """The vision-language model could not give a valid answer."""


class ComputeError(EdgeError, RuntimeError):
    """The compute worker process died (a crash, the OOM killer) while doing the work."""


class BusyError(EdgeError, RuntimeError):
    """A press is already running; one press at a time."""

    def __init__(self, message: str, episode_id: str | None = None) -> None:
        super().__init__(message)
        self.episode_id = episode_id


class StoreError(EdgeError, OSError):
    """The episode store cannot write or read (disk full, permissions, corrupt entry)."""


class NotFoundError(EdgeError, KeyError):
    """A named thing (episode, pose, object) does not exist."""
