"""core.range_scale: the range scale error of a sensor, its correction and Jacobian."""

from landmark_ros.core import range_scale
import numpy as np
import pytest

COEFFS = (0.047, -0.0044, -0.4675)
PER_M = -0.0034


def readings(rng, n=200):
    """Return readings over a camera's field of view, shape (n, 2)."""
    return np.stack([rng.uniform(0.5, 7.0, n), rng.uniform(-0.6, 0.6, n)], axis=1)


def test_default_is_the_identity(rng):
    z = readings(rng)
    z_c, J = range_scale.correct(z)
    np.testing.assert_array_equal(z_c, z)
    np.testing.assert_array_equal(J, np.broadcast_to(np.eye(2), J.shape))
    assert range_scale.is_identity(range_scale.IDENTITY, 0.0)
    assert not range_scale.is_identity((0.0, 0.0, 1e-3), 0.0)
    assert not range_scale.is_identity(range_scale.IDENTITY, 1e-3)


def test_the_correction_inverts_the_model(rng):
    z = readings(rng)
    z_c, _ = range_scale.correct(z, COEFFS, PER_M)
    g = 1.0 + COEFFS[0] + COEFFS[1] * z[:, 1] + COEFFS[2] * z[:, 1] ** 2 + PER_M * z[:, 0]
    np.testing.assert_allclose(z_c[:, 0] * g, z[:, 0], rtol=1e-14)
    np.testing.assert_array_equal(z_c[:, 1], z[:, 1])
    np.testing.assert_allclose(range_scale.scale(z, COEFFS, PER_M), g, rtol=1e-15)


def test_jacobian_against_central_differences(rng):
    z = readings(rng, 50)
    _, J = range_scale.correct(z, COEFFS, PER_M)
    step = 1e-6
    for col in range(2):
        dz = np.zeros(2)
        dz[col] = step
        plus, _ = range_scale.correct(z + dz, COEFFS, PER_M)
        minus, _ = range_scale.correct(z - dz, COEFFS, PER_M)
        np.testing.assert_allclose(J[:, :, col], (plus - minus) / (2 * step), rtol=0,
                                   atol=1e-8)


def test_single_reading_keeps_its_shape():
    z_c, J = range_scale.correct(np.array([3.0, 0.5]), COEFFS, PER_M)
    assert z_c.shape == (2,) and J.shape == (2, 2)
    batch, J_b = range_scale.correct(np.array([[3.0, 0.5]]), COEFFS, PER_M)
    np.testing.assert_array_equal(batch[0], z_c)
    np.testing.assert_array_equal(J_b[0], J)


def test_noise_is_propagated_through_the_jacobian(rng):
    z = readings(rng, 20)
    R = np.diag([0.01, 0.0004])
    z_c, R_c = range_scale.correct_with_noise(z, R, COEFFS, PER_M)
    _, J = range_scale.correct(z, COEFFS, PER_M)
    np.testing.assert_allclose(R_c, J @ R @ J.transpose(0, 2, 1), rtol=1e-15)
    assert R_c.shape == (20, 2, 2)
    assert np.all(np.linalg.eigvalsh(R_c) > 0.0)


def test_outside_the_model_is_refused():
    with pytest.raises(ValueError, match='below'):
        range_scale.correct(np.array([[3.0, 2.0]]), COEFFS, PER_M)
    with pytest.raises(ValueError, match='3 values'):
        range_scale.correct(np.array([[3.0, 0.0]]), (0.1, 0.2), 0.0)


def test_range_only_rows_give_nan_not_an_error():
    z_c, _ = range_scale.correct(np.array([[3.0, np.nan]]), COEFFS, PER_M)
    assert np.isnan(z_c[0, 0])
