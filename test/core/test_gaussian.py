"""Tests of landmark_ros.core.gaussian, gating and covariance: fusion, CI, chi2, checks."""

import math

from conftest import assert_psd, random_spd
from hypothesis import given, settings
from hypothesis import strategies as st
from landmark_ros.core import covariance, gaussian
from landmark_ros.core.arrays import unique_ints
from landmark_ros.core.covariance import (covariance_range_status, covariance_status,
                                          validate_covariance)
from landmark_ros.core.gating import chi2_survival, chi2_threshold, gate, mahalanobis_sq
from landmark_ros.core.gaussian import (covariance_intersection, covariance_intersection_omega,
                                        fuse, fuse_many, split_covariance_intersection,
                                        split_covariance_intersection_omega)
import numpy as np
import pytest

SETTINGS = settings(max_examples=100, deadline=None, derandomize=True)
RANGE_SETTINGS = settings(max_examples=300, deadline=None, derandomize=True)
seeds = st.integers(0, 2 ** 32 - 1)
dims = st.integers(1, 4)


def draw_estimate(rng, n, scale=1.0):
    """Return a random mean of size ``n`` and a random SPD covariance."""
    return rng.normal(0.0, 3.0, n), random_spd(rng, n, scale=scale)


def info_form(ms, Ps, weights=None):
    """Return the information-form product of Gaussians, ``inv(sum w_i inv(P_i))``."""
    weights = np.ones(len(ms)) if weights is None else weights
    Y = sum(w * np.linalg.inv(P) for w, P in zip(weights, Ps))
    y = sum(w * np.linalg.inv(P) @ m for w, m, P in zip(weights, ms, Ps))
    P = np.linalg.inv(Y)
    return P @ y, P


def assert_close_scaled(actual, expected, tol):
    """Assert ``|actual - expected| <= tol * max(1, max |expected|)``, entrywise."""
    expected = np.asarray(expected)
    scale = max(1.0, float(np.max(np.abs(expected))))
    np.testing.assert_allclose(actual, expected, rtol=0, atol=tol * scale)


# --- fuse ----------------------------------------------------------------------------------

def test_fuse_scalar_known_value():
    m, P = fuse([0.0], [[1.0]], [2.0], [[3.0]])
    np.testing.assert_allclose(m, [0.5], rtol=0, atol=1e-15)
    np.testing.assert_allclose(P, [[0.75]], rtol=0, atol=1e-15)
    assert m.shape == (1,) and P.shape == (1, 1)


@SETTINGS
@given(seeds, dims)
def test_fuse_matches_information_form(seed, n):
    rng = np.random.default_rng(seed)
    (m1, P1), (m2, P2) = draw_estimate(rng, n), draw_estimate(rng, n)
    m, P = fuse(m1, P1, m2, P2)
    m_ref, P_ref = info_form([m1, m2], [P1, P2])
    assert_close_scaled(P, P_ref, 1e-9)
    assert_close_scaled(m, m_ref, 1e-9)
    # Symmetric in its arguments.
    m_swap, P_swap = fuse(m2, P2, m1, P1)
    assert_close_scaled(m_swap, m, 1e-10)
    assert_close_scaled(P_swap, P, 1e-10)
    # Exactly symmetric output, PSD, and no larger than either input.
    np.testing.assert_array_equal(P, P.T)
    scale = max(np.abs(P1).max(), np.abs(P2).max())
    assert_psd(P, atol=1e-12 * scale)
    assert_psd(P1 - P, atol=1e-10 * scale)
    assert_psd(P2 - P, atol=1e-10 * scale)


@SETTINGS
@given(seeds, dims)
def test_fuse_is_associative_and_matches_fuse_many(seed, n):
    rng = np.random.default_rng(seed)
    (m1, P1), (m2, P2), (m3, P3) = (draw_estimate(rng, n) for _ in range(3))
    m_ab_c, P_ab_c = fuse(*fuse(m1, P1, m2, P2), m3, P3)
    m_a_bc, P_a_bc = fuse(m1, P1, *fuse(m2, P2, m3, P3))
    m_ac_b, P_ac_b = fuse(*fuse(m1, P1, m3, P3), m2, P2)
    m_many, P_many = fuse_many([m1, m2, m3], [P1, P2, P3])
    m_ref, P_ref = info_form([m1, m2, m3], [P1, P2, P3])
    for m, P in ((m_ab_c, P_ab_c), (m_a_bc, P_a_bc), (m_ac_b, P_ac_b), (m_many, P_many)):
        assert_close_scaled(m, m_ref, 1e-8)
        assert_close_scaled(P, P_ref, 1e-8)


def test_fuse_many_equals_sequential_fuse(rng):
    ms = rng.normal(0.0, 2.0, (6, 3))
    Ps = random_spd(rng, 3, 6)
    m, P = ms[0], Ps[0]
    for k in range(1, 6):
        m, P = fuse(m, P, ms[k], Ps[k])
    m_many, P_many = fuse_many(ms, Ps)
    assert m_many.shape == (3,) and P_many.shape == (3, 3)
    assert_close_scaled(m_many, m, 1e-9)
    assert_close_scaled(P_many, P, 1e-9)
    np.testing.assert_array_equal(P_many, P_many.T)
    # One estimate fuses to itself.
    m_one, P_one = fuse_many(ms[:1], Ps[:1])
    assert_close_scaled(m_one, ms[0], 1e-12)
    assert_close_scaled(P_one, Ps[0], 1e-12)


