"""
Tests of the fusion rules in landmark_ros.core.gaussian: split CI and the 2x2 paths.

References are computed independently with numpy.linalg (explicit inverses, the
information form) and brute-force grids; consistency is checked analytically (the
true error covariance from the gains) and by Monte Carlo with known correlations.
"""

from conftest import assert_psd, random_spd
from landmark_ros.core import _split_ci, gaussian
from landmark_ros.core.gaussian import (covariance_intersection, covariance_intersection_omega,
                                        fuse, split_covariance_intersection,
                                        split_covariance_intersection_omega)
import numpy as np
import pytest
from scipy import optimize

inv = np.linalg.inv


def T(M):
    """Swap the last two axes."""
    return np.swapaxes(M, -1, -2)


def assert_close_scaled(actual, expected, tol):
    """Assert ``|actual - expected| <= tol * max(1, max |expected|)``, entrywise."""
    expected = np.asarray(expected)
    scale = max(1.0, float(np.max(np.abs(expected))))
    np.testing.assert_allclose(actual, expected, rtol=0, atol=tol * scale)


def spd(rng, n, count=None, scale=1.0):
    """Return reasonably conditioned SPD matrices (for comparisons with inverses)."""
    return random_spd(rng, n, count, scale=scale, eps=0.05 * scale ** 2)


def sci_parts(rng, n, count=None):
    """Return ``P1_ind, P1_dep, P2_ind, P2_dep`` of random, differing sizes."""
    return tuple(spd(rng, n, count, scale=s) for s in rng.uniform(0.3, 2.0, 4))


def sci_reference(m1, P1i, P1d, m2, P2i, P2d, omega):
    """Split CI from its definition, with explicit inverses (single items)."""
    A = P1d / omega + P1i
    B = P2d / (1.0 - omega) + P2i
    Ai, Bi = inv(A), inv(B)
    P = inv(Ai + Bi)
    m = P @ (Ai @ m1 + Bi @ m2)
    P_ind = P @ Ai @ P1i @ Ai @ P + P @ Bi @ P2i @ Bi @ P
    return m, P_ind, P - P_ind


def sci_log_det(P1i, P1d, P2i, P2d, omegas):
    """Return ``log det P(omega)`` of split CI on a grid of weights (explicit inverses)."""
    w = np.asarray(omegas)[:, None, None]
    A = P1d / w + P1i
    B = P2d / (1.0 - w) + P2i
    return -np.linalg.slogdet(inv(A) + inv(B))[1]


def brute_force_minimum(parts):
    """Return ``(omega, log det P)`` minimising split CI's ``det P``: 1e-6 resolution."""
    coarse = np.linspace(1e-6, 1.0 - 1e-6, 2001)
    values = sci_log_det(*parts, coarse)
    k = int(np.argmin(values))
    fine = np.linspace(max(coarse[k] - 1e-3, 1e-6), min(coarse[k] + 1e-3, 1.0 - 1e-6), 2001)
    values = sci_log_det(*parts, fine)
    k = int(np.argmin(values))
    return fine[k], values[k]


# --- split CI against its definition --------------------------------------------------------

@pytest.mark.parametrize('n', [1, 2, 3])
def test_sci_matches_definition(n, rng):
    for _ in range(60):
        m1, m2 = rng.normal(0.0, 3.0, (2, n))
        P1i, P1d, P2i, P2d = sci_parts(rng, n)
        omega = rng.uniform(0.02, 0.98)
        m, P_ind, P_dep = split_covariance_intersection(m1, P1i, P1d, m2, P2i, P2d, omega)
        m_ref, P_ind_ref, P_dep_ref = sci_reference(m1, P1i, P1d, m2, P2i, P2d, omega)
        assert m.shape == (n,) and P_ind.shape == P_dep.shape == (n, n)
        assert_close_scaled(m, m_ref, 1e-9)
        assert_close_scaled(P_ind, P_ind_ref, 1e-9)
        assert_close_scaled(P_dep, P_dep_ref, 1e-9)


@pytest.mark.parametrize('n', [2, 3])
def test_sci_default_omega_is_the_search_result(n, rng):
    for _ in range(20):
        m1, m2 = rng.normal(0.0, 3.0, (2, n))
        parts = sci_parts(rng, n)
        omega = split_covariance_intersection_omega(*parts)
        assert np.ndim(omega) == 0 and 0.0 < omega < 1.0
        default = split_covariance_intersection(m1, parts[0], parts[1], m2, parts[2], parts[3])
        given = split_covariance_intersection(m1, parts[0], parts[1], m2, parts[2], parts[3],
                                              omega)
        for a, b in zip(default, given):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(default, sci_reference(m1, parts[0], parts[1], m2, parts[2], parts[3],
                                               omega)):
            assert_close_scaled(a, b, 1e-9)


