"""FE-specific errors, all subclasses of contracts.errors.TensorTouchError (printed as one line by the CLI)."""
from __future__ import annotations

from ...contracts.errors import TensorTouchError


class FEError(TensorTouchError):
    """Base class of every error raised by tools.fe."""


class ScenarioError(FEError):
    """An FE scenario file or object is invalid (names the field and what was expected)."""


class FEConvergenceError(FEError):
    """A load step did not converge. `partial` holds the FEResult of the frames solved so far
    (later frames flagged converged=False); it is never written as a normal result."""

    def __init__(self, message: str, partial=None):
        super().__init__(message)
        self.partial = partial


class FEResultError(FEError):
    """An FE result file is missing, corrupt or has inconsistent array shapes."""
