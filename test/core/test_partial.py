"""Tests of landmark_ros.core.partial: range-only and bearing-only views."""

from dataclasses import replace

from conftest import assert_jacobians, assert_psd, numerical_jacobian, random_spd
from landmark_ros.core import curvature as cv
from landmark_ros.core import partial as pt
from landmark_ros.core import pose2, sensors
from landmark_ros.core.landmarks import nees, sensor_in_world
import numpy as np
import pytest
from scipy.stats import chi2

SEEDS = range(50)
MOUNT = np.array([0.2, 0.05, 0.1])
P_S = np.diag([1e-4, 1e-4, 1e-5])


def _exact_views(kind, s, m, P_s=P_S, R=1e-4, R_bias=0.0):
    """Return noise-free views of ``m`` from sensor poses ``s``."""
    y = pt.observe_view(kind, s, m)[:, 0]
    return pt.Views(kind, s, P_s, y, R, R_bias)


def _sensors_around(rng, m, n, r_min=2.0, r_max=12.0):
    """Return sensor poses around ``m`` roughly facing it, shape (n, 3)."""
    angle = rng.uniform(-np.pi, np.pi, n)
    dist = rng.uniform(r_min, r_max, n)
    xy = m + dist[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    heading = pose2.wrap_angle(angle + np.pi + rng.uniform(-0.5, 0.5, n))
    return np.column_stack([xy, heading])


def _ray_intersection(s1, phi1, s2, phi2):
    """Solve ``s1 + t1 d1 = s2 + t2 d2`` directly (the independent reference)."""
    d1 = np.array([np.cos(phi1), np.sin(phi1)])
    d2 = np.array([np.cos(phi2), np.sin(phi2)])
    t = np.linalg.solve(np.column_stack([d1, -d2]), s2 - s1)
    return s1 + t[0] * d1


# --- Views -------------------------------------------------------------------------------

def test_views_broadcast_names_and_wrap():
    v = pt.Views(['range', 'bearing'], np.zeros(3), P_S, [2.0, 3.5 * np.pi], 0.01)
    assert len(v) == 2
    np.testing.assert_array_equal(v.kind, [pt.RANGE, pt.BEARING])
    assert v.s.shape == (2, 3) and v.P_s.shape == (2, 3, 3) and v.R_bias.shape == (2,)
    assert v.y[1] == pytest.approx(-0.5 * np.pi)
    assert len(v[1]) == 1 and len(v[-1]) == 1 and v[-1].kind[0] == pt.BEARING
    assert len(pt.Views.concatenate([v, v[0]])) == 3
    with pytest.raises(ValueError):
        v.y[0] = 1.0   # read-only


@pytest.mark.parametrize('change', [
    {'kind': 'camera'}, {'kind': 2}, {'R': 0.0}, {'R_bias': -1.0}, {'y': np.nan},
    {'s': np.zeros(2)}, {'P_s': -np.eye(3)}, {'P_s': np.triu(np.ones((3, 3)))},
    {'y': np.zeros(3), 'R': np.ones(2)},
])
def test_views_reject_bad_input(change):
    args = {'kind': 'range', 's': np.zeros(3), 'P_s': P_S, 'y': 1.0, 'R': 0.01}
    args.update(change)
    with pytest.raises(ValueError):
        pt.Views(**args)


def test_views_from_robot_compose_the_mounting(rng):
    pose = np.array([1.0, 2.0, 3.0])
    P_pose = random_spd(rng, 3, scale=0.1)
    v = pt.views_from_robot('bearing', pose, P_pose, 0.3, 1e-4, sensor_pose=MOUNT)
    s, P_s = sensor_in_world(pose, P_pose, MOUNT)
    np.testing.assert_allclose(v.s[0], s, atol=1e-15)
    np.testing.assert_allclose(v.P_s[0], P_s, atol=1e-15)


# --- model, Jacobians, effective variances ------------------------------------------------

def test_observe_view_is_the_column_of_observe(rng):
    s = _sensors_around(rng, np.zeros(2), 20)
    m = rng.uniform(-1, 1, (20, 2))
    z = sensors.observe(s, m)
    np.testing.assert_array_equal(pt.observe_view(pt.RANGE, s, m)[:, 0], z[:, 0])
    np.testing.assert_array_equal(pt.observe_view(pt.BEARING, s, m)[:, 0], z[:, 1])
    kinds = rng.integers(0, 2, 20)
    np.testing.assert_array_equal(pt.observe_view(kinds, s, m)[:, 0], z[np.arange(20), kinds])
    assert pt.observe_view(pt.RANGE, s[0], m[0]).shape == (1,)


@pytest.mark.parametrize('seed', SEEDS)
@pytest.mark.parametrize('kind', [pt.RANGE, pt.BEARING])
def test_view_jacobians_numerically(seed, kind):
    rng = np.random.default_rng(seed)
    s = _sensors_around(rng, np.zeros(2), 1, r_min=0.5)[0]
    if seed % 3 == 0:   # heading at +-pi
        s[2] = np.pi * (1.0 - 1e-9) * (1 if seed % 2 else -1)
    m = rng.uniform(-1, 1, 2)
    if seed % 5 == 0:   # the landmark straight behind: bearing at +-pi
        m = s[:2] - 3.0 * np.array([np.cos(s[2]), np.sin(s[2])]) + [0.0, 1e-10]
    J_h_s, J_h_m = pt.observe_view_jacobians(kind, s, m)
    assert J_h_s.shape == (1, 3) and J_h_m.shape == (1, 2)
    angle_rows = (0,) if kind == pt.BEARING else ()
    assert_jacobians(lambda s_, m_: pt.observe_view(kind, s_, m_),
                     lambda s_, m_: pt.observe_view_jacobians(kind, s_, m_), (s, m),
                     angle_rows=angle_rows)


@pytest.mark.parametrize('seed', SEEDS)
def test_effective_variance_is_the_pose_pushed_into_the_view(seed):
    rng = np.random.default_rng(seed)
    n = 6
    s = _sensors_around(rng, np.zeros(2), n)
    kinds = rng.integers(0, 2, n)
    P_s = random_spd(rng, 3, n, scale=0.05)
    views = pt.Views(kinds, s, P_s, 0.0, rng.uniform(1e-4, 1e-2, n), rng.uniform(0, 1e-3, n))
    m = rng.uniform(-1, 1, 2)
    R_eff, R_dep = pt.effective_variances(views, m)
    for i in range(n):
        J = numerical_jacobian(lambda x, i=i: pt.observe_view(kinds[i], x, m), s[i],
                               (0,) if kinds[i] == pt.BEARING else ())
        pose_term = (J @ P_s[i] @ J.T)[0, 0]
        assert R_dep[i] == pytest.approx(views.R_bias[i] + pose_term, rel=1e-6, abs=1e-15)
        assert R_eff[i] == pytest.approx(views.R[i] + R_dep[i], rel=1e-12)


def test_residuals_wrap_bearings():
    s = np.array([[0.0, 0.0, 0.0]] * 2)
    m = np.array([-5.0, 1e-3])            # bearing just below pi
    views = pt.Views([pt.BEARING, pt.RANGE], s, P_S, [-np.pi + 1e-3, 4.0], 1e-4)
    res = pt.residuals(views, m)
    assert abs(res[0]) < 3e-3
    assert res[1] == pytest.approx(4.0 - np.hypot(*m))


def test_linearise_batch_equals_single_calls(rng):
    n = 12
    s = _sensors_around(rng, np.zeros(2), n)
    views = pt.Views(rng.integers(0, 2, n), s, random_spd(rng, 3, n, 0.05),
                     rng.uniform(-3, 3, n), 1e-3, 1e-4)
    m = rng.uniform(-1, 1, (n, 2))
    batch = pt.linearise(views, m)
    for i in range(n):
        one = pt.linearise(views[i], m[i])
        for name in ('residual', 'J_h_s', 'J_h_m', 'R_eff', 'R_dep'):
            np.testing.assert_array_equal(getattr(one, name)[0], getattr(batch, name)[i])


# --- closed-form geometry -----------------------------------------------------------------

@pytest.mark.parametrize('seed', SEEDS)
def test_two_exact_bearings_give_the_ray_intersection(seed):
    rng = np.random.default_rng(seed)
    m = rng.uniform(-5, 5, 2)
    while True:
        s = _sensors_around(rng, m, 2)
        if pt.geometry(_exact_views(pt.BEARING, s, m)).reason == pt.OK:
            break
    views = _exact_views(pt.BEARING, s, m)
    # The point, whatever the uncertainty (the linearity checks have their own tests).
    init = pt.initialise(views, pt.InitialiseParams(max_relative_stddev=100.0,
                                                    max_curvature_ratio=None))
    assert init.ok, init.reason
    phi = s[:, 2] + views.y
    reference = _ray_intersection(s[0, :2], phi[0], s[1, :2], phi[1])
    np.testing.assert_allclose(init.m, reference, rtol=0, atol=1e-9)
    np.testing.assert_allclose(init.m, m, rtol=0, atol=1e-9)
    assert init.dof == 0 and init.cost < 1e-12
    assert_psd(init.P_m)
    assert_psd(init.P_m - init.P_m_dep, atol=1e-15)
    assert_psd(init.P_m_dep, atol=1e-15)


@pytest.mark.parametrize('seed', SEEDS)
def test_three_exact_ranges_give_the_point(seed):
    rng = np.random.default_rng(seed)
    m = rng.uniform(-5, 5, 2)
    s = _sensors_around(rng, m, 3)
    views = _exact_views(pt.RANGE, s, m)
    point, spread = pt.trilaterate(s[:, :2], views.y)
    np.testing.assert_allclose(point, m, rtol=0, atol=1e-9)
    init = pt.initialise(views)
    if spread < 0.05:    # nearly collinear anchors: the mirror point may fit too
        assert init.ok or init.reason in ('ambiguous', 'ill_conditioned')
        return
    assert init.ok, init.reason
    np.testing.assert_allclose(init.m, m, rtol=0, atol=1e-9)


def test_trilaterate_reports_collinear_centres():
    c = np.array([[0.0, 0.0], [1.0, 1.0], [3.0, 3.0]])
    point, spread = pt.trilaterate(c, [1.0, 1.0, 3.0])
    assert np.isnan(point).all() and spread < 1e-9
    with pytest.raises(ValueError):
        pt.trilaterate(c[:2], [1.0, 1.0])


def test_intersections_known_values():
    points, meet = pt.intersect_circles([0.0, 0.0], 5.0, [8.0, 0.0], 5.0)
    np.testing.assert_allclose(points, [[4.0, 3.0], [4.0, -3.0]], atol=1e-12)
    assert meet
    _, meet = pt.intersect_circles([0.0, 0.0], 1.0, [8.0, 0.0], 1.0)
    assert not meet
    points, t, meet = pt.intersect_ray_circle([0.0, 0.0], 0.0, [5.0, 0.0], 1.0)
    np.testing.assert_allclose(points, [[4.0, 0.0], [6.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(t, [4.0, 6.0], atol=1e-12)
    point, t1, t2, angle = pt.intersect_rays([0.0, 0.0], 0.0, [2.0, -2.0], np.pi / 2)
    np.testing.assert_allclose(point, [2.0, 0.0], atol=1e-12)
    assert t1 == pytest.approx(2.0) and t2 == pytest.approx(2.0)
    assert angle == pytest.approx(np.pi / 2)


def test_near_parallel_bearings_wait():
    m = np.array([20.0, 0.0])
    s = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])     # crossing angle 2.9 deg
    init = pt.initialise(_exact_views(pt.BEARING, s, m))
    assert init.status == pt.WAIT and init.reason == 'small_crossing_angle'
    assert np.degrees(init.crossing_angle) == pytest.approx(2.862, abs=1e-3)
    assert np.isnan(init.m).all()
    params = pt.InitialiseParams(min_triangulation_angle_deg=2.0, max_relative_stddev=1.0,
                                 max_curvature_ratio=None)
    assert pt.initialise(_exact_views(pt.BEARING, s, m), params).ok


def test_a_landmark_too_uncertain_for_the_linearisation_waits():
    """Placed only once its worst standard deviation is below 0.1 of the nearest range."""
    m = np.array([20.0, 0.0])
    s = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]])     # 5.7 deg, 20 m away
    views = _exact_views(pt.BEARING, s, m)
    flat = pt.InitialiseParams(max_curvature_ratio=None)     # this rule alone
    loose = pt.initialise(views, replace(flat, max_relative_stddev=1.0))
    assert loose.ok
    worst = np.sqrt(np.linalg.eigvalsh(loose.P_m)[1])
    nearest = np.hypot(*(s[:, :2] - m).T).min()
    assert 0.1 < worst / nearest < 1.0
    init = pt.initialise(views)
    assert init.status == pt.WAIT and init.reason == 'too_uncertain'
    tight = replace(flat, max_relative_stddev=1.01 * worst / nearest)
    assert pt.initialise(views, tight).ok
    assert pt.initialise(views, replace(
        flat, max_relative_stddev=0.99 * worst / nearest)).reason == 'too_uncertain'


