"""Tests of landmark_ros.core.ellipse: axes and contour points of 2D Gaussians."""

from conftest import random_points, random_spd
from landmark_ros.core.ellipse import ellipse_axes, ellipse_points
from landmark_ros.core.gating import mahalanobis_sq
import numpy as np
import pytest

PI = np.pi


def shoelace_area(points):
    """Return the signed area of polygons given as (..., n, 2) vertices."""
    x, y = points[..., 0], points[..., 1]
    return 0.5 * np.sum(x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y, axis=-1)


@pytest.mark.parametrize('P, major, minor, angle', [
    (np.diag([4.0, 1.0]), 2.0, 1.0, 0.0),
    (np.diag([1.0, 4.0]), 2.0, 1.0, PI / 2),
    (np.array([[2.0, 1.0], [1.0, 2.0]]), np.sqrt(3.0), 1.0, PI / 4),
    (np.array([[2.0, -1.0], [-1.0, 2.0]]), np.sqrt(3.0), 1.0, -PI / 4),
    (np.array([[1.0, 1.0], [1.0, 1.0]]), np.sqrt(2.0), 0.0, PI / 4),
    (np.zeros((2, 2)), 0.0, 0.0, None),
    (np.eye(2), 1.0, 1.0, None),
])
def test_ellipse_axes_known_values(P, major, minor, angle):
    for k in (1.0, 2.5):
        a, b, theta = ellipse_axes(P, k)
        assert np.shape(a) == np.shape(b) == np.shape(theta) == ()
        assert a == pytest.approx(k * major, abs=1e-12)
        assert b == pytest.approx(k * minor, abs=1e-12)
        assert np.isfinite(theta)
        if angle is not None:
            assert theta == pytest.approx(angle, abs=1e-12)


