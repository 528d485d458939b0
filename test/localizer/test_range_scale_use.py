"""The range scale model (core.range_scale) where the package uses ranges."""

from dataclasses import replace

from landmark_ros.core import range_scale, sensors
from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
from landmark_ros.localizer.update import correct_ranges, RANGE, RANGE_BEARING, update
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import ObserverConfig
import numpy as np

MS = 1_000_000
S = 1000 * MS
COEFFS = (0.047, -0.0044, -0.4675)
PER_M = -0.0034
LANDMARKS = np.array([[4.0, 1.0], [-3.0, 5.0], [2.0, -4.0], [6.0, 6.0], [-5.0, -2.0],
                      [3.0, 3.5], [1.0, 5.5]])


def scaled(z):
    """Return readings ``z`` (true range, bearing) with the range scale error, (N, 2)."""
    z = np.array(z, dtype=np.float64)
    p = 1.0 + COEFFS[0] + COEFFS[1] * z[:, 1] + COEFFS[2] * z[:, 1] ** 2
    z[:, 0] = z[:, 0] * p / (1.0 - PER_M * z[:, 0])   # solves r = r_true g(r, b)
    return z


def test_scaled_readings_are_what_the_model_describes():
    z = np.array([[3.0, 0.4], [5.0, -0.55], [1.0, 0.0]])
    z_c, _ = range_scale.correct(scaled(z), COEFFS, PER_M)
    np.testing.assert_allclose(z_c, z, rtol=1e-13)


def test_correct_ranges_default_and_partial_rows_untouched(rng):
    z = np.stack([rng.uniform(1, 6, 6), rng.uniform(-0.5, 0.5, 6)], axis=1)
    kind = np.array([RANGE_BEARING, RANGE, RANGE_BEARING, RANGE, RANGE_BEARING, RANGE])
    R = np.tile(np.diag([0.01, 0.0004]), (6, 1, 1))
    same, R_same = correct_ranges(z, kind, R, range_scale.IDENTITY, 0.0)
    np.testing.assert_array_equal(same, z)
    np.testing.assert_array_equal(R_same, R)
    z_c, R_c = correct_ranges(z, kind, R, COEFFS, PER_M)
    full = kind == RANGE_BEARING
    np.testing.assert_array_equal(z_c[~full], z[~full])
    np.testing.assert_array_equal(R_c[~full], R[~full])
    expect, R_expect = range_scale.correct_with_noise(z[full], R[full], COEFFS, PER_M)
    np.testing.assert_allclose(z_c[full], expect, rtol=1e-15)
    np.testing.assert_allclose(R_c[full], R_expect, rtol=1e-15)
    z_n, R_n = correct_ranges(z, kind, None, COEFFS, PER_M)
    assert R_n is None
    np.testing.assert_array_equal(z_n, z_c)


def _localize(config, pose, steps=40):
    """Return the estimate of a robot standing at ``pose`` after ``steps`` sightings."""
    loc = Localizer(config)
    loc.initialize(0, pose + np.array([0.15, -0.1, 0.03]), np.diag([0.04, 0.04, 0.01]))
    loc.set_map(np.arange(len(LANDMARKS)) + 10, LANDMARKS,
                np.tile(np.eye(2) * 1e-6, (len(LANDMARKS), 1, 1)))
    z = sensors.observe(pose, LANDMARKS)
    seen = np.abs(z[:, 1]) < 0.6
    for k in range(1, steps + 1):
        loc.add_odometry(k * 100 * MS, twist=np.zeros(2))
        loc.add_observations(k * 100 * MS, np.flatnonzero(seen) + 10, scaled(z[seen]))
    loc.add_odometry((steps + 1) * 100 * MS, twist=np.zeros(2))
    return loc.estimate()


def test_localizer_with_the_model_removes_the_scale_bias():
    pose = np.array([0.5, 0.8, 0.6])
    base = LocalizerConfig(range_stddev=0.01, range_stddev_per_m=0.0, bearing_stddev=0.005,
                           odometry_alphas=(0.0, 0.0, 0.0, 0.0), gate_probability=0.999999)
    model = replace(base, range_scale_coeffs=COEFFS, range_scale_per_m=PER_M)
    good = _localize(model, pose)
    bad = _localize(base, pose)   # mutation: the model switched off
    assert np.hypot(*(good.x[:2] - pose[:2])) < 0.005
    assert np.hypot(*(bad.x[:2] - pose[:2])) > 0.02


def test_observer_places_scaled_readings_at_the_truth():
    pose = np.array([1.0, 2.0, 0.5])
    m_true = np.array([[4.0, 3.5], [2.5, 4.0], [5.0, 1.0]])
    z = scaled(sensors.observe(pose, m_true))
    config = ObserverConfig(range_stddev=0.01, bearing_stddev=0.01,
                            range_scale_coeffs=COEFFS, range_scale_per_m=PER_M)
    placed = []
    for cfg in (config, replace(config, range_scale_coeffs=(0.0, 0.0, 0.0),
                                range_scale_per_m=0.0)):
        observer = Observer(cfg)
        observer.add_pose(S, pose, np.eye(3) * 1e-9)
        columns = {'id': np.array([7, 8, 9]), 'range': z[:, 0], 'bearing': z[:, 1]}
        batch, = observer.add_observations([ObservationMessage(S, columns)])
        placed.append(batch.m)
    np.testing.assert_allclose(placed[0], m_true, atol=1e-9)
    assert np.max(np.hypot(*(placed[1] - m_true).T)) > 0.1   # mutation: no model


