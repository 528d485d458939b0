"""
Tests of the ROS-free helpers around the nodes.

observations.py (row checks, noise, rows to landmarks), config.py, pose_buffer.py,
diagnostics.Counters and the cloud.py reader/writer round trips.
"""

from collections import Counter
import dataclasses
import math
import warnings

from conftest import random_observations, random_poses, random_spd
from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.core.sensors import MIN_RANGE
from landmark_ros.pipeline import config
from landmark_ros.pipeline import counters as diagnostics
from landmark_ros.pipeline import pose_buffer
from landmark_ros.pipeline.rows import (landmark_row_problems, landmarks_from_rows, MAX_ID,
                                        observation_noise, row_problems)
from landmark_ros.ros import cloud
from landmark_ros.ros.cloud import CloudError, CloudWriter, FieldSpec, read_columns
import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header


@pytest.fixture
def no_warnings():
    """Turn every warning into an error for the duration of a test."""
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        yield


# --- observation_noise -------------------------------------------------------------------------

def test_noise_without_noise_columns_is_one_shared_matrix():
    R = observation_noise({'range': np.array([1.0, 2.0, 3.0]), 'bearing': np.zeros(3)},
                          0.01, 0.0004)
    assert R.shape == (2, 2)
    np.testing.assert_array_equal(R, [[0.01, 0.0], [0.0, 0.0004]])


def test_noise_per_row_with_nan_falling_back_to_defaults(no_warnings):
    nan = np.nan
    columns = {'range': np.ones(4), 'bearing': np.zeros(4),
               'range_variance': np.array([0.04, nan, 0.09, nan]),
               'bearing_variance': np.array([nan, 0.001, 0.002, nan]),
               'range_bearing_covariance': np.array([0.001, nan, -0.002, nan])}
    R = observation_noise(columns, 0.01, 0.0004)
    expected = np.array([[[0.04, 0.001], [0.001, 0.0004]],
                         [[0.01, 0.0], [0.0, 0.001]],
                         [[0.09, -0.002], [-0.002, 0.002]],
                         [[0.01, 0.0], [0.0, 0.0004]]])
    np.testing.assert_array_equal(R, expected)


@pytest.mark.parametrize('present', ['range_variance', 'bearing_variance',
                                     'range_bearing_covariance'])
def test_noise_with_one_column_uses_defaults_for_the_others(present):
    values = {'range_variance': 0.5, 'bearing_variance': 0.25, 'range_bearing_covariance': 0.1}
    columns = {'range': np.ones(3), present: np.full(3, values[present])}
    R = observation_noise(columns, 0.01, 0.0004)
    assert R.shape == (3, 2, 2)
    expected = np.array([[0.01, 0.0], [0.0, 0.0004]])
    index = {'range_variance': [(0, 0)], 'bearing_variance': [(1, 1)],
             'range_bearing_covariance': [(0, 1), (1, 0)]}[present]
    for i, j in index:
        expected[i, j] = values[present]
    np.testing.assert_array_equal(R, np.broadcast_to(expected, (3, 2, 2)))


# --- row_problems ------------------------------------------------------------------------------

def _rows(count=6):
    ids = np.arange(count, dtype=np.int64) * 1000
    z = np.c_[np.linspace(1.0, 20.0, count), np.linspace(-3.0, 3.0, count)]
    R = np.repeat(np.array([[[0.01, 0.001], [0.001, 0.0004]]]), count, axis=0)
    return ids, z, R


def test_row_problems_all_valid(no_warnings):
    ids, z, R = _rows()
    for noise in (R, R[0]):
        valid, reasons = row_problems(ids, z, noise)
        assert valid.tolist() == [True] * 6 and reasons == Counter()
    # The limits themselves are valid.
    ids[:2] = [0, MAX_ID]
    z[2, 0] = MIN_RANGE
    valid, reasons = row_problems(ids, z, R)
    assert valid.all() and not reasons


@pytest.mark.parametrize('change, reason', [
    (lambda ids, z, R: z.__setitem__((1, 0), np.nan), 'observation_nonfinite'),
    (lambda ids, z, R: z.__setitem__((1, 1), np.inf), 'observation_nonfinite'),
    (lambda ids, z, R: z.__setitem__((1, 0), -np.inf), 'observation_nonfinite'),
    (lambda ids, z, R: z.__setitem__((1, 0), 0.0), 'range_not_positive'),
    (lambda ids, z, R: z.__setitem__((1, 0), -2.0), 'range_not_positive'),
    (lambda ids, z, R: z.__setitem__((1, 0), MIN_RANGE / 2), 'range_not_positive'),
    (lambda ids, z, R: ids.__setitem__(1, -1), 'invalid_id'),
    (lambda ids, z, R: ids.__setitem__(1, MAX_ID + 1), 'invalid_id'),
    (lambda ids, z, R: R.__setitem__((1, 0, 0), -0.01), 'negative_variance'),
    (lambda ids, z, R: R.__setitem__((1, 1, 1), -1e-9), 'negative_variance'),
    (lambda ids, z, R: R.__setitem__((1, 1, 1), np.nan), 'noise_covariance_nonfinite'),
    (lambda ids, z, R: R.__setitem__((1, 0, 1), 0.5), 'noise_covariance_asymmetric'),
    (lambda ids, z, R: R[1].__setitem__((slice(None), slice(None)), [[0.01, 0.1], [0.1, 0.01]]),
     'noise_covariance_not_psd'),
])
def test_row_problems_each_reason(change, reason, no_warnings):
    ids, z, R = _rows()
    change(ids, z, R)
    valid, reasons = row_problems(ids, z, R)
    assert valid.tolist() == [True, False, True, True, True, True]
    assert reasons == Counter({reason: 1})


