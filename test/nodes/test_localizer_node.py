"""
Integration tests of the ``landmark_localizer`` node over real topics (private domain).

The node runs in-process next to a tester node; every case drives it by message stamps
(never wall time): odometry twists, observation clouds, the latched map, initialpose.
"""

import math

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from landmark_ros.core import sensors
from landmark_ros.localizer import motion
from landmark_ros.nodes.localizer import LandmarkLocalizer
from landmark_ros.ros import qos
from landmark_ros.ros.conversions import stamp_ns
from landmark_ros.ros.schemas import landmark_message, observation_message
from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosutil import Collector, header, RosEnv, wait_for_match
from sensor_msgs.msg import PointCloud2

LANDMARKS = np.array([[4.0, 1.0], [-3.0, 5.0], [2.0, -4.0], [6.0, 6.0]])
IDS = np.array([11, 12, 13, 14])
T0 = 1000.0


class Rig:
    """The node, a tester with publishers on its inputs and collectors on its outputs."""

    def __init__(self, **params):
        self.env = RosEnv()
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        self.node = self.env.add(LandmarkLocalizer(context=self.env.context,
                                                   parameter_overrides=overrides))
        t = self.env.node('tester')
        self.odom_pub = t.create_publisher(Odometry, 'odometry', 100)
        self.obs_pub = t.create_publisher(PointCloud2, 'observations', 100)
        self.map_pub = t.create_publisher(PointCloud2, 'fused_landmarks', qos.LATCHED)
        self.init_pub = t.create_publisher(PoseWithCovarianceStamped, 'initialpose', 10)
        self.poses = Collector(t, PoseWithCovarianceStamped, 'pose', 100)
        self.corrections = Collector(t, TransformStamped, 'odom_to_map', 100)
        self.diagnostics = Collector(t, DiagnosticArray, '/diagnostics', 10)
        assert wait_for_match(self.env, [self.odom_pub, self.obs_pub, self.map_pub,
                                         self.init_pub],
                              [self.poses.subscription, self.corrections.subscription])
        self.counters = self.node.localizer.counters

    def close(self):
        self.env.close()

    def publish_map(self, ids=IDS, m=LANDMARKS, stddev=0.01, stamp_s=T0):
        P = np.tile(np.eye(2) * stddev ** 2, (len(ids), 1, 1))
        self.map_pub.publish(landmark_message(header(stamp_s, 'map'), ids, m, P))

    def odometry(self, stamp_s, v=0.0, w=0.0, wait=True):
        """Publish one odometry message; wait until the node has taken it (best effort)."""
        before = self.counters['odometry']
        msg = Odometry()
        msg.header = header(stamp_s, 'odom')
        msg.twist.twist.linear.x, msg.twist.twist.angular.z = v, w
        self.odom_pub.publish(msg)
        if wait:
            self.wait(lambda: self.counters['odometry'] > before)

    def observe(self, stamp_s, pose, ids=IDS, m=LANDMARKS):
        """Publish one observation cloud; wait until the node has taken its rows."""
        seen = self.node.localizer.counters.counts
        before = sum(seen.values())
        z = sensors.observe(np.tile(pose, (len(m), 1)), m)
        self.obs_pub.publish(observation_message(header(stamp_s, 'base_link'), ids, z))
        self.wait(lambda: sum(seen.values()) > before)

    def wait(self, predicate):
        assert self.env.spin_until(predicate, 10.0)


@pytest.fixture
def rig():
    r = Rig(initial_pose=[0.0, 0.0, 0.0], initial_stddev=[0.3, 0.3, 0.1])
    yield r
    r.close()


def test_pose_at_the_odometry_rate_and_late_out_of_order_sightings(rig):
    rig.publish_map()
    rig.wait(lambda: rig.node.localizer.map_size == 4)
    for k in range(20):
        rig.odometry(T0 + 0.1 * k, v=0.5)
    rig.wait(lambda: len(rig.poses.messages) == 20)  # one per odometry message
    # sightings stamped 0.5 s and 0.3 s back, sent newest first
    rig.observe(T0 + 1.6, motion.compose(np.zeros(3), [0.8, 0.0, 0.0]))
    rig.observe(T0 + 1.4, motion.compose(np.zeros(3), [0.7, 0.0, 0.0]))
    rig.wait(lambda: rig.counters['rows_used'] == 8)
    assert rig.counters['refiltered'] >= 2
    rig.odometry(T0 + 2.0, v=0.5)
    rig.wait(lambda: len(rig.poses.messages) == 21 and len(rig.corrections.messages) == 21)
    last = rig.poses.messages[-1]
    assert last.header.frame_id == 'map'
    assert abs(last.pose.pose.position.x - 1.0) < 0.05
    assert last.pose.covariance[0] < 0.3 ** 2
    assert len(rig.corrections.messages) == len(rig.poses.messages)


@pytest.fixture(params=['split_ci', 'consider'])
def map_rig(request):
    r = Rig(initial_pose=[0.0, 0.0, 0.0], initial_stddev=[0.3, 0.3, 0.1],
            correlation=request.param)
    yield r
    r.close()