def test_fuse_many_rejects_bad_input():
    with pytest.raises(ValueError, match='N >= 1'):
        fuse_many(np.zeros((0, 2)), np.zeros((0, 2, 2)))
    with pytest.raises(ValueError, match='N >= 1'):
        fuse_many(np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match='disagree on N'):
        fuse_many(np.zeros((3, 2)), np.stack([np.eye(2)] * 2))
    with pytest.raises(ValueError, match='must have shape'):
        fuse_many(np.zeros((2, 2)), np.stack([np.eye(3)] * 2))


def test_fuse_with_huge_covariance_returns_the_other(rng):
    m1, P1 = draw_estimate(rng, 3)
    m2 = rng.normal(0.0, 3.0, 3)
    huge = 1e12 * np.eye(3)
    for m, P in (fuse(m1, P1, m2, huge), fuse(m2, huge, m1, P1)):
        assert_close_scaled(m, m1, 1e-9)
        assert_close_scaled(P, P1, 1e-9)


def test_fuse_with_an_exact_estimate_returns_it(rng):
    m1 = rng.normal(0.0, 3.0, 2)
    m2, P2 = draw_estimate(rng, 2)
    zero = np.zeros((2, 2))
    for m, P in (fuse(m1, zero, m2, P2), fuse(m2, P2, m1, zero)):
        np.testing.assert_array_equal(P, zero)
        np.testing.assert_allclose(m, m1, rtol=0, atol=1e-14 * max(1.0, np.abs(m1).max()))
    # Exact in one component only: that component is kept, the other fused.
    P1 = np.diag([0.0, 2.0])
    m, P = fuse(m1, P1, m2, np.diag([1.0, 2.0]))
    assert m[0] == pytest.approx(m1[0], abs=1e-14)
    assert m[1] == pytest.approx(0.5 * (m1[1] + m2[1]), abs=1e-14)
    np.testing.assert_allclose(P, np.diag([0.0, 1.0]), atol=1e-15)


@pytest.mark.parametrize('n', [2, 3])
def test_fuse_raises_when_the_sum_is_singular(n):
    # Documented: numpy.linalg.LinAlgError if P1 + P2 is singular (not NaN or inf).
    zero = np.zeros((n, n))
    with pytest.raises(np.linalg.LinAlgError):
        fuse(np.zeros(n), zero, np.ones(n), zero)
    singular = np.zeros((n, n))
    singular[0, 0] = 1.0
    with pytest.raises(np.linalg.LinAlgError):
        fuse(np.zeros(n), singular, np.ones(n), singular)


def test_fuse_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match='must have shape'):
        fuse(np.zeros(2), np.eye(2), np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match='must have shape'):
        fuse(np.zeros(2), np.eye(3), np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match='must have shape'):
        fuse(0.0, 1.0, 0.0, 1.0)


# --- covariance intersection -------------------------------------------------------------

def ci_reference(m1, P1, m2, P2, omega):
    """Return CI from its definition in information form."""
    return info_form([m1, m2], [P1, P2], weights=[omega, 1.0 - omega])


def log_det_grid(P1, P2, omegas):
    """Return ``log det P(omega)`` of CI on a grid of weights."""
    A, B = np.linalg.inv(P1), np.linalg.inv(P2)
    infos = omegas[:, None, None] * A + (1.0 - omegas[:, None, None]) * B
    return -np.linalg.slogdet(infos)[1]


@pytest.mark.parametrize('n', [2, 3])
def test_ci_matches_definition(n, rng):
    for _ in range(50):
        (m1, P1), (m2, P2) = draw_estimate(rng, n), draw_estimate(rng, n)
        omega = rng.uniform(0.0, 1.0)
        m, P = covariance_intersection(m1, P1, m2, P2, omega=omega)
        m_ref, P_ref = ci_reference(m1, P1, m2, P2, omega)
        assert_close_scaled(m, m_ref, 1e-9)
        assert_close_scaled(P, P_ref, 1e-9)
        np.testing.assert_array_equal(P, P.T)


@pytest.mark.parametrize('n', [2, 3])
def test_ci_omega_minimises_the_determinant(n, rng):
    grid = np.linspace(0.0, 1.0, 10001)
    interior = 0
    for _ in range(40):
        P1, P2 = random_spd(rng, n), random_spd(rng, n)
        omega = covariance_intersection_omega(P1, P2)
        assert 0.0 <= omega <= 1.0 and np.ndim(omega) == 0
        best = log_det_grid(P1, P2, grid)
        at_omega = log_det_grid(P1, P2, np.array([omega]))[0]
        # Never worse than the grid (up to rounding) ...
        assert at_omega <= best.min() + 1e-9
        # ... and a stationary point inside, or a minimum at the bound.
        h = 1e-6
        lo, hi = max(omega - h, 0.0), min(omega + h, 1.0)
        slope = np.diff(log_det_grid(P1, P2, np.array([lo, hi])))[0] / (hi - lo)
        if 1e-9 < omega < 1.0 - 1e-9:
            assert abs(slope) < 1e-5, (omega, slope)
        else:
            assert slope * (0.5 - omega) >= -1e-5, (omega, slope)
        interior += 0.01 < omega < 0.99
        # The CI estimate uses it.
        _, P = covariance_intersection(np.zeros(n), P1, np.zeros(n), P2)
        _, P_omega = covariance_intersection(np.zeros(n), P1, np.zeros(n), P2, omega=omega)
        np.testing.assert_array_equal(P, P_omega)
    assert interior > 10   # the interior optimum (stationary point) is exercised


