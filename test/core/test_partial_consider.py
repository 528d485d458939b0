"""The update with the view's sensor bias as a consider state (``partial.update_consider``)."""

from landmark_ros.core import partial
from landmark_ros.core.partial import BEARING, RANGE, update, update_consider, Views
import numpy as np
import pytest
from scipy.stats import chi2

SPLIT = 'split_covariance_intersection'


def random_case(rng, count, kind):
    s = np.column_stack([rng.uniform(-3, 3, count), rng.uniform(-3, 3, count),
                         rng.uniform(-np.pi, np.pi, count)])
    A = rng.normal(size=(count, 3, 3)) * 0.02
    m = s[:, :2] + rng.uniform(1.5, 4.0, (count, 1)) * np.column_stack(
        [np.cos(s[:, 2]), np.sin(s[:, 2])])
    B = rng.normal(size=(count, 2, 2)) * 0.05
    P_dep = B @ np.swapaxes(B, 1, 2) * 0.5
    P_m = P_dep + np.eye(2) * 0.002
    y = partial.observe_views(Views(kind, s, A @ np.swapaxes(A, 1, 2), 1.0, 1e-4), m)
    noise = 0.02 if kind == RANGE else 0.01
    views = Views(kind, s, A @ np.swapaxes(A, 1, 2), y + rng.normal(0, noise, count),
                  noise ** 2, (0.5 * noise) ** 2)
    return m + rng.normal(0, 0.03, (count, 2)), P_m, views, P_dep


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_a_bias_uncorrelated_with_the_landmark_is_independent_noise(rng, kind):
    m, P_m, views, P_dep = random_case(rng, 30, kind)
    moved = Views(views.kind, views.s, views.P_s, views.y, views.R + views.R_bias)
    plain = update(m, P_m, moved, P_dep, SPLIT)
    result, c = update_consider(m, P_m, views, P_dep, np.zeros(2))
    for name in ('m', 'P_m', 'P_m_dep', 'innovation', 'S', 'omega', 'status', 'iterations',
                 'L'):
        np.testing.assert_allclose(getattr(result, name), getattr(plain, name), rtol=1e-9,
                                   atol=1e-14, err_msg=name)
    K = (result.m - m) / np.where(result.updated, result.innovation, np.inf)[:, None]
    np.testing.assert_allclose(c, K * np.sqrt(views.R_bias)[:, None], atol=1e-14)


def test_a_batch_equals_its_rows_one_by_one(rng):
    m, P_m, views, P_dep = random_case(rng, 8, RANGE)
    c = rng.normal(0, 0.005, (8, 2))
    batch, c_batch = update_consider(m, P_m, views, P_dep, c)
    for n in range(8):
        one, c_one = update_consider(m[n], P_m[n], views[n], P_dep[n], c[n])
        np.testing.assert_allclose(batch.m[n], one.m[0], atol=1e-14)
        np.testing.assert_allclose(batch.P_m[n], one.P_m[0], atol=1e-14)
        np.testing.assert_allclose(c_batch[n], c_one[0], atol=1e-14)


def _sequence(rng, method, views_per_run=40):
    """One landmark, one robot circling it with a constant range bias: final NEES."""
    m_true = np.zeros(2)
    bias_sd, noise_sd = 0.05, 0.01
    bias = rng.normal(0, bias_sd)
    P = np.eye(2) * 0.2 ** 2
    m = m_true + rng.multivariate_normal(np.zeros(2), P)
    P_dep, c = np.zeros((2, 2)), np.zeros(2)
    for angle in np.linspace(0, 4 * np.pi, views_per_run, endpoint=False):
        s = np.array([3 * np.cos(angle), 3 * np.sin(angle), angle + np.pi])
        y = 3.0 + bias + rng.normal(0, noise_sd)
        views = Views(RANGE, s, np.zeros((3, 3)), y, noise_sd ** 2, bias_sd ** 2)
        if method == 'consider':
            result, c = update_consider(m, P, views, P_dep, c)
            c = c[0]
        else:
            result = update(m, P, views, P_dep, method)
        m, P, P_dep = result.m[0], result.P_m[0], result.P_m_dep[0]
    d = m - m_true
    return d @ np.linalg.solve(P, d)


@pytest.mark.parametrize('method, consistent', [
    ('consider', True), (SPLIT, False), ('independent', False)])
def test_a_constant_bias_seen_from_every_side_counts_once(rng, method, consistent):
    runs = 100
    anees = np.mean([_sequence(rng, method) for _ in range(runs)])
    low, high = chi2.ppf([0.0005, 0.9995], 2 * runs) / runs
    print(f'{method}: ANEES {anees:.2f}, interval [{low:.2f}, {high:.2f}]')
    assert (low <= anees <= high) == consistent, anees