def test_landmark_missing_from_map_and_a_map_that_changes(map_rig):
    rig = map_rig
    rig.publish_map(IDS[:2], LANDMARKS[:2])
    rig.wait(lambda: rig.node.localizer.map_size == 2)
    rig.odometry(T0)
    rig.odometry(T0 + 0.1)
    rig.observe(T0 + 0.1, np.zeros(3))
    rig.wait(lambda: rig.counters['rows_used'] + rig.counters['landmark_not_in_map'] == 4)
    assert rig.counters['landmark_not_in_map'] == 2
    # the map moves (all landmarks shifted 0.5 m in x): the robot follows it
    rig.publish_map(IDS, LANDMARKS + [0.5, 0.0], stamp_s=T0 + 0.5)
    rig.wait(lambda: rig.counters['maps_received'] == 2)
    assert rig.node.localizer.map_size == 4
    # the diagnostics name the map in use by its header stamp
    rig.diagnostics.messages.clear()
    rig.wait(lambda: len(rig.diagnostics.messages) >= 1)
    values = {kv.key: kv.value for kv in rig.diagnostics.messages[-1].status[0].values}
    assert values['map_stamp_ns'] == str(stamp_ns(header(T0 + 0.5, 'map').stamp))
    for k in range(2, 12):
        rig.odometry(T0 + 0.1 * k)
        rig.observe(T0 + 0.1 * k, np.zeros(3), IDS, LANDMARKS)
    rig.odometry(T0 + 1.3)
    rig.wait(lambda: rig.counters['rows_used'] >= 30)
    rig.wait(lambda: len(rig.poses.messages) == 13)
    assert rig.poses.messages[-1].pose.pose.position.x > 0.3
    if rig.node.localizer.config.correlation == 'consider':  # every landmark's columns
        assert rig.node.localizer.estimate() is not None
        assert rig.node.localizer._steps[-1].C.shape == (3, 8)


def test_odometry_reset_and_a_minute_without_sightings(rig):
    rig.odometry(T0)
    for k in range(1, 601):  # a minute by stamps, no sightings
        rig.odometry(T0 + 0.1 * k, v=0.2)
    rig.wait(lambda: rig.counters['odometry'] == 601)
    status = rig.node.localizer.status()
    assert status.extra['state'] in ('stale', 'lost') and status.level != 'ok'
    assert status.extra['time_since_update_s'] == math.inf
    rig.odometry(T0 + 10.0)  # 50 s back: the odometry restarted
    rig.wait(lambda: rig.counters['odometry_reset'] == 1)
    rig.wait(lambda: len(rig.diagnostics.messages) >= 1)
    values = {kv.key: kv.value for kv in rig.diagnostics.messages[-1].status[0].values}
    assert 'state' in values and 'nis_per_dof' in values


def test_initialpose_restarts_the_filter(rig):
    msg = PoseWithCovarianceStamped()
    msg.header = header(T0, 'map')
    msg.pose.pose.position.x = 3.0
    msg.pose.pose.orientation.w = 1.0
    cov = np.zeros(36)
    cov[0] = cov[7] = 0.04
    cov[35] = 0.01
    msg.pose.covariance = cov.tolist()
    rig.init_pub.publish(msg)
    rig.wait(lambda: rig.counters['initialised'] >= 1 and rig.node.localizer.initialized)
    rig.odometry(T0 + 0.1)
    rig.odometry(T0 + 0.2)
    rig.wait(lambda: len(rig.poses.messages) >= 1)
    assert rig.poses.messages[-1].pose.pose.position.x == pytest.approx(3.0)


def test_cooperative_sighting_over_topics():
    rig = Rig(initial_pose=[0.0, 0.0, 0.0], initial_stddev=[0.5, 0.5, 0.05],
              other_robots=['/robot2'])
    try:
        t = rig.env.nodes[1]
        other_pub = t.create_publisher(PoseWithCovarianceStamped, '/robot2/pose', 10)
        robot_obs_pub = t.create_publisher(PointCloud2, 'robot_observations', 10)
        assert wait_for_match(rig.env, [other_pub, robot_obs_pub])
        rig.odometry(T0)
        rig.odometry(T0 + 0.1)
        other = PoseWithCovarianceStamped()
        other.header = header(T0 + 0.1, 'map')
        other.pose.pose.position.x, other.pose.pose.position.y = 3.0, 1.0
        other.pose.pose.orientation.w = 1.0
        cov = np.zeros(36)
        cov[0] = cov[7] = 1e-4
        cov[35] = 1e-4
        other.pose.covariance = cov.tolist()
        other_pub.publish(other)
        rig.wait(lambda: 0 in rig.node._others)
        z = sensors.observe(np.zeros((1, 3)), np.array([[3.0, 1.0]]))
        robot_obs_pub.publish(observation_message(header(T0 + 0.1, 'base_link'),
                                                  np.array([0]), z))
        rig.wait(lambda: rig.counters['robot_rows_used'] == 1)
        P = rig.node.localizer.estimate().P
        assert P[0, 0] + P[1, 1] < 0.5 * 2 * 0.25
    finally:
        rig.close()
