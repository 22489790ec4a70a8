"""User-facing errors. Each names the file/field at fault and what was expected.

The CLI prints them as one line (no traceback); the frame loop turns recoverable ones into status flags.
"""


class TensorTouchError(Exception):
    """Base class: a clear message meant for the person running the sensor."""


class ModelPackageError(TensorTouchError):
    """A model package is missing, corrupt or does not match what the runtime expects."""


class CalibrationError(TensorTouchError):
    """A calibration store entry is missing, corrupt or inconsistent."""


class SessionError(TensorTouchError):
    """A recorded session (real or twin) violates the session contract."""


class CaptureError(TensorTouchError):
    """A camera or replay source cannot deliver frames."""


class DeviceNotFoundError(CaptureError):
    """A device (camera by USB serial, force gauge, CAN interface) is not attached or not reachable."""


class CommandError(TensorTouchError):
    """A command-line option or argument is not what the command expects."""
