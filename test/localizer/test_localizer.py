"""Tests of the ROS-free localizer: motion model, update, timing, events, consistency."""

from dataclasses import replace
import math

from landmark_ros.core import pose2, sensors
from landmark_ros.localizer import motion
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer, UNKNOWN_ID
from landmark_ros.localizer.update import (BEARING, RANGE, RANGE_BEARING, SensorNoise,
                                           split_ci_weight, update, UpdateSettings)
import numpy as np
import pytest

MS = 1_000_000
LANDMARKS = np.array([[4.0, 1.0], [-3.0, 5.0], [2.0, -4.0], [6.0, 6.0], [-5.0, -2.0]])
SETTINGS = UpdateSettings(6.63, 9.21, 'independent', 0.1, 5)


def _random_spd(rng, n=3, scale=1.0):
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + np.eye(n) * 1e-3


def test_predict_matches_pose2_composition_and_jacobians():
    rng = np.random.default_rng(1)
    for _ in range(100):
        x, d = rng.normal(size=3), rng.normal(size=3) * 0.5
        P, Q = _random_spd(rng), _random_spd(rng, scale=0.1)
        x_next, P_next = motion.predict(x, P, d, Q)
        J_a, J_b = pose2.compose_jacobians(x, d)
        np.testing.assert_allclose(x_next, pose2.compose(x, d), atol=1e-12)
        np.testing.assert_allclose(P_next, J_a @ P @ J_a.T + J_b @ Q @ J_b.T, atol=1e-12)


def test_odometry_noise_is_the_textbook_model_in_delta_coordinates():
    rng = np.random.default_rng(2)
    for _ in range(100):
        delta = rng.normal(size=3) * [0.3, 0.05, 0.2]
        alphas = rng.uniform(0.0, 1.0, 4)
        rot1, trans, rot2 = motion.decompose(delta)
        # Monte Carlo-free check: push the (rot1, trans, rot2) covariance through the
        # numerical Jacobian of the composition delta(rot1, trans, rot2).

        def f(u):
            return np.array([u[1] * math.cos(u[0]), u[1] * math.sin(u[0]), u[0] + u[2]])
        u = np.array([rot1, trans, rot2])
        h = 1e-6
        J = np.column_stack([(f(u + h * e) - f(u - h * e)) / (2 * h) for e in np.eye(3)])
        a1, a2, a3, a4 = alphas
        S = np.diag([a1 * rot1 ** 2 + a2 * trans ** 2,
                     a3 * trans ** 2 + a4 * (rot1 ** 2 + rot2 ** 2),
                     a1 * rot2 ** 2 + a2 * trans ** 2])
        np.testing.assert_allclose(motion.odometry_noise(delta, alphas), J @ S @ J.T,
                                   atol=1e-8)
        np.testing.assert_allclose(f(u), delta, atol=1e-12)
        T = motion.odometry_noise_terms(delta[None])[0]
        np.testing.assert_allclose(np.einsum('i,ijk->jk', alphas, T),
                                   motion.odometry_noise(delta, alphas), atol=1e-12)


def test_scaled_motion_pieces_compose_to_the_whole():
    rng = np.random.default_rng(3)
    for _ in range(50):
        d = motion.delta_from_twist(rng.uniform(-1, 1), rng.uniform(-2, 2), 0.5)
        f = rng.uniform(0, 1)
        a = motion.scale_delta(d, f)
        np.testing.assert_allclose(motion.compose(a, motion.between(a, d)), d, atol=1e-12)
        np.testing.assert_allclose(a[2], d[2] * f, atol=1e-12)


def test_integrate_twists_matches_step_by_step_composition():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.01, 0.03, 200))
    tw = rng.normal(size=(200, 2))
    poses, deltas = motion.integrate_twists(t, tw)
    x = np.zeros(3)
    for k in range(199):
        x = motion.compose(x, motion.delta_from_twist(tw[k, 0], tw[k, 1], t[k + 1] - t[k]))
    np.testing.assert_allclose(poses[-1, :2], x[:2], atol=1e-9)
    assert abs(motion.wrap(poses[-1, 2] - x[2])) < 1e-9