def test_row_problems_precedence_and_counts(no_warnings):
    ids, z, R = _rows(8)
    z[0] = [np.nan, 0.0]
    ids[0] = -5                       # also invalid id: counted as nonfinite only
    z[1, 0] = 0.0
    ids[1] = MAX_ID + 7               # range first
    ids[2] = -1
    R[2, 0, 0] = -1.0                 # invalid id before the noise
    R[3, 0, 0] = -1.0                 # negative variance (also not PSD)
    R[4, 0, 1] = 1.0                  # asymmetric (and not PSD when symmetrised?)
    R[5] = [[1.0, 2.0], [2.0, 1.0]]   # not PSD
    valid, reasons = row_problems(ids, z, R)
    assert valid.tolist() == [False] * 6 + [True] * 2
    assert reasons == Counter(observation_nonfinite=1, range_not_positive=1, invalid_id=1,
                              negative_variance=1, noise_covariance_asymmetric=1,
                              noise_covariance_not_psd=1)
    assert sum(reasons.values()) + valid.sum() == len(ids)


def test_row_problems_shared_noise_is_not_checked_per_row():
    ids, z, _ = _rows()
    valid, reasons = row_problems(ids, z, np.array([[0.01, 0.0], [0.0, 0.0004]]))
    assert valid.all() and not reasons


# --- landmark_row_problems ---------------------------------------------------------------------

def _landmark_rows(rng, count=6):
    ids = np.arange(count, dtype=np.int64) + 10
    m = rng.uniform(-10, 10, (count, 2))
    P = random_spd(rng, 2, count, eps=0.01)
    P_dep = 0.4 * P
    return ids, m, P, P_dep


def test_landmark_rows_valid(rng, no_warnings):
    ids, m, P, P_dep = _landmark_rows(rng)
    P_dep[0] = 0.0          # no dependent part
    P_dep[1] = P[1]         # all of it dependent
    valid, reasons = landmark_row_problems(ids, m, P, P_dep)
    assert valid.all() and reasons == Counter()


def _set(array, index, value):
    array[index] = value


@pytest.mark.parametrize('change, reason', [
    (lambda ids, m, P, D: _set(m, (2, 0), np.nan), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(m, (2, 1), -np.inf), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(P, (2, 1, 1), np.inf), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(D, (2, 0, 1), np.nan), 'landmark_nonfinite'),
    (lambda ids, m, P, D: _set(ids, 2, -3), 'invalid_id'),
    (lambda ids, m, P, D: _set(ids, 2, MAX_ID + 1), 'invalid_id'),
    (lambda ids, m, P, D: _set(P, (2, 0, 1), P[2, 0, 1] + 0.5), 'covariance_asymmetric'),
    (lambda ids, m, P, D: _set(P, 2, [[1.0, 2.0], [2.0, 1.0]]), 'covariance_not_psd'),
    (lambda ids, m, P, D: _set(P, 2, -np.eye(2)), 'covariance_not_psd'),
    (lambda ids, m, P, D: (_set(P, 2, [[1.0, 1.0], [1.0, 1.0]]), _set(D, 2, 0.0)),
     'covariance_singular'),
    (lambda ids, m, P, D: (_set(P, 2, np.zeros((2, 2))), _set(D, 2, 0.0)),
     'covariance_singular'),
    (lambda ids, m, P, D: (_set(P, 2, np.diag([1.0, 1e-13])), _set(D, 2, 0.0)),
     'covariance_singular'),
    (lambda ids, m, P, D: _set(D, 2, -0.1 * np.eye(2)), 'dependent_part_invalid'),
    (lambda ids, m, P, D: _set(D, 2, 2.0 * P[2]), 'dependent_part_invalid'),
    (lambda ids, m, P, D: _set(D, 2, P[2] + np.diag([0.0, 1e-3])), 'dependent_part_invalid'),
    (lambda ids, m, P, D: _set(D, (2, 0, 1), D[2, 0, 1] + 0.1), 'dependent_part_invalid'),
])
def test_landmark_rows_each_reason(change, reason, rng, no_warnings):
    ids, m, P, P_dep = _landmark_rows(rng)
    change(ids, m, P, P_dep)
    valid, reasons = landmark_row_problems(ids, m, P, P_dep)
    assert valid.tolist() == [True, True, False, True, True, True]
    assert reasons == Counter({reason: 1})


