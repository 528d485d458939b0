"""
Start a node's console script as a process and watch it from a private context.

``Watcher`` polls the ROS graph (its own context and domain) until the node's
subscriptions, publishers and services are there, by condition and deadline.
Run as a script it prints the start times of every node (numba's cache cold: an
empty ``NUMBA_CACHE_DIR``; then warm: the same directory again)::

    .venv/bin/python test/nodes/startup.py [--runs 3]
"""

import argparse
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

BIN = Path(sys.executable).parent

ENDPOINTS = {
    'landmark_fuser': {
        'subscriptions': ['landmarks', 'partial_observations'],
        'publishers': ['fused_landmarks', 'fused_landmark_updates', 'fused_markers',
                       '/diagnostics'],
        'services': ['landmark_fuser/reset', 'landmark_fuser/save'],
    },
    'landmark_localizer': {
        'subscriptions': ['odometry', 'observations', 'fused_landmarks', 'initialpose'],
        'publishers': ['pose', 'odom_to_map', '/diagnostics'],
        'services': [],
    },
    'landmark_observer': {
        'subscriptions': ['pose', 'observations'],
        'publishers': ['landmarks', 'partial_observations', 'landmark_markers',
                       '/diagnostics'],
        'services': [],
    },
    'landmark_sim': {
        'subscriptions': [],
        'publishers': [f'robot{i}/{topic}' for i in (1, 2, 3)
                       for topic in ('pose', 'true_pose', 'observations')]
        + ['ground_truth_landmarks', '/diagnostics'],
        'services': [],
    },
}
"""Per console script, the endpoints of its node with the default parameters (names
relative to the node's namespace, or absolute)."""

REFERENCE = 'rclpy_reference'
"""A plain rclpy node with the observer's endpoints (``reference_node.py``): the time
DDS start and discovery alone take. Discovery here adds 0 to about 3 s (Fast DDS's
participant announcement period) to any new node, at random; the reference shows it."""

ENDPOINTS_OF = dict(ENDPOINTS, **{REFERENCE: ENDPOINTS['landmark_observer']})


def script(name):
    """Return the path of the console script ``name`` (None when not installed)."""
    path = BIN / name
    return path if path.is_file() and os.access(path, os.X_OK) else None


MODULES = os.environ.get('START_AS_MODULES') == '1'
"""Start ``python -m landmark_ros.nodes.NAME`` instead of the console scripts."""

PREFIX = os.environ.get('START_PREFIX', '').split()
"""A command to start ``NAME`` (``observer``, ...) with instead (e.g. another tree's)."""


def spawn(name, domain_id, namespace, log_dir, extra_env=None, args=()):
    """
    Start console script ``name`` in ``namespace``; return the Popen (stderr piped).

    SIGINT goes back to its default first (pytest started in the background of a
    script hands its children an ignored SIGINT).
    """
    short = name.split('_')[1]
    if name == REFERENCE:
        command = [sys.executable, str(Path(__file__).with_name('reference_node.py'))]
    elif PREFIX:
        command = PREFIX + [short]
    elif MODULES:
        command = [sys.executable, '-m', 'landmark_ros.nodes.' + short]
    else:
        command = [str(script(name))]
    command += ['--ros-args', '-r', f'__ns:={namespace}', *args]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1',
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_LOG_DIR=str(log_dir),
               **(extra_env or {}))
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_default_sigint)


def _default_sigint():
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def stop(process, timeout=20.0):
    """
    Send SIGINT; return ``(returncode, stdout, stderr)`` (killed after ``timeout``).

    ``process.stop_s``: seconds from the signal to the end of the process.
    """
    sent = time.monotonic()
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        return None, out, err
    finally:
        process.stop_s = time.monotonic() - sent
    return process.returncode, out, err