def test_update_is_the_kalman_update_for_a_linear_case_and_gates():
    x, P = np.array([0.0, 0.0, 0.1]), np.diag([0.04, 0.04, 0.01])
    m = LANDMARKS[:3]
    P_m = np.tile(np.eye(2) * 1e-4, (3, 1, 1))
    R = np.tile(np.diag([0.01, 0.0004]), (3, 1, 1))
    z = sensors.observe(np.tile(x, (3, 1)), m) + [[0.05, 0.01], [-0.03, 0.0], [5.0, 0.0]]
    result = update(x, P, m, P_m, z, R, np.array([RANGE_BEARING] * 3), SETTINGS)
    assert result.used.tolist() == [True, True, False] and result.gated[2]
    # The reference: one EKF step with the stacked rows 0, 1 (numerical Jacobian).
    H = np.vstack([sensors.observe_jacobians(x, m[i])[0] for i in range(2)])
    Hm = [sensors.observe_jacobians(x, m[i])[1] for i in range(2)]
    S = H @ P @ H.T + np.kron(np.eye(2), np.diag([0.01, 0.0004]))
    S[:2, :2] += Hm[0] @ P_m[0] @ Hm[0].T
    S[2:, 2:] += Hm[1] @ P_m[1] @ Hm[1].T
    K = P @ H.T @ np.linalg.inv(S)
    nu = (z[:2] - sensors.observe(np.tile(x, (2, 1)), m[:2])).reshape(-1)
    if result.iterations == 1:
        np.testing.assert_allclose(result.x, x + K @ nu, atol=1e-10)
    np.testing.assert_allclose(result.P, (np.eye(3) - K @ H) @ P, atol=1e-6)


def test_partial_rows_use_one_component():
    x, P = np.zeros(3), np.diag([0.04, 0.04, 0.01])
    m = LANDMARKS[:2]
    P_m = np.zeros((2, 2, 2))
    R = np.tile(np.diag([0.01, 0.0004]), (2, 1, 1))
    z = sensors.observe(np.tile(x, (2, 1)), m)
    z[0, 1], z[1, 0] = np.nan, np.nan
    result = update(x, P, m, P_m, z, R, np.array([RANGE, BEARING]), SETTINGS)
    assert result.dof == 2 and result.used.all()
    assert np.linalg.det(result.P) < np.linalg.det(P)


def test_split_ci_weight_goes_to_one_with_a_precise_map():
    rng = np.random.default_rng(5)
    P, H = _random_spd(rng), rng.normal(size=(2, 3))
    R = np.eye(2) * 0.01
    assert split_ci_weight(P, H, R, np.eye(2) * 1e-12) > 0.999
    # a map a tenth as uncertain as the pose (in the measurement space): both count
    assert 0.05 < split_ci_weight(P, H, R, 0.01 * H @ P @ H.T) < 0.95


def test_split_ci_is_consistent_when_the_map_shares_the_pose_error():
    # The map landmark was placed from this robot's pose: its error equals the pose's
    # position error (full correlation). The plain update is over-confident, split CI not.
    rng = np.random.default_rng(6)
    P = np.diag([0.09, 0.09, 0.0004])
    R = np.diag([1e-4, 1e-6])
    nees = {'independent': [], 'split_ci': []}
    for _ in range(400):
        e = rng.multivariate_normal(np.zeros(3), P)
        true = np.array([0.0, 0.0, 0.0])
        x = true + e
        m_true = np.array([[3.0, 1.0]])
        m = m_true + e[:2]  # the map moved with the robot's error
        z = sensors.observe(true[None], m_true) + rng.normal(0, [0.01, 0.001], (1, 2))
        for corr in nees:
            res = update(x, P, m, P[None, :2, :2], z, R[None], np.array([RANGE_BEARING]),
                         replace(SETTINGS, correlation=corr))
            err = res.x - true
            nees[corr].append(err @ np.linalg.solve(res.P, err))
    assert np.mean(nees['split_ci']) < 3.5
    assert np.mean(nees['independent']) > 4.5


