"""Opening a serial-line device (a real port, or a pyserial URL such as socket:// or loop://)."""
from __future__ import annotations

from runtime.errors import DeviceNotFoundError


def open_serial(url: str, baudrate: int, what: str, hint: str, timeout: float = 0.05):
    """pyserial's `serial_for_url`; a port that cannot be opened is one DeviceNotFoundError naming `what`."""
    import serial

    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceNotFoundError(f"{what} {url}: cannot open ({exc}); {hint}") from None
