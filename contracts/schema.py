"""Plausibility checks shared by every file format: a value's type, its range, its nesting depth.

A format's schema is its dataclass (field types) plus a table of declared ranges, or, for JSON
documents without a dataclass, explicit calls to `number` / `integer` / `numbers`. Every check
raises `SchemaError` naming the field by its dotted path and what was expected; the format's
loader re-raises it as its own error type (CalibrationError, RecipeError, ...), so the CLI prints
one line and exits 2.

    LIMITS = {"epochs": Range(1, 10_000), "lr": Range(0, 1, lo_open=True)}
    check_fields(BuildConfig, doc, "recipe.toml: build", LIMITS)

Types understood in dataclass fields: bool, int, float, str, X | None, list/tuple[X, ...],
tuple[X, Y, Z], a nested dataclass (a table), bare list/dict (type only). Integers never accept
floats (64.5 or 1e9 in an integer field is refused; TOML writes integers without a dot), floats
accept integers, and floats must be finite. A numeric field without a declared range is still
bounded: integers to 64 bits, floats to finite values (`undeclared_ranges` lists such fields so a
format's test can require a range for each).
"""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass

INT64 = (-(2 ** 63), 2 ** 63 - 1)
SEED_RANGE = (0, 2 ** 63 - 1)          # a random seed: non-negative and 64-bit
MAX_DEPTH = 32                         # deepest nesting of tables/arrays any of our documents needs
MAX_TEXT = 4096                        # longest string a configuration field holds


class SchemaError(ValueError):
    """A value outside its schema: the message names the field (dotted path) and what was expected."""


