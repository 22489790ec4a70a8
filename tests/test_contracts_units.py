"""Unit spellings and conversions (contracts/units.py)."""
import pytest
from tensortouch.contracts.units import convert, to_house


def test_unit_spellings():
    assert to_house("torque", "N·m") == (1e3, 0.0) and to_house("temperature", "°C") == (1.0, 0.0)
    assert to_house("length", "furlong") is None and to_house("force", "mm") is None
    assert convert(1500, "ms", "s") == pytest.approx(1.5) and convert(295.15, "K", "degC") == pytest.approx(22.0)
    assert convert(2.0, "N*m", "N*mm") == pytest.approx(2000.0)
    with pytest.raises(ValueError, match="cannot convert 'N' to 'mm'"):
        convert(1.0, "N", "mm")