def test_observer_propagates_a_messages_own_noise():
    pose = np.array([0.0, 0.0, 0.0])
    z = np.array([[3.0, 0.5]])
    config = ObserverConfig(range_scale_coeffs=COEFFS, range_scale_per_m=PER_M)
    observer = Observer(config)
    observer.add_pose(S, pose, np.eye(3) * 1e-9)
    columns = {'id': np.array([7]), 'range': z[:, 0], 'bearing': z[:, 1],
               'range_variance': np.array([0.04]), 'bearing_variance': np.array([0.001])}
    batch, = observer.add_observations([ObservationMessage(S, columns)])
    z_c, R_c = range_scale.correct_with_noise(z, np.diag([0.04, 0.001]), COEFFS, PER_M)
    m, P, _ = landmark_to_world_dependent(pose, np.eye(3) * 1e-9, z_c, R_c)
    np.testing.assert_allclose(batch.m, m, atol=1e-12)
    np.testing.assert_allclose(batch.P, P, atol=1e-12)
    m_raw, P_raw, _ = landmark_to_world_dependent(pose, np.eye(3) * 1e-9, z,
                                                  np.diag([0.04, 0.001])[None])
    assert not np.allclose(batch.P, P_raw, atol=1e-6)   # mutation: raw noise


def test_observer_range_only_rows_take_the_mean_scale_and_its_spread_as_noise():
    pose = np.array([0.0, 0.0, 0.0])
    r = np.array([4.0, 2.0])
    base = ObserverConfig(range_stddev=0.02, range_stddev_per_m=0.0,
                          range_scale_per_m=PER_M)
    views = []
    for no_bearing in ((0.05, 0.04), (0.0, 0.0)):
        observer = Observer(replace(base, range_scale_no_bearing=no_bearing))
        observer.add_pose(S, pose, np.eye(3) * 1e-9)
        columns = {'id': np.array([7, 8]), 'range': r}
        batch, = observer.add_observations([ObservationMessage(S, columns)])
        views.append(batch.partial_observations.views)
    g = 1.0 + 0.05 + PER_M * r
    np.testing.assert_allclose(views[0].y.reshape(-1), r / g, rtol=1e-12)
    np.testing.assert_allclose(views[0].R.reshape(-1),
                               0.02 ** 2 / g ** 2 + (0.04 * r / g) ** 2, rtol=1e-12)
    # Without the bearing part only range_scale_per_m applies.
    g1 = 1.0 + PER_M * r
    np.testing.assert_allclose(views[1].y.reshape(-1), r / g1, rtol=1e-12)
    np.testing.assert_allclose(views[1].R.reshape(-1), 0.02 ** 2 / g1 ** 2, rtol=1e-12)


def test_the_bias_is_shared_by_every_sighting_within_the_correlation_time():
    pose = np.array([0.5, 0.8, 0.6])
    config = LocalizerConfig(range_stddev=0.02, range_stddev_per_m=0.0, bearing_stddev=0.01,
                             range_bias_stddev=0.03, bearing_bias_stddev=0.005,
                             noise_correlation_time_s=10.0, correlation='independent',
                             odometry_alphas=(0.0, 0.0, 0.0, 0.0), gate_probability=0.999999)
    z = sensors.observe(pose, LANDMARKS[:3])
    P0 = np.diag([0.04, 0.04, 0.01])
    results = []
    for cfg in (config, replace(config, range_bias_stddev=0.0, bearing_bias_stddev=0.0)):
        loc = Localizer(cfg)
        loc.initialize(0, pose, P0)
        loc.set_map(np.array([10, 11, 12]), LANDMARKS[:3], np.tile(np.eye(2) * 1e-6, (3, 1, 1)))
        loc.add_odometry(0, twist=np.zeros(2))
        loc.add_odometry(MS, twist=np.zeros(2))
        loc.add_observations(MS, np.array([10, 11, 12]), z)
        assert loc.counters['rows_used'] == 3
        results.append(loc.estimate().P)
    # The k-th row of the batch shares the bias with the k - 1 before it.
    R = np.tile(np.diag([0.02 ** 2, 0.01 ** 2]), (3, 1, 1))
    R_bias = R + np.diag([0.03 ** 2, 0.005 ** 2]) * np.arange(1, 4)[:, None, None]
    settings = Localizer(config).settings
    for R_rows, P in ((R_bias, results[0]), (R, results[1])):
        expect = update(pose, P0 + Localizer(config)._floor, LANDMARKS[:3],
                        np.tile(np.eye(2) * 1e-6, (3, 1, 1)), z, R_rows,
                        np.zeros(3, np.int64), settings)
        np.testing.assert_allclose(P, expect.P, rtol=0, atol=1e-12)
    assert np.trace(results[0]) > np.trace(results[1])
