"""Yoshikawa's manipulability w = √det(J Jᵀ) (seed §III.N).

Which rows of J: the positional 3×n block (linear velocity of the fingertip point in the world
frame). A fingertip sensor needs to *place* its contact point; with n = 4 finger joints the full
6×n Jacobian has rank ≤ 4 < 6, so det(J Jᵀ) of the 6×6 product is zero up to round-off (~1e-23 and
below: the seed's "discard below 1e-23" threshold is this round-off). The 3×n block is
full-rank away from singularities and w is then the volume of the velocity ellipsoid (m³/s per
rad³ for a 3-row J)."""
from __future__ import annotations

import numpy as np


def manipulability(J: np.ndarray) -> np.ndarray:
    """w = √det(J Jᵀ) for J (..., m, n), m ≤ n; 0 where the product is singular."""
    J = np.asarray(J, dtype=np.float64)
    JJ = J @ np.swapaxes(J, -1, -2)
    det = np.linalg.det(JJ)
    return np.sqrt(np.clip(det, 0.0, None))