def test_ci_omega_at_the_bounds():
    P1 = np.array([[1.0, 0.3], [0.3, 0.5]])
    larger = P1 + np.array([[0.4, 0.1], [0.1, 0.2]])
    assert covariance_intersection_omega(P1, larger) == 1.0
    assert covariance_intersection_omega(larger, P1) == 0.0
    m, P = covariance_intersection([1.0, 2.0], P1, [3.0, 4.0], larger)
    np.testing.assert_array_equal(m, [1.0, 2.0])
    np.testing.assert_array_equal(P, P1)
    P1_3 = np.diag([1.0, 0.5, 0.2])
    assert covariance_intersection_omega(P1_3, 2.0 * P1_3) == pytest.approx(1.0, abs=1e-9)
    assert covariance_intersection_omega(2.0 * P1_3, P1_3) == pytest.approx(0.0, abs=1e-9)
    # Complementary shapes: a diagonal pair has its optimum strictly inside.
    assert 0.4 < covariance_intersection_omega(np.diag([1.0, 4.0]), np.diag([4.0, 1.0])) < 0.6
    assert covariance_intersection_omega(np.diag([1.0, 4.0]),
                                         np.diag([4.0, 1.0])) == pytest.approx(0.5, abs=1e-12)
    # Golden-section search resolves a flat optimum to about sqrt(machine epsilon).
    assert covariance_intersection_omega(np.diag([1.0, 4.0, 2.0]),
                                         np.diag([4.0, 1.0, 2.0])) == pytest.approx(0.5, abs=1e-7)


def _joint_covariances(rng, n, count, rank):
    """Return P1, P2 and cross-covariances C whose joint covariances are PSD of given rank."""
    L = rng.standard_normal((count, 2 * n, rank))
    joint = L @ np.swapaxes(L, -1, -2)
    joint[:, :n, :n] += 1e-3 * np.eye(n)
    joint[:, n:, n:] += 1e-3 * np.eye(n)
    return joint[:, :n, :n], joint[:, n:, n:], joint[:, :n, n:]


@pytest.mark.parametrize('n', [2, 3])
@pytest.mark.parametrize('rank', ['full', 'half'])
def test_ci_is_consistent_for_any_correlation(n, rank, rng):
    # Full rank: general correlation; rank n: strongly correlated errors.
    count = 200
    P1, P2, C = _joint_covariances(rng, n, count, 2 * n if rank == 'full' else n)
    zeros = np.zeros((count, n))
    for omega in (None, rng.uniform(0.0, 1.0, count), 0.0, 1.0, 0.5):
        _, P = covariance_intersection(zeros, P1, zeros, P2, omega=omega)
        w = covariance_intersection_omega(P1, P2) if omega is None else np.broadcast_to(
            omega, (count,))
        K1 = w[:, None, None] * P @ np.linalg.inv(P1)
        K2 = (1.0 - w[:, None, None]) * P @ np.linalg.inv(P2)
        K1T, K2T = np.swapaxes(K1, -1, -2), np.swapaxes(K2, -1, -2)
        true = (K1 @ P1 @ K1T + K1 @ C @ K2T + K2 @ np.swapaxes(C, -1, -2) @ K1T
                + K2 @ P2 @ K2T)
        np.testing.assert_allclose(K1 + K2, np.broadcast_to(np.eye(n), K1.shape), atol=1e-8)
        for k in range(count):
            assert_psd(P[k] - true[k], atol=1e-9 * np.abs(P[k]).max())


def test_ci_is_not_the_plain_product():
    # With identical, fully correlated estimates CI must not shrink the covariance.
    P1 = np.array([[2.0, 0.5], [0.5, 1.0]])
    m, P = covariance_intersection([1.0, 1.0], P1, [1.0, 1.0], P1)
    np.testing.assert_allclose(P, P1, atol=1e-12)
    _, P_product = fuse([1.0, 1.0], P1, [1.0, 1.0], P1)
    np.testing.assert_allclose(P_product, P1 / 2, atol=1e-12)


def test_ci_omega_zero_and_one_return_the_inputs(rng):
    (m1, P1), (m2, P2) = draw_estimate(rng, 3), draw_estimate(rng, 3)
    m, P = covariance_intersection(m1, P1, m2, P2, omega=1.0)
    np.testing.assert_array_equal(m, m1)
    np.testing.assert_array_equal(P, P1)
    m, P = covariance_intersection(m1, P1, m2, P2, omega=0.0)
    np.testing.assert_array_equal(m, m2)
    np.testing.assert_array_equal(P, P2)
    # Per row in a batch, mixed with interior weights.
    omegas = np.array([0.0, 0.3, 1.0])
    m, P = covariance_intersection(m1, P1, m2, P2, omega=omegas)
    assert m.shape == (3, 3) and P.shape == (3, 3, 3)
    np.testing.assert_array_equal(m[0], m2)
    np.testing.assert_array_equal(P[2], P1)
    m_ref, P_ref = ci_reference(m1, P1, m2, P2, 0.3)
    assert_close_scaled(m[1], m_ref, 1e-9)
    assert_close_scaled(P[1], P_ref, 1e-9)