def test_ellipse_axes_match_eigh(rng):
    n = 300
    P = random_spd(rng, 2, n)
    v = rng.standard_normal((10, 2))
    P[:10] = v[:, :, None] * v[:, None, :]            # rank one
    P[10:20] = np.diag(rng.uniform(0.1, 2.0, 2))      # axis-aligned
    for k in (1.0, 2.0, np.sqrt(5.991464547107979)):
        major, minor, angle = ellipse_axes(P, k)
        assert major.shape == minor.shape == angle.shape == (n,)
        assert major.dtype == minor.dtype == angle.dtype == np.float64
        values, vectors = np.linalg.eigh(P)
        np.testing.assert_allclose(major, k * np.sqrt(values[:, 1]), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(minor, k * np.sqrt(np.maximum(values[:, 0], 0.0)),
                                   rtol=1e-9, atol=1e-7)
        assert np.all((angle > -PI / 2 - 1e-15) & (angle <= PI / 2 + 1e-15))
        # The angle points along the major eigenvector, up to its sign (modulo pi).
        direction = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
        distinct = values[:, 1] - values[:, 0] > 1e-6 * values[:, 1]
        cross = direction[:, 0] * vectors[:, 1, 1] - direction[:, 1] * vectors[:, 0, 1]
        np.testing.assert_allclose(cross[distinct], 0.0, atol=1e-6)
        assert distinct.sum() > n - 5


def test_ellipse_points_lie_on_the_contour(rng):
    n, num = 100, 50
    mean = random_points(rng, n)
    P = random_spd(rng, 2, n)
    for k in (1.0, 3.0):
        points = ellipse_points(mean, P, k, num_points=num)
        assert points.shape == (n, num, 2) and points.dtype == np.float64
        d2 = mahalanobis_sq(points.reshape(-1, 2), np.repeat(mean, num, axis=0),
                            np.repeat(P, num, axis=0))
        np.testing.assert_allclose(d2, k * k, rtol=1e-9)
        # The first point is at the end of the major axis; points are not repeated.
        major, minor, angle = ellipse_axes(P, k)
        np.testing.assert_allclose(
            points[:, 0], mean + major[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1),
            rtol=0, atol=1e-12 * (1.0 + np.abs(mean).max()))
        assert np.all(np.linalg.norm(points[:, -1] - points[:, 0], axis=-1) > 1e-3 * minor)
        # Counter-clockwise, and the exact area of an affine image of a regular polygon.
        expected = 0.5 * num * np.sin(2.0 * PI / num) * k * k * np.sqrt(np.linalg.det(P))
        np.testing.assert_allclose(shoelace_area(points - mean[:, None, :]), expected,
                                   rtol=1e-9)


def test_ellipse_points_single():
    points = ellipse_points([1.0, -2.0], np.diag([4.0, 1.0]), k=2.0, num_points=4)
    np.testing.assert_allclose(points, [[5.0, -2.0], [1.0, 0.0], [-3.0, -2.0], [1.0, -4.0]],
                               atol=1e-12)
    assert ellipse_points([0.0, 0.0], np.eye(2)).shape == (36, 2)


@pytest.mark.parametrize('P', [
    np.array([[1.0, 1.0], [1.0, 1.0]]),
    np.diag([0.0, 2.0]),
    np.zeros((2, 2)),
    np.outer([0.3, -0.7], [0.3, -0.7]) * (1.0 + 1e-16),
    np.array([[1e-8, 1e-4], [1e-4, 1.0]]),             # rank one with rounding
])
def test_singular_covariance_gives_a_degenerate_ellipse(P):
    major, minor, angle = ellipse_axes(P, 2.0)
    assert np.isfinite(major) and np.isfinite(minor) and np.isfinite(angle)
    assert minor == pytest.approx(0.0, abs=1e-6)
    points = ellipse_points([3.0, 4.0], P, 2.0, num_points=20)
    assert np.all(np.isfinite(points))
    # All points on the segment along the major axis, within +-major of the mean.
    offsets = points - [3.0, 4.0]
    direction = np.array([np.cos(angle), np.sin(angle)])
    along = offsets @ direction
    across = offsets @ np.array([-direction[1], direction[0]])
    np.testing.assert_allclose(across, 0.0, atol=1e-6)
    assert np.all(np.abs(along) <= major + 1e-12)
    assert np.max(along) == pytest.approx(major, abs=1e-12)


def test_batch_equals_loop(rng):
    n = 15
    mean, P = random_points(rng, n), random_spd(rng, 2, n)
    axes = ellipse_axes(P, 2.0)
    points = ellipse_points(mean, P, 2.0, num_points=12)
    for k in range(n):
        for batch_value, single_value in zip(axes, ellipse_axes(P[k], 2.0)):
            assert batch_value[k] == pytest.approx(single_value, rel=1e-15, abs=1e-15)
        np.testing.assert_allclose(points[k], ellipse_points(mean[k], P[k], 2.0, 12),
                                   rtol=1e-15, atol=1e-14)
    # A batch of one stays a batch.
    assert all(np.shape(value) == (1,) for value in ellipse_axes(P[:1]))
    assert ellipse_points(mean[:1], P[:1], num_points=12).shape == (1, 12, 2)
    # Single items broadcast against batches.
    one_mean = ellipse_points(mean[0], P, 2.0, num_points=12)
    one_P = ellipse_points(mean, P[0], 2.0, num_points=12)
    assert one_mean.shape == one_P.shape == (n, 12, 2)
    for k in range(n):
        np.testing.assert_allclose(one_mean[k], ellipse_points(mean[0], P[k], 2.0, 12),
                                   rtol=1e-15, atol=1e-14)
        np.testing.assert_allclose(one_P[k], ellipse_points(mean[k], P[0], 2.0, 12),
                                   rtol=1e-15, atol=1e-14)


def test_integer_inputs_give_float64():
    assert ellipse_points([1, 2], [[4, 0], [0, 1]]).dtype == np.float64
    assert all(np.asarray(v).dtype == np.float64 for v in ellipse_axes([[4, 1], [1, 1]]))


@pytest.mark.parametrize('P', [np.eye(3), np.ones(2), np.ones((2, 3)), np.ones((2, 2, 2, 2))])
def test_wrong_shapes_raise(P):
    with pytest.raises(ValueError, match='must have shape'):
        ellipse_axes(P)
    with pytest.raises(ValueError, match='must have shape'):
        ellipse_points([0.0, 0.0], P)


def test_wrong_mean_shape_raises():
    with pytest.raises(ValueError, match='must have shape'):
        ellipse_points([0.0, 0.0, 0.0], np.eye(2))