@pytest.mark.parametrize('n', [2, 3])
@pytest.mark.parametrize('omega', ['search', 'given'])
def test_sci_batch_equals_loop(n, omega, rng):
    count = 15
    m1, m2 = rng.normal(0.0, 3.0, (2, count, n))
    parts = sci_parts(rng, n, count)
    w = None if omega == 'search' else rng.uniform(0.05, 0.95, count)
    batch = split_covariance_intersection(m1, parts[0], parts[1], m2, parts[2], parts[3], w)
    assert [np.shape(x) for x in batch] == [(count, n), (count, n, n), (count, n, n)]
    if w is None:
        omegas = split_covariance_intersection_omega(*parts)
        assert omegas.shape == (count,)
    for k in range(count):
        single = split_covariance_intersection(
            m1[k], parts[0][k], parts[1][k], m2[k], parts[2][k], parts[3][k],
            None if w is None else w[k])
        if w is None:
            assert split_covariance_intersection_omega(*(p[k] for p in parts)) == omegas[k]
        for out, ref in zip(batch, single):
            assert_close_scaled(out[k], ref, 1e-12)
    # Single covariances broadcast against a batch of means.
    single_parts = [p[0] for p in parts]
    broadcast = split_covariance_intersection(m1, single_parts[0], single_parts[1], m2,
                                              single_parts[2], single_parts[3],
                                              None if w is None else w[0])
    assert [np.shape(x) for x in broadcast] == [(count, n), (count, n, n), (count, n, n)]
    for k in (0, count - 1):
        single = split_covariance_intersection(m1[k], *single_parts[:2], m2[k],
                                               *single_parts[2:], None if w is None else w[0])
        for out, ref in zip(broadcast, single):
            assert_close_scaled(out[k], ref, 1e-12)


@pytest.mark.parametrize('n', [2, 3])
def test_sci_outputs_symmetric_psd_and_split_correctly(n, rng):
    for _ in range(40):
        m1, m2 = rng.normal(0.0, 3.0, (2, n))
        P1i, P1d, P2i, P2d = sci_parts(rng, n)
        # Rank-deficient dependent parts too: one common direction of error.
        if rng.uniform() < 0.5:
            v = rng.standard_normal(n)
            P1d = np.outer(v, v)
            P2d = 2.0 * np.outer(v, v)
        omega = rng.uniform(0.01, 0.99)
        m, P_ind, P_dep = split_covariance_intersection(m1, P1i, P1d, m2, P2i, P2d, omega)
        np.testing.assert_array_equal(P_ind, P_ind.T)
        np.testing.assert_array_equal(P_dep, P_dep.T)
        scale = np.abs(P_ind + P_dep).max()
        assert_psd(P_ind, atol=1e-12 * scale)
        assert_psd(P_dep, atol=1e-10 * scale)
        # P_dep = W1 (P1_dep / omega) W1^T + W2 (P2_dep / (1 - omega)) W2^T.
        P = P_ind + P_dep
        W1 = P @ inv(P1d / omega + P1i)
        W2 = P @ inv(P2d / (1.0 - omega) + P2i)
        assert_close_scaled(W1 + W2, np.eye(n), 1e-9)
        assert_close_scaled(P_dep, W1 @ P1d @ W1.T / omega + W2 @ P2d @ W2.T / (1 - omega),
                            1e-9)
        # No larger than the bounded inputs.
        assert_psd(P1d / omega + P1i - P, atol=1e-9 * scale)
        assert_psd(P2d / (1.0 - omega) + P2i - P, atol=1e-9 * scale)


@pytest.mark.parametrize('n', [2, 3])
def test_sci_with_zero_dependent_parts_is_fuse(n, rng):
    zero = np.zeros((n, n))
    for _ in range(30):
        m1, m2 = rng.normal(0.0, 3.0, (2, n))
        P1, P2 = spd(rng, n), spd(rng, n)
        m_ref, P_ref = fuse(m1, P1, m2, P2)
        for omega in (None, 0.1, 0.5, 0.9):
            m, P_ind, P_dep = split_covariance_intersection(m1, P1, zero, m2, P2, zero, omega)
            assert_close_scaled(m, m_ref, 1e-10)
            assert_close_scaled(P_ind, P_ref, 1e-10)
            np.testing.assert_allclose(P_dep, zero, rtol=0, atol=1e-10 * np.abs(P_ref).max())