def _simulate(seed, order='in_order', steps=1500, config=None):
    """Drive a Localizer along a simulated path; return NEES samples and the localizer."""
    rng = np.random.default_rng(seed)
    cfg = config or LocalizerConfig(odometry_alphas=(0.5, 2.0, 0.5, 0.1), range_stddev=0.05,
                                    range_stddev_per_m=0.0, bearing_stddev=0.02,
                                    initial_stddev=(0.05, 0.05, 0.02),
                                    correlation='independent')
    loc = Localizer(cfg)
    loc.set_map(np.arange(len(LANDMARKS)), LANDMARKS, np.tile(np.eye(2) * 1e-10,
                                                              (len(LANDMARKS), 1, 1)))
    x = np.zeros(3)
    loc.initialize(0, x + rng.normal(0, cfg.initial_stddev),
                   np.diag(np.square(cfg.initial_stddev)))
    held, nees, t = [], [], 0
    loc.add_odometry(0, twist=np.array([0.3, 0.0]))
    for k in range(steps):
        v, w = 0.3, 0.4 * math.sin(k / 200)
        d = motion.delta_from_twist(v, w, 0.02)
        Q = motion.odometry_noise(d, cfg.odometry_alphas) + np.eye(3) * 1e-14
        noise = rng.multivariate_normal(np.zeros(3), Q)
        x = motion.compose(x, d + noise)
        t += 20 * MS
        if k % 10 == 3:
            z = sensors.observe(np.tile(x, (len(LANDMARKS), 1)), LANDMARKS)
            z += rng.normal(0, [0.05, 0.02], z.shape)
            held.append((t, z))
        loc.add_odometry(t, twist=np.array([v, w]))
        if order == 'in_order':
            for stamp, z in held:
                loc.add_observations(stamp, np.arange(len(LANDMARKS)), z)
            held = []
        elif len(held) == 3:  # late by up to 0.5 s, and out of order
            for stamp, z in held[::-1]:
                loc.add_observations(stamp, np.arange(len(LANDMARKS)), z)
            held = []
        est = loc.estimate()
        if k > 100 and k % 5 == 0:
            e = est.x - x
            e[2] = motion.wrap(e[2])
            nees.append(e @ np.linalg.solve(est.P, e))
    return np.array(nees), loc


def test_simulated_pose_nees_is_inside_its_interval():
    means = [np.mean(_simulate(seed)[0]) for seed in range(6)]
    assert 2.2 < np.mean(means) < 4.0, means


def test_late_and_out_of_order_sightings_give_nearly_the_in_order_estimate():
    nees_in, loc_in = _simulate(11)
    nees_late, loc_late = _simulate(11, order='late')
    assert loc_late.counters['refiltered'] > 0
    # the same rows, up to a few that the gate judges from a slightly different state
    assert abs(loc_late.counters['rows_used'] - loc_in.counters['rows_used']) <= 5
    a, b = loc_in.estimate(), loc_late.estimate()
    assert np.linalg.norm(a.x[:2] - b.x[:2]) < 0.05
    assert 1.5 < np.mean(nees_late) < 4.5


def test_sightings_ahead_of_the_odometry_wait_and_old_ones_are_dropped():
    loc = Localizer(LocalizerConfig(window_s=0.5))
    loc.set_map(np.arange(5), LANDMARKS, np.tile(np.eye(2) * 1e-4, (5, 1, 1)))
    loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
    loc.add_odometry(0, twist=np.zeros(2))
    z = sensors.observe(np.zeros((5, 3)), LANDMARKS)
    loc.add_observations(100 * MS, np.arange(5), z)
    assert loc.counters['waiting_for_odometry'] == 5 and loc.counters['rows_used'] == 0
    loc.add_odometry(150 * MS, twist=np.zeros(2))
    assert loc.counters['rows_used'] == 5
    for k in range(2, 30):
        loc.add_odometry(k * 100 * MS, twist=np.zeros(2))
    loc.add_observations(200 * MS, np.arange(5), z)
    assert loc.counters['too_old'] == 5