def test_landmark_rows_small_but_regular_covariances_are_valid(no_warnings):
    # The singularity test is relative to the scale of the matrix.
    for s in (1e-150, 1e-8, 1.0, 1e8, 1e150):
        P = np.array([[[2.0, 0.5], [0.5, 1.0]]]) * s
        valid, reasons = landmark_row_problems(np.array([1]), np.zeros((1, 2)), P, 0.5 * P)
        assert valid.all() and not reasons, s


def test_landmark_rows_precedence(rng, no_warnings):
    ids, m, P, P_dep = _landmark_rows(rng, 7)
    m[0, 0] = np.nan
    ids[0] = -1                               # nonfinite first
    ids[1] = -1
    P[1] = -np.eye(2)                         # invalid id before the covariance
    P[2, 0, 1] += 5.0                         # asymmetric (and not PSD) -> asymmetric
    P[3] = [[1.0, 1.0], [1.0, 1.0]]           # singular; its dependent part now too large
    valid, reasons = landmark_row_problems(ids, m, P, P_dep)
    assert valid.tolist() == [False] * 4 + [True] * 3
    assert reasons == Counter(landmark_nonfinite=1, invalid_id=1, covariance_asymmetric=1,
                              covariance_singular=1)


def test_landmark_rows_huge_covariances_without_warnings(no_warnings):
    P = np.array([np.eye(2) * 1e200])
    valid, reasons = landmark_row_problems(np.array([1]), np.zeros((1, 2)), P, 0.5 * P)
    assert valid.all() and not reasons


# --- landmarks_from_rows -----------------------------------------------------------------------

@pytest.mark.parametrize('per_row_noise', [False, True])
@pytest.mark.parametrize('extras', [False, True])
def test_landmarks_from_rows_matches_the_core(per_row_noise, extras, rng, no_warnings):
    count = 40
    ids = rng.integers(0, MAX_ID, count)
    z = random_observations(rng, count)
    R = random_spd(rng, 2, count, scale=0.1) if per_row_noise else np.diag([0.01, 0.0004])
    pose, P_pose = random_poses(rng), random_spd(rng, 3, scale=0.1)
    sensor_pose = np.array([0.3, -0.1, 0.2]) if extras else None
    R_bias = np.diag([0.0025, 1e-4]) if extras else None
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose,
                                                       sensor_pose, R_bias)
    ref = landmark_to_world_dependent(pose, P_pose, z, R, R_bias, sensor_pose)
    assert kept.dtype == bool and kept.tolist() == [True] * count
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    assert reasons == Counter()
    assert m.shape == (count, 2) and P_m.shape == P_dep.shape == (count, 2, 2)


def test_landmarks_from_rows_with_a_pose_per_row(rng, no_warnings):
    count = 12
    ids = np.arange(count)
    z = random_observations(rng, count)
    z[3, 0] = -1.0
    R = np.diag([0.01, 0.0004])
    pose, P_pose = random_poses(rng, count), random_spd(rng, 3, count, scale=0.1)
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose)
    assert kept.tolist() == [k != 3 for k in range(count)]
    ref = landmark_to_world_dependent(pose[kept], P_pose[kept], z[kept], R)
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    assert reasons == Counter(range_not_positive=1)


def test_landmarks_from_rows_drops_invalid_rows(rng, no_warnings):
    count = 10
    ids = np.arange(count, dtype=np.int64)
    z = random_observations(rng, count)
    R = random_spd(rng, 2, count, scale=0.1)
    z[1, 0] = np.nan
    z[4, 0] = 0.0
    ids[6] = -1
    R[8, 1, 1] = -1.0
    pose, P_pose = random_poses(rng), random_spd(rng, 3, scale=0.1)
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose)
    keep = np.array([0, 2, 3, 5, 7, 9])
    np.testing.assert_array_equal(np.flatnonzero(kept), keep)
    ref = landmark_to_world_dependent(pose, P_pose, z[keep], R[keep])
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    assert reasons == Counter(observation_nonfinite=1, range_not_positive=1, invalid_id=1,
                              negative_variance=1)
    assert kept.sum() + sum(reasons.values()) == count


def test_landmarks_from_rows_drops_nonfinite_results_without_warnings(rng, no_warnings):
    ids = np.array([1, 2, 3, 4, 5], np.int64)
    z = np.array([[5.0, 0.1], [1e200, 0.3], [1e300, -1.0], [7.0, 2.0], [-1.0, 0.0]])
    pose, P_pose = np.array([1.0, 2.0, 0.3]), random_spd(rng, 3, scale=0.1)
    R = np.diag([0.01, 0.0004])
    R_bias = np.diag([1e-4, 1e-6])
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids, z, R, pose, P_pose,
                                                       R_bias=R_bias)
    assert kept.tolist() == [True, False, False, True, False]
    assert reasons == Counter(result_nonfinite=2, range_not_positive=1)
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(P_m)) and np.all(np.isfinite(P_dep))
    ref = landmark_to_world_dependent(pose, P_pose, z[[0, 3]], R, R_bias)
    for actual, expected in zip((m, P_m, P_dep), ref):
        np.testing.assert_array_equal(actual, expected)
    # Every row dropped: empty outputs of the right shapes.
    kept, m, P_m, P_dep, reasons = landmarks_from_rows(ids[1:3], z[1:3], R, pose, P_pose)
    assert kept.tolist() == [False, False] and m.shape == (0, 2) and P_m.shape == (0, 2, 2)
    assert P_dep.shape == (0, 2, 2) and reasons == Counter(result_nonfinite=2)