def test_rays_crossing_behind_wait():
    # Both sensors look away from each other: the lines meet behind them.
    s = np.array([[0.0, 0.0, np.pi / 4], [4.0, 0.0, 3 * np.pi / 4]])
    views = pt.Views(pt.BEARING, s, P_S, [np.pi, np.pi], 1e-4)
    assert pt.initialise(views).reason == 'rays_do_not_cross'


def test_one_view_waits():
    views = _exact_views(pt.RANGE, np.zeros((1, 3)), np.array([1.0, 2.0]))
    assert pt.initialise(views).reason == 'too_few_views'


def test_two_ranges_are_ambiguous_until_a_third():
    m = np.array([2.0, 3.0])
    s = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 1.0], [3.0, -4.0, 2.0], [12.0, 0.0, 0.0]])
    two = _exact_views(pt.RANGE, s[:2], m)
    assert pt.initialise(two).reason == 'ambiguous'
    collinear = _exact_views(pt.RANGE, s[[0, 1, 3]], m)       # all on the x axis
    assert pt.initialise(collinear).reason == 'ambiguous'
    three = _exact_views(pt.RANGE, s[:3], m)
    init = pt.initialise(three)
    assert init.ok, init.reason
    np.testing.assert_allclose(init.m, m, atol=1e-9)
    # A bearing picks one of the two points instead.
    bearing = _exact_views(pt.BEARING, s[2:3], m)
    init = pt.initialise(pt.Views.concatenate([two, bearing]))
    assert init.ok, init.reason
    np.testing.assert_allclose(init.m, m, atol=1e-9)


