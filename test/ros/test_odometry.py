"""
The observer with ``pose_type: odometry``: robot_localization-style nav_msgs/Odometry in.

The pose part and its 6x6 covariance are used, the twist ignored; the checks and the
counters are those of the pose path, plus ``pose_wrong_child_frame``.
"""

import math

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.nodes.observer import LandmarkObserver
from landmark_ros.ros.conversions import InputError, pose_from_msg, pose_from_odometry
from landmark_ros.ros.schemas import observation_message, read_landmarks
from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosutil import Collector, header, wait_for_match
from sensor_msgs.msg import PointCloud2

# The textbook case 2 (as in test_observer_node.py): pose, its covariance, observation,
# noise (range_stddev 0.5, bearing_stddev 0.2) and the landmark with its covariance.
POSE = (1.0, 2.0, 0.5)
P_POSE = np.diag([0.08, 0.6, 0.02])
Z = (4.0, 0.7)
M_EXPECTED = np.array([2.44943102, 5.72815634])
P_EXPECTED = np.array([[0.94677477, -0.23978943], [-0.23978943, 0.94322523]])
DEADLINE_S = 10.0


def odometry(stamp_s, frame='odom', child='base_link', pose=POSE, P_pose=P_POSE):
    """Return an Odometry as robot_localization publishes it, with a 3D pose and a twist."""
    msg = Odometry(header=header(stamp_s, frame), child_frame_id=child)
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = pose[0], pose[1], 0.3
    p.orientation.z, p.orientation.w = math.sin(pose[2] / 2), math.cos(pose[2] / 2)
    covariance = np.diag([0.0, 0.0, 1e-3, 1e-4, 1e-4, 0.0])   # z, roll, pitch: ignored
    covariance[np.ix_([0, 1, 5], [0, 1, 5])] = P_pose
    msg.pose.covariance = covariance.ravel().tolist()
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = 0.7, -0.2
    msg.twist.covariance = (np.eye(6) * 0.01).ravel().tolist()
    return msg


class OdometryRig:
    """An observer reading odometry, a publisher of its inputs, a landmark collector."""

    def __init__(self, env, **params):
        params = {'pose_type': 'odometry', 'range_stddev': 0.5, 'bearing_stddev': 0.2,
                  'max_wait_s': 30.0, **params}
        self.env = env
        self.node = env.add(LandmarkObserver(
            context=env.context, namespace='/robot1',
            parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))
        tester = env.node('tester')
        self.odometry_pub = tester.create_publisher(Odometry, '/robot1/odometry', 10)
        self.observation_pub = tester.create_publisher(PointCloud2, '/robot1/observations', 10)
        self.landmarks = Collector(tester, PointCloud2, '/robot1/landmarks')
        self.diagnostics = Collector(tester, DiagnosticArray, '/diagnostics')
        assert wait_for_match(env, [self.odometry_pub, self.observation_pub],
                              [self.landmarks.subscription], DEADLINE_S)

    @property
    def counts(self):
        """Return the observer's counters."""
        return self.node.observer.counters.counts

    def send(self, publisher, msg):
        """Publish and spin until the observer has counted the message."""
        before = sum(self.counts.values())
        publisher.publish(msg)
        assert self.env.spin_until(lambda: sum(self.counts.values()) > before, DEADLINE_S)


@pytest.mark.parametrize('frame', ['odom', 'map'])
def test_odometry_pose_and_covariance_give_the_textbook_landmark(env, frame):
    rig = OdometryRig(env, world_frame=frame, base_frame='base_link')
    names = dict(rig.node.get_subscriber_names_and_types_by_node(
        'landmark_observer', '/robot1'))
    assert names['/robot1/odometry'] == ['nav_msgs/msg/Odometry']
    assert '/robot1/pose' not in names
    rig.send(rig.odometry_pub, odometry(10.0, frame))
    rig.send(rig.observation_pub, observation_message(header(10.0, 'laser'), [7], [Z]))
    assert env.spin_until(lambda: rig.landmarks.messages, DEADLINE_S)
    msg = rig.landmarks.messages[0]
    assert msg.header.frame_id == frame
    ids, m, P = read_landmarks(msg)[:3]
    assert ids.tolist() == [7]
    np.testing.assert_allclose(m[0], M_EXPECTED, rtol=0, atol=1e-8)
    np.testing.assert_allclose(P[0], P_EXPECTED, rtol=0, atol=1e-8)
    assert rig.counts['poses_in'] == 1