def test_odometry_events_have_named_counters():
    loc = Localizer(LocalizerConfig(max_odometry_gap_s=0.5, max_speed_mps=2.0))
    loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
    loc.add_odometry(0, pose=np.zeros(3))
    loc.add_odometry(100 * MS, pose=np.array([0.1, 0.0, 0.0]))
    sigma = loc.estimate().P[0, 0]
    loc.add_odometry(200 * MS, pose=np.array([5.0, 0.0, 0.0]))  # 49 m/s: a jump
    assert loc.counters['odometry_jump'] == 1
    assert loc.estimate().x[0] == pytest.approx(0.1) and loc.estimate().P[0, 0] > sigma
    loc.add_odometry(1500 * MS, pose=np.array([5.2, 0.0, 0.0]))  # 1.3 s later: a gap
    assert loc.counters['odometry_gap'] == 1
    loc.add_odometry(1500 * MS, pose=np.array([5.2, 0.0, 0.0]))
    assert loc.counters['odometry_out_of_order'] == 1
    loc.add_odometry(1600 * MS, pose=np.zeros(3))  # the odometry restarted at its origin
    assert loc.counters['odometry_reset'] == 1
    x_before = loc.estimate().x.copy()
    loc.add_odometry(1700 * MS, pose=np.array([0.1, 0.0, 0.0]))
    assert loc.estimate().x[0] == pytest.approx(x_before[0] + 0.1)
    loc.add_odometry(1700 * MS - 5_000 * MS, pose=np.array([0.1, 0.0, 0.0]))
    assert loc.counters['odometry_reset'] == 2


def test_missing_and_unlabelled_landmarks_are_counted_and_skipped():
    loc = Localizer()
    loc.set_map(np.array([1, 2]), LANDMARKS[:2], np.tile(np.eye(2) * 1e-4, (2, 1, 1)))
    loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
    loc.add_odometry(0, twist=np.zeros(2))
    z = sensors.observe(np.zeros((3, 3)), LANDMARKS[:3])
    assert loc.add_observations(0, np.array([1, 7, UNKNOWN_ID]), z) == 1
    assert loc.counters['landmark_not_in_map'] == 1 and loc.counters['no_id'] == 1
    assert loc.counters['rows_used'] == 1
    # before any map: its own reason, not a landmark missing from a map
    loc = Localizer()
    loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
    loc.add_odometry(0, twist=np.zeros(2))
    assert loc.add_observations(0, np.array([1, 7]), z[:2]) == 0
    assert loc.counters['map_empty'] == 2 and loc.counters['landmark_not_in_map'] == 0


def test_status_reports_lost_and_stale():
    cfg = LocalizerConfig(lost_after_s=60.0, lost_position_stddev=0.5)
    loc = Localizer(cfg)
    loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
    loc.add_odometry(0, twist=np.array([0.5, 0.0]))
    assert loc.status().extra['state'] == 'ok' or loc.status().level == 'warn'
    t = 0
    for _ in range(61 * 10):  # a minute without sightings, by stamps
        t += 100 * MS
        loc.add_odometry(t, twist=np.array([0.5, 0.0]))
    status = loc.status()
    assert status.level == 'error' and status.extra['state'] == 'lost'
    assert status.extra['time_since_update_s'] == math.inf


def test_config_validates():
    with pytest.raises(ValueError):
        LocalizerConfig(correlation='magic')
    with pytest.raises(ValueError):
        LocalizerConfig(odometry_alphas=(1.0, -1.0, 0.0, 0.0))
    with pytest.raises(ValueError):
        LocalizerConfig(window_s=-1.0)