class Watcher:
    """A private context and node in ``domain_id`` that watches the ROS graph."""

    def __init__(self, domain_id):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('start_watcher', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def missing(self, name, namespace):
        """Return the endpoints of node ``name`` not (yet) in the graph, as text."""
        expected = ENDPOINTS_OF[name]
        node_name = name
        absolute = [] if namespace == '/' else [namespace]

        def full(topic):
            return topic if topic.startswith('/') else '/'.join(absolute + [topic])
        try:
            found = {
                'subscriptions': self.node.get_subscriber_names_and_types_by_node(
                    node_name, namespace),
                'publishers': self.node.get_publisher_names_and_types_by_node(
                    node_name, namespace),
                'services': self.node.get_service_names_and_types_by_node(
                    node_name, namespace),
            }
        except Exception:  # noqa: B902 - rclpy's NodeNameNonExistentError: not there yet
            return [f'node {namespace}/{node_name}']
        out = []
        for kind, topics in expected.items():
            names = {topic for topic, _ in found[kind]}
            out += [f'{kind[:-1]} {full(t)}' for t in topics if full(t) not in names]
        return out

    def wait_endpoints(self, name, namespace, process, deadline_s):
        """
        Return seconds until every endpoint of the node appeared, or None at the deadline.

        Waits on the executor (10 ms at a time), not by sleeping; stops early when
        the process ends.
        """
        start = time.monotonic()
        while time.monotonic() - start < deadline_s:
            if not self.missing(name, namespace):
                return time.monotonic() - start
            if process is not None and process.poll() is not None:
                return None
            self.executor.spin_once(timeout_sec=0.01)
        return None

    def close(self):
        """Shut the executor, node and context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def measure(name, domain_id, cache_dir, log_dir, settle_s=0.0):
    """
    Return seconds from spawn until the node's endpoints exist (None: not in 60 s).

    ``settle_s``: seconds the watcher runs before the spawn. Fast DDS announces a new
    participant five times in its first 0.5 s, then every 3 s; a node that joins
    after that burst learns of the watcher from its reply, and when the reply is
    missed, from the next periodic announcement (a plain rclpy node alike).
    """
    watcher = Watcher(domain_id)
    try:
        settled = time.monotonic() + settle_s
        while time.monotonic() < settled:
            watcher.executor.spin_once(timeout_sec=0.01)
        namespace = f'/start_{os.getpid()}'
        started = time.monotonic()
        process = spawn(name, domain_id, namespace, log_dir,
                        {'NUMBA_CACHE_DIR': str(cache_dir)})
        seconds = watcher.wait_endpoints(name, namespace, process, 60.0)
        if seconds is not None:
            seconds = time.monotonic() - started
        code, _, err = stop(process)
        if code != 0 or 'Traceback' in err:
            print(f'{name}: exit {code}\n{err}', file=sys.stderr)
        return seconds
    finally:
        watcher.close()


def main():
    """Print the start time of each node, numba's cache cold then warm."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--domain', type=int, default=150 + os.getpid() % 50)
    parser.add_argument('--settle', type=float, default=0.0,
                        help='seconds the watcher runs before each start (default 0)')
    options = parser.parse_args()
    log_dir = Path(tempfile.mkdtemp(prefix='start_logs_'))
    print('node                cache  seconds to every endpoint (runs)')
    for name in [*ENDPOINTS, REFERENCE]:
        for kind in ('cold', 'warm'):
            times = []
            cache = Path(tempfile.mkdtemp(prefix='numba_cache_'))
            if kind == 'warm':
                measure(name, options.domain, cache, log_dir)     # fills the cache
            for _ in range(options.runs):
                if kind == 'cold':
                    shutil.rmtree(cache)
                    cache.mkdir()
                times.append(measure(name, options.domain, cache, log_dir, options.settle))
            shutil.rmtree(cache, ignore_errors=True)
            text = ' '.join('none' if t is None else f'{t:.2f}' for t in times)
            print(f'{name:<19} {kind:<6} {text}', flush=True)
    shutil.rmtree(log_dir, ignore_errors=True)


if __name__ == '__main__':
    main()
