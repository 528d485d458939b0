"""The fuser's QoS override parameters, and the permissions of the map file it writes."""

import os
import stat

from landmark_ros.fuser import map_file
from landmark_ros.nodes.fuser import LandmarkFuser
from landmark_ros.ros.schemas import landmark_message
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosutil import header
from sensor_msgs.msg import PointCloud2

DEADLINE_S = 10.0


def fuser(env, **params):
    """Return a fuser node with the parameters ``params`` (QoS overrides included)."""
    params = {'fusion': 'independent', 'min_observations': 1, 'publish_rate_hz': 50.0,
              **params}
    return env.add(LandmarkFuser(context=env.context, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()]))


def test_each_input_subscription_has_qos_override_parameters(env):
    node = fuser(env, input_topics=['/robot1/landmarks', '/robot2/landmarks'])
    for topic in ('/robot1/landmarks', '/robot2/landmarks'):
        for policy in ('reliability', 'history', 'depth'):
            name = f'qos_overrides.{topic}.subscription.{policy}'
            assert node.has_parameter(name), name
            assert node.describe_parameters([name])[0].read_only, name
    assert node.get_parameter('qos_overrides./robot1/landmarks.subscription.reliability'
                              ).value == 'reliable'
    assert node.get_parameter('qos_overrides./robot1/landmarks.subscription.depth'
                              ).value == 100


def test_a_best_effort_override_lets_a_best_effort_publisher_in(env):
    node = fuser(env, **{
        'input_topics': ['/robot1/landmarks', '/robot2/landmarks'],
        'qos_overrides./robot1/landmarks.subscription.reliability': 'best_effort',
        'qos_overrides./robot1/landmarks.subscription.depth': 5})
    profiles = {s.topic_name: s.qos_profile for s in node.subscriptions}
    assert profiles['/robot1/landmarks'].reliability == ReliabilityPolicy.BEST_EFFORT
    assert profiles['/robot1/landmarks'].depth == 5
    assert profiles['/robot2/landmarks'].depth == 100
    info, = node.get_subscriptions_info_by_topic('/robot1/landmarks')
    assert info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    reliable, = node.get_subscriptions_info_by_topic('/robot2/landmarks')
    assert reliable.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    tester = env.node('tester')
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.VOLATILE)
    pub = tester.create_publisher(PointCloud2, '/robot1/landmarks', best_effort)
    assert env.spin_until(lambda: pub.get_subscription_count() == 1, DEADLINE_S)
    C = np.diag([0.01, 0.02])
    source = node.sources['/robot1/landmarks']
    # Best effort: resend until the fuser has the row.
    assert env.spin_until(lambda: pub.publish(landmark_message(
        header(1.0, 'map'), [3], [[1.0, 2.0]], [C])) or source.counts['messages_in'], DEADLINE_S)
    assert env.spin_until(lambda: 3 in node.fuser.map.snapshot()[0].tolist(), DEADLINE_S)


RECORD_MAP = {'world_frame': 'map', 'fusion': 'independent'}


@pytest.mark.parametrize('umask', [0o022, 0o027, 0o002])
def test_a_new_map_file_gets_the_usual_mode(tmp_path, umask):
    path = tmp_path / 'map.json'
    old = os.umask(umask)
    try:
        map_file.save(str(path), [], **RECORD_MAP)
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask
    assert map_file.load(str(path), 'map')['landmarks'] == []


def test_a_saved_map_keeps_the_mode_of_the_file_it_replaces(tmp_path):
    path = tmp_path / 'map.json'
    map_file.save(str(path), [], **RECORD_MAP)
    os.chmod(path, 0o640)
    map_file.save(str(path), [], **RECORD_MAP)
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    assert not [p for p in tmp_path.iterdir() if p.name.endswith('.tmp')]