def test_sightings_within_the_correlation_time_share_the_correlated_noise():
    cfg = LocalizerConfig(range_correlated_fraction=0.5, bearing_correlated_fraction=0.5,
                          noise_correlation_time_s=2.0)
    loc = Localizer(cfg)
    stamps = [0, 500 * MS, 1000 * MS, 1900 * MS, 2600 * MS]
    counts = [loc._shared(t, np.array([7, 8]))[0] for t in stamps]
    assert counts == [1, 2, 3, 4, 3]  # the sighting at 0 and 500 ms left the window
    assert loc._shared(0, np.array([9]))[0] == 1
    # without a correlation time every sighting stands alone
    assert Localizer()._shared(0, np.array([7, 7]))[0] == 1


def _nees_after_repeated_biased_sightings(**overrides):
    """NEES of the pose after one landmark seen 100 times in 2 s with one 2.6-sigma error."""
    settings = {'range_stddev': 0.1, 'range_stddev_per_m': 0.0, 'bearing_stddev': 0.01,
                'range_correlated_fraction': 0.9, 'bearing_correlated_fraction': 0.0,
                'odometry_alphas': (0.0, 0.0, 0.0, 0.0)}
    cfg = LocalizerConfig(**{**settings, **overrides})
    loc = Localizer(cfg)
    loc.set_map(np.array([1]), LANDMARKS[:1], np.eye(2)[None] * 1e-10)
    loc.initialize(0, np.zeros(3), np.diag([0.25, 0.25, 1e-6]))
    z = sensors.observe(np.zeros((1, 3)), LANDMARKS[:1]) + [[0.25, 0.0]]  # 2.6 sigma
    for k in range(100):
        loc.add_odometry(k * 20 * MS, twist=np.zeros(2))
        loc.add_observations(k * 20 * MS, np.array([1]), z)
    est = loc.estimate()
    return est.x @ np.linalg.solve(est.P, est.x)


def test_correlated_noise_sharing_makes_repeated_biased_sightings_honest():
    # One landmark seen 100 times in 2 s with the same (correlated) range error: counted
    # as independent, the pose collapses on the bias; shared, its NEES stays small.
    def final_nees(tau):
        return _nees_after_repeated_biased_sightings(noise_correlation_time_s=tau,
                                                     correlation='independent')
    # Counted alone, 100 sightings of one error weigh 100; shared, the k-th weighs 1/k
    # (the trailing count), 5.2 in all: the transient of a first encounter stays
    # over-confident by that harmonic sum (documented in Localizer._shared).
    assert final_nees(0.0) > 8.0 * final_nees(8.0)
    assert final_nees(8.0) < 6.8 * 5.2 * 1.2


def test_dependent_correlated_noise_keeps_repeated_biased_sightings_honest():
    # The same 100 sightings of one error as above: in the part of unknown correlation
    # with the pose (split CI), each counts once against any correlation, and the pose
    # stays consistent from the first sighting on, with no count of sightings.
    def final_nees(correlated_noise, correlation='split_ci'):
        return _nees_after_repeated_biased_sightings(
            noise_correlation_time_s=0.0, correlation=correlation,
            correlated_noise=correlated_noise)
    counted_alone = final_nees('count')     # no correlation time: each sighting alone
    assert counted_alone > 30.0
    assert final_nees('dependent') < 6.8    # 2.6 sigma along one direction, at most
    # Without split CI there is no part of unknown correlation: the count form applies.
    assert final_nees('dependent', 'independent') == final_nees('count', 'independent')


