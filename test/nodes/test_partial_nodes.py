"""Partial observations over DDS: observers publish them, the fuser places the landmark."""

import math

from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.nodes.fuser import LandmarkFuser
from landmark_ros.nodes.observer import LandmarkObserver
from landmark_ros.pipeline.partial_rows import PARTIAL_COLUMNS, RANGE_SCALE_COLUMNS
from landmark_ros.ros.cloud import CloudWriter
from landmark_ros.ros.qos import LATCHED
from landmark_ros.ros.schemas import (observation_message, read_landmarks,
                                      read_partial_observations)
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosutil import Collector, header, pose_message, wait_for_match
from sensor_msgs.msg import PointCloud2

DEADLINE_S = 20.0
P_POSE = np.diag([1e-4, 1e-4, 1e-5])
LANDMARK = np.array([3.0, 4.0])
BEARING_ONLY = CloudWriter((('id', np.uint32), ('bearing', np.float64)))


def params(values):
    """Return rclpy Parameters from a dict."""
    return [Parameter(name, value=value) for name, value in values.items()]


def bearing_only_cloud(stamp, landmark_id, bearing):
    """Return an observation cloud with ``id`` and ``bearing`` only."""
    rows = BEARING_ONLY.rows(1)
    rows['id'], rows['bearing'] = landmark_id, bearing
    return BEARING_ONLY.message(header(stamp, 'camera'), rows)


@pytest.mark.parametrize('deprecated', [False, True])
def test_observers_publish_partial_observations_and_the_fuser_places_the_landmark(env,
                                                                                  deprecated):
    # deprecated: the former names, kept for one release, still work end to end: the
    # fuser's constraint_topics and the observers' landmark_constraints topic.
    ns = f'/partial_test_{env.domain_id}'
    topic = 'landmark_constraints' if deprecated else 'partial_observations'
    parameter = 'constraint_topics' if deprecated else 'partial_observation_topics'
    fuser = env.add(LandmarkFuser(context=env.context, namespace=ns, parameter_overrides=params({
        'input_topics': ['robot1/landmarks', 'robot2/landmarks'],
        parameter: [f'robot1/{topic}', f'robot2/{topic}'],
        'fusion': 'split_covariance_intersection', 'publish_rate_hz': 50.0})))
    tester = env.node('views_tester')
    maps = Collector(tester, PointCloud2, f'{ns}/fused_landmarks', LATCHED)
    rigs = []
    for robot in ('robot1', 'robot2'):
        observer = env.add(LandmarkObserver(
            context=env.context, namespace=f'{ns}/{robot}',
            parameter_overrides=params({'bearing_stddev': 0.01,
                                        'publish_landmark_constraints': deprecated})))
        pose_pub = tester.create_publisher(PoseWithCovarianceStamped, f'{ns}/{robot}/pose', 10)
        obs_pub = tester.create_publisher(PointCloud2, f'{ns}/{robot}/observations', 10)
        partial = Collector(tester, PointCloud2, f'{ns}/{robot}/{topic}')
        assert wait_for_match(env, [pose_pub, obs_pub], [partial.subscription], DEADLINE_S)
        rigs.append((observer, pose_pub, obs_pub, partial))
    assert all((o.deprecated_partial_pub is not None) == deprecated for o, _, _, _ in rigs)
    assert env.spin_until(lambda: all(
        (o.deprecated_partial_pub if deprecated else o.partial_pub).get_subscription_count()
        >= 2 for o, _, _, _ in rigs), DEADLINE_S)

    poses = [np.array([0.0, 0.0, 0.3]), np.array([6.0, 0.0, -0.2])]
    for k, ((observer, pose_pub, obs_pub, partial), pose) in enumerate(zip(rigs, poses)):
        bearing = math.atan2(*(LANDMARK - pose[:2])[::-1]) - pose[2]
        count = observer.counters['poses_in']
        pose_pub.publish(pose_message(10.0, pose, P_POSE))
        assert env.spin_until(lambda: observer.counters['poses_in'] > count, DEADLINE_S)
        # Robot 1 sends a bearing-only cloud, robot 2 a range-bearing row with NaN range.
        obs_pub.publish(bearing_only_cloud(10.0, 7, bearing) if k == 0 else
                        observation_message(header(10.0, 'camera'), [7], [[math.nan, bearing]]))
        assert env.spin_until(lambda: partial.messages, DEADLINE_S)
        msg = partial.messages[-1]
        assert [f.name for f in msg.fields] == list(PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS)
        assert not msg.is_bigendian and msg.header.frame_id == 'map'
        rows = read_partial_observations(msg)
        assert rows['id'].tolist() == [7] and rows['kind'].tolist() == [1]
        np.testing.assert_allclose(rows['value'], [bearing], atol=1e-12)
        np.testing.assert_allclose([rows['sensor_x'][0], rows['sensor_y'][0]], pose[:2])
        assert all(np.isfinite(np.asarray(v, dtype=float)).all() for v in rows.values())
        assert observer.counters['partial_rows'] == 1

    def placed():
        return maps.messages and read_landmarks(maps.messages[-1]).ids.tolist() == [7]
    assert env.spin_until(placed, DEADLINE_S), 'the fuser never placed landmark 7'
    rows = read_landmarks(maps.messages[-1])
    np.testing.assert_allclose(rows.m[0], LANDMARK, atol=1e-9)
    assert fuser.fuser.counters['landmarks_initialised'] == 1
    source = fuser.fuser.sources[f'{ns}/robot1/{topic}']
    assert source.counts['partial_fused'] == 1