@dataclass(frozen=True)
class Range:
    """A closed interval [lo, hi]; `lo_open` excludes lo (for "> 0"). None = unbounded on that side."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False

    def holds(self, v) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return self.hi is None or v <= self.hi

    def __str__(self) -> str:
        def show(v):
            return str(v) if isinstance(v, int) else f"{v:g}"

        lo = "-inf" if self.lo is None else show(self.lo)
        hi = "inf" if self.hi is None else show(self.hi)
        return f"{'(' if self.lo_open or self.lo is None else '['}{lo}, {hi}{')' if self.hi is None else ']'}"


def _show(v) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def number(v, path: str, rng: Range | None = None, what: str = "a number") -> float:
    """A finite int or float inside `rng`; returns it as float."""
    if not _is_number(v):
        raise SchemaError(f"{path} is {_show(v)}, expected {what}{_in(rng)}")
    try:
        f = float(v)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise SchemaError(f"{path} is {_show(v)}, expected a finite number{_in(rng)}")
    if rng is not None and not rng.holds(f):
        raise SchemaError(f"{path} is {_show(v)}, expected {what} in {rng}")
    return f


def integer(v, path: str, rng: Range | tuple | None = None, what: str = "an integer") -> int:
    """An int (not bool, not float) inside `rng` (default: 64-bit)."""
    rng = Range(*rng) if isinstance(rng, tuple) else rng
    if not isinstance(v, int) or isinstance(v, bool):
        raise SchemaError(f"{path} is {_show(v)}, expected {what}{_in(rng)}")
    lo, hi = INT64
    if not lo <= v <= hi:
        raise SchemaError(f"{path} is {_show(v)}, expected {what} that fits 64 bits{_in(rng)}")
    if rng is not None and not rng.holds(v):
        raise SchemaError(f"{path} is {_show(v)}, expected {what} in {rng}")
    return v


def numbers(v, path: str, n: int, rng: Range | None = None, what: str = "numbers") -> list[float]:
    """A list of exactly `n` finite numbers, each inside `rng`."""
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise SchemaError(f"{path} is {_show(v)}, expected a list of {n} {what}{_in(rng)}")
    return [number(x, f"{path}[{i}]", rng) for i, x in enumerate(v)]


def text(v, path: str, choices: tuple | None = None, max_len: int = MAX_TEXT) -> str:
    if not isinstance(v, str):
        raise SchemaError(f"{path} is {_show(v)}, expected a string")
    if len(v) > max_len:
        raise SchemaError(f"{path} is {len(v)} characters long, expected at most {max_len}")
    if choices is not None and v not in choices:
        raise SchemaError(f"{path} is {_show(v)}, expected one of {', '.join(map(str, choices))}")
    return v


def _in(rng) -> str:
    return f" in {rng}" if rng is not None else ""


def check_depth(obj, path: str, limit: int = MAX_DEPTH) -> None:
    """Nesting of lists/tuples/dicts at most `limit` deep (iterative: no recursion to exhaust); the
    error names the field where the nesting goes too deep."""
    stack = [(obj, 0, "")]
    while stack:
        o, d, at = stack.pop()
        if isinstance(o, dict):
            children = [(v, f"{at}.{k}" if at else str(k)) for k, v in o.items()]
        elif isinstance(o, (list, tuple)):
            children = [(v, f"{at}[{i}]") for i, v in enumerate(o)]
        else:
            continue
        if d >= limit:
            head = at if len(at) <= 60 else at[:57] + "..."
            raise SchemaError(f"{path}: {head or 'the document'} is nested more than {limit} levels deep")
        stack.extend((c, d + 1, p) for c, p in children)


def finite_everywhere(obj, path: str = "") -> None:
    """Every float anywhere in a JSON-like tree (dicts, lists) is finite; else a SchemaError naming where."""
    stack = [(obj, path)]
    while stack:
        o, p = stack.pop()
        if isinstance(o, float) and not math.isfinite(o):
            raise SchemaError(f"{p} is {o!r}, expected a finite number")
        if isinstance(o, dict):
            stack.extend((v, f"{p}.{k}" if p else str(k)) for k, v in o.items())
        elif isinstance(o, list):
            stack.extend((v, f"{p}[{i}]") for i, v in enumerate(o))


def _union_args(tp) -> tuple | None:
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        return typing.get_args(tp)
    return None


def check_value(v, tp, path: str, rng=None):
    """`v` against the type `tp` (see the module docstring) and, for numbers, the range `rng`
    (a Range, an (lo, hi) tuple, or for strings a tuple of choices)."""
    if isinstance(rng, tuple) and rng and all(isinstance(c, str) for c in rng):
        return text(v, path, choices=rng) if v is not None or _union_args(tp) is None else None
    if isinstance(rng, tuple):
        rng = Range(*rng)
    args = _union_args(tp)
    if args is not None:
        if v is None and type(None) in args:
            return None
        real = [a for a in args if a is not type(None)]
        errors = []
        for a in real:
            try:
                return check_value(v, a, path, rng)
            except SchemaError as exc:
                errors.append(exc)
        raise errors[0] if len(real) == 1 else SchemaError(
            f"{path} is {_show(v)}, expected {' or '.join(_name(a) for a in args)}")
    if tp is typing.Any:
        return v
    if tp is bool:
        if not isinstance(v, bool):
            raise SchemaError(f"{path} is {_show(v)}, expected true or false")
        return v
    if tp is int:
        return integer(v, path, rng)
    if tp is float:
        return number(v, path, rng)
    if tp is str:
        return text(v, path)
    if dataclasses.is_dataclass(tp):
        if isinstance(v, tp):
            return v
        if not isinstance(v, dict):
            raise SchemaError(f"{path} is {_show(v)}, expected a table of {tp.__name__} fields")
        check_fields(tp, v, path)
        return v
    origin = typing.get_origin(tp) or tp
    if origin in (list, tuple):
        if not isinstance(v, (list, tuple)):
            raise SchemaError(f"{path} is {_show(v)}, expected a list")
        items = typing.get_args(tp)
        if items and not (len(items) == 2 and items[1] is Ellipsis) and origin is tuple:
            if len(v) != len(items):
                raise SchemaError(f"{path} has {len(v)} items, expected {len(items)}")
            for i, (x, t) in enumerate(zip(v, items)):
                check_value(x, t, f"{path}[{i}]", rng)
        elif items:
            for i, x in enumerate(v):
                check_value(x, items[0], f"{path}[{i}]", rng)
        check_depth(v, path)
        return v
    if origin is dict:
        if not isinstance(v, dict):
            raise SchemaError(f"{path} is {_show(v)}, expected a table")
        check_depth(v, path)
        return v
    return v


def _name(tp) -> str:
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string",
            type(None): "nothing (null)"}.get(tp, getattr(tp, "__name__", str(tp)))


def check_fields(cls, data: dict, where: str, limits: dict | None = None) -> None:
    """Every key of `data` that names a field of dataclass `cls`, by the field's type and its
    declared range in `limits` (field name -> Range, (lo, hi), or a tuple of allowed strings).
    Unknown keys are left to the caller (each format words that error its own way)."""
    hints = typing.get_type_hints(cls)
    limits = limits or {}
    for f in dataclasses.fields(cls):
        if f.name in data:
            check_value(data[f.name], hints[f.name], f"{where}.{f.name}" if where else f.name, limits.get(f.name))


def undeclared_ranges(cls, limits: dict) -> list[str]:
    """The int/float fields of `cls` (also inside X | None and tuples) without an entry in `limits`."""
    def numeric(tp) -> bool:
        if tp in (int, float):
            return True
        args = _union_args(tp) or (typing.get_args(tp) if typing.get_origin(tp) in (list, tuple) else ())
        return any(numeric(a) for a in args if a is not Ellipsis)

    hints = typing.get_type_hints(cls)
    return [f.name for f in dataclasses.fields(cls) if numeric(hints[f.name]) and f.name not in limits]