@pytest.mark.parametrize('seed', range(20))
def test_mixed_kinds_place_the_landmark(seed):
    rng = np.random.default_rng(seed)
    m = rng.uniform(-5, 5, 2)
    s = _sensors_around(rng, m, 4)
    kinds = np.array([pt.RANGE, pt.BEARING, pt.RANGE, pt.BEARING])
    init = pt.initialise(_exact_views(kinds, s, m))
    assert init.ok, init.reason
    np.testing.assert_allclose(init.m, m, atol=1e-9)
    # A range and a bearing from the same sensor fix the point (range-bearing).
    init = pt.initialise(_exact_views([pt.RANGE, pt.BEARING], s[[0, 0]], m))
    assert init.ok, init.reason
    np.testing.assert_allclose(init.m, m, atol=1e-9)


def test_inconsistent_views_wait_and_robust_loss_recovers(rng):
    m = np.array([1.0, 1.0])
    s = _sensors_around(rng, m, 8)
    views = _exact_views(pt.RANGE, s, m, R=0.05 ** 2)
    y = views.y + 0.05 * rng.standard_normal(8)
    y[3] += 2.0     # an outlier
    bad = pt.Views(views.kind, views.s, views.P_s, y, views.R)
    assert pt.initialise(bad).reason == 'inconsistent'
    plain = pt.initialise(bad, pt.InitialiseParams(consistency_probability=None))
    robust = pt.initialise(bad, pt.InitialiseParams(consistency_probability=None,
                                                    loss='cauchy'))
    assert plain.ok and robust.ok
    assert np.linalg.norm(robust.m - m) < 0.5 * np.linalg.norm(plain.m - m)