@pytest.mark.parametrize('omega', [-0.1, 1.1, -1e-12, 1.0 + 1e-12, np.nan, np.inf,
                                   [0.5, 1.5], [np.nan, 0.5]])
def test_ci_omega_outside_unit_interval_raises(omega):
    with pytest.raises(ValueError, match=r'omega must lie in \[0, 1\]'):
        covariance_intersection([0.0, 0.0], np.eye(2), [1.0, 1.0], 2.0 * np.eye(2),
                                omega=omega)


# --- batches -------------------------------------------------------------------------------

def _estimates(rng, n, dim):
    return rng.normal(0.0, 3.0, (n, dim)), random_spd(rng, dim, n)


BATCH_FUNCTIONS = {
    'fuse': lambda m1, P1, m2, P2: fuse(m1, P1, m2, P2),
    'covariance_intersection': lambda m1, P1, m2, P2: covariance_intersection(m1, P1, m2, P2),
    'covariance_intersection_fixed': lambda m1, P1, m2, P2: covariance_intersection(
        m1, P1, m2, P2, omega=0.25),
    'covariance_intersection_omega': lambda m1, P1, m2, P2: (
        covariance_intersection_omega(P1, P2),),
    'mahalanobis_sq': lambda m1, P1, m2, P2: (mahalanobis_sq(m1, m2, P1 + P2),),
    'covariance_status': lambda m1, P1, m2, P2: (covariance_status(P1 - 0.2 * P2),),
}


@pytest.mark.parametrize('dim', [2, 3])
@pytest.mark.parametrize('name', sorted(BATCH_FUNCTIONS))
def test_batch_equals_loop(name, dim, rng):
    fn = BATCH_FUNCTIONS[name]
    n = 12
    (m1, P1), (m2, P2) = _estimates(rng, n, dim), _estimates(rng, n, dim)
    batch = fn(m1, P1, m2, P2)
    singles = [fn(m1[k], P1[k], m2[k], P2[k]) for k in range(n)]
    for i, out in enumerate(batch):
        out = np.asarray(out)
        assert out.shape == (n,) + np.shape(singles[0][i])
        if name != 'covariance_status':
            assert out.dtype == np.float64
        for k in range(n):
            assert_close_scaled(out[k], singles[k][i], 1e-12)
    # A batch of one stays a batch.
    for out, single in zip(fn(m1[:1], P1[:1], m2[:1], P2[:1]), singles[0]):
        assert np.shape(out) == (1,) + np.shape(single)
        assert_close_scaled(np.asarray(out)[0], single, 1e-12)
    # Single items broadcast against batches: first estimate single, then second.
    for mixed, index in (((m1[0], P1[0], m2, P2), lambda k: (m1[0], P1[0], m2[k], P2[k])),
                         ((m1, P1, m2[0], P2[0]), lambda k: (m1[k], P1[k], m2[0], P2[0]))):
        outs = fn(*mixed)
        for k in range(n):
            for out, single in zip(outs, fn(*index(k))):
                assert np.shape(out)[0] == n
                assert_close_scaled(np.asarray(out)[k], single, 1e-12)


def test_one_batched_argument_makes_every_output_a_batch(rng):
    # With only one argument a batch of N (a mean or a covariance), every output is a
    # batch of N, so that m[k] goes with P[k]. Checked for all functions, reporting all.
    n = 5
    problems = []
    for name in sorted(BATCH_FUNCTIONS):
        fn = BATCH_FUNCTIONS[name]
        for dim in (2, 3):
            batch = (*_estimates(rng, n, dim), *_estimates(rng, n, dim))
            for index in range(4):
                if name in ('covariance_intersection_omega', 'covariance_status') and (
                        index in (0, 2)):
                    continue   # means not used
                args = [a if i == index else a[0] for i, a in enumerate(batch)]
                outs = fn(*args)
                shapes = [np.shape(out) for out in outs]
                if any(shape[:1] != (n,) for shape in shapes):
                    problems.append(f'{name} ({dim}D) with only argument {index} batched: '
                                    f'output shapes {shapes}')
                    continue
                for k in range(n):
                    args_k = [a[k] if i == index else a for i, a in enumerate(args)]
                    for out, single in zip(outs, fn(*args_k)):
                        assert_close_scaled(np.asarray(out)[k], single, 1e-12)
    assert not problems, '\n'.join(problems)


def test_single_outputs_are_scalars():
    assert np.shape(mahalanobis_sq([1.0, 2.0], [0.0, 0.0], np.eye(2))) == ()
    assert np.shape(covariance_intersection_omega(np.eye(2), 2.0 * np.eye(2))) == ()
    assert np.shape(covariance_intersection_omega(np.eye(3), 2.0 * np.eye(3))) == ()
    assert np.shape(covariance_status(np.eye(2))) == ()
    assert np.shape(gate(1.0, 2.0)) == ()


# --- Mahalanobis distance, gate, NEES-style consistency ----------------------------------