def _spoil(**changes):
    def change(msg):
        for path, value in changes.items():
            target = msg
            *parents, leaf = path.split('.')
            for name in parents:
                target = getattr(target, name)
            setattr(target, leaf, value)
    return change


def _covariance(index, value):
    def change(msg):
        msg.pose.covariance[index] = value
    return change


BAD_ODOMETRY = {
    'child_frame': ('pose_wrong_child_frame', _spoil(child_frame_id='base_footprint')),
    'frame': ('pose_wrong_frame', _spoil(**{'header.frame_id': 'map'})),
    'position': ('pose_nonfinite', _spoil(**{'pose.pose.position.x': math.nan})),
    'quaternion': ('pose_bad_quaternion', _spoil(**{'pose.pose.orientation.z': 0.0,
                                                    'pose.pose.orientation.w': 0.0})),
    'covariance': ('pose_covariance_not_psd', _covariance(35, -0.01)),
    'asymmetric': ('pose_covariance_asymmetric', _covariance(1, 0.05)),
}


@pytest.mark.parametrize('case', list(BAD_ODOMETRY))
def test_bad_odometry_is_dropped_with_its_reason(env, case):
    reason, change = BAD_ODOMETRY[case]
    rig = OdometryRig(env, world_frame='odom', base_frame='base_link')
    bad = odometry(10.0)
    change(bad)
    rig.send(rig.odometry_pub, bad)
    problems = {k: v for k, v in rig.counts.items() if v and k != 'observation_messages_in'}
    assert problems == {reason: 1}
    assert rig.counts['poses_in'] == 0
    # The diagnostics report it as the pose path's reasons are reported.
    assert env.spin_until(lambda: any(
        s.name == '/robot1/landmark_observer' and reason in s.message
        for a in rig.diagnostics.messages for s in a.status), DEADLINE_S)
    rig.send(rig.odometry_pub, odometry(10.0))
    assert rig.counts['poses_in'] == 1


def test_any_child_frame_without_base_frame(env):
    rig = OdometryRig(env, world_frame='odom')
    rig.send(rig.odometry_pub, odometry(10.0, child='whatever'))
    assert rig.counts['poses_in'] == 1


def test_default_pose_type_does_not_subscribe_odometry(env):
    node = env.add(LandmarkObserver(context=env.context, namespace='/robot2'))
    names = dict(node.get_subscriber_names_and_types_by_node('landmark_observer', '/robot2'))
    assert names['/robot2/pose'] == ['geometry_msgs/msg/PoseWithCovarianceStamped']
    assert '/robot2/odometry' not in names


def test_an_unknown_pose_type_is_refused(env):
    with pytest.raises(ValueError, match='pose_type must be one of'):
        LandmarkObserver(context=env.context,
                         parameter_overrides=[Parameter('pose_type', value='twist')])


def test_pose_from_odometry_checks_the_child_frame_after_the_pose_checks():
    pose, P_pose = pose_from_odometry(odometry(1.0), 'odom', 'base_link')
    np.testing.assert_allclose(pose, POSE, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(P_pose, P_POSE)
    with pytest.raises(InputError) as error:
        pose_from_odometry(odometry(1.0, child='base_footprint'), 'odom', 'base_link')
    assert error.value.reason == 'pose_wrong_child_frame'
    with pytest.raises(InputError) as error:
        pose_from_odometry(odometry(1.0, frame='map', child='x'), 'odom', 'base_link')
    assert error.value.reason == 'pose_wrong_frame'
    # The pose path and the odometry path read the same pose.
    same = PoseWithCovarianceStamped(header=odometry(1.0).header, pose=odometry(1.0).pose)
    np.testing.assert_array_equal(pose_from_msg(same, 'odom')[1], P_pose)


def test_twist_only_odometry_is_refused_as_a_missing_pose():
    msg = Odometry(header=header(1.0, 'odom'), child_frame_id='base_link')
    msg.pose.pose.orientation.w = 1.0          # an identity pose, zero covariance
    msg.twist.twist.linear.x = 0.5
    with pytest.raises(InputError) as error:
        pose_from_odometry(msg, 'odom', 'base_link')
    assert error.value.reason == 'odometry_pose_missing'
    # An exact pose elsewhere, or the origin with a covariance, is still a pose.
    msg.pose.covariance = np.eye(6).ravel().tolist()
    np.testing.assert_array_equal(pose_from_odometry(msg, 'odom', 'base_link')[0], 0.0)
    pose_from_odometry(odometry(1.0, P_pose=np.zeros((3, 3))), 'odom', 'base_link')
