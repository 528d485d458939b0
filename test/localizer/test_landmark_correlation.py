"""The localizer's update with the landmarks of one update correlated in any way."""

from dataclasses import replace

from landmark_ros.core import sensors
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
from landmark_ros.localizer.update import (landmark_bound, RANGE_BEARING, update,
                                           UpdateSettings)
import numpy as np
import pytest

ONE_STEP = UpdateSettings(1e9, 1e9, 'split_ci', iterate_threshold=1e9, max_iterations=1)


def _spd(rng, n, scale):
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + np.eye(n) * scale ** 2 * 0.1


def _orthonormal_rows(rng, rows, dim):
    """Return ``rows`` orthonormal rows of length ``dim`` (random)."""
    Q, _ = np.linalg.qr(rng.normal(size=(dim, dim)))
    return Q[:rows]


def _joint(rng, blocks, common=False):
    """
    Return a joint covariance with the given diagonal blocks and random cross blocks.

    Each block is ``L_i u_i`` with ``Cov(u_i) = I``: the rows of ``u_i`` are
    orthonormal combinations of one standard normal vector, so the cross blocks
    ``L_i Q_i Q_j^T L_j^T`` are those of a valid joint. ``common``: all 2x2 blocks
    take the same combination (one error shared by every landmark).
    """
    dim = sum(len(b) for b in blocks)
    shared = _orthonormal_rows(rng, 2, dim)
    factors = []
    for b in blocks:
        L = np.linalg.cholesky(b)
        Q = shared if common and len(b) == 2 else _orthonormal_rows(rng, len(b), dim)
        factors.append(L @ Q)
    F = np.vstack(factors)
    return F @ F.T


def _block_diag(blocks):
    n = sum(len(b) for b in blocks)
    out, k = np.zeros((n, n)), 0
    for b in blocks:
        out[k:k + len(b), k:k + len(b)] = b
        k += len(b)
    return out


def test_the_bound_holds_for_any_correlation_and_the_plain_blocks_do_not():
    rng = np.random.default_rng(1)
    for trial in range(200):
        M = np.array([_spd(rng, 2, rng.uniform(0.01, 1.0)) for _ in range(rng.integers(2, 7))])
        joint = _joint(rng, list(M), common=trial % 2 == 0)
        gap = _block_diag(list(landmark_bound(M))) - joint
        assert np.linalg.eigvalsh(gap)[0] >= -1e-12 * np.abs(joint).max()
    # one error shared by two equal landmarks: the plain blocks miss half of it
    M = np.array([np.eye(2), np.eye(2)])
    joint = np.kron(np.ones((2, 2)), np.eye(2))
    assert np.linalg.eigvalsh(_block_diag(list(M)) - joint)[0] < -0.9
    assert np.linalg.eigvalsh(_block_diag(list(landmark_bound(M))) - joint)[0] > -1e-12


def test_one_row_and_rows_without_map_term():
    M = np.array([[[0.3, 0.1], [0.1, 0.2]]])
    assert landmark_bound(M) is M
    M = np.array([[[0.3, 0.1], [0.1, 0.2]], np.zeros((2, 2)), [[0.1, 0.0], [0.0, 0.1]]])
    bound = landmark_bound(M)
    assert np.all(bound[1] == 0.0)
    c = np.sqrt([0.5, 0.0, 0.2])
    np.testing.assert_allclose(bound[0], M[0] * c.sum() / c[0], rtol=1e-15)
    np.testing.assert_allclose(bound[2], M[2] * c.sum() / c[2], rtol=1e-15)


def _case(rng, n):
    x = np.array([0.3, -0.2, 0.4])
    P = _spd(rng, 3, 0.15)
    a = rng.uniform(-3.0, 3.0, n)
    m = x[:2] + rng.uniform(2.0, 6.0, (n, 1)) * np.c_[np.cos(a), np.sin(a)]
    P_m = np.array([_spd(rng, 2, rng.uniform(0.05, 0.3)) for _ in range(n)])
    R = np.array([np.diag([0.05 ** 2, 0.02 ** 2])] * n)
    return x, P, m, P_m, R


def _true_error_covariance(x, P, m, P_m, R, joint, settings):
    """Return the update's covariance and the true covariance of its error (linear)."""
    n = len(m)
    z = sensors.observe(x[None], m)
    kind = np.full(n, RANGE_BEARING)
    result = update(x, P, m, P_m, z, R, kind, settings)
    K = np.empty((3, 2 * n))   # x+ is linear in z with one step: its columns are K
    for k in range(2 * n):
        dz = np.zeros(2 * n)
        dz[k] = 1e-3
        K[:, k] = (update(x, P, m, P_m, z + dz.reshape(n, 2), R, kind, settings).x
                   - result.x) / 1e-3
    _, J_z_m = sensors.observe_jacobians(x, m)
    T = np.hstack([result.A, -K @ _block_diag(list(J_z_m))])
    return result.P, T @ joint @ T.T + K @ _block_diag(list(R)) @ K.T


@pytest.mark.parametrize('common', [True, False])
def test_the_update_bounds_its_error_for_any_landmark_correlation(common):
    # The prior's error and the landmarks' errors in any joint (the prior correlated
    # with them too): with landmark_correlation unknown the updated covariance bounds
    # the true covariance of the updated error (first order), every time.
    rng = np.random.default_rng(2)
    settings = replace(ONE_STEP, landmark_correlation='unknown')
    for _ in range(40):
        x, P, m, P_m, R = _case(rng, int(rng.integers(2, 6)))
        joint = _joint(rng, [P] + list(P_m), common=common)
        P_new, true = _true_error_covariance(x, P, m, P_m, R, joint, settings)
        assert np.linalg.eigvalsh(P_new - true)[0] >= -1e-6 * np.trace(true)


def test_independent_landmarks_are_over_confident_when_they_share_one_error():
    # Four landmarks with one shared error, independent of the prior: the default
    # counts it four times, the bound once.
    rng = np.random.default_rng(3)
    x, P, m, P_m, R = _case(rng, 4)
    P_m[:] = np.eye(2) * 0.04
    joint = _block_diag([P, np.kron(np.ones((4, 4)), np.eye(2) * 0.04)])
    P_new, true = _true_error_covariance(x, P, m, P_m, R, joint, ONE_STEP)
    assert np.linalg.eigvalsh(P_new - true)[0] < -0.1 * np.linalg.eigvalsh(true)[0]
    bounded = replace(ONE_STEP, landmark_correlation='unknown')
    P_new, true = _true_error_covariance(x, P, m, P_m, R, joint, bounded)
    assert np.linalg.eigvalsh(P_new - true)[0] >= -1e-9


def test_one_landmark_is_the_same_update_either_way():
    rng = np.random.default_rng(4)
    x, P, m, P_m, R = _case(rng, 1)
    z = sensors.observe(x[None], m) + [[0.03, -0.01]]
    kind = np.array([RANGE_BEARING])
    a = update(x, P, m, P_m, z, R, kind, replace(ONE_STEP, max_iterations=5))
    b = update(x, P, m, P_m, z, R, kind,
               replace(ONE_STEP, max_iterations=5, landmark_correlation='unknown'))
    assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


def test_the_localizer_takes_the_parameter():
    assert Localizer(LocalizerConfig()).settings.landmark_correlation == 'independent'
    loc = Localizer(LocalizerConfig(landmark_correlation='unknown'))
    assert loc.settings.landmark_correlation == 'unknown'
    with pytest.raises(ValueError, match='landmark_correlation'):
        LocalizerConfig(landmark_correlation='any')