def test_initialise_params_validate():
    for bad in ({'min_triangulation_angle_deg': 0.0}, {'max_condition': 0.5},
                {'max_stddev': 0.0}, {'max_relative_stddev': 0.0},
                {'consistency_probability': 1.0}, {'loss': 'l2'}):
        with pytest.raises(ValueError):
            pt.InitialiseParams(**bad)


def test_initialise_covariance_is_the_inverse_information(rng):
    m = np.array([0.5, -0.5])
    s = _sensors_around(rng, m, 5)
    kinds = np.array([0, 1, 1, 0, 1])
    P_s = random_spd(rng, 3, 5, scale=0.02)
    views = _exact_views(kinds, s, m, P_s=P_s, R=np.array([4e-3, 1e-4, 1e-4, 4e-3, 1e-4]),
                         R_bias=1e-5)
    init = pt.initialise(views)
    lin = pt.linearise(views, init.m)
    J = lin.J_h_m[:, 0, :]
    information = J.T @ np.diag(1.0 / lin.R_eff) @ J
    np.testing.assert_allclose(init.P_m @ information, np.eye(2), atol=1e-9)
    # The dependent part follows the views' dependent variances: all dependent -> P_m.
    all_dep = pt.Views(kinds, s, P_s, views.y, 1e-12 * views.R, views.R)
    init = pt.initialise(all_dep, pt.InitialiseParams(max_condition=1e12))
    np.testing.assert_allclose(init.P_m_dep, init.P_m, rtol=1e-9)


# --- updates ------------------------------------------------------------------------------

def _random_pairs(rng, n, kinds=None):
    m = rng.uniform(-5, 5, (n, 2))
    s = np.array([_sensors_around(rng, mi, 1)[0] for mi in m])
    kinds = rng.integers(0, 2, n) if kinds is None else kinds
    m_est = m + rng.normal(0, 0.1, (n, 2))
    P_m = random_spd(rng, 2, n, scale=0.1, eps=1e-3)
    P_dep = 0.5 * random_spd(rng, 2, n, scale=0.05, eps=0.0)
    P_dep = np.where(np.linalg.eigvalsh(P_m - P_dep)[:, :1, None] > 0, P_dep, 0.0)
    y = pt.observe_view(kinds, s, m)[:, 0]
    views = pt.Views(kinds, s, random_spd(rng, 3, n, 0.02), y, np.where(kinds, 1e-4, 1e-3),
                     1e-5)
    return m_est, P_m, P_dep, views


@pytest.mark.parametrize('method', pt.METHODS)
def test_update_batch_equals_single_calls(rng, method):
    m, P_m, P_dep, views = _random_pairs(rng, 30)
    batch = pt.update(m, P_m, views, P_dep, method=method)
    for i in range(30):
        one = pt.update(m[i], P_m[i], views[i], P_dep[i], method=method)
        for name in ('m', 'P_m', 'P_m_dep', 'innovation', 'S', 'mahalanobis_sq', 'omega',
                     'status'):
            np.testing.assert_allclose(getattr(one, name)[0], getattr(batch, name)[i],
                                       rtol=1e-12, atol=1e-15, err_msg=name)