@pytest.mark.parametrize('n', [2, 3])
def test_sci_with_zero_independent_parts_is_ci(n, rng):
    zero = np.zeros((n, n))
    for _ in range(30):
        m1, m2 = rng.normal(0.0, 3.0, (2, n))
        P1, P2 = spd(rng, n), spd(rng, n)
        for omega in (0.1, 0.37, 0.5, 0.9):
            m, P_ind, P_dep = split_covariance_intersection(m1, zero, P1, m2, zero, P2, omega)
            m_ci, P_ci = covariance_intersection(m1, P1, m2, P2, omega=omega)
            assert_close_scaled(m, m_ci, 1e-10)
            assert_close_scaled(P_dep, P_ci, 1e-10)
            np.testing.assert_array_equal(P_ind, zero)
        # The default weight is the CI optimum.
        omega = split_covariance_intersection_omega(zero, P1, zero, P2)
        omega_ci = covariance_intersection_omega(P1, P2)
        assert abs(omega - omega_ci) <= 1e-6
        _, P_ci = covariance_intersection(m1, P1, m2, P2)
        _, _, P_dep = split_covariance_intersection(m1, zero, P1, m2, zero, P2)
        assert np.linalg.det(P_dep) <= np.linalg.det(P_ci) * (1.0 + 2e-2)


@pytest.mark.parametrize('omega', [0.0, 1.0, -0.1, 1.1, -1e-300, np.nextafter(1.0, 2.0),
                                   np.nan, np.inf, -np.inf, [0.5, 1.0], [np.nan, 0.5]])
def test_sci_omega_outside_open_unit_interval_raises(omega):
    eye = np.eye(2)
    bad = [w for w in np.atleast_1d(omega) if not 0.0 < w < 1.0][0]
    with pytest.raises(ValueError, match='strictly between 0 and 1'):
        split_covariance_intersection(np.zeros((2, 2)), eye, eye, np.ones((2, 2)), eye, eye,
                                      omega=omega)
    with pytest.raises(ValueError, match='strictly between 0 and 1'):
        split_covariance_intersection(np.zeros(3), np.eye(3), np.eye(3), np.ones(3),
                                      np.eye(3), np.eye(3), omega=bad)


def test_sci_rejects_mismatched_shapes():
    eye = np.eye(2)
    with pytest.raises(ValueError):
        split_covariance_intersection(np.zeros(2), np.eye(3), eye, np.zeros(2), eye, eye, 0.5)
    with pytest.raises(ValueError):
        split_covariance_intersection(np.zeros(2), eye, eye, np.zeros(3), eye, eye, 0.5)


# --- the omega search --------------------------------------------------------------------------

@pytest.fixture(scope='module')
def omega_cases():
    """Return (omega found, brute-force optimum, log det P at both) for 2D and 3D cases."""
    rng = np.random.default_rng(20240611)
    rows = []
    for n in (2, 3):
        for _ in range(60):
            parts = sci_parts(rng, n)
            omega = split_covariance_intersection_omega(*parts)
            best, minimum = brute_force_minimum(parts)
            rows.append((omega, best, sci_log_det(*parts, [omega])[0], minimum))
    return np.array(rows).T


def test_sci_omega_is_near_the_brute_force_optimum(omega_cases):
    omega, best, found, minimum = omega_cases
    assert np.all((omega > 0.0) & (omega < 1.0))
    interior = (best > 0.02) & (best < 0.98)
    assert interior.sum() > 30 and (~interior).sum() > 5   # both kinds are exercised
    # Newton to 1e-12: omega within the brute force's 1e-6 grid of an interior
    # optimum; at a bound it goes to the edge (1e-9 from it), beyond the brute force's
    # 1e-6 grid, so it may do slightly better than that grid.
    assert np.all(np.abs(omega - best)[interior] <= 2e-6)
    assert np.all(np.minimum(omega, 1.0 - omega)[~interior & ((best < 2e-6) | (best > 1 - 2e-6))]
                  <= 1e-6)


def test_sci_omega_det_within_1e5_of_minimum(omega_cases):
    _, _, found, minimum = omega_cases
    assert np.all(np.expm1(found - minimum) <= 1e-5)


def test_sci_omega_batch_equals_single(rng):
    parts = sci_parts(rng, 2, 10)
    batch = split_covariance_intersection_omega(*parts)
    assert batch.shape == (10,)
    for k in range(10):
        assert split_covariance_intersection_omega(*(p[k] for p in parts)) == batch[k]
    # Each element stops on its own: a batch with other elements gives the same bits.
    mixed = [np.concatenate([p[3:], p[:3]]) for p in parts]
    np.testing.assert_array_equal(split_covariance_intersection_omega(*mixed),
                                  np.concatenate([batch[3:], batch[:3]]))


