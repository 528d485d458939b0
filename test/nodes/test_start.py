"""
The console scripts start like ROS nodes: endpoints early, a clean Ctrl-C at any moment.

Each test starts a node's console script as its own process in a domain of its
own and watches it from a private context (``startup.Watcher``): by condition and
deadline, never by a fixed sleep.
"""

import importlib.util
import os
import signal
import time

from diagnostic_msgs.msg import DiagnosticArray
from landmark_ros.ros import qos
from landmark_ros.ros.schemas import landmark_message
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosutil import header, next_domain_id
from sensor_msgs.msg import PointCloud2
import startup

NODES = list(startup.ENDPOINTS)

START_DEADLINE_S = float(os.environ.get('LANDMARK_START_DEADLINE_S', '3.0'))
"""Longest time from spawn until every endpoint of a node is in the graph, on a machine
whose run queue is at most one process per core; scaled by the load when it is longer."""


def _load_factor():
    return max(1.0, os.getloadavg()[0] / (os.cpu_count() or 1))


@pytest.fixture
def watcher():
    """Watch the graph of a domain of its own from a private context."""
    watcher = startup.Watcher(next_domain_id())
    watcher.domain_id = watcher.context.get_domain_id()
    yield watcher
    watcher.close()


@pytest.fixture
def start(watcher, tmp_path):
    """Return a function that starts a node's process (killed in teardown if alive)."""
    processes = []
    if startup.script('landmark_fuser') is None:
        pytest.skip('the console scripts are not installed (pip install -e .)')

    def start(name, *args, cache=None):
        namespace = f'/start_{os.getpid()}_{watcher.domain_id}_{len(processes)}'
        extra = {} if cache is None else {'NUMBA_CACHE_DIR': str(cache)}
        process = startup.spawn(name, watcher.domain_id, namespace, tmp_path / 'log',
                                extra, args)
        process.namespace = namespace
        processes.append(process)
        return process
    yield start
    for process in processes:
        if process.poll() is None:
            process.kill()
            process.communicate()


def _mapped(process, library):
    """Return whether ``process`` has a shared object whose path has ``library`` mapped."""
    try:
        with open(f'/proc/{process.pid}/maps') as maps:
            return library in maps.read()
    except OSError:
        return False


def _until(watcher, predicate, deadline_s):
    """Wait on the watcher's executor (5 ms at a time) until ``predicate()`` or the deadline."""
    deadline = time.monotonic() + deadline_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        watcher.executor.spin_once(timeout_sec=0.005)
    return True


START_TRIES = 3
"""Starts a node gets to show its endpoints within the deadline. Fast DDS adds 0 to about
3 s of discovery (its participant announcement period) to any new node at random, a
plain rclpy node included (``startup.py`` prints that reference): the node's own start
is the fastest of a few."""


@pytest.mark.parametrize('name', NODES)
def test_every_endpoint_exists_within_the_deadline(start, watcher, name):
    deadline_s = START_DEADLINE_S * _load_factor()
    missed = []
    for _ in range(START_TRIES):
        process = start(name)
        seconds = watcher.wait_endpoints(name, process.namespace, process, deadline_s)
        if seconds is None:
            missed.append(f'{watcher.missing(name, process.namespace)}, exit {process.poll()}')
        code, _, err = startup.stop(process)
        assert code == 0 and 'Traceback' not in err, err
        if seconds is not None:
            return
    pytest.fail(f'{name}: still missing after {deadline_s:.1f} s in {START_TRIES} starts: '
                + '; '.join(missed))


# Moments of a start, each found by a condition: a library the process has mapped
# (numpy and rclpy while the node module imports; scipy while the node is built:
# before the observer's and fuser's endpoints, after the simulator's), its endpoints
# in the graph, its first diagnostics.
MOMENTS = {
    'importing numpy': lambda w, p, name: _until(
        w, lambda: _mapped(p, '_multiarray_umath'), 30.0),
    'importing rclpy': lambda w, p, name: _until(
        w, lambda: _mapped(p, '_rclpy_pybind11'), 30.0),
    'endpoints there': lambda w, p, name: w.wait_endpoints(
        name, p.namespace, p, 30.0) is not None,
    'importing scipy': lambda w, p, name: _until(w, lambda: _mapped(p, '/scipy/'), 30.0),
    'running': lambda w, p, name: _first_diagnostics(w),
}


