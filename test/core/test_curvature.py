"""Tests of landmark_ros.core.curvature: second derivatives and relative curvatures."""

from conftest import numerical_jacobian
from landmark_ros.core import curvature as cv
from landmark_ros.core import sensors
import numpy as np
import pytest
from scipy.stats import chi2

SEEDS = range(20)


def test_confidence_radius_is_the_2_dof_chi_square_quantile():
    assert cv.CONFIDENCE_RADIUS_95 ** 2 == pytest.approx(chi2.ppf(0.95, 2), rel=1e-12)


@pytest.mark.parametrize('seed', SEEDS)
def test_hessians_match_central_differences_of_the_jacobians(seed):
    rng = np.random.default_rng(seed)
    pose = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
    m = pose[:2] + rng.uniform(0.5, 8.0) * np.array([np.cos(a := rng.uniform(-4, 4)),
                                                     np.sin(a)])
    H = cv.observe_hessians(pose, m)
    assert H.shape == (2, 2, 2) and H.dtype == np.float64
    for k in range(2):
        def row(x, k=k):
            return sensors.observe_jacobians(pose, x)[1][k]
        numeric = numerical_jacobian(row, m)
        np.testing.assert_allclose(H[k], numeric, rtol=0, atol=1e-6)
        np.testing.assert_allclose(H[k], H[k].T, rtol=0, atol=1e-15)


def test_hessians_batch_like_single_items_and_refuse_a_landmark_on_the_sensor():
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(-5, 5, (6, 2)), rng.uniform(-3, 3, 6)])
    m = rng.uniform(6, 9, (6, 2))
    batch = cv.observe_hessians(poses, m)
    assert batch.shape == (6, 2, 2, 2)
    for i in range(6):
        np.testing.assert_allclose(batch[i], cv.observe_hessians(poses[i], m[i]), atol=0)
    with pytest.raises(ValueError, match='range'):
        cv.observe_hessians(np.zeros(3), np.zeros(2))


def _model_curvatures(f, m, R, step=1e-4):
    """
    Return the reference curvatures of the whitened model ``f`` (N views at ``m``).

    Accelerations from central second differences along each direction, split by the
    tangent plane.
    """
    w = 1.0 / np.sqrt(R)
    J = numerical_jacobian(lambda x: f(x) * w, m)
    Q, upper = np.linalg.qr(J)
    best = [0.0, 0.0]
    for angle in np.linspace(0.0, np.pi, 720, endpoint=False):
        delta = np.linalg.solve(upper, [np.cos(angle), np.sin(angle)])
        e = step * delta / np.linalg.norm(delta)
        a = (f(m + e) - 2.0 * f(m) + f(m - e)) * w / step ** 2 * (delta @ delta)
        tangent = Q @ (Q.T @ a)
        best = [max(best[0], np.linalg.norm(tangent)), max(best[1], np.linalg.norm(a - tangent))]
    return best


@pytest.mark.parametrize('seed', range(5))
def test_relative_curvatures_match_second_differences_of_the_model(seed):
    rng = np.random.default_rng(seed)
    n = 12
    s = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(-3, 3, n)])
    m = np.array([6.0, 4.0])
    kind = rng.integers(0, 2, n)
    R = np.where(kind == 0, 0.01, 4e-4) * rng.uniform(0.5, 2.0, n)

    def f(x):
        return sensors.observe(s, x)[np.arange(n), kind]

    J = sensors.observe_jacobians(s, m)[1][np.arange(n), kind]
    H = cv.observe_hessians(s, m)[np.arange(n), kind]
    got = cv.relative_curvatures(J, H, R)
    expected = _model_curvatures(f, m, R)
    np.testing.assert_allclose(got, expected, rtol=2e-3)


def test_a_linear_model_has_no_curvature_and_a_rank_deficient_one_is_infinite():
    J = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    assert cv.relative_curvatures(J, np.zeros((3, 2, 2)), np.ones(3)) == (0.0, 0.0)
    assert cv.relative_curvatures(J[:, :1] * [1.0, 1.0], np.zeros((3, 2, 2)),
                                  np.ones(3)) == (np.inf, np.inf)


def test_curvature_grows_as_the_views_get_more_precise_relative_to_the_bend():
    """
    Ranges from a short arc: the valley is curved on the scale of the noise.

    Halving the noise standard deviation halves the region: the curvature in
    standard deviations halves too (it scales with the standard deviation).
    """
    angle = np.linspace(-0.3, 0.3, 20)
    s = np.column_stack([5.0 * np.cos(angle), 5.0 * np.sin(angle), np.zeros(20)])
    m = np.array([0.5, 0.3])
    J = sensors.observe_jacobians(s, m)[1][:, 0]
    H = cv.observe_hessians(s, m)[:, 0]
    loose = cv.relative_curvatures(J, H, np.full(20, 0.01))
    tight = cv.relative_curvatures(J, H, np.full(20, 0.0025))
    np.testing.assert_allclose(tight, 0.5 * np.array(loose), rtol=1e-9)
    assert loose[0] > loose[1] > 0.0    # the banana is parameter effects mostly
