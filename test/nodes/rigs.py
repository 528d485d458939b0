"""The node tests' shared pieces: a rig per node, one decoder of clouds and diagnostics."""

import os

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.nodes.fuser import LandmarkFuser
from landmark_ros.nodes.observer import LandmarkObserver
from landmark_ros.observer.observer import THROUGHPUT_COUNTERS
from landmark_ros.ros.qos import LATCHED
from landmark_ros.ros.schemas import landmark_message, observation_message, read_landmarks
import numpy as np
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosutil import Collector, header, pose_message, wait_for_match
from sensor_msgs.msg import PointCloud2

DEADLINE_S = 20.0
"""Longest wait for something that must happen."""

NOT_BEFORE_S = 0.3
"""How long a test waits to see that something does not happen."""

ZERO3 = np.zeros((3, 3))

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def decode(msg, frame=None):
    """Read a landmark cloud (checked finite; in ``frame`` when given): ``Landmarks``."""
    if frame is not None:
        assert msg.header.frame_id == frame
    rows = read_landmarks(msg)
    assert all(np.all(np.isfinite(v)) for v in rows[1:4]), 'non-finite landmark published'
    return rows


def values_of(status):
    """Return the key-value pairs of a DiagnosticStatus as a dict."""
    return {kv.key: kv.value for kv in status.values}


def params(values):
    """Return parameter overrides for a node."""
    return [Parameter(name, value=value) for name, value in values.items()]


class ObserverRig:
    """
    An observer node, publishers of its inputs and a collector of its landmarks.

    The tester node lives in the root namespace and uses absolute topic names when
    the observer is namespaced. ``send_*`` waits until the observer has counted the
    message, so inputs are handled in the order the test sends them.
    """

    def __init__(self, env, namespace=None, node=None, tester=None, **params):
        self.env = env
        if node is None:
            kwargs = {} if namespace is None else {'namespace': namespace}
            node = LandmarkObserver(
                context=env.context,
                parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
                **kwargs)
        self.node = env.add(node)
        ns = node.get_namespace().rstrip('/')
        self.tester = tester or env.node('tester' + ns.replace('/', '_'))
        self.pose_pub = self.tester.create_publisher(PoseWithCovarianceStamped,
                                                     ns + '/pose', 10)
        self.obs_pub = self.tester.create_publisher(PointCloud2, ns + '/observations', 10)
        self.landmarks = Collector(self.tester, PointCloud2, ns + '/landmarks')
        assert wait_for_match(env, [self.pose_pub, self.obs_pub],
                              [self.landmarks.subscription]), 'topics did not match'

    @property
    def counts(self):
        """Return the observer's counters."""
        return self.node.counters.counts

    def problems(self):
        """Return the non-zero rejection counters."""
        return {k: v for k, v in self.counts.items() if k not in THROUGHPUT_COUNTERS and v}

    def _send(self, publisher, msg):
        before = sum(self.counts.values())
        publisher.publish(msg)
        assert self.env.spin_until(lambda: sum(self.counts.values()) > before), \
            'the observer did not handle the message'

    def send_pose(self, msg):
        """Publish a pose message and wait until the observer has handled it."""
        self._send(self.pose_pub, msg)

    def pose(self, stamp, pose, P_pose=ZERO3, frame='map'):
        """Publish a planar pose and wait until the observer has handled it."""
        self.send_pose(pose_message(stamp, pose, P_pose, frame))

    def send_cloud(self, msg):
        """Publish an observation cloud and wait until the observer has handled it."""
        self._send(self.obs_pub, msg)

    def observe(self, stamp, ids, z, R=None, frame='laser'):
        """Publish observation rows and wait until the observer has handled them."""
        msg = observation_message(header(stamp, frame), ids, z, R)
        self.send_cloud(msg)
        return msg

    def wait_landmarks(self, count=1, timeout=5.0):
        """Spin until ``count`` landmark clouds arrived; return them, checked finite."""
        assert self.env.spin_until(lambda: len(self.landmarks.messages) >= count, timeout), \
            f'{len(self.landmarks.messages)} landmark messages, expected {count}'
        for msg in self.landmarks.messages:
            decode(msg)
        return self.landmarks.messages

    def assert_no_more_landmarks(self, count=0, within=NOT_BEFORE_S):
        """Spin until a deadline and assert no more than ``count`` clouds arrived."""
        assert not self.env.spin_until(lambda: len(self.landmarks.messages) > count, within), \
            'unexpected landmark message'
        assert len(self.landmarks.messages) == count

    def observe_one(self, stamp, pose, P_pose, z, landmark_id=7):
        """Send a pose and one observation of ``landmark_id``; return the cloud it gives."""
        self.pose(stamp, pose, P_pose)
        count = len(self.landmarks.messages)
        self.observe(stamp, [landmark_id], [z])
        assert self.env.spin_until(lambda: len(self.landmarks.messages) > count, DEADLINE_S)
        return decode(self.landmarks.messages[-1])


