"""The schema of a model package's manifest.json (docs/model_package.md): types and plausible ranges.

runtime/stages/model.py `load_package` calls `check_manifest` before it looks at any file, then
checks `runtime.contacts` against the runtime's ContactConfig and the files' hashes. Checked here:

- `schema_version` >= 1 (load_package refuses newer ones), `name` (when present) and `created` strings; no NaN or infinity anywhere, nesting at most
  schema.MAX_DEPTH deep;
- `input`: `size` [H, W] integers in INPUT_PX; `channels` the six names of contracts.fields
  INPUT_CHANNELS in order; `dtype` "float32"; `layout` "NCHW"; `range` two finite numbers lo < hi;
- `output`: `channels` the 15 of docs/fields.md in order, `units` (when present) theirs,
  `size` (when present) the input's, `normalization` (when present) "minmax", `bounds` one
  [lo, hi] per channel, finite numbers within ±BOUND_LIMIT with lo <= hi.

Every problem is one ModelPackageError naming the manifest and the field.
"""
from __future__ import annotations

from .errors import ModelPackageError
from .fields import CHANNEL_UNITS, CHANNELS, INPUT_CHANNELS
from .schema import MAX_DEPTH, Range, SchemaError, check_depth, finite_everywhere, integer, number, text

INPUT_PX = Range(8, 2048)           # model input H / W (the calibration tables' grid)
BOUND_LIMIT = 1e6                   # |bound| in mm or MPa: far beyond any gel
DTYPES = ("float32",)
LAYOUTS = ("NCHW",)


def check_manifest(m: dict, where) -> None:
    """ModelPackageError("<where>: <field> ...") for the first field outside the schema."""
    try:
        _check(m)
    except SchemaError as exc:
        raise ModelPackageError(f"{where}: {exc}") from None




def _exact_list(v, path: str, names: tuple) -> None:
    if not (isinstance(v, list) and len(v) == len(names) and all(isinstance(x, str) for x in v)) \
            or tuple(v) != names:
        raise SchemaError(f"{path} is {str(v)[:80]}, expected the {len(names)} names {list(names)} in order")


def _check(m: dict) -> None:
    check_depth(m, "manifest", MAX_DEPTH)
    finite_everywhere(m)
    integer(m.get("schema_version"), "schema_version", Range(1, None), what="a version number >= 1")
    if "name" in m:
        text(m["name"], "name", max_len=200)
    if m.get("created") is not None:
        text(m["created"], "created", max_len=64)
    inp, out = m["input"], m["output"]
    size = inp.get("size")
    if not (isinstance(size, list) and len(size) == 2):
        raise SchemaError(f"input.size is {size!r}, expected [H, W] positive integers")
    for i, v in enumerate(size):
        integer(v, f"input.size[{i}]", INPUT_PX, what="a positive integer")
    _exact_list(inp.get("channels"), "input.channels", INPUT_CHANNELS)
    if "dtype" in inp:
        text(inp["dtype"], "input.dtype", DTYPES)
    if "layout" in inp:
        text(inp["layout"], "input.layout", LAYOUTS)
    if "range" in inp:
        rng = inp["range"]
        if not (isinstance(rng, list) and len(rng) == 2):
            raise SchemaError(f"input.range is {rng!r}, expected [lo, hi]")
        lo, hi = (number(v, f"input.range[{i}]", Range(-1e6, 1e6)) for i, v in enumerate(rng))
        if not lo < hi:
            raise SchemaError(f"input.range is {rng!r}, expected lo < hi")
    _exact_list(out.get("channels"), "output.channels", CHANNELS)
    if "units" in out:
        _exact_list(out["units"], "output.units", CHANNEL_UNITS)
    if "size" in out and out["size"] != size:
        raise SchemaError(f"output.size is {str(out['size'])[:40]}, expected the input size {size}")
    if "layout" in out:
        text(out["layout"], "output.layout", LAYOUTS)
    if "normalization" in out:
        text(out["normalization"], "output.normalization", ("minmax",))
    bounds = out.get("bounds")
    if not isinstance(bounds, dict):
        raise SchemaError("output.bounds must be an object {channel: [lo, hi]}")
    lim = Range(-BOUND_LIMIT, BOUND_LIMIT)
    for c in CHANNELS:
        b = bounds.get(c)
        if not (isinstance(b, list) and len(b) == 2):
            raise SchemaError(f"output.bounds.{c} is {str(b)[:40]}, expected [lo, hi] finite with lo <= hi")
        lo, hi = (number(v, f"output.bounds.{c}[{i}]", lim) for i, v in enumerate(b))
        if not lo <= hi:
            raise SchemaError(f"output.bounds.{c} is {b!r}, expected [lo, hi] finite with lo <= hi")
