"""Range views with a bearing-dependent scale (``Views.range_scale``): model and checks."""

from conftest import numerical_jacobian
from landmark_ros.core import partial, range_scale, sensors
from landmark_ros.core.partial import (BEARING, linearise, observe_views,
                                       observe_views_jacobians, RANGE, residuals, Views)
import numpy as np
import pytest

LENS = (0.0455, -0.005, -0.4646)     # MRCLAM's camera (docs/evaluation.md)
LIMIT = 0.59


def random_views(rng, count, kind=RANGE):
    s = np.column_stack([rng.uniform(-2, 2, count), rng.uniform(-2, 2, count),
                         rng.uniform(-np.pi, np.pi, count)])
    A = rng.normal(size=(count, 3, 3)) * 0.05
    q = np.column_stack([rng.uniform(-0.05, 0.05, count), rng.uniform(-0.05, 0.05, count),
                         rng.uniform(-0.5, 0.0, count)])
    return Views(kind, s, A @ np.swapaxes(A, 1, 2), rng.uniform(1, 5, count), 0.01, 0.0, q,
                 rng.uniform(0.3, 0.9, count))


def in_view(views, rng):
    """Return landmarks in front of each sensor, inside its bearing limit, 1 to 5 m away."""
    b = rng.uniform(-0.9, 0.9, len(views)) * views.range_scale_bearing_limit
    r = rng.uniform(1.0, 5.0, len(views))
    heading = views.s[:, 2] + b
    return views.s[:, :2] + r[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])


def test_a_range_view_predicts_the_reading_of_the_lens_model(rng):
    # range_scale.scale is the reading's scale at the true bearing (k = 0): the same value.
    views = Views(RANGE, [0.5, -0.2, 0.3], np.zeros((3, 3)), 3.0, 0.01, 0.0, LENS, LIMIT)
    for b in np.linspace(-0.5, 0.5, 11):
        m = views.s[0, :2] + 2.5 * np.array([np.cos(0.3 + b), np.sin(0.3 + b)])
        g = range_scale.scale([2.5, b], LENS)
        assert observe_views(views, m)[0] == pytest.approx(2.5 * g, abs=1e-12)


def test_without_a_range_scale_observe_views_is_observe_view(rng):
    views = random_views(rng, 20)
    plain = Views(views.kind, views.s, views.P_s, views.y, views.R)
    m = in_view(views, rng)
    np.testing.assert_allclose(observe_views(plain, m), partial.observe_view(
        plain.kind, plain.s, m)[:, 0], rtol=0, atol=1e-12)
    J_s, J_m = partial.observe_view_jacobians(plain.kind, plain.s, m)
    np.testing.assert_allclose(observe_views_jacobians(plain, m)[0], J_s, atol=1e-12)
    np.testing.assert_allclose(observe_views_jacobians(plain, m)[1], J_m, atol=1e-12)


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_jacobians_match_central_differences_inside_and_beyond_the_limit(rng, kind):
    views = random_views(rng, 12, kind)
    m = in_view(views, rng)
    # Half of the landmarks outside the field of view: the scale is constant there.
    outside = np.arange(len(views)) % 2 == 1
    b = np.where(outside, 1.3, 1.0) * sensors.observe(views.s, m)[:, 1]
    b = np.where(outside, np.sign(b) * (views.range_scale_bearing_limit + 0.2), b)
    r = np.hypot(*(m - views.s[:, :2]).T)
    heading = views.s[:, 2] + b
    m = views.s[:, :2] + r[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    J_h_s, J_h_m = observe_views_jacobians(views, m)
    angle = [0] if kind == BEARING else []
    for n in range(len(views)):
        one = views[n]

        def at_m(x, one=one):
            return observe_views(one, x)

        def at_s(x, one=one):
            return observe_views(Views(one.kind, x, one.P_s, one.y, one.R, one.R_bias,
                                       one.range_scale, one.range_scale_bearing_limit), m[n])
        np.testing.assert_allclose(J_h_m[n], numerical_jacobian(at_m, m[n], angle),
                                   rtol=0, atol=1e-8)
        np.testing.assert_allclose(J_h_s[n], numerical_jacobian(at_s, views.s[n], angle),
                                   rtol=0, atol=1e-8)


def test_a_batch_equals_its_views_one_by_one(rng):
    views = Views.concatenate([random_views(rng, 6), random_views(rng, 6, BEARING)])
    m = in_view(views, rng)
    lin = linearise(views, m)
    for n in range(len(views)):
        one = linearise(views[n], m[n])
        for name in ('residual', 'J_h_s', 'J_h_m', 'R_eff', 'R_dep'):
            np.testing.assert_allclose(getattr(lin, name)[n], getattr(one, name)[0],
                                       rtol=0, atol=1e-14)
    np.testing.assert_allclose(residuals(views, m), lin.residual, rtol=0, atol=0)


def test_views_refuse_a_scale_that_is_not_a_model_of_a_lens():
    args = (RANGE, [0, 0, 0], np.zeros((3, 3)), 2.0, 0.01, 0.0)
    with pytest.raises(ValueError, match='bearing limit'):
        Views(*args, LENS, 0.0)
    with pytest.raises(ValueError, match='bearing limit'):
        Views(*args, LENS, 4.0)
    with pytest.raises(ValueError, match='finite'):
        Views(*args, (np.nan, 0, 0), LIMIT)
    with pytest.raises(ValueError, match='below'):
        Views(*args, LENS, np.pi)      # the polynomial is -3.6 at pi: not a scale
    with pytest.raises(ValueError, match='shape'):
        Views(*args, (0.0, 0.0), LIMIT)


def test_initialise_places_a_landmark_from_lens_scaled_ranges(rng):
    # Noise-free readings of a camera with MRCLAM's lens: the model recovers the truth;
    # the plain range model is off by the scale.
    m_true = np.array([2.0, 1.0])
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    xy = m_true + 2.5 * np.column_stack([np.cos(angles), np.sin(angles)])
    b = rng.uniform(-0.5, 0.5, len(angles))
    theta = np.arctan2(*(m_true - xy).T[::-1]) - b
    s = np.column_stack([xy, theta])
    r = np.hypot(*(m_true - xy).T) * range_scale.scale(np.column_stack([np.zeros(12), b]),
                                                       LENS)
    P_s = np.eye(3) * 1e-6
    lens = Views(RANGE, s, P_s, r, 1e-4, 0.0, LENS, LIMIT)
    placed = partial.initialise(lens, partial.InitialiseParams())
    assert placed.ok
    np.testing.assert_allclose(placed.m, m_true, atol=1e-6)
    plain = partial.initialise(Views(RANGE, s, P_s, r, 1e-4), partial.InitialiseParams())
    assert not plain.ok or np.hypot(*(plain.m - m_true)) > 10 * np.hypot(*(placed.m - m_true))
