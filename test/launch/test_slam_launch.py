"""
``ros2 launch landmark_ros team.launch.py sim:=true localize:=true``: the closed-loop team.

The localizers run on the simulated wheel odometry and the fused map, the observers on
the localizers' poses, the fuser on the observers: the team publishes localizer poses
(with a covariance) near the truth and a fused map, and stops on Ctrl-C leaving nothing.
Skipped without ``../shared`` (ros-tools).
"""

import math
import re

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from landmark_ros.ros.qos import LATCHED
from landmark_ros.ros.schemas import read_landmarks
from launch_rig import build_workspace, Launch, require_tools
import numpy as np
import pytest
from rosutil import Collector, next_domain_id, RosEnv
from sensor_msgs.msg import PointCloud2
from test_team_launch import MAP_DEADLINE_S, stop_cleanly
import yaml

pytestmark = pytest.mark.slow


@pytest.fixture(scope='module')
def install(tmp_path_factory):
    """Build a colcon workspace holding the package; return its install directory."""
    require_tools()
    return build_workspace(tmp_path_factory.mktemp('slam_ws'))


def _xy_yaw(pose):
    q = pose.orientation
    return pose.position.x, pose.position.y, 2.0 * math.atan2(q.z, q.w)


def _near(estimates, truths, tolerance_m=1.0):
    """Return whether the newest estimate lies within ``tolerance_m`` of the truth then."""
    if not estimates or not truths:
        return False
    est = estimates[-1]
    stamp = est.header.stamp.sec + 1e-9 * est.header.stamp.nanosec
    true = min(truths, key=lambda m: abs(
        m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec - stamp))
    x, y, _ = _xy_yaw(est.pose.pose)
    tx, ty, _ = _xy_yaw(true.pose)
    return math.hypot(x - tx, y - ty) <= tolerance_m


def _offset(estimates, truths):
    """Return the newest estimate, its true pose then, and their distance (for messages)."""
    est = estimates[-1]
    stamp = est.header.stamp.sec + 1e-9 * est.header.stamp.nanosec
    true = min(truths, key=lambda m: abs(
        m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec - stamp))
    x, y, yaw = _xy_yaw(est.pose.pose)
    tx, ty, tyaw = _xy_yaw(true.pose)
    return f'estimate {(x, y, yaw)}, truth {(tx, ty, tyaw)}, {math.hypot(x - tx, y - ty):.2f} m'


def test_closed_loop_team_localizes_and_fuses_a_map(install, tmp_path):
    # Two precision sources per robot (observer.precision): the launch lists each
    # robot's landmarks/precision_1 among the fuser's inputs.
    observer = yaml.safe_load((install / 'landmark_ros/share/landmark_ros/config/observer.yaml')
                              .read_text())
    section = observer['/**/landmark_observer']['ros__parameters']
    section.update(precision_sources=2, precision_base_m=0.1)
    observer_params = tmp_path / 'observer.yaml'
    observer_params.write_text(yaml.safe_dump(observer))
    with Launch(install, ['sim:=true', 'localize:=true', f'observer_params:={observer_params}'],
                next_domain_id(), tmp_path / 'launch.log') as team:
        env = RosEnv(domain_id=team.domain_id)
        try:
            node = env.node('watcher')
            maps = Collector(node, PointCloud2, '/fused_landmarks', LATCHED)
            poses = [Collector(node, PoseWithCovarianceStamped, f'/robot{i}/pose')
                     for i in (1, 2, 3)]
            truths = [Collector(node, PoseStamped, f'/robot{i}/true_pose') for i in (1, 2, 3)]
            observed = [Collector(node, PointCloud2, f'/robot{i}/landmarks') for i in (1, 2, 3)]
            precise = [Collector(node, PointCloud2, f'/robot{i}/landmarks/precision_1')
                       for i in (1, 2, 3)]

            def ready():
                return (team.popen.poll() is not None or (
                    maps.messages and len(read_landmarks(maps.messages[-1]).ids) >= 5
                    and all(len(p.messages) > 20 for p in poses)
                    and all(o.messages for o in observed)
                    and any(p.messages for p in precise)))

            assert env.spin_until(ready, MAP_DEADLINE_S), team.output()[-3000:]
            assert team.popen.poll() is None, team.output()[-3000:]
            # The localizers' poses carry a covariance and follow the simulated robots
            # (the observers place the sightings with them).
            for estimates, true in zip(poses, truths):
                covariance = np.array(estimates.messages[-1].pose.covariance).reshape(6, 6)
                assert covariance[0, 0] > 0.0 and covariance[1, 1] > 0.0
                assert env.spin_until(lambda: _near(estimates.messages, true.messages), 30.0), (
                    _offset(estimates.messages, true.messages))
            assert len(read_landmarks(maps.messages[-1]).ids) >= 5
            for i in (1, 2, 3):     # the fuser and the watcher on every level's topic
                for topic in (f'/robot{i}/landmarks', f'/robot{i}/landmarks/precision_1'):
                    assert node.count_subscribers(topic) == 2, topic
            # The simulator waits for the localizers' odometry, not for its own pose,
            # which nobody reads here: it starts long before its 60 s limit.
            started = re.search(r'simulation started after ([0-9.]+) s', team.output())
            assert started and float(started.group(1)) < 30.0, team.output()[-3000:]
        finally:
            env.close()
        stop_cleanly(team)
