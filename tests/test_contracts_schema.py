"""The field checker (contracts/schema.py) on each kind of annotation it reads, with hand-worked values."""
from __future__ import annotations

import dataclasses

import pytest
from tensortouch.contracts.schema import Range


@dataclasses.dataclass
class Inner:
    k: int = 1


@dataclasses.dataclass
class Doc:
    n: int = 1
    x: float = 1.0
    opt: float | None = None
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    many: tuple[str, ...] = ()
    flag: bool = False
    inner: Inner = dataclasses.field(default_factory=Inner)


def test_schema_types_hand_worked():
    """contracts/schema.py on each kind of annotation it reads, with the values worked out by hand."""
    from tensortouch.contracts.schema import SchemaError, check_fields

    limits = {"n": Range(1, 10), "x": Range(0, 1, lo_open=True), "opt": Range(0, 5), "xyz": Range(-1, 1)}
    ok = {"n": 10, "x": 1, "opt": None, "xyz": [1, -1, 0.5], "many": ["a"], "flag": True, "inner": {"k": 3}}
    check_fields(Doc, ok, "d", limits)
    for bad, want in (({"n": 10.0}, "d.n is 10.0, expected an integer in [1, 10]"), ({"n": True}, "d.n is True"),
                      ({"n": 11}, "in [1, 10]"), ({"x": 0}, "d.x is 0, expected a number in (0, 1]"),
                      ({"x": 10 ** 400}, "expected a finite number"), ({"opt": 6.0}, "d.opt is 6.0"),
                      ({"xyz": [0, 0]}, "d.xyz has 2 items, expected 3"), ({"xyz": [0, 0, 2]}, "d.xyz[2] is 2"),
                      ({"many": [1]}, "d.many[0] is 1, expected a string"), ({"flag": 1}, "d.flag is 1, expected true"),
                      ({"inner": {"k": "3"}}, "d.inner.k is '3'"), ({"inner": 3}, "expected a table of Inner")):
        with pytest.raises(SchemaError) as info:
            check_fields(Doc, {**ok, **bad}, "d", limits)
        assert want in str(info.value), str(info.value)