def sci_slope(parts, w):
    """Return d/dw log det(P^-1) of split CI from explicit inverses (numpy)."""
    P1i, P1d, P2i, P2d = parts
    Ai, Bi = inv(P1d / w + P1i), inv(P2d / (1.0 - w) + P2i)
    P = inv(Ai + Bi)
    return np.trace(P @ (Ai @ P1d @ Ai / w ** 2 - Bi @ P2d @ Bi / (1.0 - w) ** 2))


def exact_sci_omega(parts):
    """Return the exact split-CI optimum: scipy's root of the slope (brentq), else the end."""
    lo, hi = 1e-7, 1.0 - 1e-7
    if sci_slope(parts, lo) <= 0.0:
        return lo
    if sci_slope(parts, hi) >= 0.0:
        return hi
    return optimize.brentq(lambda w: sci_slope(parts, w), lo, hi, xtol=1e-15, rtol=1e-15)


@pytest.mark.parametrize('n', [2, 3])
def test_sci_omega_is_the_exact_optimum(n, rng):
    # The old map searched a coarse grid (within 1e-3 of the optimum); now the optimum:
    # Newton on the exact slope for 2x2 (1e-9 here), golden section on log det (whose
    # flat top limits it to about sqrt(eps)) for other sizes.
    tol = 1e-9 if n == 2 else 1e-6
    interior = 0
    for _ in range(40):
        parts = sci_parts(rng, n)
        m1, m2 = rng.normal(0.0, 3.0, (2, n))
        omega = split_covariance_intersection_omega(*parts)
        best = exact_sci_omega(parts)
        assert sci_log_det(*parts, [omega])[0] <= sci_log_det(*parts, [best])[0] + 1e-12
        if not 1e-4 < best < 1.0 - 1e-4:
            assert min(abs(omega - best), abs(omega - 1e-9), abs(omega - 1 + 1e-9)) <= 1e-6
            continue
        interior += 1
        assert abs(omega - best) <= tol, (omega, best)
        fused = split_covariance_intersection(m1, parts[0], parts[1], m2, parts[2], parts[3])
        reference = sci_reference(m1, *parts[:2], m2, *parts[2:], best)
        for a, b in zip(fused, reference):
            assert_close_scaled(a, b, tol)
    assert interior >= 20


