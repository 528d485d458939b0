"""``source_correlation``: split CI across sources, or the product of independent sources."""

from landmark_ros.core.arrays import inverse_2x2, symmetric_2x2
from landmark_ros.fusion import source_sums
from landmark_ros.fusion.landmark_map import LandmarkMap
from landmark_ros.fusion.methods import make_method
from landmark_ros.fusion.source_sums import SourceSums
import numpy as np
import pytest


def _random_cov(rng, n, scale):
    A = rng.normal(0.0, scale, (n, 2, 2))
    return A @ np.swapaxes(A, 1, 2) + 1e-3 * scale ** 2 * np.eye(2)


def _filled(independent, rng, sources=4, rows=6):
    """Return a SourceSums of landmark 0 and each source's estimate ``(m, P_ind, P_dep)``."""
    sums, alone = SourceSums(independent), []
    for code in range(sources):
        z = rng.normal(0.0, 1.0, (rows, 2))
        R_ind, R_dep = _random_cov(rng, rows, 0.3), _random_cov(rng, rows, 0.1)
        sums.add(np.zeros(rows, np.int64), np.full(rows, code), z, R_ind, R_dep)
        one = SourceSums()
        one.add(np.zeros(rows, np.int64), np.zeros(rows, np.int64), z, R_ind, R_dep)
        alone.append(one.fold(np.array([0])))
    return sums, alone


def test_independent_sources_fuse_as_the_product_of_their_estimates():
    rng = np.random.default_rng(4)
    for _ in range(20):
        sums, alone = _filled(True, rng)
        fused = sums.fold(np.array([0]))
        information = sum(np.linalg.inv(e.P_ind[0] + e.P_dep[0]) for e in alone)
        P = np.linalg.inv(information)
        m = P @ sum(np.linalg.solve(e.P_ind[0] + e.P_dep[0], e.m[0]) for e in alone)
        np.testing.assert_allclose(fused.m[0], m, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fused.P_ind[0] + fused.P_dep[0], P, rtol=1e-9, atol=1e-14)
        for part in (fused.P_ind[0], fused.P_dep[0]):
            np.testing.assert_allclose(part, part.T)
            assert np.linalg.eigvalsh(part).min() >= -1e-15


def test_one_source_is_the_same_either_way():
    # Within a source the dependent parts are bounded by CI whatever the setting.
    rng = np.random.default_rng(5)
    for _ in range(10):
        state = rng.bit_generator.state
        a = _filled(True, rng, sources=1)[0].fold(np.array([0]))
        rng.bit_generator.state = state
        b = _filled(False, rng, sources=1)[0].fold(np.array([0]))
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def test_split_ci_across_sources_is_no_tighter_than_the_product():
    rng = np.random.default_rng(6)
    for _ in range(20):
        state = rng.bit_generator.state
        tight = _filled(True, rng)[0].fold(np.array([0]))
        rng.bit_generator.state = state
        wide = _filled(False, rng)[0].fold(np.array([0]))
        gap = (wide.P_ind[0] + wide.P_dep[0]) - (tight.P_ind[0] + tight.P_dep[0])
        assert np.linalg.eigvalsh(gap).min() >= -1e-12


def _nees(independent, shared_bias, trials=3000, sources=4, rows=20, seed=0):
    """Average NEES of the fold when each source has a bias (its own, or one shared)."""
    rng = np.random.default_rng(seed)
    W, B = np.diag([0.04, 0.01]), np.array([[0.02, 0.006], [0.006, 0.01]])
    L_W, L_B = np.linalg.cholesky(W), np.linalg.cholesky(B)
    sums = SourceSums(independent)
    landmarks = np.repeat(np.arange(trials), rows)
    common = rng.normal(size=(trials, 2)) @ L_B.T
    for code in range(sources):
        bias = common if shared_bias else rng.normal(size=(trials, 2)) @ L_B.T
        z = np.repeat(bias, rows, axis=0) + rng.normal(size=(trials * rows, 2)) @ L_W.T
        n = len(z)
        sums.add(landmarks, np.full(n, code), z, np.broadcast_to(W, (n, 2, 2)),
                 np.broadcast_to(B, (n, 2, 2)))
    fused = sums.fold(np.arange(trials))
    e = fused.m     # the truth is the origin
    a, b, c = inverse_2x2(*(x for x in source_sums.entries(fused.P_ind + fused.P_dep)))
    return float(np.mean(a * e[:, 0] ** 2 + 2.0 * b * e[:, 0] * e[:, 1] + c * e[:, 1] ** 2))


def test_monte_carlo_each_setting_is_consistent_where_its_assumption_holds():
    # 3,000 trials: the mean of chi-square(2) lies within 2 +- 0.16 (99.7 %).
    assert abs(_nees(True, shared_bias=False) - 2.0) < 0.16
    assert _nees(False, shared_bias=False) < 1.0          # split CI: under-confident
    assert _nees(True, shared_bias=True) > 4.0            # the product: over-confident
    assert _nees(False, shared_bias=True) < 2.16          # split CI: conservative


def test_the_setting_is_checked():
    with pytest.raises(ValueError, match='source_correlation'):
        LandmarkMap(source_correlation='partly')
    with pytest.raises(ValueError, match='fusion'):
        make_method('kalman')
    method = make_method('split_covariance_intersection', 'independent')
    method.reset()
    assert method.sums.independent


def test_a_map_with_independent_sources_holds_the_fold():
    rng = np.random.default_rng(7)
    z = rng.normal(0.0, 0.1, (8, 2))
    R = symmetric_2x2(np.full(8, 0.01), np.zeros(8), np.full(8, 0.01))
    estimates = []
    for setting in ('unknown', 'independent'):
        landmarks = LandmarkMap(source_correlation=setting)
        for k in range(8):
            landmarks.update([3], z[k:k + 1], R[k:k + 1], source=f'robot{k % 4}',
                             R_dep=0.5 * R[k:k + 1])
        _, P, _ = landmarks.estimate(3)
        estimates.append(np.trace(P))
    assert estimates[1] < estimates[0]
