"""Axes through a contact point cloud (tools/grasp/axis.py): line distance by hand, PCA, and the best
inlier axis that ignores a second object's points."""
import numpy as np
import pytest
from tensortouch.tools.grasp.axis import best_inlier_axis, line_distance, pca_axis


def test_line_distance_hand_worked():
    d = line_distance([[0, 3, 4], [5, 0, 0], [2, 1, 0]], np.zeros(3), np.array([1.0, 0, 0]))
    np.testing.assert_allclose(d, [5.0, 0.0, 1.0])


def test_pca_axis_of_points_on_a_line():
    t = np.linspace(-1, 1, 11)
    pts = np.outer(t, [0.6, 0.8, 0.0]) + [1.0, 2.0, 3.0]
    ax = pca_axis(pts)
    np.testing.assert_allclose(ax.point, [1.0, 2.0, 3.0], atol=1e-12)
    assert abs(ax.direction @ [0.6, 0.8, 0.0]) == pytest.approx(1.0)
    assert ax.inliers.all()
    with pytest.raises(ValueError, match="at least 2 points, got 1"):
        pca_axis(pts[:1])


def test_best_inlier_axis_keeps_the_line_and_drops_the_other_object():
    rng = np.random.default_rng(4)
    t = rng.uniform(-0.05, 0.05, 60)
    line = np.column_stack([t, np.zeros(60), np.zeros(60)]) + rng.normal(0, 0.001, (60, 3))
    blob = rng.normal([0.04, 0.04, 0.0], 0.003, (25, 3))        # another object 4 cm off the line
    pts = np.vstack([line, blob])
    ax = best_inlier_axis(pts, radius=0.01, rng=0)
    assert abs(ax.direction[0]) > 0.99
    assert ax.inliers[:60].all() and not ax.inliers[60:].any()
    assert abs(pca_axis(pts).direction[0]) < abs(ax.direction[0])   # PCA is pulled off by the blob
    with pytest.raises(ValueError, match="at least 2 points"):
        best_inlier_axis(pts[:1])