@pytest.mark.parametrize('method', pt.METHODS)
def test_update_reduces_variance_along_H_and_stays_psd(rng, method):
    m, P_m, P_dep, views = _random_pairs(rng, 200)
    result = pt.update(m, P_m, views, P_dep, method=method)
    assert result.updated.mean() > 0.9
    H = pt.linearise(views, m).J_h_m[:, 0, :]
    before = np.einsum('ni,nij,nj->n', H, P_m, H)
    after = np.einsum('ni,nij,nj->n', H, result.P_m, H)
    assert np.all(after <= before * (1.0 + 1e-9))
    if method == 'independent':
        assert np.all(after < before)
    assert_psd(result.P_m, atol=1e-12)
    assert_psd(result.P_m_dep, atol=1e-12)
    assert_psd(result.P_m - result.P_m_dep, atol=1e-12)


def test_independent_update_equals_the_information_form(rng):
    m, P_m, P_dep, views = _random_pairs(rng, 50)
    result = pt.update(m, P_m, views, P_dep, gate_probability=1 - 1e-12)
    lin = pt.linearise(views, m)
    for i in range(50):
        H = lin.J_h_m[i]
        information = np.linalg.inv(P_m[i]) + H.T @ H / lin.R_eff[i]
        P = np.linalg.inv(information)
        np.testing.assert_allclose(result.P_m[i], P, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(
            result.m[i], m[i] + (P @ H.T)[:, 0] * lin.residual[i] / lin.R_eff[i], rtol=1e-9)


@pytest.mark.parametrize('method', pt.METHODS)
def test_huge_variance_view_changes_nothing(rng, method):
    m, P_m, P_dep, views = _random_pairs(rng, 20)
    vague = pt.Views(views.kind, views.s, views.P_s, views.y, 1e12, 0.0)
    result = pt.update(m, P_m, vague, P_dep, method=method)
    assert np.all(result.updated)
    np.testing.assert_allclose(result.m, m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.P_m, P_m, rtol=1e-9, atol=1e-15)


def test_gate_and_too_close(rng):
    m, P_m, P_dep, views = _random_pairs(rng, 3, kinds=np.array([0, 0, 1]))
    y = views.y.copy()
    y[1] += 100.0    # an outlier range
    views = pt.Views(views.kind, views.s, views.P_s, y, views.R)
    m[2] = views.s[2, :2]
    result = pt.update(m, P_m, views, P_dep)
    np.testing.assert_array_equal(result.status, [pt.UPDATED, pt.GATED, pt.TOO_CLOSE])
    np.testing.assert_array_equal(result.m[1:], m[1:])
    np.testing.assert_array_equal(result.P_m[1:], P_m[1:])
    assert np.isnan(result.innovation[2])
    with pytest.raises(ValueError):
        pt.update(m, P_m, views, method='product')
    with pytest.raises(ValueError):
        pt.update(m, P_m, views, method='covariance_intersection', omega=1.0)


def _posterior_det(m, P_m, views, P_dep, method, omega):
    result = pt.update(m, P_m, views, P_dep, method=method, omega=omega,
                       gate_probability=1 - 1e-12)
    return np.linalg.det(result.P_m)


@pytest.mark.parametrize('method', ['covariance_intersection', 'split_covariance_intersection'])
def test_omega_minimises_the_posterior_determinant(rng, method):
    m, P_m, P_dep, views = _random_pairs(rng, 40)
    best = pt.update(m, P_m, views, P_dep, method=method, gate_probability=1 - 1e-12)
    det_best = np.linalg.det(best.P_m)
    for omega in np.linspace(0.001, 0.999, 101):
        det = _posterior_det(m, P_m, views, P_dep, method, np.full(40, omega))
        assert np.all(det_best <= det * (1.0 + 1e-9))


def test_ci_omega_closed_form(rng):
    # det P+ is proportional to 1 / (w (hph (1 - w) + R w)): w = hph / (2 (hph - R)).
    m, P_m, P_dep, views = _random_pairs(rng, 200)
    lin = pt.linearise(views, m)
    H = lin.J_h_m[:, 0, :]
    hph = np.einsum('ni,nij,nj->n', H, P_m, H)
    omega = pt.view_omega(H, np.zeros_like(P_m), P_m, np.zeros(200), lin.R_eff)
    with np.errstate(divide='ignore'):
        expected = np.where(hph > 2.0 * lin.R_eff, hph / (2.0 * (hph - lin.R_eff)), 1.0)
    np.testing.assert_allclose(omega, np.clip(expected, 0, 1 - pt.OMEGA_EDGE), atol=1e-9)


def test_split_ci_without_dependent_parts_is_the_plain_update(rng):
    m, P_m, _, views = _random_pairs(rng, 20)
    ind = pt.Views(views.kind, views.s, 0.0 * views.P_s, views.y, views.R)
    plain = pt.update(m, P_m, ind, method='independent')
    split = pt.update(m, P_m, ind, method='split_covariance_intersection')
    np.testing.assert_allclose(split.m, plain.m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(split.P_m, plain.P_m, rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(split.P_m_dep, 0.0, atol=1e-15)


# --- consistency by Monte Carlo -----------------------------------------------------------

def _trial(rng, kinds, k, method):
    """Initialise from ``k`` views, update with the rest; return the NEES or None."""
    n = len(kinds)
    m_true = rng.uniform(-5, 5, 2)
    pose_true = _sensors_around(rng, m_true, n, r_min=3.0)
    A = np.diag([0.03, 0.03, 0.005]) @ (np.eye(3) + 0.3 * rng.uniform(-1, 1, (3, 3)))
    P_pose = A @ A.T                      # declared, and sampled below
    pose = pose_true + rng.multivariate_normal(np.zeros(3), P_pose, n)
    s_true = pose2.compose(pose_true, MOUNT)
    R = np.where(kinds == pt.RANGE, 0.05 ** 2, 0.005 ** 2)
    y = pt.observe_view(kinds, s_true, m_true)[:, 0] + np.sqrt(R) * rng.standard_normal(n)
    views = pt.views_from_robot(kinds, pose, P_pose, y, R, sensor_pose=MOUNT)
    init = pt.initialise(views[:k])
    if not init.ok:
        return None
    m, P_m, P_dep = init.m, init.P_m, init.P_m_dep
    for i in range(k, n):
        result = pt.update(m, P_m, views[i], P_dep, method=method)
        m, P_m, P_dep = result.m[0], result.P_m[0], result.P_m_dep[0]
    return nees(m, P_m, m_true)


TRIALS = 200
KINDS = {'bearing': [pt.BEARING] * 6, 'range': [pt.RANGE] * 6, 'mixed': [0, 1, 0, 1, 1, 0]}


@pytest.mark.parametrize('kinds, method', [
    ('bearing', 'independent'), ('range', 'independent'), ('mixed', 'independent'),
    ('bearing', 'split_covariance_intersection'), ('range', 'covariance_intersection'),
])
def test_anees_inside_the_chi_square_interval(rng, kinds, method):
    values = [_trial(rng, np.array(KINDS[kinds]), 3, method) for _ in range(TRIALS)]
    values = np.array([v for v in values if v is not None])
    # Waits: near-collinear anchors, narrow angles, curved valleys (three views).
    assert len(values) > 0.8 * TRIALS
    lo, hi = chi2.ppf([0.005, 0.995], 2 * len(values)) / len(values)
    anees = values.mean()
    if method == 'independent':
        assert lo <= anees <= hi, (anees, lo, hi)
    else:   # the intersections are conservative by design
        assert anees <= hi, (anees, lo, hi)


@pytest.mark.parametrize('grouped, consistent', [(False, False), (True, True)])
def test_initialisation_covariance_with_a_bias_shared_by_each_sensor(grouped, consistent):
    """Monte Carlo: two cameras with a bias each, five views apiece; ANEES with the groups."""
    rng = np.random.default_rng(3)
    m = np.array([0.0, 5.0])
    xy = np.concatenate([np.column_stack([np.linspace(-4, -2, 5), np.zeros(5)]),
                         np.column_stack([np.linspace(2, 4, 5), np.zeros(5)])])
    s = np.column_stack([xy, np.full(10, 1.0)])
    sensor = np.repeat([0, 1], 5)
    P_s = np.diag([1e-4, 1e-4, 1e-5])
    sigma, bias = 0.003, 0.02
    runs, nees = 300, []
    for _ in range(runs):
        errors = (rng.normal(0, bias, 2)[sensor] + rng.normal(0, sigma, 10))
        pose_error = rng.multivariate_normal(np.zeros(3), P_s, 2)[sensor]
        y = pt.observe_view(pt.BEARING, s + pose_error, m)[:, 0] + errors
        views = pt.Views(pt.BEARING, s, P_s, y, sigma ** 2, bias ** 2)
        init = (pt.initialise(views, bias_group=sensor, pose_group=sensor) if grouped
                else pt.initialise(views))
        assert init.ok, init.reason
        d = init.m - m
        nees.append(d @ np.linalg.solve(init.P_m, d))
        assert_psd(init.P_m - init.P_m_dep, atol=1e-15)
    anees = np.mean(nees)
    low, high = chi2.ppf([0.0005, 0.9995], 2 * runs) / runs
    assert (low <= anees <= high) == consistent, anees


def test_a_mirror_image_the_data_cannot_reject_waits():
    """
    Ranges from a nearly straight path: the mirror image may fit best by chance.

    The demo's range-only robot (seed 0, robot 2) sees landmark 3 from 31 stops along
    4.1 m with 0.46 m of curvature. The mirror image 7.8 m away fits its ranges with
    cost 29.4, the true point's minimum with 41.0 (both well inside chi-square with
    29 dof); their difference (11.6) exceeds the 1-dof ambiguity bound, so a rule on
    the difference alone placed the mirror with a 10 cm covariance (NEES 64,769).
    """
    from landmark_ros.sim.simulation import SimConfig, Simulation
    config = SimConfig(robots=3, landmarks=20, seed=0, duration_s=20.0,
                       sensor_kinds=('rb', 'range', 'bearing'))
    sim = Simulation(config)
    robot, landmark = 1, 3
    poses, ranges = [], []
    for j in range(sim.observations_until(int(config.duration_s * 1e9))):
        meas = sim.measure(robot, j)
        hit = np.flatnonzero(meas.ids == landmark)
        if hit.size:
            k = sim.poses_until(meas.stamp_ns) - 1
            p0, p1 = sim.reported_pose(robot, k)[2], sim.reported_pose(robot, k + 1)[2]
            a = (meas.stamp_ns - sim.pose_stamp_ns(k)) / sim.pose_period_ns
            poses.append(p0 + a * (p1 - p0))
            ranges.append(meas.z[hit[0], 0])
    views = pt.views_from_robot(pt.RANGE, poses, config.P_pose, ranges,
                                config.range_stddev ** 2)
    assert len(views) == 31
    truth = sim.world.positions[list(sim.world.ids).index(landmark)]
    difference_only = pt.initialise(views, pt.InitialiseParams(
        consistency_probability=None, max_curvature_ratio=None))
    assert difference_only.ok and np.hypot(*(difference_only.m - truth)) > 7.0
    init = pt.initialise(views)
    assert init.status == pt.WAIT and init.reason == 'ambiguous'


def _approach_path(n=50):
    """Return poses of a robot driving at a landmark on a gently curving path (seed 9)."""
    anchor = np.array([[0.07, -5.91], [0.66, -5.35], [1.34, -4.69], [1.86, -3.84],
                       [2.3, -2.75], [2.57, -2.2]])
    u, k = np.linspace(0.0, 1.0, n), np.linspace(0.0, 1.0, len(anchor))
    return np.column_stack([np.interp(u, k, anchor[:, 0]), np.interp(u, k, anchor[:, 1]),
                            np.zeros(n)])


def test_ranges_along_a_curved_valley_wait_until_the_gaussian_fits():
    """
    Ranges from a robot driving at a landmark: a long valley bent on the noise scale.

    The Gaussian of the normal equations lies along the valley's tangent; the truth
    lies along the curve. Without the curvature rule one placement in three passes
    every other test and the placed ones have an average NEES far above 2 (one in
    eight beyond the 99.9 % quantile); with it (Bates and Watts' rule) they wait as
    ``too_curved``. 300 noise draws, simulator noise (0.1 m, pose 0.05 m).
    """
    s = _approach_path()
    m = np.array([3.75, 1.0])
    P_s = np.diag([0.0025, 0.0025, 1e-4])
    rng = np.random.default_rng(0)
    old = pt.InitialiseParams(max_curvature_ratio=None)
    old_nees, new_reasons = [], []
    for _ in range(300):
        y = pt.observe_view(pt.RANGE, s, m)[:, 0] + rng.standard_normal(len(s)) * np.sqrt(
            0.01 + 0.0025)
        views = pt.Views(pt.RANGE, s, P_s, y, 0.01)
        placed = pt.initialise(views, old)
        if placed.ok:
            old_nees.append(nees(placed.m, placed.P_m, m))
        new_reasons.append(pt.initialise(views).reason)
    assert len(old_nees) > 60
    assert np.mean(old_nees) > 10.0
    assert np.mean(np.array(old_nees) > chi2.ppf(0.999, 2)) > 0.05
    assert 'ok' not in new_reasons and new_reasons.count('too_curved') == len(old_nees)


def test_the_curvature_rule_is_bates_and_watts_ratio():
    """A placement waits exactly when 2.45 standard deviations exceed half the bend radius."""
    s = _approach_path(30)
    m = np.array([3.75, 1.0])
    views = _exact_views(pt.RANGE, s, m, P_s=np.diag([0.0025, 0.0025, 1e-4]), R=0.01)
    free = pt.InitialiseParams(max_curvature_ratio=None, max_relative_stddev=1.0,
                               max_stddev=100.0)
    placed = pt.initialise(views, free)
    assert placed.ok
    lin = pt.linearise(views, placed.m)
    H = cv.observe_hessians(views.s, placed.m)[:, pt.RANGE]
    ratio = max(cv.relative_curvatures(lin.J_h_m[:, 0], H, lin.R_eff)) * cv.CONFIDENCE_RADIUS_95
    assert 0.0 < ratio
    above = replace(free, max_curvature_ratio=1.01 * ratio)
    below = replace(free, max_curvature_ratio=0.99 * ratio)
    assert pt.initialise(views, above).ok
    assert pt.initialise(views, below).reason == 'too_curved'
    with pytest.raises(ValueError, match='max_curvature_ratio'):
        pt.InitialiseParams(max_curvature_ratio=0.0)


# --- the iterated update ------------------------------------------------------------------

def _elongated_prior(angle_deg, major=0.5, minor=0.05):
    """Return a landmark 3 m ahead of a sensor at the origin, its prior long at an angle."""
    a = np.radians(angle_deg)
    rotation = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.array([3.0, 0.0]), rotation @ np.diag([major ** 2, minor ** 2]) @ rotation.T


def test_a_nearly_linear_view_is_updated_once_and_iterating_changes_nothing(rng):
    # 10^7 m away with a 1 m prior: the range is linear to 1e-7 m over the prior. The
    # update does not iterate, and forced iterations (threshold 0) land on the EKF's
    # result (for a linear model the Gauss-Newton step from the EKF's point is zero).
    m = np.array([1e7, 0.0]) + rng.normal(0.0, 1.0, 2)
    P_m = random_spd(rng, 2, scale=1.0, eps=0.1)
    views = pt.Views(pt.RANGE, np.zeros((1, 3)), np.zeros((1, 3, 3)),
                     [np.hypot(*m) + 0.3], 0.01)
    for method in pt.METHODS:
        kwargs = {'P_m_dep': 0.3 * P_m, 'method': method, 'gate_probability': 1 - 1e-9}
        plain = pt.update(m, P_m, views, iterate_threshold=None, **kwargs)
        default = pt.update(m, P_m, views, **kwargs)
        forced = pt.update(m, P_m, views, iterate_threshold=0.0, **kwargs)
        assert plain.iterations.tolist() == default.iterations.tolist() == [1]
        np.testing.assert_array_equal(default.m, plain.m)
        np.testing.assert_array_equal(default.P_m, plain.P_m)
        assert forced.iterations[0] >= 2
        np.testing.assert_allclose(forced.m, plain.m, rtol=0, atol=1e-6)
        np.testing.assert_allclose(forced.P_m, plain.P_m, rtol=0, atol=1e-5)
        np.testing.assert_allclose(forced.P_m_dep, plain.P_m_dep, rtol=0, atol=1e-5)


@pytest.mark.parametrize('method', pt.METHODS)
def test_the_iterated_update_converges_to_the_posterior_mode(rng, method):
    # Gauss-Newton's fixed point: the gradient of the posterior cost is zero there,
    # (m - m0)^T A^-1 = H(m)^T (y - h(m)) / a(m), with A, a the method's terms.
    m0, P_m = _elongated_prior(45.0)
    P_dep = 0.4 * P_m
    s = np.array([[0.0, 0.0, 0.3]])
    P_s = np.diag([1e-4, 1e-4, 1e-5])[None]
    for y in (2.75, 3.25, 3.4):
        views = pt.Views(pt.RANGE, s, P_s, [y], 0.02 ** 2, 0.01 ** 2)
        result = pt.update(m0, P_m, views, P_dep, method=method)
        assert result.status[0] == pt.UPDATED
        assert 2 <= result.iterations[0] < 10      # iterated, and converged
        lin = pt.linearise(views, result.m)
        H, omega = lin.J_h_m[0, 0], result.omega[0]
        if method == 'independent':
            A, a = P_m, lin.R_eff[0]
        elif method == 'covariance_intersection':
            A, a = P_m / omega, lin.R_eff[0] / (1.0 - omega)
        else:
            A = P_m - P_dep + P_dep / omega
            a = views.R[0] + lin.R_dep[0] / (1.0 - omega)
        gradient = np.linalg.solve(A, result.m[0] - m0) - H * lin.residual[0] / a
        scale = np.linalg.norm(np.linalg.solve(A, result.m[0] - m0))
        assert np.linalg.norm(gradient) <= 1e-3 * scale
        # The covariance is the Joseph form at the mode: PSD, and tight along H there.
        assert_psd(result.P_m, atol=1e-15)
        assert H @ result.P_m @ H <= 1.0001 * a


def test_iterating_where_the_step_is_not_linear_makes_the_update_consistent():
    """
    Monte Carlo: a range view of a landmark whose prior is long across the line of sight.

    The landmark is 3 m from the sensor, its prior 0.5 m by 0.05 m at 45 deg to the
    line of sight, 2 cm of range noise; the truth is drawn from the prior.
    The EKF linearises at the prior mean and its step bends off the circle of the
    measured range: ANEES 6.2 over 4,000 draws. The iterated update (the default
    criterion) is inside the chi-square interval; the plain update is far above it.
    """
    rng = np.random.default_rng(1)
    n = 4000
    m0, P_m = _elongated_prior(45.0)
    truth = rng.multivariate_normal(m0, P_m, n)
    y = np.hypot(*truth.T) + rng.normal(0.0, 0.02, n)
    views = pt.Views(np.full(n, pt.RANGE), np.zeros((n, 3)), np.zeros((n, 3, 3)), y,
                     0.02 ** 2)
    low, high = chi2.ppf([0.005, 0.995], 2 * n) / n
    anees = {}
    for threshold in (None, pt.ITERATE_THRESHOLD):
        result = pt.update(m0, P_m, views, gate_probability=1 - 1e-9,
                           iterate_threshold=threshold)
        assert result.updated.all()
        e = result.m - truth
        anees[threshold] = np.mean(np.einsum('ni,nij,nj->n', e, np.linalg.inv(result.P_m), e))
    assert anees[None] > 2.0 * high, anees
    assert low <= anees[pt.ITERATE_THRESHOLD] <= high, (anees, low, high)
