"""TensorTouch: calibrated optical tactile sensing (fields, contacts and wrench from a fisheye gel sensor).

One namespace for the house's folders: `tensortouch.contracts`, `tensortouch.drivers`,
`tensortouch.runtime`, `tensortouch.tools`. An installed wheel holds them under this package
(pyproject.toml maps them); in a source checkout they stay where the design card puts them, at the
repository root, and are found there.
"""
import os as _os

_here = _os.path.dirname(_os.path.abspath(__file__))
_root = _os.path.dirname(_here)
if not _os.path.isdir(_os.path.join(_here, "runtime")) and _os.path.isfile(_os.path.join(_root, "runtime", "__init__.py")):
    __path__.append(_root)  # noqa: F821 (the package's own search path)
