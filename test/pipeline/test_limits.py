"""Plausible ranges (``pipeline.limits``): the same limit and reason on every path."""

from dataclasses import fields

from landmark_ros.core.partial import BEARING, RANGE, Views
from landmark_ros.fuser.partial import partial_row_problems
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline import limits
from landmark_ros.pipeline.config import ObserverConfig
from landmark_ros.pipeline.partial_rows import PartialObservations
from landmark_ros.pipeline.rows import landmark_row_problems
import numpy as np
import pytest

S = 10 ** 9


def observer_with_pose():
    observer = Observer(ObserverConfig(max_wait_s=0.0))
    observer.add_pose(S, np.zeros(3), np.eye(3) * 1e-4)
    return observer


@pytest.mark.parametrize('columns, reason', [
    ({'range': [4.0, 4.0], 'bearing': [0.1, 1e17]}, 'bearing_out_of_range'),
    ({'range': [np.nan, np.nan], 'bearing': [0.1, -1e17]}, 'bearing_out_of_range'),
    ({'range': [4.0, 1e9], 'bearing': [0.1, 0.2]}, 'range_out_of_range'),
    ({'range': [4.0, 1e9]}, 'range_out_of_range'),
    ({'range': [4.0, 5.0], 'range_variance': [0.01, 1e-200]}, 'noise_variance_out_of_range'),
    ({'range': [4.0, 5.0], 'bearing': [0.1, 0.2], 'bearing_variance': [0.01, 1e200]},
     'noise_variance_out_of_range'),
    ({'range': [4.0, 5.0], 'bearing': [0.1, 0.2],
      'range_bearing_covariance': [0.0, -1e13]}, 'noise_variance_out_of_range'),
])
def test_an_implausible_observation_row_is_counted_and_the_other_row_kept(columns, reason):
    observer = observer_with_pose()
    columns = {name: np.asarray(values, np.float64) for name, values in columns.items()}
    columns['id'] = np.array([1, 2], np.int64)
    batch, = observer.add_observations([ObservationMessage(S, columns, None)])
    assert observer.counters[reason] == 1
    assert (batch.ids.tolist() + batch.partial_observations.ids.tolist()) == [1]


@pytest.mark.parametrize('pose, P_pose, reason', [
    ([0.0, 0.0, 1e17], np.eye(3), 'pose_out_of_range'),
    ([2e7, 0.0, 0.0], np.eye(3), 'pose_out_of_range'),
    ([1.0, 0.0, 0.0], np.eye(3) * 1e13, 'pose_variance_out_of_range'),
])
def test_an_implausible_pose_is_refused(pose, P_pose, reason):
    observer = Observer(ObserverConfig())
    observer.add_pose(S, np.array(pose), P_pose)
    assert observer.counters[reason] == 1 and len(observer.poses) == 0


def constraint_columns(kind, y, R, theta=0.0):
    """Return two constraint rows; the second has ``y``, ``R`` and ``theta`` as sent."""
    views = Views(np.array([kind, kind]), np.zeros((2, 3)), np.zeros((2, 3, 3)),
                  np.array([1.0, 1.0]), np.array([0.01, 0.01]), np.zeros(2))
    columns = PartialObservations(np.array([1, 2], np.int64), views,
                                  np.zeros(2, np.int64)).columns()
    columns = {name: np.array(values) for name, values in columns.items()}
    columns['value'][1], columns['variance'][1], columns['sensor_theta'][1] = y, R, theta
    return columns


@pytest.mark.parametrize('columns, reason', [
    (constraint_columns(BEARING, 1e17, 0.01), 'bearing_out_of_range'),
    (constraint_columns(RANGE, 1e9, 0.01), 'range_out_of_range'),
    (constraint_columns(RANGE, 2.0, 1e-200), 'variance_out_of_range'),
    (constraint_columns(RANGE, 2.0, 0.01, 1e17), 'pose_out_of_range'),
])
def test_an_implausible_partial_observation_row_is_refused_by_the_fuser(columns, reason):
    valid, reasons = partial_row_problems(columns)
    assert valid.tolist() == [True, False] and reasons == {reason: 1}


def test_a_landmark_beyond_the_coordinate_limit_is_refused():
    ids = np.array([1, 2], np.int64)
    m = np.array([[1.0, 2.0], [2e7, 0.0]])
    P = np.broadcast_to(np.eye(2) * 0.1, (2, 2, 2)).copy()
    valid, reasons = landmark_row_problems(ids, m, P, P * 0.5)
    assert valid.tolist() == [True, False] and reasons == {'landmark_out_of_range': 1}


def test_the_table_names_every_limit_once_with_its_reason():
    rows = limits.table()
    assert len(rows) == len(limits.LIMITS)
    reasons = {row['reason'] for row in rows}
    for reason in ('range_out_of_range', 'bearing_out_of_range', 'noise_variance_out_of_range',
                   'variance_out_of_range', 'pose_out_of_range', 'pose_variance_out_of_range',
                   'landmark_out_of_range'):
        assert reason in reasons
    assert all(float(row['low']) <= float(row['high']) for row in rows)


def test_odometry_without_a_pose_is_recognised():
    assert limits.odometry_pose_missing(np.zeros(3), np.zeros(36))
    assert not limits.odometry_pose_missing(np.zeros(3), np.eye(6).ravel())
    assert not limits.odometry_pose_missing(np.array([1.0, 0.0, 0.0]), np.zeros(36))


def test_configured_noise_stays_within_the_variance_limit_and_sensor_pose_is_checked():
    specs = {spec.name: spec.metadata for spec in fields(ObserverConfig)}
    for name in ('range_stddev', 'bearing_stddev', 'range_bias_stddev', 'bearing_bias_stddev'):
        assert specs[name]['high'] ** 2 <= limits.MAX_VARIANCE
    with pytest.raises(ValueError, match='sensor_pose'):
        ObserverConfig(sensor_pose=(0.0, 0.0, 1e17))
    ObserverConfig(sensor_pose=(0.3, -0.1, 3.0))


def test_the_markdown_table_has_a_row_per_limit():
    text = limits.markdown()
    assert text.count('\n') == len(limits.LIMITS) + 2 and 'bearing_out_of_range' in text
