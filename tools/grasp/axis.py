"""Axes through a contact point cloud: the PCA principal axis and the RANSAC-like best inlier
axis (the 3D line with the most points within a radius, seed §III.N: 1 cm)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Axis:
    point: np.ndarray        # (3,) a point on the line
    direction: np.ndarray    # (3,) unit direction
    inliers: np.ndarray      # (N,) bool, points within the radius (all True for PCA)


def line_distance(points: np.ndarray, point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Distance of each point (N,3) to the line (point, unit direction)."""
    rel = np.asarray(points, float) - point
    return np.linalg.norm(rel - np.outer(rel @ direction, direction), axis=1)


def pca_axis(points: np.ndarray) -> Axis:
    """Centroid and first principal direction of the cloud."""
    P = np.asarray(points, float)
    if len(P) < 2:
        raise ValueError(f"pca_axis needs at least 2 points, got {len(P)}")
    c = P.mean(0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    return Axis(c, vt[0] / np.linalg.norm(vt[0]), np.ones(len(P), bool))


def best_inlier_axis(points: np.ndarray, radius: float = 0.01, trials: int = 500,
                     rng: np.random.Generator | int | None = 0) -> Axis:
    """RANSAC-like cylinder fit: lines through random point pairs, keep the one with the most
    points within `radius`, then refine it by PCA of its inliers (kept only if it does not lose
    inliers)."""
    P = np.asarray(points, float)
    n = len(P)
    if n < 2:
        raise ValueError(f"best_inlier_axis needs at least 2 points, got {n}")
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    i = rng.integers(0, n, trials)
    j = rng.integers(0, n, trials)
    keep = i != j
    a, b = P[i[keep]], P[j[keep]]
    d = b - a
    norm = np.linalg.norm(d, axis=1)
    ok = norm > 1e-12
    a, d = a[ok], d[ok] / norm[ok, None]
    if not len(a):
        return pca_axis(P)
    best, best_count = None, -1
    for start in range(0, len(a), 64):  # (lines × points) in blocks to bound memory
        A, D = a[start:start + 64], d[start:start + 64]
        rel = P[None, :, :] - A[:, None, :]
        along = np.einsum("lpk,lk->lp", rel, D)
        dist = np.linalg.norm(rel - along[..., None] * D[:, None, :], axis=2)
        counts = (dist <= radius).sum(1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best = int(counts[k]), (A[k], D[k])
    point, direction = best
    inl = line_distance(P, point, direction) <= radius
    if inl.sum() >= 2:
        ref = pca_axis(P[inl])
        inl_ref = line_distance(P, ref.point, ref.direction) <= radius
        if inl_ref.sum() >= inl.sum():
            point, direction, inl = ref.point, ref.direction, inl_ref
    return Axis(np.asarray(point), np.asarray(direction), inl)