def test_mahalanobis_sq_matches_explicit_inverse(rng):
    for dim in (1, 2, 3, 5):
        for _ in range(20):
            x, mean = rng.normal(0, 3, dim), rng.normal(0, 3, dim)
            P = random_spd(rng, dim)
            d = x - mean
            expected = d @ np.linalg.inv(P) @ d
            assert mahalanobis_sq(x, mean, P) == pytest.approx(expected, rel=1e-9)
    assert mahalanobis_sq([3.0, 4.0], [0.0, 0.0], np.diag([9.0, 4.0])) == pytest.approx(5.0)
    assert mahalanobis_sq([1.0, 1.0], [1.0, 1.0], np.eye(2)) == 0.0


def test_mahalanobis_sq_is_chi_square_distributed(rng):
    # For samples of N(mean, P), d2 has mean n and P(d2 <= chi2(n, p)) = p.
    P = random_spd(rng, 3)
    mean = np.array([1.0, -2.0, 0.5])
    x = rng.multivariate_normal(mean, P, 200000)
    d2 = mahalanobis_sq(x, mean, P)
    assert d2.shape == (200000,)
    assert d2.mean() == pytest.approx(3.0, abs=0.03)
    assert np.mean(gate(d2, chi2_threshold(3, 0.95))) == pytest.approx(0.95, abs=0.003)


def test_gate():
    threshold = chi2_threshold(2, 0.95)
    assert gate(threshold, threshold)
    assert gate(0.0, threshold)
    assert not gate(np.nextafter(threshold, np.inf), threshold)
    result = gate(np.array([1.0, 6.0, 5.99]), threshold)
    np.testing.assert_array_equal(result, [True, False, True])
    assert result.dtype == bool


# --- chi-square -----------------------------------------------------------------------------

@pytest.mark.parametrize('dof, probability, expected', [
    (1, 0.95, 3.841458820694124),
    (2, 0.95, 5.991464547107979),
    (3, 0.95, 7.814727903251178),
    (2, 0.999, 13.815510557964274),
    (2, 0.5, 2.0 * math.log(2.0)),          # dof 2 is exponential: -2 log(1 - p)
    (2, 0.99, -2.0 * math.log(0.01)),
])
def test_chi2_threshold_reference_values(dof, probability, expected):
    assert chi2_threshold(dof, probability) == pytest.approx(expected, rel=1e-12)


def test_chi2_threshold_matches_scipy():
    stats = pytest.importorskip('scipy.stats')
    for dof in range(1, 11):
        for probability in (0.5, 0.9, 0.95, 0.99, 0.999, 0.9999):
            assert chi2_threshold(dof, probability) == pytest.approx(
                stats.chi2.ppf(probability, dof), rel=1e-9), (dof, probability)
    for dof in (20, 37, 100):
        for probability in (0.01, 0.5, 0.999):
            assert chi2_threshold(dof, probability) == pytest.approx(
                stats.chi2.ppf(probability, dof), rel=1e-9), (dof, probability)


def test_chi2_survival_matches_scipy():
    stats = pytest.importorskip('scipy.stats')
    for dof in list(range(1, 11)) + [25, 50, 51]:
        for x in (1e-6, 0.01, 0.5, 1.0, 2.0, 3.84, 7.5, 15.0, 30.0, 60.0, 120.0):
            expected = stats.chi2.sf(x, dof)
            assert chi2_survival(x, dof) == pytest.approx(expected, rel=1e-9, abs=1e-300), (
                dof, x)


def test_chi2_survival_closed_forms():
    for dof in range(1, 12):
        assert chi2_survival(0.0, dof) == 1.0
        assert chi2_survival(-1.0, dof) == 1.0
    for x in (0.1, 1.0, 4.0, 10.0):
        assert chi2_survival(x, 2) == pytest.approx(math.exp(-x / 2), rel=1e-14)
        assert chi2_survival(x, 1) == pytest.approx(math.erfc(math.sqrt(x / 2)), rel=1e-14)
        assert chi2_survival(x, 4) == pytest.approx(math.exp(-x / 2) * (1 + x / 2), rel=1e-14)
        assert chi2_survival(x, 3) == pytest.approx(
            math.erfc(math.sqrt(x / 2)) + math.sqrt(2 * x / math.pi) * math.exp(-x / 2),
            rel=1e-14)


def test_chi2_threshold_inverts_survival():
    for dof in (1, 2, 3, 7, 50):
        previous = 0.0
        for probability in (0.01, 0.5, 0.9, 0.99, 0.999999):
            threshold = chi2_threshold(dof, probability)
            assert threshold > previous
            previous = threshold
            assert chi2_survival(threshold, dof) == pytest.approx(1.0 - probability, rel=1e-9)


@pytest.mark.parametrize('dof', [0, -1, 101, 2.5, 1e300, np.inf, -np.inf])
def test_chi2_threshold_rejects_bad_dof(dof):
    with pytest.raises(ValueError, match='dof must be an integer from 1 to 100'):
        chi2_threshold(dof, 0.95)


def test_chi2_threshold_rejects_nan_dof():
    with pytest.raises(ValueError):
        chi2_threshold(np.nan, 0.95)


@pytest.mark.parametrize('probability', [0.0, 1.0, -0.5, 1.5, np.nan])
def test_chi2_threshold_rejects_bad_probability(probability):
    with pytest.raises(ValueError, match='probability'):
        chi2_threshold(2, probability)


def test_chi2_threshold_accepts_integral_floats_and_numpy_ints():
    assert chi2_threshold(2.0, 0.95) == chi2_threshold(2, 0.95)
    assert chi2_threshold(np.int64(3), 0.95) == chi2_threshold(3, 0.95)


