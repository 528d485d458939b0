"""The observer's precision sources: a message goes to the topic of its dependent part."""

from landmark_ros.observer.precision import (dependent_stddev, precision_level,
                                             precision_topics)
import numpy as np
import pytest
from rigs import decode, ObserverRig
from rosutil import Collector, wait_for_match
from sensor_msgs.msg import PointCloud2


def _P_dep(*stddevs):
    return np.array([np.diag([s * s, 0.25 * s * s]) for s in stddevs])


def test_the_level_doubles_from_the_base_and_is_clipped():
    # Levels from 0.1 m: below 0.2 m, to 0.4 m, to 0.8 m, beyond (clipped to 3).
    levels = [precision_level(_P_dep(s), 4, 0.1) for s in
              (1e-9, 0.05, 0.199, 0.201, 0.399, 0.401, 0.79, 0.81, 50.0)]
    assert levels == [0, 0, 0, 1, 1, 2, 2, 3, 3]
    assert precision_level(_P_dep(50.0), 1, 0.1) == 0        # one source: always 0
    assert precision_level(np.zeros((0, 2, 2)), 4, 0.1) == 0  # no row: landmarks


def test_a_message_is_placed_by_the_median_of_its_rows_largest_stddev():
    P_dep = _P_dep(0.1, 0.3, 0.9)
    P_dep[1] = np.diag([0.0, 0.09])     # the larger eigenvalue, whatever its axis
    assert dependent_stddev(P_dep) == pytest.approx(0.3, rel=1e-12)
    assert precision_level(P_dep, 4, 0.1) == 1


def test_one_source_is_the_landmark_topic_itself():
    assert precision_topics('landmarks', 1) == ['landmarks']
    assert precision_topics('/r1/landmarks', 3) == [
        '/r1/landmarks', '/r1/landmarks/precision_1', '/r1/landmarks/precision_2']


def test_the_node_publishes_each_message_on_its_level(env):
    rig = ObserverRig(env, precision_sources=3, precision_base_m=0.1)
    ns = rig.node.get_namespace().rstrip('/')
    topics = precision_topics(ns + '/landmarks', 3)
    collectors = [rig.landmarks] + [Collector(rig.tester, PointCloud2, t) for t in topics[1:]]
    assert wait_for_match(env, rig.node.landmark_pubs, [c.subscription for c in collectors])
    # A pose known to s in position (not in heading) gives every row s^2 I as its
    # dependent part: levels 0, 0, 1, 2 (clipped) for 0.05, 0.15, 0.25 and 1.0 m.
    expected = []
    for k, (s, level) in enumerate([(0.05, 0), (0.15, 0), (0.25, 1), (1.0, 2)]):
        stamp = 1.0 + k
        rig.pose(stamp, (1.0, 2.0, 0.3), np.diag([s * s, s * s, 0.0]))
        rig.observe(stamp, [7, 8], [(2.0, 0.1), (3.0, -0.2)])
        expected.append((int(stamp), level))
    rig.observe(4.0, [], np.zeros((0, 2)))     # no row: on landmarks
    expected.append((4, 0))
    assert env.spin_until(lambda: sum(len(c.messages) for c in collectors) == len(expected)), \
        ([len(c.messages) for c in collectors], rig.counts)
    got = sorted((m.header.stamp.sec, level) for level, c in enumerate(collectors)
                 for m in c.messages)
    assert got == sorted(expected)
    for level, c in enumerate(collectors):
        for msg in c.messages:
            ids, m, P, P_dep = decode(msg)[:4]
            if len(ids):
                assert precision_level(P_dep, 3, 0.1) == level
                assert np.all(np.linalg.eigvalsh(P - P_dep) > 0.0)


def test_the_split_is_read_only(env):
    rig = ObserverRig(env)
    assert len(rig.node.landmark_pubs) == 1
    for name in ('precision_sources', 'precision_base_m'):
        assert rig.node.describe_parameters([name])[0].read_only, name
