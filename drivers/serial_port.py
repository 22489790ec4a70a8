"""Opening a serial-line device (a real port, or a pyserial URL such as socket:// or loop://)."""
from __future__ import annotations

from ..contracts.errors import DeviceNotFoundError


def open_serial(url: str, baudrate: int, what: str, hint: str, timeout: float = 0.05):
    """pyserial's `serial_for_url`; a port that cannot be opened is one DeviceNotFoundError naming `what`."""
    import serial

    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceNotFoundError(f"{what} {url}: cannot open ({exc}); {hint}") from None


def close_serial(port, thread, stop, what: str, log) -> None:
    """Stop a reader thread (set `stop`, join) and close its port; closing an unplugged port may fail."""
    stop.set()
    if thread is not None:
        thread.join(timeout=2.0)
    if port is not None:
        try:
            port.close()
        except Exception as exc:  # noqa: BLE001 - nothing left to do for a port that is gone
            log.debug("%s: close: %s", what, exc)