# --- covariance checks ------------------------------------------------------------------

GOOD = np.array([[2.0, 0.3], [0.3, 1.0]])


@pytest.mark.parametrize('P, code', [
    (GOOD, covariance.COVARIANCE_OK),
    (np.zeros((2, 2)), covariance.COVARIANCE_OK),
    (np.zeros((3, 3)), covariance.COVARIANCE_OK),
    (np.diag([1.0, 0.0]), covariance.COVARIANCE_OK),                     # singular PSD
    (np.array([[1.0, 1.0], [1.0, 1.0]]), covariance.COVARIANCE_OK),      # rank one
    (GOOD + np.array([[0.0, 2e-15], [0.0, 0.0]]), covariance.COVARIANCE_OK),  # rounding
    (np.diag([1.0, -1e-12]), covariance.COVARIANCE_OK),                  # rounding
    (np.array([[1.0, np.nan], [np.nan, 1.0]]), covariance.COVARIANCE_NONFINITE),
    (np.diag([np.inf, 1.0]), covariance.COVARIANCE_NONFINITE),
    (np.diag([-np.inf, 1.0]), covariance.COVARIANCE_NONFINITE),
    (np.array([[1.0, np.nan], [0.0, -1.0]]), covariance.COVARIANCE_NONFINITE),  # first problem
    (np.array([[1.0, 0.5], [0.4, 1.0]]), covariance.COVARIANCE_ASYMMETRIC),
    (GOOD + np.array([[0.0, 1e-6], [0.0, 0.0]]), covariance.COVARIANCE_ASYMMETRIC),
    (np.array([[1.0, 2.0], [0.0, -1.0]]), covariance.COVARIANCE_ASYMMETRIC),
    (np.array([[1.0, 2.0], [2.0, 1.0]]), covariance.COVARIANCE_NOT_PSD),
    (np.diag([1.0, -1e-6]), covariance.COVARIANCE_NOT_PSD),
    (-np.eye(3), covariance.COVARIANCE_NOT_PSD),
    (np.diag([1e-20, -1e-20]), covariance.COVARIANCE_NOT_PSD),           # relative, not absolute
])
def test_covariance_status(P, code):
    assert covariance_status(P) == code
    if code == covariance.COVARIANCE_OK:
        returned = validate_covariance(P)
        assert returned.dtype == np.float64
        np.testing.assert_array_equal(returned, P)
    else:
        with pytest.raises(ValueError, match=covariance.COVARIANCE_PROBLEMS[code]):
            validate_covariance(P)


def test_covariance_status_accepts_rounding_of_real_products(rng):
    J = rng.standard_normal((200, 3, 2))
    P = J @ random_spd(rng, 2, 200) @ np.swapaxes(J, -1, -2)   # rank 2, not symmetrised
    np.testing.assert_array_equal(covariance_status(P), covariance.COVARIANCE_OK)


def test_covariance_status_batch_codes_and_validate_index():
    batch = np.stack([GOOD, np.zeros((2, 2)), np.diag([np.nan, 1.0]),
                      np.array([[1.0, 0.5], [0.4, 1.0]]), np.array([[1.0, 2.0], [2.0, 1.0]]),
                      GOOD])
    codes = covariance_status(batch)
    np.testing.assert_array_equal(codes, [0, 0, 1, 2, 3, 0])
    assert covariance_status(batch[:1]).shape == (1,)
    with pytest.raises(ValueError, match=r'landmark P: 3 matrix\(es\) rejected, first at index '
                                         r'2: covariance_nonfinite'):
        validate_covariance(batch, name='landmark P')
    with pytest.raises(ValueError, match='first at index 1: covariance_not_psd'):
        validate_covariance(np.stack([GOOD, -GOOD]))
    np.testing.assert_array_equal(validate_covariance(batch[:2]), batch[:2])


def test_covariance_status_rtol():
    P = np.diag([1.0, -1e-6])
    assert covariance_status(P, rtol=1e-5) == covariance.COVARIANCE_OK
    assert covariance_status(P, rtol=1e-7) == covariance.COVARIANCE_NOT_PSD
    validate_covariance(P, rtol=1e-5)


@pytest.mark.parametrize('P', [np.zeros((2, 3)), np.zeros(3), np.zeros(()),
                               np.zeros((2, 2, 2, 2)), np.zeros((4, 2, 3))])
def test_covariance_checks_reject_wrong_shapes(P):
    with pytest.raises(ValueError, match='must have shape'):
        covariance_status(P)
    with pytest.raises(ValueError, match='must have shape'):
        validate_covariance(P)


# --- covariance range and scale safety ---------------------------------------------------

def in_range_covariance(log_top, log_condition, angle):
    """Return a 2x2 covariance with largest eigenvalue 10^log_top, given condition, rotated."""
    big = 10.0 ** log_top
    c, s = math.cos(angle), math.sin(angle)
    rotation = np.array([[c, -s], [s, c]])
    P = rotation @ np.diag([big, big / 10.0 ** log_condition]) @ rotation.T
    return 0.5 * (P + P.T)


log_conditions = st.one_of(st.just(8.99), st.just(0.0), st.floats(0.0, 8.99))
angles = st.floats(0.0, math.pi)


