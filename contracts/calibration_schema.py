"""The plausibility schema of calibration.json: values that are not only finite but could describe a sensor.

contracts/store.py checks the document's shape (fields present, types, hashes, table shapes and
table values) and then calls `check_calibration` for what ties the numbers to the sensor:

- `camera` {width, height}: integers in CAMERA_PX. When present, the gel circle must fit that image:
  its centre inside the frame, its radius between MIN_RADIUS_PX and the frame's long side. Without
  it (older versions), the centre must lie in [0, CAMERA_PX.hi] and the radius in
  [MIN_RADIUS_PX, CAMERA_PX.hi]; the runtime then checks the circle against the real frame before
  using it (runtime/stages/preprocess.py `Preprocessor.prepare`).
- `model_size`: the θ/φ tables' grid, integers in MODEL_PX (the model must have the same input size:
  checked where the model meets the calibration, runtime/pipeline.py).
- `gel` (the gel's design geometry, mm): each length of GEL_MM a finite number in its range (> 0
  where a length cannot be 0), `shape` one of GEL_SHAPES; other keys are notes.
- anywhere in the document: no NaN or infinity (JSON's NaN/Infinity extensions), no nesting deeper
  than schema.MAX_DEPTH, `effects` a list of objects, `created` and `version` strings,
  `schema_version` >= 0.

Every problem is one CalibrationError naming the file and the field.
"""
from __future__ import annotations

from .errors import CalibrationError
from .schema import MAX_DEPTH, Range, SchemaError, check_depth, finite_everywhere, integer, number, numbers, text

CAMERA_PX = Range(16, 16384)            # camera image width / height, px
MODEL_PX = Range(8, 2048)               # model_size (table grid) H / W
MIN_RADIUS_PX = 8.0                     # a gel circle smaller than this cannot hold a model grid
GEL_SHAPES = ("dome", "flattened_dome")
# design lengths of a fingertip gel (mm): the paper's is 12 / 6 / 2, a sphere of 15 mm centred 7 mm low
GEL_MM = {"base_radius_mm": Range(0, 200, lo_open=True), "cap_height_mm": Range(0, 200, lo_open=True),
          "skirt_mm": Range(0, 200), "radius_mm": Range(0, 1000, lo_open=True),
          "center_z_mm": Range(-1000, 1000), "height_mm": Range(0, 200, lo_open=True)}


def check_calibration(meta: dict, where: str) -> None:
    """Raise CalibrationError when a field of calibration.json (already type-checked by the store)
    is implausible for a sensor; see the module docstring for the rules."""
    try:
        _check(meta)
    except SchemaError as exc:
        raise CalibrationError(f"{where}: {exc}") from None




def _check(meta: dict) -> None:
    check_depth(meta, "calibration.json", MAX_DEPTH)
    finite_everywhere(meta, "")
    if "schema_version" in meta:
        integer(meta["schema_version"], "schema_version", Range(0, None), what="a version number >= 0")
    for key in ("created", "version"):
        if meta.get(key) is not None:
            text(meta[key], key, max_len=64)
    h, w = meta["model_size"]
    integer(h, "model_size[0]", MODEL_PX)
    integer(w, "model_size[1]", MODEL_PX)
    cam = meta.get("camera")
    if cam is not None:
        if not isinstance(cam, dict) or not {"width", "height"} <= set(cam):
            raise SchemaError(f"camera is {cam!r}, expected {{\"width\": W, \"height\": H}} (px)")
        cw = integer(cam["width"], "camera.width", CAMERA_PX)
        ch = integer(cam["height"], "camera.height", CAMERA_PX)
        cx_rng, cy_rng, r_rng = Range(0, cw), Range(0, ch), Range(MIN_RADIUS_PX, max(cw, ch))
        frame = f" of the {cw}x{ch} camera image"
    else:
        cx_rng = cy_rng = Range(0, CAMERA_PX.hi)
        r_rng = Range(MIN_RADIUS_PX, CAMERA_PX.hi)
        frame = ""
    cx, cy = numbers(meta["gel_center_px"], "gel_center_px", 2)
    if not (cx_rng.holds(cx) and cy_rng.holds(cy)):
        raise SchemaError(f"gel_center_px is [{cx:.6g}, {cy:.6g}], expected the gel centre inside the image{frame} "
                          f"(x in {cx_rng}, y in {cy_rng})")
    number(meta["gel_radius_px"], "gel_radius_px", r_rng,
           what=f"a gel radius (px) between {MIN_RADIUS_PX:g} and the image's long side{frame}")
    gel = meta.get("gel")
    if gel is not None:
        if not isinstance(gel, dict):
            raise SchemaError(f"gel is {gel!r}, expected an object of the gel's design lengths (mm)")
        if "shape" in gel:
            text(gel["shape"], "gel.shape", GEL_SHAPES)
        for key, v in gel.items():
            if key in GEL_MM:
                number(v, f"gel.{key}", GEL_MM[key], what="a length in mm")
    effects = meta.get("effects")
    if effects is not None and not all(isinstance(e, dict) for e in effects):
        raise SchemaError("effects must be a list of objects {\"name\": ..., \"params\": {...}}")
