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


class BusInUseError(DeviceError):
    """Another process holds the Dynamixel port (the daemon, or a second command): one bus,
    one owner."""


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


class DescriptionError(ModelError):
    """A reference class's description says how the object feels instead of naming it."""


class VLMError(EdgeError):
    """The vision-language model could not give a valid answer."""


class ComputeError(EdgeError, RuntimeError):
    """The compute worker process died (a crash, the OOM killer) while doing the work."""


class BusyError(EdgeError, RuntimeError):
    """A press is already running; one press at a time."""

    def __init__(self, message: str, episode_id: str | None = None) -> None:
        super().__init__(message)
        self.episode_id = episode_id


class StateError(EdgeError, ValueError):
    """The named thing exists but its state does not allow this (HTTP 409)."""


class StoreError(EdgeError, OSError):
    """The episode store cannot write or read (disk full, permissions, corrupt entry)."""


class NotFoundError(EdgeError, KeyError):
    """A named thing (episode, pose, object) does not exist."""


class VLMUnavailableError(VLMError):
    """The VLM could not be reached or stayed busy after every retry: try again later."""


class VLMTimeoutError(VLMUnavailableError, TimeoutError):
    """No complete answer within ``total_timeout_s`` (or no connection in ``connect_timeout_s``)."""


class VLMConnectionError(VLMUnavailableError, ConnectionError):
    """Connection refused, reset or dropped before a complete answer."""


class VLMHTTPError(VLMError):
    """The server answered an HTTP error; ``status`` and a short ``excerpt`` of its body."""

    def __init__(self, message: str, status: int, excerpt: str = "") -> None:
        super().__init__(message)
        self.status = status
        self.excerpt = excerpt


class VLMServerError(VLMHTTPError, VLMUnavailableError):
    """408/409/429/5xx, still so after every retry."""


class VLMRejectedError(VLMHTTPError):
    """A status that is never retried (400, 401, 403, 404, 413, other 4xx, a redirect)."""


class VLMFormatRefusedError(VLMRejectedError):
    """The server refused the structured-output mode (``response_format``) it was sent."""


class VLMResponseError(VLMError, ValueError):
    """The server's 200 answer is unusable: not JSON, no choices, or an error object."""


class VLMResponseTooLargeError(VLMResponseError):
    """The response body is larger than ``max_response_bytes``."""


class SensorLayoutError(SensorError):
    """The server's sensors do not match the configured pads/taxels: fix the configuration."""


class PromptError(EdgeError, ValueError):
    """A prompt template is malformed, or the values to render into it are unusable."""


class ImageError(EdgeError, ValueError):
    """The image is not a usable JPEG/PNG (or cannot be brought under the size limits)."""


class EvalVLMError(EdgeError, RuntimeError):
    """The evaluation cannot start or had to stop; what is cached stays cached."""


class BadRequest(EdgeError, ValueError):
    """An API request the daemon refuses (HTTP 400): the message says what to change."""


class StartError(EdgeError, RuntimeError):
    """The daemon cannot start; the message is the one line a person needs to fix it."""


class PressRefusedError(EdgeError, RuntimeError):
    """A press stopped before the gripper closed: what it found makes the press meaningless
    (the object already touches the fingers)."""