@st.composite
def covariances(draw):
    """Draw 2x2 covariances anywhere in the accepted range, often at its corners."""
    log_condition = draw(log_conditions)
    low = -12.0 + log_condition + 0.01
    log_top = draw(st.one_of(st.just(low), st.just(11.99), st.floats(low, 11.99)))
    return in_range_covariance(log_top, log_condition, draw(angles))


@pytest.mark.parametrize('P, code', [
    (np.eye(2), covariance.COVARIANCE_OK),
    (np.diag([1e-12, 1e-12]), covariance.COVARIANCE_OK),
    (np.diag([1e12, 1e12]), covariance.COVARIANCE_OK),
    (np.diag([1e12, 1e3 + 1.0]), covariance.COVARIANCE_OK),
    (np.diag([1.0, 0.99e-12]), covariance.COVARIANCE_TOO_SMALL),
    (np.zeros((2, 2)), covariance.COVARIANCE_TOO_SMALL),
    (1e-200 * np.eye(2), covariance.COVARIANCE_TOO_SMALL),
    (np.diag([1.01e12, 1.0]), covariance.COVARIANCE_TOO_LARGE),
    (np.array([[1e200, 1e199], [1e199, 1e200]]), covariance.COVARIANCE_TOO_LARGE),
    (np.diag([1e12, 1e3 - 1.0]), covariance.COVARIANCE_ILL_CONDITIONED),
    (np.array([[1.0, 1.0], [1.0, 1.0]]), covariance.COVARIANCE_ILL_CONDITIONED),   # rank one
    (np.array([[1.0, 1.0 - 1e-11], [1.0 - 1e-11, 1.0]]), covariance.COVARIANCE_ILL_CONDITIONED),
    (np.diag([np.nan, 1.0]), covariance.COVARIANCE_NONFINITE),
    (np.diag([1.0, 2.0, 3.0]), covariance.COVARIANCE_OK),
    (np.diag([1.0, 2.0, 1e-10]), covariance.COVARIANCE_ILL_CONDITIONED),
    (np.diag([1.0, 2.0, 1e-13]), covariance.COVARIANCE_TOO_SMALL),
])
def test_covariance_range_status(P, code):
    assert covariance_range_status(P) == code
    if code:
        assert code in covariance.COVARIANCE_RANGE_PROBLEMS


def test_covariance_range_status_batch_and_names():
    batch = np.stack([np.eye(2), 1e-13 * np.eye(2), 1e13 * np.eye(2), np.diag([1.0, 1e-10])])
    np.testing.assert_array_equal(covariance_range_status(batch), [0, 4, 5, 6])
    assert covariance_range_status(batch[:1]).shape == (1,)
    assert set(covariance.COVARIANCE_RANGE_PROBLEMS.values()) >= {
        'covariance_too_small', 'covariance_too_large', 'covariance_ill_conditioned'}
    assert not set(covariance.COVARIANCE_RANGE_PROBLEMS) & {
        covariance.COVARIANCE_ASYMMETRIC, covariance.COVARIANCE_NOT_PSD}
    with pytest.raises(ValueError, match='must have shape'):
        covariance_range_status(np.zeros(3))


@SETTINGS
@given(log_conditions, angles)
def test_covariance_range_status_condition_bound(log_condition, angle):
    P = in_range_covariance(0.0, log_condition, angle)
    assert covariance_range_status(P) == covariance.COVARIANCE_OK
    P = in_range_covariance(0.0, 9.01 + log_condition / 10.0, angle)
    assert covariance_range_status(P) == covariance.COVARIANCE_ILL_CONDITIONED


def assert_finite_symmetric_psd(P, tol, scale=None):
    """Assert finite, exactly symmetric and PSD up to ``tol`` times ``scale`` (max |P|)."""
    assert np.all(np.isfinite(P))
    np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
    scale = np.abs(P).max() if scale is None else scale
    assert np.linalg.eigvalsh(P)[..., 0] >= -tol * scale


def assert_relative(actual, expected, tol):
    """Assert ``|actual - expected| <= tol * max |expected|`` and no NaN or inf."""
    assert np.all(np.isfinite(actual))
    np.testing.assert_allclose(actual, expected, rtol=0, atol=tol * np.abs(expected).max())


RANGE_TOL = 1e-5
"""Relative tolerance against numpy: condition numbers up to 1e9 leave about 2e-7."""


@RANGE_SETTINGS
@given(covariances(), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0))
def test_closed_forms_are_scale_safe_in_the_accepted_range(P, x, y):
    from landmark_ros.core import arrays
    a, b, c = arrays.entries_2x2(P)
    assert covariance_range_status(P) == covariance.COVARIANCE_OK
    assert_relative(arrays.det(P), np.linalg.det(P), RANGE_TOL)
    assert_relative(arrays.det_2x2(a, b, c), np.linalg.det(P), RANGE_TOL)
    assert_relative(gaussian.information(P), np.linalg.inv(P), RANGE_TOL)
    assert_relative(np.array(arrays.inverse_2x2(a, b, c)),
                    np.linalg.inv(P)[[0, 0, 1], [0, 1, 1]], RANGE_TOL)
    B = np.array([[x, 1.0], [y, -2.0]]) * math.sqrt(P[0, 0])
    assert_relative(arrays.solve(P, B), np.linalg.solve(P, B), RANGE_TOL)
    d = np.array([x, y]) * math.sqrt(max(P[0, 0], P[1, 1]))
    reference = d @ np.linalg.solve(P, d)
    # Relative to the reference, absolute below the normal floats (x = 9e-160 gives a
    # reference of 8e-319, where even numpy keeps few digits).
    assert abs(mahalanobis_sq(d, np.zeros(2), P) - reference) <= (
        RANGE_TOL * reference + np.finfo(np.float64).tiny)


