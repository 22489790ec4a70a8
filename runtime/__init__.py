"""TensorTouch deploy runtime: camera frame -> baseline -> int8 ONNX -> fields -> contacts -> Zenoh.

Units at every boundary: mm, N, MPa (N/mm^2), s, degC. Angles in radians inside arrays.
This package imports only the standard library and the eight runtime dependencies.
"""

__version__ = "0.1.0"
