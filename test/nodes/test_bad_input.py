"""
Input that once crashed or poisoned a node, and stops under load, through real nodes.

Each case asserts the named counter, a node that is still alive (it handles the next
good message), a map that is unchanged and finite, and for stops an exit code 0
without a traceback.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.ros.schemas import landmark_message, observation_message
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rigs import DEADLINE_S, FuserRig, ObserverRig, unique_namespace
from rosutil import header, pose_message, wait_for_match
from sensor_msgs.msg import PointCloud2
from test_fuser_node import assert_rows, C
from visualization_msgs.msg import MarkerArray

I2 = np.eye(2)


def good_map(rig):
    """Fuse two observations of landmark 1 and return the published map rows."""
    rig.send('a/landmarks', [1, 1], [[1.0, 2.0], [1.0, 2.0]], [C, C])
    return rig.wait_map(lambda rows: rows.ids.tolist() == [1])


def assert_alive_and_unchanged(rig, before):
    """Assert the map is still ``before`` (finite) and a good message is still fused."""
    rows = rig.wait_map()
    assert np.all(np.isfinite(rows.m)) and np.all(np.isfinite(rows.P))
    assert_rows(rows, [(1, before.m[0], before.P[0], before.P_dep[0], before.observations[0])])
    rig.send('a/landmarks', [1], [[1.0, 2.0]], [C])
    rig.wait_map(lambda rows: rows.observations.tolist() == [3])


@pytest.mark.parametrize('P, count, reason', [
    (1e-200 * I2, 1, 'covariance_too_small'),
    (np.array([[1e200, 1e199], [1e199, 1e200]]), 1, 'covariance_too_large'),
    (1e300 * I2, 3, 'covariance_too_large'),
    (np.array([[1.0, 1.0 - 1e-12], [1.0 - 1e-12, 1.0]]), 1, 'covariance_ill_conditioned'),
])
def test_degenerate_covariances_are_rejected_by_the_fuser(env, P, count, reason):
    rig = FuserRig(env, fusion='split_covariance_intersection')
    before = good_map(rig)
    rig.send('a/landmarks', [1] * count + [2] * count, [[1.0, 2.0]] * 2 * count,
             [P] * 2 * count)
    assert rig.counts('a/landmarks')[reason] == 2 * count
    assert_alive_and_unchanged(rig, before)


def test_partial_dependent_field_group_is_a_named_rejection(env):
    rig = FuserRig(env)
    before = good_map(rig)
    msg = landmark_message(header(1.0, 'map'), [1], [[1.0, 2.0]], [C], [0.5 * C])
    msg.fields = [f for f in msg.fields if f.name not in ('cov_dep_xy', 'cov_dep_yy')]
    rig.send_msg('a/landmarks', msg)
    assert rig.counts('a/landmarks')['partial_field_group'] == 1
    assert_alive_and_unchanged(rig, before)


def test_bytes_that_are_no_cloud_are_a_named_rejection(env):
    # The fuser takes its landmark topics raw: cut or random bytes on the wire are
    # counted as malformed_message, and the next good cloud is fused.
    rig = FuserRig(env)
    before = good_map(rig)
    good = serialize_message(landmark_message(header(1.0, 'map'), [1], [[1.0, 2.0]], [C]))
    rng = np.random.default_rng(3)
    bad = [good[:len(good) // 2], b'\x00\x01' + rng.integers(0, 256, 64, np.uint8).tobytes()]
    for payload in bad:
        rig.send_msg('a/landmarks', payload)
    assert rig.counts('a/landmarks')['malformed_message'] == len(bad)
    assert_alive_and_unchanged(rig, before)


def test_an_exception_in_the_fusion_timer_is_counted_and_the_node_goes_on(env):
    rig = FuserRig(env)
    before = good_map(rig)
    update = rig.node.fuser.map.update
    calls = []

    def broken(*args, **kwargs):
        calls.append(1)
        raise RuntimeError('injected fault')
    rig.node.fuser.map.update = broken
    rig.pubs['a/landmarks'].publish(landmark_message(header(1.0, 'map'), [1], [[9.0, 9.0]],
                                                     [C]))
    assert env.spin_until(lambda: rig.node.fuser.counters['internal_error'] == 1, DEADLINE_S)
    rig.node.fuser.map.update = update
    assert calls == [1]
    assert_alive_and_unchanged(rig, before)


def test_tiny_noise_with_an_exact_pose_never_leaves_the_observer(env):
    tester = env.node('observer_tester')
    observer = ObserverRig(env, unique_namespace(env) + '/robot1', tester=tester,
                           range_stddev=0.5, bearing_stddev=0.2)
    observer.pose_pub.publish(pose_message(10.0, [1.0, 2.0, 0.5], np.zeros((3, 3))))
    assert env.spin_until(lambda: observer.node.counters['poses_in'] == 1, DEADLINE_S)
    R = np.array([np.diag([1e-200, 1e-200]), np.diag([0.01, 0.001])])
    msg = observation_message(header(10.0, 'camera'), [7, 8], [[4.0, 0.7], [3.0, 0.2]], R)
    observer.obs_pub.publish(msg)
    assert env.spin_until(lambda: observer.landmarks.messages, DEADLINE_S)
    assert observer.landmarks.messages[0].width == 1                # landmark 8 only
    # 1e-200 is outside the plausible variances (pipeline.limits): refused as input.
    assert observer.node.counters['noise_variance_out_of_range'] == 1


def test_malformed_clouds_are_named_reasons_never_internal_error(env):
    observer = ObserverRig(env, unique_namespace(env) + '/robot1')
    observer.pose_pub.publish(pose_message(10.0, [1.0, 2.0, 0.5], np.eye(3) * 1e-3))
    assert env.spin_until(lambda: observer.node.counters['poses_in'] == 1, DEADLINE_S)
    zero_step = PointCloud2(width=3, height=1, point_step=0, row_step=0)
    for msg in (PointCloud2(), zero_step):
        msg.header = header(10.0, 'camera')
        observer.obs_pub.publish(msg)
    assert env.spin_until(lambda: observer.node.counters['point_step_invalid'] == 1
                          and observer.node.counters['missing_field'] == 1, DEADLINE_S)
    observer.obs_pub.publish(observation_message(header(10.0, 'camera'), [7], [[4.0, 0.7]]))
    assert env.spin_until(lambda: observer.landmarks.messages, DEADLINE_S)
    assert observer.node.counters['internal_error'] == 0


# Stops under load ------------------------------------------------------------------------

ROUNDS = int(os.environ.get('LANDMARK_STOP_ROUNDS', '6'))
"""Stops per node; raise it to hunt rare races (LANDMARK_STOP_ROUNDS=100)."""


def node_command(executable, namespace, *params):
    """Return the command of a console script with SIGINT at its default disposition."""
    path = Path(sys.executable).parent / executable
    command = [sys.executable, '-c', 'import os, signal, sys; '
               'signal.signal(signal.SIGINT, signal.SIG_DFL); '
               'os.execv(sys.argv[1], sys.argv[1:])', str(path),
               '--ros-args', '-r', f'__ns:={namespace}']
    for param in params:
        command += ['-p', param]
    return command


class Flood:
    """Publish poses and observation clouds (or landmark clouds) from a thread."""

    def __init__(self, publishers, make):
        self.publishers, self.make = publishers, make
        self.stop = threading.Event()
        self.sent = 0
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self):
        while not self.stop.is_set():
            for publisher, msg in zip(self.publishers, self.make(self.sent)):
                publisher.publish(msg)
            self.sent += 1
            self.stop.wait(0.0005)   # pacing; returns at once when stopped

    def close(self):
        self.stop.set()
        self.thread.join(timeout=10.0)


@pytest.mark.slow
@pytest.mark.parametrize('kind', ['observer', 'fuser', 'sim'])
def test_stops_under_load_exit_0_without_a_traceback(env, tmp_path, kind):
    namespace = unique_namespace(env)
    tester = env.node('stop_tester')
    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    rows = 100
    ids = np.arange(rows)
    z = np.column_stack([np.linspace(1.0, 9.0, rows), np.linspace(-1.0, 1.0, rows)])
    if kind == 'observer':
        executable, params = 'landmark_observer', ('marker_rate_hz:=50.0',
                                                   'diagnostics_period_s:=0.05')
        publishers = [
            tester.create_publisher(PoseWithCovarianceStamped, f'{namespace}/pose', reliable),
            tester.create_publisher(PointCloud2, f'{namespace}/observations', reliable)]
        listen = f'{namespace}/landmark_markers'

        def make(k):
            stamp = 1.0 + 0.001 * k
            return [pose_message(stamp, [0.01 * k, 0.0, 0.0], np.eye(3) * 1e-4),
                    observation_message(header(stamp, 'camera'), ids, z)]
    elif kind == 'fuser':
        executable, params = 'landmark_fuser', ('input_topics:=[landmarks]',
                                                'diagnostics_period_s:=0.05',
                                                'publish_rate_hz:=100.0')
        publishers = [tester.create_publisher(PointCloud2, f'{namespace}/landmarks', reliable)]
        listen = f'{namespace}/fused_markers'
        m = z.copy()
        P = np.broadcast_to(C, (rows, 2, 2))

        def make(k):
            return [landmark_message(header(1.0 + 0.001 * k, 'map'), ids, m, P)]
    else:
        executable, params = 'landmark_sim', ('time_scale:=20.0', 'robots:=3',
                                              'wait_for_subscribers_s:=0.0')
        publishers = []
        listen = f'{namespace}/robot1/observations'

        def make(k):
            return []
    listener = tester.create_subscription(
        MarkerArray if kind != 'sim' else PointCloud2, listen, lambda msg: None, reliable)
    process_env = dict(os.environ, ROS_DOMAIN_ID=str(env.domain_id), PYTHONUNBUFFERED='1',
                       ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                       ROS_LOG_DIR=str(tmp_path / 'ros_log'))
    for round_ in range(ROUNDS):
        stem = tmp_path / f'{kind}{round_}'
        with open(f'{stem}.out', 'w') as out, open(f'{stem}.err', 'w') as err:
            process = subprocess.Popen(node_command(executable, namespace, *params),
                                       env=process_env, stdout=out, stderr=err)
        flood = None
        try:
            assert wait_for_match(env, publishers, [listener], DEADLINE_S), \
                Path(f'{stem}.err').read_text()
            flood = Flood(publishers, make)
            deadline = time.monotonic() + 0.2 + 0.1 * round_
            env.spin_until(lambda: time.monotonic() > deadline, 5.0)
            process.send_signal(signal.SIGINT if round_ % 2 else signal.SIGTERM)
            code = process.wait(timeout=20.0)
        finally:
            if flood is not None:
                flood.close()
            if process.poll() is None:
                process.kill()
                process.wait(timeout=10.0)
        errors = Path(f'{stem}.err').read_text()
        assert code == 0 and 'Traceback' not in errors, f'round {round_}: {code}\n{errors}'