@RANGE_SETTINGS
@given(covariances(), covariances(), covariances(), covariances(), st.floats(0.01, 0.99))
def test_fusion_is_scale_safe_in_the_accepted_range(P1, P2, P3, P4, omega):
    # Any two covariances of the range, however different their scales.
    m1, m2 = np.array([1.0, -2.0]) * math.sqrt(P1[0, 0]), np.array([0.5, 3.0]) * math.sqrt(
        P2[1, 1])
    inv = np.linalg.inv
    m, P = fuse(m1, P1, m2, P2)
    P_ref = inv(inv(P1) + inv(P2))
    assert_finite_symmetric_psd(P, RANGE_TOL)
    assert_relative(P, P_ref, RANGE_TOL)
    m_ref = P_ref @ (inv(P1) @ m1 + inv(P2) @ m2)
    assert_relative(m, m_ref, RANGE_TOL * max(1.0, np.abs(np.r_[m1, m2]).max()
                                              / np.abs(m_ref).max()))
    m_many, P_many = fuse_many([m1, m2], [P1, P2])
    assert_relative(P_many, P_ref, RANGE_TOL)
    # Covariance intersection: the found weight is the best (log det), outputs sound.
    w = covariance_intersection_omega(P1, P2)
    assert 0.0 <= w <= 1.0

    def ci_log_det(weight):
        return -np.linalg.slogdet(weight * inv(P1) + (1.0 - weight) * inv(P2))[1]

    grid = np.linspace(0.0, 1.0, 201)
    assert ci_log_det(w) <= min(ci_log_det(g) for g in grid) + 1e-6
    for weight in (None, omega):
        m, P = covariance_intersection(m1, P1, m2, P2, weight)
        assert_finite_symmetric_psd(P, RANGE_TOL)
        assert np.all(np.isfinite(m))
    _, P = covariance_intersection(m1, P1, m2, P2, omega)
    assert_relative(P, inv(omega * inv(P1) + (1.0 - omega) * inv(P2)), RANGE_TOL)
    # Split CI with independent parts P1, P2 and dependent parts P3, P4.
    w = split_covariance_intersection_omega(P1, P3, P2, P4)
    assert 0.0 < w < 1.0
    for weight in (w, omega):
        m, P_ind, P_dep = split_covariance_intersection(m1, P1, P3, m2, P2, P4, weight)
        assert np.all(np.isfinite(m))
        # Each part PSD to rounding of the total (a part may be far smaller).
        total = np.abs(P_ind + P_dep).max()
        assert_finite_symmetric_psd(P_ind, RANGE_TOL, total)
        assert_finite_symmetric_psd(P_dep, RANGE_TOL, total)
        A, B = P3 / weight + P1, P4 / (1.0 - weight) + P2
        P_ref = inv(inv(A) + inv(B))
        assert_relative(P_ind + P_dep, P_ref, RANGE_TOL)


# --- projection onto the positive semi-definite 2x2 matrices -----------------------------------

def test_psd_projection_2x2_clips_negative_eigenvalues(rng):
    from landmark_ros.core.arrays import psd_projection_2x2
    A = rng.normal(size=(500, 2, 2))
    S = 0.5 * (A + np.swapaxes(A, 1, 2))
    S[:100] = A[:100] @ np.swapaxes(A[:100], 1, 2)            # already PSD
    S[100:120] = -S[100:120] @ S[100:120]                      # negative semi-definite
    a, b, c = psd_projection_2x2(S[:, 0, 0], S[:, 0, 1], S[:, 1, 1])
    got = np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)
    w, V = np.linalg.eigh(S)
    expected = V @ (np.clip(w, 0.0, None)[..., None] * np.swapaxes(V, 1, 2))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * np.abs(S).max())
    assert np.array_equal(got[:100], S[:100])                  # bit for bit when PSD
    assert np.linalg.eigvalsh(got).min() >= -1e-12 * np.abs(S).max()
    assert (got[100:120] == 0.0).all()
    np.testing.assert_allclose(np.stack(psd_projection_2x2(a, b, c)), np.stack([a, b, c]),
                               rtol=0, atol=1e-12 * np.abs(S).max())     # idempotent
    single = [psd_projection_2x2(*S[k, [0, 0, 1], [0, 1, 1]]) for k in range(120, 140)]
    np.testing.assert_array_equal(np.array(single), np.stack([a, b, c], 1)[120:140])


@pytest.mark.parametrize('dtype', [np.int64, np.int32, np.intp, np.uint8])
@pytest.mark.parametrize('size', [0, 1, 2, 7, 1000])
def test_unique_ints_is_np_unique(dtype, size):
    rng = np.random.default_rng(size)
    values = rng.integers(0, max(size // 3, 1) + 1, (size, 1) if size % 2 else size).astype(dtype)
    got = unique_ints(values)
    expected = np.unique(values)
    assert got.dtype == expected.dtype
    np.testing.assert_array_equal(got, expected)