def unique_namespace(env):
    """Return a namespace of its own for a test's nodes (other runs may share the domain)."""
    return f'/fuser_test_{os.getpid()}_{env.domain_id}'


class FuserRig:
    """
    A fuser node, a publisher per input topic and collectors of its map and diagnostics.

    ``send`` waits until the fuser has counted the message and fused its queue, so
    inputs are handled in the order the test sends them.
    """

    def __init__(self, env, topics=('a/landmarks', 'b/landmarks'), **overrides):
        values = {'input_topics': list(topics), 'fusion': 'independent',
                  'publish_rate_hz': 50.0, 'diagnostics_period_s': 0.1, **overrides}
        self.env = env
        self.ns = unique_namespace(env)
        self.node = env.add(LandmarkFuser(context=env.context, namespace=self.ns,
                                          parameter_overrides=params(values)))
        self.name = self.node.get_fully_qualified_name()
        self.tester = env.node('fuser_tester')
        self.pubs = {topic: self.tester.create_publisher(PointCloud2, self.resolved(topic),
                                                         RELIABLE)
                     for topic in topics}
        self.maps = Collector(self.tester, PointCloud2, f'{self.ns}/fused_landmarks', LATCHED)
        self.diagnostics = Collector(self.tester, DiagnosticArray, '/diagnostics')
        assert wait_for_match(env, self.pubs.values(),
                              [self.maps.subscription, self.diagnostics.subscription],
                              DEADLINE_S), 'topics did not match'

    def resolved(self, topic):
        """Return the full name of an input topic (as given in ``input_topics``)."""
        return f'{self.ns}/{topic}'

    def counts(self, topic):
        """Return the counters of one source."""
        return self.node.sources[topic].counts

    def send_msg(self, topic, msg):
        """Publish a cloud and wait until the fuser has counted it and fused its queue."""
        source = self.node.sources[topic]
        before = source.counts['messages_in']
        self.pubs[topic].publish(msg)
        assert self.env.spin_until(
            lambda: source.counts['messages_in'] > before and not source.queue, DEADLINE_S), \
            'the fuser did not handle the message'

    def send(self, topic, ids, m, P, P_dep=None, frame='map', stamp=1.0):
        """Publish landmark rows and wait until the fuser has fused them."""
        msg = landmark_message(header(stamp, frame), ids, m, P, P_dep)
        self.send_msg(topic, msg)
        return msg

    def wait_map(self, predicate=lambda rows: True, timeout=DEADLINE_S):
        """Spin until the newest map satisfies ``predicate``; return its rows."""
        def ready():
            return self.maps.messages and predicate(decode(self.maps.messages[-1], 'map'))
        assert self.env.spin_until(ready, timeout), 'map never as expected; last: %s' % (
            self.maps.messages and decode(self.maps.messages[-1], 'map'),)
        return decode(self.maps.messages[-1], 'map')

    def assert_no_new_map(self, count, within=NOT_BEFORE_S):
        """Spin until a deadline and assert that no map beyond ``count`` arrived."""
        assert not self.env.spin_until(lambda: len(self.maps.messages) > count, within), \
            f'unexpected map: {decode(self.maps.messages[-1], "map")}'

    def wait_diagnostics(self, predicate, timeout=DEADLINE_S, since=None):
        """
        Spin until a DiagnosticArray of this fuser satisfies ``predicate``.

        ``predicate`` gets the statuses as a dict: ``'fuser'`` for the fuser's own, the
        input topic (as given in ``input_topics``) for each source. Only arrays received
        from index ``since`` on count (by default: new ones).
        """
        seen = len(self.diagnostics.messages) if since is None else since
        keys = {self.name: 'fuser'}
        keys.update({f'{self.name}: {self.resolved(topic)}': topic for topic in self.pubs})

        def find():
            for array in self.diagnostics.messages[seen:]:
                statuses = {keys[status.name]: status for status in array.status
                            if status.name in keys}
                if 'fuser' in statuses and predicate(statuses):
                    return statuses
            return None
        assert self.env.spin_until(lambda: find() is not None, timeout), 'no such diagnostics'
        return find()
