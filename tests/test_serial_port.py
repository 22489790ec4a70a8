"""Opening and closing serial lines (drivers/serial_port.py) on pyserial's loop:// URL."""
import logging
import threading

import pytest

pytest.importorskip("serial")

from tensortouch.contracts.errors import DeviceNotFoundError  # noqa: E402
from tensortouch.drivers.serial_port import close_serial, open_serial  # noqa: E402


def test_loop_url_echoes_and_close_stops_the_reader():
    port = open_serial("loop://", 115200, "gauge", "check the cable")
    port.write(b"1.25 N\r\n")
    assert port.readline() == b"1.25 N\r\n"
    stop = threading.Event()
    reader = threading.Thread(target=stop.wait)
    reader.start()
    close_serial(port, reader, stop, "gauge", logging.getLogger("t"))
    assert stop.is_set() and not reader.is_alive() and not port.is_open


def test_a_port_that_cannot_be_opened_is_one_error_naming_the_device(tmp_path):
    missing = str(tmp_path / "ttyUSB7")
    with pytest.raises(DeviceNotFoundError, match=rf"force gauge {missing}: cannot open .*; plug it in"):
        open_serial(missing, 9600, "force gauge", "plug it in")


def test_closing_a_port_that_is_gone_only_logs(caplog):
    class Gone:
        def close(self):
            raise OSError("device unplugged")

    stop = threading.Event()
    with caplog.at_level(logging.DEBUG, logger="t"):
        close_serial(Gone(), None, stop, "mocap", logging.getLogger("t"))
    assert stop.is_set() and "mocap: close: device unplugged" in caplog.text
