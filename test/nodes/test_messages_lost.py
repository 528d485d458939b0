"""
Messages the middleware loses on the way to the fuser are counted, not lost silently.

A reliable publisher keeps only its last ``depth`` messages: when the fuser does not
acknowledge them in time (here: its process stopped with SIGSTOP, as a starved machine
would), the oldest are overwritten. The fuser counts the gap as ``messages_lost`` against
the source, logs it and fuses what did arrive.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.nodes.localizer import LandmarkLocalizer
from landmark_ros.ros.qos import DIAGNOSTICS
from landmark_ros.ros.schemas import landmark_message
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rigs import DEADLINE_S, ObserverRig, unique_namespace, values_of
from rosutil import Collector, header
from sensor_msgs.msg import PointCloud2

MESSAGES = 1000
DEPTH = 2
C = 0.01 * np.eye(2)


def start_fuser(env, namespace, tmp_path):
    """Start a fuser process in ``namespace``; return it (stderr in ``fuser.err``)."""
    command = [sys.executable, '-m', 'landmark_ros.nodes.fuser', '--ros-args',
               '-r', f'__ns:={namespace}', '-p', 'min_observations:=1',
               '-p', 'diagnostics_period_s:=0.1']
    process_env = dict(os.environ, ROS_DOMAIN_ID=str(env.domain_id),
                       ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
                       ROS_LOG_DIR=str(tmp_path / 'ros_log'))
    with open(tmp_path / 'fuser.err', 'w') as err:
        return subprocess.Popen(command, env=process_env, stdout=subprocess.DEVNULL,
                                stderr=err, cwd=tmp_path)


def send(pub, i):
    """Publish landmark ``i`` alone at x = ``i``."""
    pub.publish(landmark_message(header(1.0 + 0.01 * i, 'map'), [i], [[float(i), 0.0]], [C]))


def source_values(collector, topic):
    """Return the values of the newest diagnostics status of the fuser's source ``topic``."""
    for array in reversed(collector.messages):
        for status in array.status:
            if status.name.endswith(f': {topic}'):
                return values_of(status)
    return {}


def test_messages_a_stopped_fuser_never_acknowledged_are_counted_lost(env, tmp_path):
    namespace = unique_namespace(env)
    topic = f'{namespace}/landmarks'
    tester = env.node('lossy_publisher')
    pub = tester.create_publisher(
        PointCloud2, topic, QoSProfile(depth=DEPTH, reliability=ReliabilityPolicy.RELIABLE))
    diagnostics = Collector(tester, DiagnosticArray, '/diagnostics', DIAGNOSTICS)
    process = start_fuser(env, namespace, tmp_path)
    stderr = Path(tmp_path / 'fuser.err')
    try:
        # Subscribed and fusing: its first diagnostics with this source came.
        assert env.spin_until(lambda: pub.get_subscription_count() >= 1
                              and source_values(diagnostics, topic), 3 * DEADLINE_S), \
            stderr.read_text()[-3000:]
        send(pub, 0)
        assert env.spin_until(lambda: source_values(diagnostics, topic).get('messages_in')
                              == '1', DEADLINE_S), stderr.read_text()[-3000:]
        process.send_signal(signal.SIGSTOP)
        for i in range(1, MESSAGES + 1):
            send(pub, i)
            env.executor.spin_once(timeout_sec=0.001)
        process.send_signal(signal.SIGCONT)

        def settled():
            values = source_values(diagnostics, topic)
            return (int(values.get('messages_in', 0)) + int(values.get('messages_lost', 0))
                    == MESSAGES + 1)
        assert env.spin_until(settled, 3 * DEADLINE_S), \
            str(source_values(diagnostics, topic)) + stderr.read_text()[-3000:]
        values = source_values(diagnostics, topic)
        # At most DEPTH were kept for the stopped reader, plus what it took before
        # the stop reached its receive thread.
        assert int(values['messages_lost']) >= MESSAGES // 2, values
        assert int(values['messages_in']) >= DEPTH, values
        assert env.spin_until(lambda: 'messages_lost' in stderr.read_text(), DEADLINE_S)
    finally:
        process.send_signal(signal.SIGCONT)
        process.kill()
        process.wait(timeout=10.0)


def test_the_observer_counts_the_gaps_of_its_pose_and_observation_inputs(env):
    rig = ObserverRig(env)
    on_pose = rig.node.pose_subscription.callback
    on_pose(PoseWithCovarianceStamped(), {'publication_sequence_number': 1})
    on_pose(PoseWithCovarianceStamped(), {'publication_sequence_number': 5})
    assert rig.counts['messages_lost'] == 3
    inputs = rig.node.observation_inputs
    inputs.receive(PointCloud2(), 'observations', {'publication_sequence_number': 10})
    inputs.receive(PointCloud2(), 'observations', {'publication_sequence_number': 12})
    assert rig.counts['messages_lost'] == 3 + 1


def test_the_localizer_counts_the_gaps_of_its_odometry(env):
    node = env.add(LandmarkLocalizer(context=env.context))
    env.node('wheels').create_publisher(Odometry, '/odometry', 10)
    assert env.spin_until(lambda: node.count_publishers('odometry') == 1, DEADLINE_S)
    on_odometry = next(s for s in node.subscriptions if s.topic_name == '/odometry')
    for number in (3, 4, 9):
        on_odometry.callback(Odometry(), {'publication_sequence_number': number})
    assert node.localizer.counters['messages_lost'] == 4