def test_sensor_noise_without_dependent_parts_is_the_plain_update():
    rng = np.random.default_rng(5)
    x, P = np.array([0.1, -0.2, 0.3]), _random_spd(rng, scale=0.3)
    m = LANDMARKS[:3]
    z = sensors.observe(x[None], m) + rng.normal(0.0, [0.05, 0.02], (3, 2))
    R = np.tile(np.diag([0.05, 0.02]) ** 2, (3, 1, 1))
    P_m = np.tile(np.eye(2) * 0.01, (3, 1, 1))
    kind = np.full(3, RANGE_BEARING)
    settings = replace(SETTINGS, correlation='split_ci')
    plain = update(x, P, m, P_m, z, R, kind, settings)
    split = update(x, P, m, P_m, z, SensorNoise(R, np.zeros_like(R)), kind, settings)
    np.testing.assert_array_equal(split.x, plain.x)
    np.testing.assert_array_equal(split.P, plain.P)
    # Part of the noise moved to the dependent side costs information, never gains it.
    moved = update(x, P, m, P_m, z, SensorNoise(0.5 * R, 0.5 * R, np.diag([1e-4, 1e-5])),
                   kind, settings)
    assert np.linalg.det(moved.P) > np.linalg.det(plain.P)


def test_simulated_wheel_odometry_follows_the_documented_model():
    from landmark_ros.sim.odometry import wheel_odometry
    alphas = (0.05, 0.5, 0.05, 0.01)
    truth = np.array([[0.0, 0.0, 0.0], [0.2, 0.05, 0.3]])
    generator = np.random.default_rng(7)
    steps = np.array([wheel_odometry(truth, alphas, generator)[1] for _ in range(4000)])
    e = steps - truth[1]
    e[:, 2] = (e[:, 2] + math.pi) % (2 * math.pi) - math.pi
    Q = motion.odometry_noise(motion.between(truth[0], truth[1]), alphas)
    np.testing.assert_allclose(np.cov(e.T), Q, rtol=0.15, atol=2e-5)


def test_monte_carlo_pose_nees_is_near_three():
    from landmark_ros.eval.localization_montecarlo import run_seed
    means = [run_seed(seed, duration_s=20.0)[0] for seed in range(3)]
    assert 2.0 < np.mean(means) < 4.0, means


def test_a_sighting_of_a_well_localized_robot_helps_and_stays_consistent():
    from landmark_ros.localizer.localizer import Estimate
    rng = np.random.default_rng(9)
    P = np.diag([0.5, 0.5, 0.01])
    nees, shrink = [], []
    for _ in range(200):
        true = np.array([1.0, 2.0, 0.3])
        other_true = np.array([4.0, 3.0, 0.0])
        P_other = np.diag([0.01, 0.01, 0.001])
        other = Estimate(0, other_true + rng.multivariate_normal(np.zeros(3), P_other),
                         P_other)
        loc = Localizer(LocalizerConfig(range_stddev=0.05, range_stddev_per_m=0.0,
                                        bearing_stddev=0.01))
        loc.initialize(0, true + rng.multivariate_normal(np.zeros(3), P), P)
        loc.add_odometry(0, twist=np.zeros(2))
        z = sensors.observe(true[None], other_true[None, :2])[0] + rng.normal(0, [0.05, 0.01])
        loc.add_robot_sighting(0, z, other, other_id='robot2')
        est = loc.estimate()
        e = est.x - true
        nees.append(e @ np.linalg.solve(est.P, e))
        shrink.append(np.trace(est.P[:2, :2]) / np.trace(P[:2, :2]))
    assert loc.counters['robot_rows_used'] == 1
    assert np.mean(shrink) < 0.7
    assert np.mean(nees) < 3.6
    stale = Estimate(10**9, other_true, P_other)
    loc.add_robot_sighting(0, z, stale)
    assert loc.counters['robot_stale'] == 1


def test_docs_list_every_parameter_with_its_default():
    from pathlib import Path
    from landmark_ros.pipeline.config import markdown_table
    docs = Path(__file__).resolve().parents[2] / 'docs' / 'localization.md'
    assert markdown_table(LocalizerConfig) in docs.read_text()


