"""Helpers for tests that spin real rclpy nodes: private contexts and domains, waits."""

import itertools
import os
import time

from landmark_ros.ros.schemas import make_header, pose_message  # noqa: F401 (re-exported)
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

_WORKERS = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
_WORKER = int(os.environ.get('PYTEST_XDIST_WORKER', 'gw0')[2:] or 0)
_WIDTH = max(1, 100 // _WORKERS)
_domains = itertools.count(os.getpid() % _WIDTH)


def next_domain_id():
    """
    Return a ROS_DOMAIN_ID for this test: distinct per test and per process.

    The IDs 1 to 100, split evenly between pytest-xdist workers (each its own range);
    100 to 199 are the MRCLAM replay's and the demo's.
    """
    return 1 + _WORKER * _WIDTH + next(_domains) % _WIDTH


class RosEnv:
    """A private context, domain and executor; shut everything down in ``close``."""

    def __init__(self, domain_id=None, args=None):
        self.domain_id = next_domain_id() if domain_id is None else domain_id
        self.context = Context()
        # args: command line of the context, e.g. ['--ros-args', '--params-file', f].
        rclpy.init(args=args, context=self.context, domain_id=self.domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []

    def add(self, node):
        """Add a node to the executor and return it."""
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name, **kwargs):
        """Create a plain helper node in this context."""
        return self.add(rclpy.create_node(name, context=self.context, **kwargs))

    def spin_until(self, predicate, timeout=5.0):
        """Spin until ``predicate()`` is true; return it (False on timeout)."""
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return predicate()
            self.executor.spin_once(timeout_sec=0.01)
        return True

    def spin_for(self, seconds):
        """Spin for a fixed time (to let timers fire), without sleeping idle."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def close(self):
        """Destroy every node, shut the executor and context down."""
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)


header = make_header
"""Return a Header at ``stamp_s`` seconds (the package's own builder)."""


class Collector:
    """Subscribe to a topic and keep every message received."""

    def __init__(self, node, msg_type, topic, qos=10):
        self.messages = []
        self.subscription = node.create_subscription(msg_type, topic, self.messages.append, qos)


def wait_for_match(env, publishers=(), subscriptions=(), timeout=5.0):
    """Spin until every publisher and subscription has a match."""
    return env.spin_until(
        lambda: all(p.get_subscription_count() > 0 for p in publishers)
        and all(s.get_publisher_count() > 0 for s in subscriptions), timeout)