def test_landmarks_from_rows_dependent_part_is_the_pose_and_bias(rng, no_warnings):
    count = 20
    ids = np.arange(count)
    z = random_observations(rng, count)
    R = np.diag([0.01, 0.0004])
    pose = random_poses(rng)
    # Exact pose, no bias: nothing dependent.
    _, _, P_m, P_dep, _ = landmarks_from_rows(ids, z, R, pose, np.zeros((3, 3)))
    np.testing.assert_array_equal(P_dep, np.zeros((count, 2, 2)))
    # The dependent part grows with the pose covariance, the total by as much.
    P_pose = random_spd(rng, 3, scale=0.1)
    _, _, P_m2, P_dep2, _ = landmarks_from_rows(ids, z, R, pose, P_pose)
    np.testing.assert_allclose(P_m2 - P_m, P_dep2, rtol=0, atol=1e-12)
    # A bias adds the same to both.
    R_bias = np.diag([0.0025, 1e-4])
    _, _, P_m3, P_dep3, _ = landmarks_from_rows(ids, z, R, pose, P_pose, R_bias=R_bias)
    np.testing.assert_allclose(P_m3 - P_m2, P_dep3 - P_dep2, rtol=0, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(P_dep3 - P_dep2)[:, -1] > 0)


# --- config ------------------------------------------------------------------------------------

@pytest.mark.parametrize('cls', [config.ObserverConfig, config.FuserConfig])
def test_config_defaults_are_valid(cls):
    cfg = cls()
    for spec in dataclasses.fields(cls):
        value = getattr(cfg, spec.name)
        assert value == config.field_default(spec)
        low, high = spec.metadata['low'], spec.metadata['high']
        if low is not None:
            assert low <= value <= high
        assert spec.metadata['description']
    assert cls.from_values({}) == cfg
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.log_throttle_s = 1.0


def test_config_coercion_of_numbers():
    cfg = config.ObserverConfig(range_stddev=1, max_pending=5.0, sensor_pose=[1, 2, 0.5])
    assert cfg.range_stddev == 1.0 and type(cfg.range_stddev) is float
    assert cfg.max_pending == 5 and type(cfg.max_pending) is int
    assert cfg.sensor_pose == (1.0, 2.0, 0.5)
    assert all(type(v) is float for v in cfg.sensor_pose)
    cfg = config.FuserConfig(input_topics=['a', 'b'])
    assert cfg.input_topics == ('a', 'b')


@pytest.mark.parametrize('cls, name, value, message', [
    (config.ObserverConfig, 'range_stddev', True, 'must be a number'),
    (config.ObserverConfig, 'range_stddev', '0.1', 'must be a number'),
    (config.ObserverConfig, 'range_stddev', None, 'must be a number'),
    (config.ObserverConfig, 'range_stddev', math.nan, 'must be finite'),
    (config.ObserverConfig, 'max_wait_s', math.inf, 'must be finite'),
    (config.ObserverConfig, 'max_pending', 5.5, 'must be an integer'),
    (config.ObserverConfig, 'max_pending', False, 'must be a number'),
    (config.ObserverConfig, 'world_frame', 5, 'must be a string'),
    (config.ObserverConfig, 'sensor_pose', (0.0, 0.0), 'must have 3 entries'),
    (config.ObserverConfig, 'sensor_pose', (0.0, 0.0, 0.0, 0.0), 'must have 3 entries'),
    (config.ObserverConfig, 'sensor_pose', (0.0, 'x', 0.0), 'must hold finite numbers'),
    (config.ObserverConfig, 'sensor_pose', (0.0, True, 0.0), 'must hold finite numbers'),
    (config.ObserverConfig, 'sensor_pose', (0.0, math.nan, 0.0), 'must hold finite numbers'),
    (config.FuserConfig, 'input_topics', ['a', 3], 'must be a list of strings'),
    (config.FuserConfig, 'gate_probability', 1, 'outside'),
    (config.FuserConfig, 'gate_probability', 0.4, 'outside'),
    (config.FuserConfig, 'min_observations', 0, 'outside'),
    (config.ObserverConfig, 'range_stddev', -0.1, 'outside'),
    (config.ObserverConfig, 'bearing_stddev', 3.2, 'outside'),
    (config.ObserverConfig, 'pose_buffer_s', 0.0, 'outside'),
])
def test_config_rejects_bad_values(cls, name, value, message):
    with pytest.raises(ValueError, match=message):
        cls(**{name: value})
    with pytest.raises(ValueError, match=message):
        cls.from_values({name: value})


def test_config_range_limits_are_inclusive():
    assert config.ObserverConfig(bearing_stddev=math.pi).bearing_stddev == math.pi
    assert config.ObserverConfig(range_stddev=0.0).range_stddev == 0.0
    assert config.FuserConfig(gate_probability=0.999999).gate_probability == 0.999999


