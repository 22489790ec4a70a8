"""Physical units at the session boundary: the house system (mm, N, N*mm, s, degC, MPa, rad) and the
other spellings a recording may use, each as an affine map to the house unit (house = scale·v + offset).

A session whose manifest states, say, `"length": "m", "force": "mN"` is read in house units: every
stream column is converted when the table is loaded (contracts/session.py), so no later stage sees the
recording's own units. An unknown spelling is an error naming the field and the accepted spellings.
"""
from __future__ import annotations

import math

HOUSE = {"length": "mm", "force": "N", "torque": "N*mm", "time": "s", "temperature": "degC",
         "stress": "MPa", "angle": "rad"}

_LIN = {
    "length": {"mm": 1.0, "m": 1e3, "cm": 10.0, "um": 1e-3, "µm": 1e-3, "in": 25.4},
    "force": {"N": 1.0, "mN": 1e-3, "kN": 1e3},
    "torque": {"N*mm": 1.0, "N*m": 1e3, "Nm": 1e3, "mN*m": 1.0, "mN*mm": 1e-3},
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9},
    "stress": {"MPa": 1.0, "kPa": 1e-3, "Pa": 1e-6, "N/mm^2": 1.0, "GPa": 1e3},
    "angle": {"rad": 1.0, "deg": math.pi / 180.0},
}
_AFFINE = {"temperature": {"degC": (1.0, 0.0), "C": (1.0, 0.0), "K": (1.0, -273.15),
                           "degF": (5.0 / 9.0, -32.0 * 5.0 / 9.0)}}


def _spelling(unit: str) -> str:
    """'N·m', 'N m', 'N.m' → 'N*m'; '°C' → 'degC'; 'N/mm²' → 'N/mm^2'."""
    u = str(unit).strip().replace("·", "*").replace("⋅", "*").replace(" ", "*").replace(".", "*")
    return u.replace("°C", "degC").replace("°F", "degF").replace("²", "^2")


def accepted(quantity: str) -> list[str]:
    """The spellings accepted for a quantity (house unit first)."""
    table = _AFFINE.get(quantity) or _LIN.get(quantity) or {}
    return [HOUSE[quantity]] + sorted(k for k in table if k != HOUSE[quantity])


def to_house(quantity: str, unit: str) -> tuple[float, float] | None:
    """(scale, offset) taking values in `unit` to the house unit of `quantity`; None if not known."""
    u = _spelling(unit)
    if quantity in _AFFINE:
        return _AFFINE[quantity].get(u)
    s = _LIN.get(quantity, {}).get(u)
    return None if s is None else (s, 0.0)


def convert(value: float, unit: str, to_unit: str) -> float:
    """`value` in `unit` expressed in `to_unit` (both spellings of one quantity in the tables above);
    ValueError naming both units when they are not."""
    if _spelling(unit) == _spelling(to_unit):
        return float(value)
    for quantity in HOUSE:
        a, b = to_house(quantity, unit), to_house(quantity, to_unit)
        if a is not None and b is not None:
            return (float(value) * a[0] + a[1] - b[1]) / b[0]
    raise ValueError(f"cannot convert {unit!r} to {to_unit!r}")
