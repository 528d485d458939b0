"""Helpers for tests that spin real rclpy nodes: private contexts and domains, waits."""

import itertools
import os
import time

from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Header

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

_domains = itertools.count(1 + os.getpid() % 100)


def next_domain_id():
    """Return a ROS_DOMAIN_ID for this test: distinct per test and per process."""
    return 1 + next(_domains) % 200


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


def header(stamp_s, frame_id):
    """Return a Header at ``stamp_s`` seconds."""
    sec = int(np.floor(stamp_s))
    result = Header(frame_id=frame_id)
    result.stamp.sec, result.stamp.nanosec = sec, int(round((stamp_s - sec) * 1e9))
    return result


def pose_message(stamp_s, pose, P_pose, frame_id='map'):
    """Return a PoseWithCovarianceStamped for a planar pose and its 3x3 covariance."""
    msg = PoseWithCovarianceStamped(header=header(stamp_s, frame_id))
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(pose[0]), float(pose[1])
    msg.pose.pose.orientation.z = float(np.sin(pose[2] / 2.0))
    msg.pose.pose.orientation.w = float(np.cos(pose[2] / 2.0))
    covariance = np.zeros((6, 6))
    index = [0, 1, 5]
    covariance[np.ix_(index, index)] = P_pose
    msg.pose.covariance = covariance.reshape(-1).tolist()
    return msg


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