def test_config_relations():
    with pytest.raises(ValueError, match='max_pose_gap_s'):
        config.ObserverConfig(pose_buffer_s=1.0, max_pose_gap_s=2.0)
    assert config.ObserverConfig(pose_buffer_s=2.0, max_pose_gap_s=2.0).max_pose_gap_s == 2.0
    with pytest.raises(ValueError, match='fusion'):
        config.FuserConfig(fusion='average')
    for fusion in ('independent', 'covariance_intersection', 'split_covariance_intersection'):
        assert config.FuserConfig(fusion=fusion).fusion == fusion
    with pytest.raises(ValueError, match='at least one topic'):
        config.FuserConfig(input_topics=[])
    with pytest.raises(ValueError, match='at least one topic'):
        config.FuserConfig(input_topics=['a', ''])
    with pytest.raises(ValueError, match='repeat'):
        config.FuserConfig(input_topics=['a', 'b', 'a'])


def test_config_from_values_ignores_unknown_names():
    cfg = config.FuserConfig.from_values({'fusion': 'independent', 'use_sim_time': True,
                                          'qos_overrides': {}})
    assert cfg.fusion == 'independent'


def test_config_rejects_a_string_for_a_list_of_strings():
    with pytest.raises(ValueError):
        config.FuserConfig(input_topics='ab')


# --- pose_buffer -------------------------------------------------------------------------------

S = 1_000_000_000   # ns per second


def _cov(k):
    return np.diag([0.01, 0.02, 0.001]) * (1 + k)