def quadratic_stop_cases(seed, count):
    """Return entries of random split-CI parts, from mild to 1e4 scales and near-singular."""
    rng = np.random.default_rng(seed)
    out = []
    for spread in (0.5, 2.0, 4.0):
        A = rng.normal(size=(count, 2, 2)) * 10.0 ** rng.uniform(-spread, spread, (count, 1, 1))
        floor = 10.0 ** rng.uniform(-2.0 * spread, 0.0, (count, 1, 1))
        P1 = A @ np.swapaxes(A, 1, 2) + floor * np.eye(2)
        P2 = np.roll(P1, 1, axis=0) * rng.uniform(0.1, 10.0, (count, 1, 1))
        f1, f2 = rng.uniform(0.0, 1.0, (2, count, 1, 1))
        f1[:count // 8] = 0.0       # singular dependent parts
        f2[count // 8:count // 4] = 1.0
        out.append(tuple((P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]) for P in (
            (1.0 - f1) * P1, f1 * P1, (1.0 - f2) * P2, f2 * P2)))
    return out


def test_sci_omega_quadratic_stop_agrees_with_the_full_search(monkeypatch):
    # The early stop (quadratic convergence predicts the next step below the tolerance)
    # gives the full search's weight but where log det is flat to rounding; never after
    # a jump to an end of the bracket, where the Newton steps are tiny and not converging.
    for parts in quadratic_stop_cases(3, 20_000):
        quick = gaussian.sci_omega_2x2(*parts)
        with monkeypatch.context() as patch:
            patch.setattr(_split_ci, 'OMEGA_QUADRATIC', 0.0)
            full = gaussian.sci_omega_2x2(*parts)
        difference = np.abs(quick - full)
        assert difference.max() <= 1e-6
        assert np.quantile(difference, 0.999) <= 1e-10


def test_sci_omega_quadratic_stop_saves_a_newton_step(monkeypatch):
    calls = []
    slope = _split_ci._sci_slope
    monkeypatch.setattr(_split_ci, '_sci_slope', lambda *a: calls.append(1) or slope(*a))
    parts = quadratic_stop_cases(5, 400)[0]
    counts = []
    for quadratic in (_split_ci.OMEGA_QUADRATIC, 0.0):
        monkeypatch.setattr(_split_ci, 'OMEGA_QUADRATIC', quadratic)
        calls.clear()
        for i in range(100, 400):   # one element at a time: a call per Newton step
            gaussian.sci_omega_2x2(*(tuple(x[i:i + 1] for x in part) for part in parts))
        counts.append(len(calls))
    assert counts[0] <= counts[1] - 0.15 * 300, counts     # 1479 against 1554 here


def test_sci_omega_stays_inside_a_collapsed_bracket():
    # Found by test_gaussian's range test: scales 1e-12 to 1e12 make the slope rounding
    # noise; the bracket narrows to nothing while the Newton point lands past 1.
    P1i = np.array([[285288441006.45984, 444295202210.24756],
                    [444295202210.24756, 691958552321.5609]])
    P2i = np.array([[977237220955.8112, 0.0], [0.0, 1000.0]])
    P1d = np.array([[9.965365501409348e-06, -2.1774718636614557e-05],
                    [-2.1774718636614557e-05, 4.757862925559931e-05]])
    P2d = 1.0232929922807536e-12 * np.eye(2)
    omega = split_covariance_intersection_omega(P1i, P1d, P2i, P2d)
    assert 0.8 < omega < 0.85


def test_ci_omega_is_the_exact_optimum(rng):
    for _ in range(40):
        P1, P2 = spd(rng, 2), spd(rng, 2)
        omega = covariance_intersection_omega(P1, P2)
        A, B = inv(P1), inv(P2)

        def slope(w):
            return np.trace(inv(w * A + (1.0 - w) * B) @ (A - B))

        if slope(0.0) > 0.0 > slope(1.0):
            best = optimize.brentq(slope, 0.0, 1.0, xtol=1e-15, rtol=1e-15)
            assert abs(omega - best) <= 1e-9
        else:
            assert omega == (1.0 if slope(1.0) >= 0.0 else 0.0)


def test_sci_omega_with_singular_dependent_parts(rng):
    # Zero or rank-1 dependent parts keep the objective finite (multiplied-out form).
    P1i, P2i = spd(rng, 2), spd(rng, 2)
    v = rng.standard_normal(2)
    for P1d, P2d in ((np.zeros((2, 2)), np.outer(v, v)), (np.outer(v, v), np.zeros((2, 2))),
                     (np.outer(v, v), 3.0 * np.outer(v, v))):
        omega = split_covariance_intersection_omega(P1i, P1d, P2i, P2d)
        assert 0.0 < omega < 1.0
        parts = (P1i, P1d, P2i, P2d)
        _, minimum = brute_force_minimum(parts)
        found = sci_log_det(*parts, [omega])[0]
        assert found <= minimum + 1e-5


# --- consistency with known correlations -------------------------------------------------------

SAMPLES = 200_000


def correlated(rng, L1, L2, rho, count):
    """Return errors with covariances L1 L1^T, L2 L2^T and cross-covariance rho L1 L2^T."""
    a, b = rng.standard_normal((2, count, L1.shape[0]))
    return a @ L1.T, (rho * a + np.sqrt(1.0 - rho ** 2) * b) @ L2.T


def true_covariance(W1, W2, P1, P2, C):
    """Return the covariance of ``W1 e1 + W2 e2`` given cov(e1, e2) = C."""
    return W1 @ P1 @ W1.T + W2 @ P2 @ W2.T + W1 @ C @ W2.T + W2 @ C.T @ W1.T


def nees(m, x, P):
    """Mean squared Mahalanobis error of the estimates ``m`` of ``x`` (one ``P``)."""
    d = m - x
    return float(np.mean(np.sum(d * np.linalg.solve(P, d.T).T, axis=1)))


def max_excess(P, true):
    """Largest eigenvalue of ``true - P``: > 0 where the estimate is over-confident."""
    return float(np.linalg.eigvalsh(true - P)[-1])


@pytest.mark.parametrize('rho', [-0.9, 0.0, 0.5, 1.0])
def test_sci_and_ci_are_consistent_for_any_dependent_correlation(rho, rng):
    n = 2
    x = rng.normal(0.0, 5.0, n)
    P1i, P1d, P2i, P2d = sci_parts(rng, n)
    L1d, L2d = np.linalg.cholesky(P1d), np.linalg.cholesky(P2d)
    C = rho * L1d @ L2d.T   # cross-covariance of the dependent errors
    d1, d2 = correlated(rng, L1d, L2d, rho, SAMPLES)
    i1 = rng.standard_normal((SAMPLES, n)) @ np.linalg.cholesky(P1i).T
    i2 = rng.standard_normal((SAMPLES, n)) @ np.linalg.cholesky(P2i).T
    m1, m2 = x + d1 + i1, x + d2 + i2
    P1, P2 = P1i + P1d, P2i + P2d
    # The samples have the intended covariances.
    joint = np.cov(np.hstack([m1, m2]).T)
    np.testing.assert_allclose(joint, np.block([[P1, C], [C.T, P2]]), rtol=0,
                               atol=0.02 * np.abs(joint).max())

    for omega in (None, 0.3, 0.7):
        m, P_ind, P_dep = split_covariance_intersection(m1, P1i, P1d, m2, P2i, P2d, omega)
        P = P_ind[0] + P_dep[0]
        np.testing.assert_array_equal(P_ind[0], P_ind[-1])
        w = split_covariance_intersection_omega(P1i, P1d, P2i, P2d) if omega is None else omega
        W1 = P @ inv(P1d / w + P1i)
        W2 = P @ inv(P2d / (1.0 - w) + P2i)
        true = true_covariance(W1, W2, P1, P2, C)
        # Analytic: P bounds the true error covariance whatever rho.
        assert max_excess(P, true) <= 1e-10 * np.abs(P).max()
        # The estimator really is W1 m1 + W2 m2, and Monte Carlo agrees.
        np.testing.assert_allclose(m[:5], m1[:5] @ W1.T + m2[:5] @ W2.T, rtol=0, atol=1e-9)
        empirical = np.cov((m - x).T)
        np.testing.assert_allclose(empirical, true, rtol=0, atol=0.02 * np.abs(true).max())
        assert max_excess(P, empirical) <= 0.02 * np.abs(P).max()
        assert nees(m, x, P) <= 2.0 + 0.03

    # Covariance intersection: the whole covariance is treated as dependent.
    C_total = C   # independent parts are uncorrelated
    for omega in (None, 0.3, 0.7):
        m, P = covariance_intersection(m1, P1, m2, P2, omega)
        P = P[0]
        w = covariance_intersection_omega(P1, P2) if omega is None else omega
        W1, W2 = w * P @ inv(P1), (1.0 - w) * P @ inv(P2)
        true = true_covariance(W1, W2, P1, P2, C_total)
        assert max_excess(P, true) <= 1e-10 * np.abs(P).max()
        assert max_excess(P, np.cov((m - x).T)) <= 0.02 * np.abs(P).max()
        assert nees(m, x, P) <= 2.0 + 0.03


def test_ci_is_consistent_with_an_arbitrary_cross_covariance(rng):
    # Joint covariances of any rank; the cross-covariance is not split in any way.
    n = 2
    for _ in range(3):
        L = rng.standard_normal((2 * n, 2 * n - 1))
        joint = L @ L.T + 1e-2 * np.eye(2 * n)
        P1, P2 = joint[:n, :n], joint[n:, n:]
        x = rng.normal(0.0, 5.0, n)
        e = rng.standard_normal((SAMPLES, 2 * n)) @ np.linalg.cholesky(joint).T
        m, P = covariance_intersection(x + e[:, :n], P1, x + e[:, n:], P2)
        assert max_excess(P[0], np.cov((m - x).T)) <= 0.02 * np.abs(P[0]).max()
        assert nees(m, x, P[0]) <= 2.0 + 0.03


@pytest.mark.parametrize('rho', [0.5, 1.0])
def test_independent_fusion_is_over_confident_with_correlated_errors(rho, rng):
    # Dependent errors dominate (90 %); both estimates have the same shape.
    n = 2
    x = rng.normal(0.0, 5.0, n)
    D = spd(rng, n)
    I_part = 0.1 * D + 0.01 * np.eye(n)
    L = np.linalg.cholesky(D)
    d1, d2 = correlated(rng, L, L, rho, SAMPLES)
    if rho == 1.0:
        np.testing.assert_array_equal(d1, d2)   # the identical dependent error
    Li = np.linalg.cholesky(I_part)
    m1 = x + d1 + rng.standard_normal((SAMPLES, n)) @ Li.T
    m2 = x + d2 + rng.standard_normal((SAMPLES, n)) @ Li.T
    P1 = P2 = D + I_part

    m, P = fuse(m1, P1, m2, P2)
    true = true_covariance(0.5 * np.eye(n), 0.5 * np.eye(n), P1, P2, rho * D)
    assert max_excess(P[0], true) > 0.1 * np.abs(P[0]).max()        # analytic
    assert max_excess(P[0], np.cov((m - x).T)) > 0.1 * np.abs(P[0]).max()   # sampled
    independent = nees(m, x, P[0])
    assert independent > (3.5 if rho == 1.0 else 2.6)

    m, P = covariance_intersection(m1, P1, m2, P2)
    assert nees(m, x, P[0]) <= 2.0 + 0.03
    m, P_ind, P_dep = split_covariance_intersection(m1, I_part, D, m2, I_part, D)
    assert nees(m, x, P_ind[0] + P_dep[0]) <= 2.0 + 0.03


def test_nees_is_tight_when_the_errors_are_independent(rng):
    # The Monte Carlo check can tell a consistent, tight fusion (NEES ~ 2) apart.
    n = 2
    x = rng.normal(0.0, 5.0, n)
    P1, P2 = spd(rng, n), spd(rng, n)
    m1 = x + rng.standard_normal((SAMPLES, n)) @ np.linalg.cholesky(P1).T
    m2 = x + rng.standard_normal((SAMPLES, n)) @ np.linalg.cholesky(P2).T
    m, P = fuse(m1, P1, m2, P2)
    assert abs(nees(m, x, P[0]) - 2.0) <= 0.03
    zero = np.zeros((n, n))
    m, P_ind, P_dep = split_covariance_intersection(m1, P1, zero, m2, P2, zero)
    assert abs(nees(m, x, P_ind[0] + P_dep[0]) - 2.0) <= 0.03
    # CI ignores the independence: conservative, NEES clearly below 2.
    m, P = covariance_intersection(m1, P1, m2, P2)
    assert nees(m, x, P[0]) < 1.9


# --- closed-form 2x2 paths equal the generic computations --------------------------------------

def _block_diag_3(P2x2, extra):
    """Embed 2x2 matrices in 3x3 ones with an uncoupled third axis."""
    P2x2 = np.asarray(P2x2)
    out = np.zeros(P2x2.shape[:-2] + (3, 3))
    out[..., :2, :2] = P2x2
    out[..., 2, 2] = extra
    return out


def test_fuse_2x2_matches_information_form(rng):
    count = 300
    scales = 10.0 ** rng.uniform(-4, 4, count)
    m1, m2 = rng.normal(0.0, 3.0, (2, count, 2)) * scales[:, None]
    P1 = random_spd(rng, 2, count) * scales[:, None, None] ** 2
    P2 = random_spd(rng, 2, count) * scales[:, None, None] ** 2
    m, P = fuse(m1, P1, m2, P2)
    Y1, Y2 = inv(P1), inv(P2)
    P_ref = inv(Y1 + Y2)
    m_ref = (P_ref @ (Y1 @ m1[..., None] + Y2 @ m2[..., None]))[..., 0]
    for k in range(count):
        s = scales[k]
        np.testing.assert_allclose(P[k], P_ref[k], rtol=0, atol=1e-8 * s * s * max(
            1.0, np.abs(P_ref[k]).max() / s ** 2))
        np.testing.assert_allclose(m[k], m_ref[k], rtol=0, atol=1e-8 * s * max(
            1.0, np.abs(m_ref[k]).max() / s))
    np.testing.assert_array_equal(P, T(P))


def test_fuse_2x2_matches_the_generic_path(rng):
    count = 200
    m1, m2 = rng.normal(0.0, 3.0, (2, count, 2))
    P1, P2 = random_spd(rng, 2, count), random_spd(rng, 2, count)
    # One input singular in some rows (an exactly known direction).
    v = rng.standard_normal((count, 2))
    P1[::4] = v[::4, :, None] * v[::4, None, :]
    m, P = fuse(m1, P1, m2, P2)
    m3, P3 = fuse(np.c_[m1, np.zeros(count)], _block_diag_3(P1, 1.0),
                  np.c_[m2, np.zeros(count)], _block_diag_3(P2, 1.0))
    assert_close_scaled(m, m3[:, :2], 1e-9)
    assert_close_scaled(P, P3[:, :2, :2], 1e-9)
    # Covariance form written out with numpy: P = P1 S^-1 P2, m = m1 + P1 S^-1 (m2 - m1).
    K = P1 @ inv(P1 + P2)
    assert_close_scaled(P, K @ P2, 1e-9)
    assert_close_scaled(m, m1 + (K @ (m2 - m1)[..., None])[..., 0], 1e-9)
    # The singular rows know the direction perpendicular to v exactly: m keeps m1 there.
    u = np.stack([-v[::4, 1], v[::4, 0]], axis=1)
    d = np.einsum('ki,ki->k', u, m[::4] - m1[::4])
    np.testing.assert_allclose(d, 0.0, rtol=0, atol=1e-9 * np.abs(m).max())
    np.testing.assert_allclose(np.einsum('ki,kij,kj->k', u, P[::4], u), 0.0, rtol=0,
                               atol=1e-9 * np.abs(P).max())


def test_fuse_2x2_with_an_exact_estimate(rng):
    m1, m2 = rng.normal(0.0, 3.0, (2, 2))
    m, P = fuse(m1, np.zeros((2, 2)), m2, spd(rng, 2))
    np.testing.assert_allclose(m, m1, rtol=0, atol=1e-14)
    np.testing.assert_allclose(P, np.zeros((2, 2)), rtol=0, atol=1e-15)


def test_ci_omega_2x2_matches_brute_force_and_golden_section(rng):
    grid = np.linspace(0.0, 1.0, 20_001)
    cases = [random_spd(rng, 2, 2) for _ in range(150)]
    scale = 10.0 ** rng.uniform(-3, 3)
    cases += [(P1 * scale, P2 * scale) for P1, P2 in cases[:20]]
    cases += [(np.eye(2), np.eye(2)), (np.diag([1.0, 4.0]), np.diag([4.0, 1.0])),
              (np.eye(2), 2.0 * np.eye(2)), (3.0 * np.eye(2), np.eye(2))]
    interior = 0
    for P1, P2 in cases:
        omega = covariance_intersection_omega(P1, P2)
        assert 0.0 <= omega <= 1.0
        A, B = inv(P1), inv(P2)

        def log_det_info(w):
            w = np.atleast_1d(w)[:, None, None]
            return np.linalg.slogdet(w * A + (1.0 - w) * B)[1]

        values = log_det_info(grid)
        at = log_det_info(omega)[0]
        assert at >= values.max() - 1e-12
        golden = gaussian._omega_golden(A, B)
        assert at >= log_det_info(golden)[0] - 1e-12
        best = grid[int(np.argmax(values))]
        if 0.01 < best < 0.99:
            interior += 1
            # Interior optimum: the stationary point, found exactly (unlike the grid).
            assert abs(omega - golden) <= 1e-6
            assert abs(omega - best) <= 1e-4
    assert interior > 40


def test_ci_2x2_matches_the_generic_path(rng):
    count = 100
    m1, m2 = rng.normal(0.0, 3.0, (2, count, 2))
    P1, P2 = random_spd(rng, 2, count), random_spd(rng, 2, count)
    omegas = rng.uniform(0.0, 1.0, count)
    m, P = covariance_intersection(m1, P1, m2, P2, omegas)
    m3, P3 = covariance_intersection(np.c_[m1, np.zeros(count)], _block_diag_3(P1, 1.0),
                                     np.c_[m2, np.zeros(count)], _block_diag_3(P2, 1.0),
                                     omegas)
    assert_close_scaled(m, m3[:, :2], 1e-9)
    assert_close_scaled(P, P3[:, :2, :2], 1e-9)


def test_split_ci_2x2_matches_the_generic_path(rng):
    count = 100
    m1, m2 = rng.normal(0.0, 3.0, (2, count, 2))
    parts = sci_parts(rng, 2, count)
    omegas = rng.uniform(0.01, 0.99, count)
    out2 = split_covariance_intersection(m1, *parts[:2], m2, *parts[2:], omegas)
    # The generic (n = 3) path on block-diagonal embeddings: the third axis does not
    # couple, so the 2x2 blocks must agree with the closed form.
    embedded = [_block_diag_3(p, e) for p, e in zip(parts, (0.5, 0.25, 1.0, 2.0))]
    out3 = split_covariance_intersection(np.c_[m1, np.zeros(count)], *embedded[:2],
                                         np.c_[m2, np.zeros(count)], *embedded[2:], omegas)
    assert_close_scaled(out2[0], out3[0][:, :2], 1e-9)
    assert_close_scaled(out2[1], out3[1][:, :2, :2], 1e-9)
    assert_close_scaled(out2[2], out3[2][:, :2, :2], 1e-9)
    # And the closed form itself against the definition written out with numpy.
    for k in range(count):
        ref = sci_reference(m1[k], *(p[k] for p in parts[:2]), m2[k],
                            *(p[k] for p in parts[2:]), omegas[k])
        for out, r in zip(out2, ref):
            assert_close_scaled(out[k], r, 1e-9)
    # The private closed form is what the public function returns.
    e = gaussian.entries_2x2
    direct = _split_ci._split_ci_2x2(m1, e(parts[0]), e(parts[1]), m2, e(parts[2]),
                                     e(parts[3]), omegas)
    for a, b in zip(direct, out2):
        np.testing.assert_array_equal(a, b)


def test_split_ci_omega_2x2_objective_matches_the_generic_one(rng):
    # The 2x2 and generic objectives pick the same grid point on embedded problems.
    count = 60
    parts = sci_parts(rng, 2, count)
    omega2 = split_covariance_intersection_omega(*parts)
    # The third axis adds a factor to det(P^-1) that depends on omega, so embed with
    # zero dependent part and identical independent parts: its factor is constant.
    embedded = [_block_diag_3(p, e) for p, e in zip(parts, (1.0, 0.0, 1.0, 0.0))]
    omega3 = split_covariance_intersection_omega(*embedded)
    # Both paths find the same optimum; the parabolic step lands within float noise.
    np.testing.assert_allclose(omega2, omega3, rtol=0, atol=1e-6)
    for k in range(count):
        single = [p[k] for p in parts]
        a, b = sci_log_det(*single, [omega2[k], omega3[k]])
        assert abs(a - b) <= 1e-10