def _first_diagnostics(watcher):
    received = []
    subscription = watcher.node.create_subscription(
        DiagnosticArray, '/diagnostics', received.append, qos.DIAGNOSTICS)
    try:
        return _until(watcher, lambda: received, 60.0)
    finally:
        watcher.node.destroy_subscription(subscription)


@pytest.mark.parametrize('moment', list(MOMENTS))
@pytest.mark.parametrize('name', NODES)
def test_sigint_at_any_moment_exits_0_without_a_traceback(start, watcher, name, moment):
    process = start(name)
    reached = MOMENTS[moment](watcher, process, name)
    assert reached or process.poll() is None, f'{name} ended before {moment}'
    code, out, err = startup.stop(process, timeout=30.0)
    assert code == 0, f'{name} stopped while {moment}: exit {code}\n{err}'
    assert 'Traceback' not in err and 'Traceback' not in out, err


@pytest.mark.parametrize('name', NODES)
def test_repeated_sigint_while_stopping_still_exits_0(start, watcher, name):
    # Ctrl-C in a terminal signals the whole process group and ros2 launch forwards
    # its own SIGINT: a node gets two, the second while it shuts down or while Python
    # finalises (which restores the default handler of a signal it handles). Keep
    # signalling until the process has gone, so one lands in every phase of the stop.
    process = start(name)
    assert watcher.wait_endpoints(name, process.namespace, process, 30.0) is not None
    deadline = time.monotonic() + 30.0
    while process.poll() is None and time.monotonic() < deadline:
        process.send_signal(signal.SIGINT)
        _until(watcher, lambda: process.poll() is not None, 0.02)
    code, out, err = startup.stop(process, timeout=5.0)
    assert code == 0, f'{name}: exit {code} under repeated SIGINT\n{err}'
    assert 'Traceback' not in err and 'Traceback' not in out, err


STOP_DEADLINE_S = 5.0
"""ros2 launch sends SIGTERM 5 s after SIGINT (sigterm_timeout), then SIGKILL."""


@pytest.mark.skipif(
    importlib.util.find_spec('landmark_ros.fusion') is None,
    reason="the map's numba compile blocks the fuser's build here (no background compile)")
@pytest.mark.parametrize('moment', ['endpoints there', 'running'])
def test_sigint_ends_the_fuser_at_once_with_numbas_cache_cold(start, watcher, tmp_path,
                                                              moment):
    process = start('landmark_fuser', cache=tmp_path / 'numba_cache')
    assert MOMENTS[moment](watcher, process, 'landmark_fuser'), process.poll()
    code, _, err = startup.stop(process, timeout=60.0)
    assert code == 0 and 'Traceback' not in err, err
    assert process.stop_s < STOP_DEADLINE_S, process.stop_s


RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def test_clouds_sent_as_soon_as_the_fuser_subscribes_are_all_fused(start, watcher):
    # Numba's cache is the shared one (warm after the first start): the cold compile
    # is measured apart (startup.py).
    process = start('landmark_fuser', '-p', 'min_observations:=1', '-p',
                    'fusion:=independent')
    ns = process.namespace
    pub = watcher.node.create_publisher(PointCloud2, f'{ns}/landmarks', RELIABLE)
    maps = []
    watcher.node.create_subscription(PointCloud2, f'{ns}/fused_landmarks', maps.append,
                                     qos.LATCHED)
    assert _until(watcher, lambda: pub.get_subscription_count() > 0, 60.0), \
        process.poll()
    count = 60      # 3 s at 20 Hz, from the moment the subscription matched
    sent_at = time.monotonic()
    for k in range(count):
        assert _until(watcher, lambda: time.monotonic() >= sent_at + 0.05 * k, 5.0)
        pub.publish(landmark_message(header(1.0 + 0.05 * k, 'map'), [k + 1],
                                     [[float(k), 0.0]], [0.01 * np.eye(2)]))

    def fused():
        return maps and len(landmark_ids(maps[-1])) == count
    assert _until(watcher, fused, 60.0), (
        f'{len(landmark_ids(maps[-1])) if maps else 0} of {count} landmarks fused')
    code, _, err = startup.stop(process)
    assert code == 0 and 'queue_overflow' not in err, err


def landmark_ids(msg):
    """Return the IDs of a landmark cloud."""
    from landmark_ros.ros.schemas import read_landmarks
    return read_landmarks(msg)[0].tolist()


def test_the_watcher_sees_a_missing_endpoint(watcher):
    # The condition the start test waits on can fail: no node, every endpoint missing.
    missing = watcher.missing('landmark_fuser', '/nowhere')
    assert missing == ['node /nowhere/landmark_fuser']