def _buffer(stamps, poses, duration=100 * S, gap=S // 10, max_size=10000):
    buf = pose_buffer.PoseBuffer(duration, gap, max_size)
    for k, (stamp, pose) in enumerate(zip(stamps, poses)):
        buf.add(stamp, np.array(pose, float), _cov(k))
    return buf


def test_interpolate_position_linear_and_covariance_linear():
    p0, p1 = np.array([0.0, 1.0, 0.1]), np.array([2.0, -3.0, 0.5])
    for f in (0.0, 0.25, 0.5, 1.0):
        pose, P = pose_buffer.interpolate(p0, _cov(0), p1, _cov(3), f)
        np.testing.assert_allclose(pose, [2.0 * f, 1.0 - 4.0 * f, 0.1 + 0.4 * f], rtol=0,
                                   atol=1e-15)
        np.testing.assert_allclose(P, (1 - f) * _cov(0) + f * _cov(3), rtol=0, atol=1e-15)


@pytest.mark.parametrize('theta0, theta1, f, expected', [
    (3.0, -3.0, 0.5, math.pi),                       # across +-pi, not through 0
    (-3.0, 3.0, 0.5, math.pi),
    (3.0, -3.0, 0.25, 3.0 + 0.25 * (2 * math.pi - 6.0)),
    (-3.1, 3.1, 0.5, math.pi),
    (0.2, -0.2, 0.5, 0.0),
    (-math.pi, math.pi - 1e-9, 0.5, -math.pi),
    (1.0, 1.0 + 3.0, 0.5, 2.5),
])
def test_interpolate_yaw_on_the_shortest_arc(theta0, theta1, f, expected):
    pose, _ = pose_buffer.interpolate(np.array([0.0, 0.0, theta0]), _cov(0),
                                      np.array([0.0, 0.0, theta1]), _cov(1), f)
    assert -math.pi <= pose[2] < math.pi
    assert abs(wrap_angle(pose[2] - expected)) < 1e-9


def test_lookup_statuses():
    buf = pose_buffer.PoseBuffer(100 * S, S // 10)
    assert buf.lookup(5 * S).status == pose_buffer.WAIT          # empty
    assert buf.newest_ns is None and len(buf) == 0
    poses = [[0.0, 0.0, 0.0], [1.0, 2.0, 0.5], [3.0, 2.0, 1.0]]
    buf = _buffer([10 * S, 11 * S, 13 * S], poses)
    assert buf.newest_ns == 13 * S and len(buf) == 3
    found = buf.lookup(11 * S)                                    # exact stamp
    assert found.status == pose_buffer.FOUND
    np.testing.assert_array_equal(found.pose, poses[1])
    np.testing.assert_array_equal(found.P_pose, _cov(1))
    mid = buf.lookup(12 * S)                                      # interpolated
    assert mid.status == pose_buffer.FOUND
    np.testing.assert_allclose(mid.pose, [2.0, 2.0, 0.75], rtol=0, atol=1e-15)
    np.testing.assert_allclose(mid.P_pose, 0.5 * (_cov(1) + _cov(2)), rtol=0, atol=1e-15)
    quarter = buf.lookup(10 * S + S // 4)
    np.testing.assert_allclose(quarter.pose, [0.25, 0.5, 0.125], rtol=0, atol=1e-15)
    # Newer than every pose: wait, also just after the newest.
    assert buf.lookup(13 * S + 1).status == pose_buffer.WAIT
    assert buf.lookup(20 * S).status == pose_buffer.WAIT
    # Older than the buffer: the oldest pose within the gap, else too old.
    early = buf.lookup(10 * S - S // 10)
    assert early.status == pose_buffer.FOUND
    np.testing.assert_array_equal(early.pose, poses[0])
    assert buf.lookup(10 * S - S // 10 - 1).status == pose_buffer.TOO_OLD
    assert buf.lookup(0).status == pose_buffer.TOO_OLD
    assert buf.lookup(0).pose is None


def test_lookup_final_takes_the_newest_within_the_gap():
    poses = [[0.0, 0.0, 0.0], [1.0, 2.0, 0.5]]
    buf = _buffer([10 * S, 11 * S], poses)
    late = buf.lookup(11 * S + S // 10, final=True)
    assert late.status == pose_buffer.FOUND
    np.testing.assert_array_equal(late.pose, poses[1])
    np.testing.assert_array_equal(late.P_pose, _cov(1))
    assert buf.lookup(11 * S + S // 10).status == pose_buffer.WAIT
    assert buf.lookup(11 * S + S // 10 + 1, final=True).status == pose_buffer.WAIT
    # final changes nothing inside the buffer.
    np.testing.assert_array_equal(buf.lookup(10 * S, final=True).pose, poses[0])


def test_lookup_returns_copies():
    buf = _buffer([S, 2 * S], [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    found = buf.lookup(S)
    found.pose[:] = 99.0
    found.P_pose[:] = 99.0
    again = buf.lookup(S)
    np.testing.assert_array_equal(again.pose, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(again.P_pose, _cov(0))


def test_trimming_by_duration_and_size():
    buf = pose_buffer.PoseBuffer(5 * S, 0)
    for k in range(11):
        buf.add(k * S, np.array([k, 0.0, 0.0]), _cov(0))
    assert len(buf) == 6                         # stamps 5..10 s: newest - duration kept
    assert buf.lookup(5 * S).status == pose_buffer.FOUND
    assert buf.lookup(5 * S - 1).status == pose_buffer.TOO_OLD
    buf = pose_buffer.PoseBuffer(100 * S, 0, max_size=4)
    for k in range(10):
        buf.add(k * S, np.array([k, 0.0, 0.0]), _cov(0))
    assert len(buf) == 4
    np.testing.assert_array_equal(buf.lookup(6 * S).pose, [6.0, 0.0, 0.0])
    assert buf.lookup(5 * S).status == pose_buffer.TOO_OLD
    buf.clear()
    assert len(buf) == 0 and buf.lookup(6 * S).status == pose_buffer.WAIT


def test_add_refuses_non_increasing_stamps():
    buf = _buffer([S, 2 * S], [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    for stamp in (2 * S, S, 0):
        with pytest.raises(ValueError, match='not newer'):
            buf.add(stamp, np.zeros(3), _cov(0))
    assert len(buf) == 2 and buf.newest_ns == 2 * S
    buf.add(2 * S + 1, np.zeros(3), _cov(0))
    assert len(buf) == 3


def test_integer_stamps_are_exact_at_large_values():
    base = 1_700_000_000 * S     # a wall-clock time in ns: beyond float64's exact integers
    buf = _buffer([base, base + 2], [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    mid = buf.lookup(base + 1)
    assert mid.status == pose_buffer.FOUND
    np.testing.assert_allclose(mid.pose, [1.0, 0.0, 0.0], rtol=0, atol=1e-15)
    assert buf.lookup(base + 3).status == pose_buffer.WAIT


# --- diagnostics.Counters ----------------------------------------------------------------------

class Clock:
    """A settable clock for Counters."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_counters_count_and_throttle_per_reason():
    lines, clock = [], Clock()
    counters = diagnostics.Counters(lines.append, throttle_s=5.0, clock=clock)
    counters.add('bad_row', 3, 'three bad rows')
    counters.add('late', 1)                    # counted, never logged without detail
    counters.add('nothing', 0, 'ignored')      # non-positive counts are ignored
    counters.add('nothing', -2, 'ignored')
    assert lines == ['bad_row x3: three bad rows']
    assert counters['bad_row'] == 3 and counters['late'] == 1 and counters['nothing'] == 0
    assert 'nothing' not in counters.counts
    clock.now += 1.0
    counters.add('bad_row', 2, 'suppressed')
    counters.add('other', 1, 'another kind is not throttled by the first')
    clock.now += 3.9
    counters.add('bad_row', 4, 'suppressed too')
    assert lines == ['bad_row x3: three bad rows',
                     'other x1: another kind is not throttled by the first']
    clock.now += 0.1   # 5 s after the last report
    counters.add('bad_row', 1, 'back')
    assert lines[-1] == 'bad_row x1: back (6 more since the last report)'
    clock.now += 10.0
    counters.add('bad_row', 1, 'quiet since')
    assert lines[-1] == 'bad_row x1: quiet since'
    assert counters['bad_row'] == 11
    assert diagnostics.status_values(counters.counts, {'state': 'ok'}) == [
        ('state', 'ok'), ('bad_row', '11'), ('late', '1'), ('other', '1')]


def test_counters_without_detail_do_not_reset_the_throttle():
    lines, clock = [], Clock()
    counters = diagnostics.Counters(lines.append, throttle_s=2.0, clock=clock)
    counters.add('x', 1, 'a')
    clock.now += 1.0
    counters.add('x', 5)          # no detail: not part of "more since the last report"
    clock.now += 1.0
    counters.add('x', 1, 'b')
    assert lines == ['x x1: a', 'x x1: b'] and counters['x'] == 7


def test_counters_zero_throttle_logs_every_time():
    lines, clock = [], Clock()
    counters = diagnostics.Counters(lines.append, throttle_s=0.0, clock=clock)
    for _ in range(3):
        counters.add('x', 1, 'd')
    assert lines == ['x x1: d'] * 3


# --- cloud -------------------------------------------------------------------------------------

ALL_TYPES = [('i8', np.int8, PointField.INT8), ('u8', np.uint8, PointField.UINT8),
             ('i16', np.int16, PointField.INT16), ('u16', np.uint16, PointField.UINT16),
             ('i32', np.int32, PointField.INT32), ('u32', np.uint32, PointField.UINT32),
             ('f32', np.float32, PointField.FLOAT32), ('f64', np.float64, PointField.FLOAT64)]


def _fill(rows, rng):
    values = {}
    for name, dtype, _ in ALL_TYPES:
        if np.dtype(dtype).kind == 'f':
            column = rng.standard_normal(len(rows)).astype(dtype) * 1e3
            column[:2] = [np.finfo(dtype).max, np.nan]
        else:
            info = np.iinfo(dtype)
            column = rng.integers(info.min, info.max, len(rows), dtype=dtype, endpoint=True)
            column[:2] = [info.min, info.max]
        rows[name] = column
        values[name] = column
    return values


def test_cloud_writer_reader_round_trip_all_datatypes(rng):
    writer = CloudWriter([(name, dtype) for name, dtype, _ in ALL_TYPES])
    rows = writer.rows(25)
    values = _fill(rows, rng)
    header = Header(frame_id='map')
    msg = writer.message(header, rows)
    assert msg.header.frame_id == 'map' and msg.height == 1 and msg.width == 25
    assert not msg.is_bigendian and msg.point_step % 8 == 0
    assert msg.row_step == msg.point_step * 25 == len(msg.data)
    assert [f.datatype for f in msg.fields] == [code for _, _, code in ALL_TYPES]
    for f, (_, dtype, _) in zip(msg.fields, ALL_TYPES):
        assert f.offset % np.dtype(dtype).itemsize == 0 and f.count == 1
    columns = read_columns(msg, tuple(FieldSpec(name, (code,)) for name, _, code in ALL_TYPES))
    for name, dtype, _ in ALL_TYPES:
        expected = values[name]
        got = columns[name]
        if np.dtype(dtype).kind == 'f':
            assert got.dtype == np.float64
            np.testing.assert_array_equal(got, expected.astype(np.float64))
        else:
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, expected.astype(np.int64))


def test_cloud_writer_layout_aligns_fields():
    writer = CloudWriter([('a', np.uint8), ('b', np.float64), ('c', np.uint16),
                          ('d', np.float32)])
    assert [f.offset for f in writer.fields] == [0, 8, 16, 20]
    assert writer.dtype.itemsize == 24
    writer = CloudWriter([('a', np.uint8)])
    assert writer.dtype.itemsize == 8


def _manual_cloud(values, dtype, height, width, row_step=None, bigendian=False, pad=b'\xab'):
    """Build a PointCloud2 from a structured array of height * width rows by hand."""
    msg = PointCloud2()
    msg.height, msg.width = height, width
    msg.is_bigendian = bigendian
    msg.point_step = dtype.itemsize
    msg.row_step = row_step or width * dtype.itemsize
    codes = {np.dtype(t).newbyteorder('='): c for _, t, c in ALL_TYPES}
    msg.fields = [PointField(name=name, offset=dtype.fields[name][1],
                             datatype=codes[dtype.fields[name][0].newbyteorder('=')], count=1)
                  for name in dtype.names]
    data = b''
    raw = values.tobytes()
    for r in range(height):
        row = raw[r * width * dtype.itemsize:(r + 1) * width * dtype.itemsize]
        data += row + pad * (msg.row_step - len(row))
    msg.data = data
    return msg


def test_cloud_reader_big_endian(rng):
    dtype = np.dtype({'names': ['x', 'id', 'v'], 'formats': ['>f8', '>u4', '>i2'],
                      'offsets': [0, 8, 12], 'itemsize': 16})
    values = np.zeros(7, dtype)
    values['x'] = rng.standard_normal(7)
    values['id'] = rng.integers(0, 2 ** 32, 7)
    values['v'] = rng.integers(-2 ** 15, 2 ** 15, 7)
    msg = _manual_cloud(values, dtype, 1, 7, bigendian=True)
    columns = read_columns(msg, (FieldSpec('x', (PointField.FLOAT64,)),
                                 FieldSpec('id', (PointField.UINT32,)),
                                 FieldSpec('v', (PointField.INT16,))))
    np.testing.assert_array_equal(columns['x'], values['x'])
    np.testing.assert_array_equal(columns['id'], values['id'].astype(np.int64))
    np.testing.assert_array_equal(columns['v'], values['v'].astype(np.int64))


def test_cloud_reader_height_and_row_padding(rng):
    dtype = np.dtype({'names': ['x', 'id'], 'formats': ['<f4', '<u4'], 'offsets': [0, 4],
                      'itemsize': 12})
    height, width = 3, 4
    values = np.zeros(height * width, dtype)
    values['x'] = np.arange(12) * 1.5
    values['id'] = np.arange(12) + 100
    msg = _manual_cloud(values, dtype, height, width, row_step=width * 12 + 7)
    assert len(msg.data) == height * (width * 12 + 7)
    columns = read_columns(msg, (FieldSpec('x', (PointField.FLOAT32,)),
                                 FieldSpec('id', (PointField.UINT32,))))
    np.testing.assert_array_equal(columns['x'], values['x'])
    np.testing.assert_array_equal(columns['id'], np.arange(12) + 100)


def test_cloud_reader_optional_fields_and_empty_clouds(rng):
    writer = CloudWriter([('x', np.float32), ('id', np.uint32)])
    specs = (FieldSpec('x', (PointField.FLOAT32,)), FieldSpec('id', (PointField.UINT32,)),
             FieldSpec('range_variance', (PointField.FLOAT32,), required=False))
    rows = writer.rows(3)
    rows['x'] = [1.0, 2.0, 3.0]
    columns = read_columns(writer.message(Header(), rows), specs)
    assert set(columns) == {'x', 'id'}
    columns = read_columns(writer.message(Header(), writer.rows(0)), specs)
    assert columns['x'].shape == (0,) and columns['x'].dtype == np.float64
    assert columns['id'].shape == (0,) and columns['id'].dtype == np.int64


def _valid_message():
    writer = CloudWriter([('x', np.float32), ('id', np.uint32)])
    rows = writer.rows(4)
    rows['x'] = [1.0, 2.0, 3.0, 4.0]
    return writer.message(Header(), rows)


SPECS = (FieldSpec('x', (PointField.FLOAT32, PointField.FLOAT64)),
         FieldSpec('id', (PointField.UINT32,)))


def _break(change):
    msg = _valid_message()
    change(msg)
    return msg


@pytest.mark.parametrize('change, reason', [
    (lambda msg: setattr(msg, 'fields', msg.fields[:1]), 'missing_field'),
    (lambda msg: setattr(msg.fields[0], 'name', 'y'), 'missing_field'),
    (lambda msg: setattr(msg.fields[1], 'datatype', PointField.INT32), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[0], 'datatype', PointField.INT32), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[0], 'count', 2), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[0], 'count', 0), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[1], 'offset', msg.point_step - 2), 'data_length_mismatch'),
    (lambda msg: setattr(msg.fields[0], 'datatype', PointField.FLOAT64) or setattr(
        msg.fields[0], 'offset', msg.point_step - 4), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'row_step', msg.row_step - 1), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'data', bytes(msg.data)[:-1]), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'data', bytes(msg.data) + b'\x00'), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'height', 2), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'width', 5), 'data_length_mismatch'),
])
def test_cloud_errors(change, reason):
    msg = _break(change)
    with pytest.raises(CloudError) as info:
        read_columns(msg, SPECS)
    assert info.value.reason == reason
    assert str(info.value).startswith(reason + ': ')
    assert isinstance(info.value, ValueError)


def test_cloud_valid_message_reads():
    columns = read_columns(_valid_message(), SPECS)
    np.testing.assert_array_equal(columns['x'], [1.0, 2.0, 3.0, 4.0])
    assert cloud.DATATYPES[np.dtype(np.float32)] == PointField.FLOAT32


def test_cloud_reader_accepts_a_list_of_specs():
    columns = read_columns(_valid_message(), list(SPECS))
    np.testing.assert_array_equal(columns['x'], [1.0, 2.0, 3.0, 4.0])


def test_cloud_layout_cache_does_not_mix_layouts(rng):
    # The same specs on clouds of different layouts (offsets, endianness) read correctly.
    specs = (FieldSpec('x', (PointField.FLOAT64,)), FieldSpec('id', (PointField.UINT32,)))
    for order in ('<', '>'):
        for offsets in ([0, 8], [4, 0], [8, 0]):
            dtype = np.dtype({'names': ['x', 'id'], 'formats': [order + 'f8', order + 'u4'],
                              'offsets': offsets, 'itemsize': 16})
            values = np.zeros(5, dtype)
            values['x'] = rng.standard_normal(5)
            values['id'] = rng.integers(0, 1000, 5)
            msg = _manual_cloud(values, dtype, 1, 5, bigendian=order == '>')
            columns = read_columns(msg, specs)
            np.testing.assert_array_equal(columns['x'], values['x'])
            np.testing.assert_array_equal(columns['id'], values['id'])
    # And a bad layout raises every time, not only the first.
    for _ in range(2):
        with pytest.raises(CloudError):
            read_columns(_break(lambda msg: setattr(msg.fields[0], 'count', 2)), SPECS)