def test_odometry_scales_apply_to_pose_and_twist_motion():
    for kwargs in ({'twist': np.array([1.0, 0.5])}, {'pose': None}):
        loc = Localizer(LocalizerConfig(odometry_speed_scale=0.9,
                                        odometry_yaw_rate_scale=0.7))
        loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
        if 'pose' in kwargs:
            loc.add_odometry(0, pose=np.zeros(3))
            loc.add_odometry(100 * MS, pose=np.array([0.1, 0.0, 0.05]))
            expected = [0.09, 0.0, 0.035]
        else:
            loc.add_odometry(0, **kwargs)
            loc.add_odometry(100 * MS, **kwargs)
            expected = motion.delta_from_twist(1.0, 0.5, 0.1) * [0.9, 0.9, 0.7]
        np.testing.assert_allclose(loc.estimate().x, expected, atol=1e-12)


def test_speed_scale_per_yaw_rate_slows_the_motion_in_turns():
    # speed scale 1.04 - 1.1 |w|: straight 1.04, at 0.4 rad/s 0.6
    config = LocalizerConfig(odometry_speed_scale=1.04, odometry_yaw_rate_scale=0.9,
                             odometry_speed_scale_per_yaw_rate=-1.1)
    for w, scale in ((0.0, 1.04), (0.4, 0.6), (-0.4, 0.6), (2.0, 0.0)):
        loc = Localizer(config)
        loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
        loc.add_odometry(0, twist=np.array([0.1, w]))
        loc.add_odometry(100 * MS, twist=np.array([0.1, w]))
        expected = motion.delta_from_twist(0.1, w, 0.1) * [scale, scale, 0.9]
        np.testing.assert_allclose(loc.estimate().x, expected, atol=1e-12)
        # from consecutive odometry poses: the yaw rate is the turn over the step
        loc = Localizer(config)
        loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
        loc.add_odometry(0, pose=np.zeros(3))
        loc.add_odometry(100 * MS, pose=motion.delta_from_twist(0.1, w, 0.1))
        np.testing.assert_allclose(loc.estimate().x, expected, atol=1e-12)


def test_sensor_noise_has_the_observers_three_range_terms():
    config = LocalizerConfig(range_stddev=0.02, range_stddev_per_m=0.005,
                             range_stddev_per_m2=0.002, bearing_stddev=0.015)
    z = np.array([[4.0, 0.1], [0.5, -1.0], [np.nan, 0.3]])
    R = Localizer(config).sensor_noise(z)
    # By hand at r = 4: 0.02^2 + 0.02^2 + 0.032^2 = 0.001824 m^2.
    np.testing.assert_allclose(R[0, 0, 0], 0.001824, rtol=0, atol=1e-15)
    np.testing.assert_allclose(R[1, 0, 0], 0.02 ** 2 + 0.0025 ** 2 + 0.0005 ** 2,
                               rtol=0, atol=1e-15)
    assert R[2, 0, 0] == 0.02 ** 2     # a bearing-only row: no range, its range term unused
    np.testing.assert_array_equal(R[:, 1, 1], 0.015 ** 2)
    np.testing.assert_array_equal(R[:, 0, 1], 0.0)


def test_yaw_per_m_turns_the_robot_by_the_distance_driven():
    # -0.04 rad per metre of odometry distance, forwards and backwards alike
    config = LocalizerConfig(odometry_yaw_rate_scale=0.9, odometry_yaw_per_m=-0.04)
    for v, w in ((0.5, 0.0), (-0.5, 0.0), (0.3, 0.4)):
        loc = Localizer(config)
        loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
        loc.add_odometry(0, twist=np.array([v, w]))
        loc.add_odometry(100 * MS, twist=np.array([v, w]))
        delta = motion.delta_from_twist(v, w, 0.1)
        expected = delta * [1.0, 1.0, 0.9] + [0.0, 0.0, -0.04 * math.hypot(*delta[:2])]
        np.testing.assert_allclose(loc.estimate().x, expected, atol=1e-12)
        assert loc.estimate().x[2] < 0.9 * delta[2]
