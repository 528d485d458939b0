"""
Launch-free integration tests of the ``landmark_fuser`` node.

Each test runs the fuser (in process, or as its own process for persistence and
parameter errors) in a private context and DDS domain (``RosEnv``), feeds it over
real topics and checks the map it publishes. Expected numbers come from the
textbook exercise (case 5: two robots see landmark 7), from closed forms for equal
covariances, or from the core fusion functions applied to the observers' outputs.
"""

from dataclasses import fields
import json
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from landmark_ros.core.gaussian import (covariance_intersection, split_covariance_intersection,
                                        split_covariance_intersection_omega)
from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.fuser import map_file
from landmark_ros.nodes.fuser import LandmarkFuser
from landmark_ros.pipeline.config import DEPRECATED_PARAMETERS, FuserConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.ros.qos import LATCHED
from landmark_ros.ros.schemas import (landmark_message, read_landmark_cloud, read_landmarks)
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rigs import (DEADLINE_S, decode, FuserRig, ObserverRig, params, RELIABLE,
                  unique_namespace, values_of)
from rosutil import Collector, header, wait_for_match
from sensor_msgs.msg import PointCloud2, PointField
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray
import yaml

REPO_ROOT = Path(__file__).resolve().parents[2]
SHIPPED_YAML = REPO_ROOT / 'config' / 'fuser.yaml'
NAN, INF = float('nan'), float('inf')
I2 = np.eye(2)
ZERO2 = np.zeros((2, 2))
C = 0.01 * I2
"""Covariance of the hand-made observations: 0.1 m standard deviation."""

FUSER = '/landmark_fuser'
"""Name of the fuser node (in the root namespace: ``ns + FUSER`` in another)."""

# The textbook exercise, case 5: robots 1 and 2 observe landmark 7 with noise R.
TEXTBOOK_PARAMS = {'range_stddev': 0.5, 'bearing_stddev': 0.2}
R_TEXTBOOK = np.diag([0.25, 0.04])
POSE1, POSE1_COV, Z1 = np.array([1.0, 2.0, 0.5]), np.diag([0.08, 0.6, 0.02]), np.array([4.0, 0.7])
POSE2, POSE2_COV, Z2 = np.array([6.0, 4.0, 2.1]), np.diag([0.20, 0.09, 0.03]), np.array([4.0, 0.3])
M_CASE2 = np.array([2.44943102, 5.72815634])
PM_CASE1 = np.array([[0.58879177, -0.13171532], [-0.13171532, 0.30120823]])
PM_CASE2 = np.array([[0.94677477, -0.23978943], [-0.23978943, 0.94322523]])
M_CASE5 = np.array([2.58757252, 6.15534036])
P_CASE5 = np.array([[0.37966125, 0.07773125], [0.07773125, 0.36999739]])


# Reference values and decoding -----------------------------------------------------------

def polar_jacobian(pose, z):
    """Return d(landmark)/d(range, bearing) for a sensor at the robot origin."""
    r, angle = z[0], pose[2] + z[1]
    return np.array([[math.cos(angle), -r * math.sin(angle)],
                     [math.sin(angle), r * math.cos(angle)]])


def pose_term(pose, P_pose, z):
    """Return the pose part ``J_pose P_pose J_pose^T`` of a landmark's covariance."""
    angle = pose[2] + z[1]
    dx, dy = z[0] * math.cos(angle), z[0] * math.sin(angle)
    J_pose = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx]])
    return J_pose @ P_pose @ J_pose.T


def copy_fields(msg):
    """Give ``msg`` its own PointField objects (the writer's are shared by every message)."""
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in msg.fields]
    return msg


def int32_id_cloud(ids, m, P, frame='map'):
    """Return a landmark cloud whose ``id`` field is INT32 (so it can hold negative IDs)."""
    names = ['id', 'x', 'y', 'z', 'cov_xx', 'cov_xy', 'cov_yy']
    dtype = np.dtype({'names': names, 'formats': ['<i4'] + ['<f8'] * 6,
                      'offsets': [0] + [8 * k for k in range(1, 7)], 'itemsize': 56})
    rows = np.zeros(len(ids), dtype)
    rows['id'], rows['x'], rows['y'] = ids, np.asarray(m)[:, 0], np.asarray(m)[:, 1]
    P = np.asarray(P)
    rows['cov_xx'], rows['cov_xy'], rows['cov_yy'] = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    msg = PointCloud2(header=header(1.0, frame), height=1, width=len(ids), point_step=56,
                      row_step=56 * len(ids), is_bigendian=False, is_dense=True)
    msg.fields = [PointField(name=name, offset=dtype.fields[name][1], count=1,
                             datatype=PointField.INT32 if name == 'id' else PointField.FLOAT64)
                  for name in names]
    msg.data = rows.tobytes()
    return msg


def call(env, client, timeout=DEADLINE_S):
    """Call a Trigger service and return its response."""
    assert env.spin_until(client.service_is_ready, timeout), f'no service {client.srv_name}'
    future = client.call_async(Trigger.Request())
    assert env.spin_until(future.done, timeout), f'no answer from {client.srv_name}'
    return future.result()


# Fixtures and the in-process rig ---------------------------------------------------------

def assert_rows(rows, expected, atol=0.0):
    """Assert map rows equal ``[(id, m, P, P_dep, observations), ...]``."""
    assert rows.ids.tolist() == [e[0] for e in expected]
    for i, (_, m, P, P_dep, observations) in enumerate(expected):
        np.testing.assert_allclose(rows.m[i], m, rtol=0, atol=atol)
        np.testing.assert_allclose(rows.P[i], P, rtol=0, atol=atol)
        np.testing.assert_allclose(rows.P_dep[i], P_dep, rtol=0, atol=atol)
        assert rows.observations[i] == observations


# 1-2. Observers and the fuser: the textbook case 5 ---------------------------------------------

@pytest.mark.parametrize('fusion', ['independent', 'split_covariance_intersection',
                                    'covariance_intersection'])
def test_textbook_case5_through_two_observers_and_the_fuser(env, fusion):
    topics = ('robot1/landmarks', 'robot2/landmarks')
    rig = FuserRig(env, topics, fusion=fusion)
    observers = [ObserverRig(env, f'{rig.ns}/{ns}', tester=rig.tester, **TEXTBOOK_PARAMS)
                 for ns in ('robot1', 'robot2')]
    # Observer outputs are volatile: wait until the fuser (and the tester) listen.
    assert env.spin_until(lambda: all(o.node.landmark_pub.get_subscription_count() >= 2
                                      for o in observers), DEADLINE_S)

    outputs = []
    for observer, topic, (pose, P_pose, z) in zip(
            observers, topics, [(POSE1, POSE1_COV, Z1), (POSE2, POSE2_COV, Z2)]):
        outputs.append(observer.observe_one(10.0, pose, P_pose, z))
        source = rig.node.sources[topic]
        assert env.spin_until(lambda: source.counts['messages_in'] == 1 and not source.queue,
                              DEADLINE_S), f'{topic} never reached the fuser'
    (_, m1, P1, D1, _), (_, m2, P2, D2, _) = outputs
    # The observers publish the textbook landmark, the pose terms as dependent parts.
    np.testing.assert_allclose(m1[0], M_CASE2, rtol=0, atol=1e-8)
    np.testing.assert_allclose(P1[0], PM_CASE2, rtol=0, atol=1e-8)
    np.testing.assert_allclose(D1[0], PM_CASE2 - PM_CASE1, rtol=0, atol=1e-8)
    np.testing.assert_allclose(D2[0], pose_term(POSE2, POSE2_COV, Z2), rtol=0, atol=1e-12)
    np.testing.assert_allclose(P2[0] - D2[0], polar_jacobian(POSE2, Z2) @ R_TEXTBOOK
                               @ polar_jacobian(POSE2, Z2).T, rtol=0, atol=1e-12)

    if fusion == 'independent':
        m, P, P_dep, atol = M_CASE5, P_CASE5, ZERO2, 1e-8
    elif fusion == 'split_covariance_intersection':
        # The map folds the sources from the smallest covariance up.
        first, second = sorted([(m1[0], P1[0] - D1[0], D1[0]), (m2[0], P2[0] - D2[0], D2[0])],
                               key=lambda s: np.linalg.det(s[1] + s[2]))
        omega = split_covariance_intersection_omega(first[1], first[2], second[1], second[2])
        m, P_ind, P_dep = split_covariance_intersection(*first, *second, omega)
        P, atol = P_ind + P_dep, 1e-12
    else:
        m, P = covariance_intersection(m1[0], P1[0], m2[0], P2[0])
        P_dep, atol = P, 1e-12
    rows = rig.wait_map(lambda rows: rows.ids.tolist() == [7])
    assert_rows(rows, [(7, m, P, P_dep, 2)], atol=atol)
    assert rig.maps.messages[-1].header.frame_id == 'map'
    for topic in topics:
        assert rig.counts(topic)['fused'] == 1 and rig.counts(topic)['observations_in'] == 1
    assert rig.node.fuser.counters['landmarks_confirmed'] == 1


def test_textbook_case5_without_ids_over_dds_gives_one_new_landmark(env):
    topics = ('robot1/landmarks', 'robot2/landmarks')
    # alpha 0.49: the track score confirms on the second row (the map's min_observations).
    rig = FuserRig(env, topics, false_track_probability=0.49)
    observers = [ObserverRig(env, f'{rig.ns}/{ns}', tester=rig.tester, **TEXTBOOK_PARAMS)
                 for ns in ('robot1', 'robot2')]
    assert env.spin_until(lambda: all(o.node.landmark_pub.get_subscription_count() >= 2
                                      for o in observers), DEADLINE_S)
    for observer, topic, (pose, P_pose, z) in zip(
            observers, topics, [(POSE1, POSE1_COV, Z1), (POSE2, POSE2_COV, Z2)]):
        observer.observe_one(10.0, pose, P_pose, z, landmark_id=UNKNOWN_ID)
        cloud = read_landmark_cloud(observer.landmarks.messages[-1])[1]
        np.testing.assert_array_equal(cloud.scan.robot_xy, pose[:2])
        np.testing.assert_array_equal(cloud.scan.P_pose, P_pose)
        source = rig.node.sources[topic]
        assert env.spin_until(lambda: source.counts['messages_in'] == 1 and not source.queue,
                              DEADLINE_S), f'{topic} never reached the fuser'
    first = FuserConfig().first_new_id
    rows = rig.wait_map(lambda rows: rows.ids.tolist() == [first])
    assert_rows(rows, [(first, M_CASE5, P_CASE5, ZERO2, 2)], atol=1e-8)
    assert read_landmark_cloud(rig.maps.messages[-1])[1].classes.tolist() == [0]
    assert rig.counts(topics[0])['new_tentative'] == 1
    assert rig.counts(topics[1])['associated'] == 1


@pytest.mark.parametrize('bias', [(0.0, 0.0), (0.3, 0.1)])
def test_observer_dependent_part_is_the_pose_term_plus_the_bias_term(env, bias):
    tester = env.node('tester')
    observer = ObserverRig(env, f'{unique_namespace(env)}/robot1', tester=tester,
                           range_bias_stddev=bias[0], bearing_bias_stddev=bias[1],
                           **TEXTBOOK_PARAMS)
    R_bias = np.diag(np.square(bias))
    J = polar_jacobian(POSE1, Z1)
    bias_term = J @ R_bias @ J.T
    # Case 1 (exact pose): only the bias is dependent; case 2 adds the pose term.
    for stamp, P_pose, P_expected in [(10.0, np.zeros((3, 3)), PM_CASE1),
                                      (11.0, POSE1_COV, PM_CASE2)]:
        _, m, P, P_dep, _ = observer.observe_one(stamp, POSE1, P_pose, Z1)
        np.testing.assert_allclose(m[0], M_CASE2, rtol=0, atol=1e-8)
        np.testing.assert_allclose(P[0], P_expected + bias_term, rtol=0, atol=1e-8)
        np.testing.assert_allclose(P_dep[0], P_expected - PM_CASE1 + bias_term, rtol=0,
                                   atol=1e-8)
        _, P_ref, P_dep_ref = landmark_to_world_dependent(
            POSE1, P_pose, Z1, R_TEXTBOOK, R_bias if any(bias) else None)
        np.testing.assert_allclose(P[0], P_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(P_dep[0], P_dep_ref, rtol=0, atol=1e-12)


# 3. Gating, confirmation and re-initialisation -----------------------------------------------

def test_outlier_of_a_confirmed_landmark_is_gated_out(env):
    rig = FuserRig(env, min_observations=2)
    a, b = 'a/landmarks', 'b/landmarks'
    rig.send(a, [1], [[0.05, 0.0]], [C])
    rig.assert_no_new_map(0)                       # one observation: not confirmed yet
    rig.send(b, [1], [[-0.03, 0.02]], [C])
    rows = rig.wait_map(lambda rows: rows.ids.tolist() == [1])
    assert_rows(rows, [(1, [0.01, 0.01], C / 2, ZERO2, 2)], atol=1e-12)
    before = rig.node.fuser.map.snapshot()
    count, since = len(rig.maps.messages), len(rig.diagnostics.messages)

    rig.send(b, [1], [[10.0, 10.0]], [C])        # far outside the gate
    rig.assert_no_new_map(count)
    for old, new in zip(before, rig.node.fuser.map.snapshot()):
        np.testing.assert_array_equal(old, new)
    assert rig.counts(b)['gated_out'] == 1 and rig.counts(a)['gated_out'] == 0
    assert rig.counts(b)['fused'] == 1 and rig.counts(b)['observations_in'] == 2
    # The first status after the rejection warns about it.
    statuses = rig.wait_diagnostics(lambda s: values_of(s['fuser']).get('gated_out') == '1',
                                    since=since)
    fuser = statuses['fuser']
    assert fuser.level == DiagnosticStatus.WARN and 'rejected: gated_out' in fuser.message
    assert values_of(fuser)['landmarks'] == '1'
    assert values_of(statuses[b])['gated_out'] == '1'
    assert 'gated_out' not in values_of(statuses[a])


def test_unconfirmed_outlier_is_never_published(env):
    rig = FuserRig(env, min_observations=2)
    a, b = 'a/landmarks', 'b/landmarks'
    rig.send(a, [2], [[50.0, 50.0]], [C])        # first observation of ID 2: an outlier
    rig.send(b, [2], [[5.02, 4.98]], [C])
    rig.assert_no_new_map(0)                       # two that disagree: nothing confirmed
    rig.send(a, [2], [[4.98, 5.0]], [C])
    rows = rig.wait_map(lambda rows: rows.ids.tolist() == [2])
    assert_rows(rows, [(2, [5.0, 4.99], C / 2, ZERO2, 2)], atol=1e-12)
    rig.assert_no_new_map(len(rig.maps.messages))
    for msg in rig.maps.messages:
        rows = decode(msg)
        assert np.all(np.abs(rows.m - [50.0, 50.0]).max(axis=1) > 40.0), 'outlier published'
    assert rig.counts(a)['gated_out'] == 1 and rig.counts(b)['gated_out'] == 0


def test_moved_landmark_is_reinitialised(env):
    rig = FuserRig(env, min_observations=2, max_consecutive_rejections=3)
    a, b = 'a/landmarks', 'b/landmarks'
    rig.send(a, [3], [[0.0, 0.0]], [C])
    rig.send(b, [3], [[0.02, -0.02]], [C])
    rig.wait_map(lambda rows: rows.ids.tolist() == [3])
    count = len(rig.maps.messages)
    moved = np.array([[3.02, 0.01], [2.99, -0.02], [3.0, 0.04]])
    for i, z in enumerate(moved[:2]):
        rig.send(a if i % 2 == 0 else b, [3], [z], [C])
        rig.assert_no_new_map(count)             # rejected, not yet the limit
    assert rig.node.fuser.counters['landmarks_reinitialised'] == 0
    since = len(rig.diagnostics.messages)
    rig.send(a, [3], [moved[2]], [C])            # the third in a row: rebuilt from them
    rows = rig.wait_map(lambda rows: rows.observations.tolist() == [3])
    assert_rows(rows, [(3, moved.mean(axis=0), C / 3, ZERO2, 3)], atol=1e-12)
    assert rig.node.fuser.counters['landmarks_reinitialised'] == 1
    assert rig.counts(a)['gated_out'] == 2 and rig.counts(b)['gated_out'] == 1
    statuses = rig.wait_diagnostics(
        lambda s: values_of(s['fuser']).get('landmarks_reinitialised') == '1', since=since)
    assert 'landmarks_reinitialised' in statuses['fuser'].message
    # The new place is the landmark now: a consistent observation is fused.
    rig.send(b, [3], [[3.0, 0.0]], [C])
    rig.wait_map(lambda rows: rows.observations.tolist() == [4])


# 4. Late subscribers, markers and reset ------------------------------------------------------

def test_late_subscriber_markers_and_reset(env):
    sigma = 3.0
    rig = FuserRig(env, min_observations=1, marker_sigma=sigma)
    a = 'a/landmarks'
    P2 = np.array([[0.04, 0.01], [0.01, 0.02]])
    rig.send(a, [1, 2], [[1.0, 2.0], [3.0, -1.0]], [C, P2])
    rows = rig.wait_map(lambda rows: rows.ids.tolist() == [1, 2])
    rig.assert_no_new_map(len(rig.maps.messages))
    count = len(rig.maps.messages)

    # A late subscriber gets the current map (transient local), no new publication.
    late = Collector(env.node('late_subscriber'), PointCloud2, f'{rig.ns}/fused_landmarks',
                     LATCHED)
    assert env.spin_until(lambda: late.messages, DEADLINE_S), 'late subscriber got no map'
    assert len(late.messages) == 1 and len(rig.maps.messages) == count
    assert bytes(late.messages[0].data) == bytes(rig.maps.messages[-1].data)
    assert_rows(decode(late.messages[0]), [(1, [1.0, 2.0], C, ZERO2, 1),
                                           (2, [3.0, -1.0], P2, ZERO2, 1)])

    # Markers are built once someone subscribes: one ellipse and one label per landmark.
    markers = Collector(rig.tester, MarkerArray, f'{rig.ns}/fused_markers', LATCHED)
    assert env.spin_until(lambda: markers.messages, DEADLINE_S), 'no markers'
    array = markers.messages[-1]
    ellipses = {m.id: m for m in array.markers if m.type == Marker.CYLINDER}
    labels = {m.id: m for m in array.markers if m.type == Marker.TEXT_VIEW_FACING}
    assert len(array.markers) == 4 and set(ellipses) == set(labels) == {1, 2}
    for i, landmark_id in enumerate(rows.ids.tolist()):
        ellipse, label = ellipses[landmark_id], labels[landmark_id]
        for marker in (ellipse, label):
            assert marker.header.frame_id == 'map' and marker.action == Marker.ADD
            np.testing.assert_allclose([marker.pose.position.x, marker.pose.position.y],
                                       rows.m[i], rtol=0, atol=1e-12)
        assert label.text == str(landmark_id)
        eigenvalues = np.linalg.eigvalsh(rows.P[i])
        np.testing.assert_allclose([ellipse.scale.x, ellipse.scale.y],
                                   2.0 * sigma * np.sqrt(eigenvalues[::-1]), rtol=1e-9)

    # ~/reset clears the map: an empty map and a DELETEALL marker arrive.
    response = call(env, rig.tester.create_client(Trigger, f'{rig.name}/reset'))
    assert response.success and response.message == 'cleared 2 landmarks'
    rows = rig.wait_map(lambda rows: len(rows.ids) == 0)
    assert read_landmarks(rig.maps.messages[-1]).observations.tolist() == []
    assert env.spin_until(lambda: any(m.action == Marker.DELETEALL
                                      for m in markers.messages[-1].markers), DEADLINE_S)
    assert len(markers.messages[-1].markers) == 1
    assert len(rig.node.fuser.map) == 0
    # A new map starts from scratch.
    rig.send(a, [2], [[7.0, 7.0]], [C])
    assert_rows(rig.wait_map(lambda rows: len(rows.ids) == 1), [(2, [7.0, 7.0], C, ZERO2, 1)])


# 5. Bad input ---------------------------------------------------------------------------------

def test_bad_rows_are_counted_and_good_rows_of_the_message_fused(env):
    rig = FuserRig(env, topics=('a/landmarks',), min_observations=1)
    a = 'a/landmarks'
    rows = [  # id, m, P, P_dep, reason (None: good)
        (1, (1.0, 1.0), C, ZERO2, None),
        (2, (NAN, 0.0), C, ZERO2, 'landmark_nonfinite'),
        (3, (0.0, INF), C, ZERO2, 'landmark_nonfinite'),
        (4, (0.0, 0.0), [[INF, 0.0], [0.0, 1.0]], ZERO2, 'landmark_nonfinite'),
        (5, (0.0, 0.0), C, [[NAN, 0.0], [0.0, 0.0]], 'landmark_nonfinite'),
        (6, (0.0, 0.0), [[1.0, 2.0], [2.0, 1.0]], ZERO2, 'covariance_not_psd'),
        (7, (0.0, 0.0), [[-1.0, 0.0], [0.0, 1.0]], ZERO2, 'covariance_not_psd'),
        (8, (0.0, 0.0), [[1.0, 1.0], [1.0, 1.0]], ZERO2, 'covariance_singular'),
        (9, (0.0, 0.0), ZERO2, ZERO2, 'covariance_singular'),
        (10, (0.0, 0.0), C, 2.0 * C, 'dependent_part_invalid'),
        (11, (0.0, 0.0), C, [[-1e-3, 0.0], [0.0, 1e-3]], 'dependent_part_invalid'),
        (12, (3.0, 4.0), C, 0.5 * C, None),
    ]
    ids, m, P, P_dep, reasons = zip(*rows)
    since = len(rig.diagnostics.messages)
    rig.send(a, ids, m, P, P_dep)
    expected = {'messages_in': 1, 'observations_in': len(rows), 'fused': 2}
    for reason in reasons:
        if reason:
            expected[reason] = expected.get(reason, 0) + 1
    assert dict(+rig.counts(a)) == expected
    assert_rows(rig.wait_map(lambda rows: len(rows.ids) == 2),
                [(1, (1.0, 1.0), C, ZERO2, 1), (12, (3.0, 4.0), C, ZERO2, 1)])
    statuses = rig.wait_diagnostics(lambda s: values_of(s[a]).get('fused') == '2',
                                    since=since)
    source = values_of(statuses[a])
    assert source['landmark_nonfinite'] == '4' and source['covariance_singular'] == '2'
    assert 'rejected: ' in statuses['fuser'].message


def _missing_field(msg):
    msg.fields = [f for f in copy_fields(msg).fields if f.name != 'cov_yy']
    return msg


def _unsupported_type(msg):
    next(f for f in copy_fields(msg).fields if f.name == 'x').datatype = PointField.INT32
    return msg


def _short_data(msg):
    msg.data = bytes(msg.data)[:-3]
    return msg


def _odom_frame(msg):
    msg.header.frame_id = 'odom'
    return msg


@pytest.mark.parametrize('reason, spoil', [
    ('wrong_frame', _odom_frame), ('missing_field', _missing_field),
    ('unsupported_field_type', _unsupported_type), ('data_length_mismatch', _short_data)])
def test_bad_message_is_dropped_and_counted_per_source(env, reason, spoil):
    rig = FuserRig(env, min_observations=1)
    a, b = 'a/landmarks', 'b/landmarks'
    rig.send_msg(b, spoil(landmark_message(header(1.0, 'map'), [5, 6], [[1.0, 1.0]] * 2,
                                           [C, C])))
    assert dict(+rig.counts(b)) == {'messages_in': 1, reason: 1}
    assert rig.node.fuser.counters[reason] == 1
    rig.assert_no_new_map(0)
    # The node keeps working: good rows from both sources are fused.
    rig.send(a, [7], [[2.0, 2.0]], [C])
    rig.send(b, [8], [[3.0, 3.0]], [C])
    rows = rig.wait_map(lambda rows: rows.ids.tolist() == [7, 8])
    statuses = rig.wait_diagnostics(lambda s: values_of(s[b]).get('fused') == '1')
    assert values_of(statuses[b])[reason] == '1'
    assert reason not in values_of(statuses[a])
    assert_rows(rows, [(7, (2.0, 2.0), C, ZERO2, 1), (8, (3.0, 3.0), C, ZERO2, 1)])


def test_a_publisher_with_incompatible_qos_is_counted_against_its_source(env):
    # The inputs are reliable: a best-effort publisher never reaches them. The fuser
    # finds it with the diagnostics (no QoS event handlers on its inputs) and counts it
    # once on its source.
    rig = FuserRig(env, min_observations=1)
    a, b = 'a/landmarks', 'b/landmarks'
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    publisher = rig.tester.create_publisher(PointCloud2, rig.resolved(b), best_effort)
    assert env.spin_until(lambda: rig.counts(b)['incompatible_qos'] >= 1, DEADLINE_S)
    assert rig.node.fuser.counters['incompatible_qos'] == 1
    assert 'incompatible_qos' not in rig.counts(a)
    publisher.publish(landmark_message(header(1.0, 'map'), [5], [[1.0, 1.0]], [C]))
    rig.send(a, [7], [[2.0, 2.0]], [C])      # the other source is fused as before
    rig.wait_map(lambda rows: rows.ids.tolist() == [7])
    statuses = rig.wait_diagnostics(lambda s: 'incompatible_qos' in values_of(s[b]))
    assert values_of(statuses[b])['incompatible_qos'] == '1'
    assert rig.counts(b)['incompatible_qos'] == 1


def test_negative_id_in_an_int32_field_is_an_invalid_row(env):
    rig = FuserRig(env, topics=('a/landmarks',), min_observations=1)
    rig.send_msg('a/landmarks', int32_id_cloud([-1, 21], [[1.0, 1.0], [2.0, 2.0]], [C, C]))
    assert dict(+rig.counts('a/landmarks')) == {
        'messages_in': 1, 'observations_in': 2, 'invalid_id': 1, 'fused': 1}
    assert_rows(rig.wait_map(lambda rows: len(rows.ids) == 1), [(21, (2.0, 2.0), C, ZERO2, 1)])


def test_flooding_source_overflows_only_its_own_queue(env):
    flood, calm = 'flood/landmarks', 'calm/landmarks'
    rig = FuserRig(env, topics=(flood, calm), min_observations=1, update_period_s=1.0,
                   max_queue_messages=3)
    ids, messages = np.arange(100, 105), 20
    base = np.stack([ids * 1.0, np.zeros(len(ids))], axis=1)
    for i in range(messages):
        rig.pubs[flood].publish(landmark_message(header(1.0 + 0.01 * i, 'map'), ids,
                                                 base + 0.001 * i, [C] * len(ids)))
    rig.pubs[calm].publish(landmark_message(header(2.0, 'map'), [200], [[5.0, 5.0]], [C]))
    sources = rig.node.sources
    assert env.spin_until(lambda: sources[flood].counts['messages_in'] == messages
                          and sources[calm].counts['messages_in'] == 1, DEADLINE_S)
    assert env.spin_until(lambda: not sources[flood].queue and not sources[calm].queue,
                          DEADLINE_S)
    counts = rig.counts(flood)
    rows = len(ids) * messages
    # At most one batch can have run while the burst came in (1 s period).
    assert counts['queue_overflow'] % len(ids) == 0
    assert len(ids) * (messages - 6) <= counts['queue_overflow'] <= len(ids) * (messages - 3)
    assert counts['fused'] + counts['queue_overflow'] == rows
    assert dict(+rig.counts(calm)) == {'messages_in': 1, 'observations_in': 1, 'fused': 1}
    rows = rig.wait_map(lambda rows: 200 in rows.ids)
    assert rows.ids.tolist() == [100, 101, 102, 103, 104, 200]
    assert rig.node.fuser.counters['queue_overflow'] == counts['queue_overflow']


def test_silent_and_stopped_sources_are_stale_in_the_diagnostics(env):
    live, silent = 'live/landmarks', 'silent/landmarks'
    rig = FuserRig(env, topics=(live, silent), min_observations=1, source_timeout_s=0.3)
    rig.send(live, [1], [[1.0, 1.0]], [C])
    statuses = rig.wait_diagnostics(
        lambda s: values_of(s[live])['stale'] == 'false', timeout=5.0)
    status = statuses[live]
    assert status.level == DiagnosticStatus.OK and status.message == 'ok'
    assert float(values_of(status)['age_s']) <= 0.3
    assert status.hardware_id == rig.resolved(live)
    status = statuses[silent]
    assert status.level == DiagnosticStatus.WARN and status.message == 'stale'
    assert values_of(status)['stale'] == 'true' and values_of(status)['age_s'] == 'never'
    fuser = statuses['fuser']
    assert values_of(fuser)['landmarks'] == '1' and values_of(fuser)['fusion'] == 'independent'
    assert fuser.level == DiagnosticStatus.WARN
    assert f'stale: {rig.resolved(silent)}' in fuser.message
    assert fuser.message.startswith('1 landmarks')
    # The live source stops: stale after source_timeout_s.
    statuses = rig.wait_diagnostics(
        lambda s: values_of(s[live])['stale'] == 'true', timeout=5.0)
    status = statuses[live]
    assert status.level == DiagnosticStatus.WARN and float(values_of(status)['age_s']) >= 0.3
    assert f'stale: {rig.resolved(live)}, {rig.resolved(silent)}' in statuses['fuser'].message


# 6. Persistence -------------------------------------------------------------------------------

def fuser_command():
    """Return the command that starts the fuser as its own process."""
    script = REPO_ROOT / '.venv' / 'bin' / 'landmark_fuser'
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, '-m', 'landmark_ros.nodes.fuser']


@pytest.fixture
def start_fuser(env, tmp_path):
    """
    Return ``start(*param_overrides)``: a fuser process in its own namespace.

    The namespace (``start.namespace``) keeps its topics, services and diagnostics
    apart from any other fuser that may share the DDS domain (parallel test runs).
    Every process still running is killed in teardown.
    """
    processes = []

    def start(*overrides):
        # SIGINT back to its default first: a child inherits an ignored SIGINT (pytest
        # started in the background of a script), and the tests rely on SIGINT.
        command = [sys.executable, '-c', 'import os, signal, sys; '
                   'signal.signal(signal.SIGINT, signal.SIG_DFL); '
                   'os.execv(sys.argv[1], sys.argv[1:])']
        command += fuser_command() + ['--ros-args', '-r', f'__ns:={start.namespace}']
        for override in overrides:
            command += ['-p', override]
        process_env = dict(os.environ, ROS_DOMAIN_ID=str(env.domain_id),
                           ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
                           ROS_LOG_DIR=str(tmp_path / 'ros_log'))
        stem = tmp_path / f'fuser{len(processes)}'
        with open(f'{stem}.out', 'w') as out, open(f'{stem}.err', 'w') as err:
            process = subprocess.Popen(command, env=process_env, stdout=out, stderr=err,
                                       cwd=tmp_path)
        process.stderr_path = Path(f'{stem}.err')
        processes.append(process)
        return process

    start.namespace = unique_namespace(env)
    try:
        yield start
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.wait(timeout=10.0)


@pytest.mark.parametrize('where', ['unset', 'missing_directory'])
def test_save_service_reports_failure(env, tmp_path, where):
    map_path = '' if where == 'unset' else str(tmp_path / 'missing' / 'map.json')
    rig = FuserRig(env, topics=('a/landmarks',), min_observations=1, map_file=map_path)
    rig.send('a/landmarks', [1], [[1.0, 1.0]], [C])
    response = call(env, rig.tester.create_client(Trigger, f'{rig.name}/save'))
    assert not response.success
    if where == 'unset':
        assert response.message == 'map_file is not set'
    else:
        assert response.message == 'save failed: see the log'
        counters = rig.node.fuser.counters
        assert counters['save_failed'] == 1 and counters['saves'] == 0
        statuses = rig.wait_diagnostics(lambda s: 'save_failed' in values_of(s['fuser']),
                                        since=0)
        assert statuses['fuser'].level == DiagnosticStatus.WARN
        assert 'save_failed' in statuses['fuser'].message
    assert list(tmp_path.iterdir()) == []


def test_a_successful_save_is_not_a_problem_in_the_diagnostics(env, tmp_path):
    rig = FuserRig(env, topics=('a/landmarks',), min_observations=1,
                   map_file=str(tmp_path / 'map.json'), autosave_period_s=0.05)
    since = len(rig.diagnostics.messages)
    rig.send('a/landmarks', [1], [[1.0, 1.0]], [C])
    assert env.spin_until(lambda: rig.node.fuser.counters['saves'] == 1, DEADLINE_S)
    assert (tmp_path / 'map.json').exists()
    # The first status that counts the save: nothing went wrong, the source is fresh.
    statuses = rig.wait_diagnostics(lambda s: values_of(s['fuser']).get('saves') == '1',
                                    since=since)
    assert statuses['a/landmarks'].level == DiagnosticStatus.OK
    assert 'rejected' not in statuses['fuser'].message, statuses['fuser'].message
    assert statuses['fuser'].level == DiagnosticStatus.OK


def temporary_files(directory):
    """Return the names of the map file's temporary files in ``directory``."""
    return sorted(p.name for p in directory.glob('.map.json.*.tmp'))


def assert_map_equals_file(rows, document):
    """Assert published map rows equal a map file's landmarks exactly."""
    records = sorted(document['landmarks'], key=lambda r: r['id'])
    assert rows.ids.tolist() == [r['id'] for r in records]
    np.testing.assert_array_equal(rows.m, np.array([r['mean'] for r in records]).reshape(-1, 2))
    np.testing.assert_array_equal(
        rows.P, np.array([r['covariance'] for r in records]).reshape(-1, 2, 2))
    np.testing.assert_array_equal(
        rows.P_dep, np.array([r['covariance_dependent'] for r in records]).reshape(-1, 2, 2))
    assert rows.observations.tolist() == [r['observations'] for r in records]


def persistence_params(path, *more):
    """Return the parameter overrides of a fuser that saves to ``path``."""
    return (f'map_file:={path}', 'fusion:=independent', 'min_observations:=1',
            'input_topics:=[landmarks]') + more


def file_version(path):
    """
    Return what tells one save of ``path`` from another, None if it does not exist.

    The inode alone does not: ext4 hands a replaced file's inode to the next new file,
    so two saves in a row alternate between two inodes.
    """
    try:
        status = path.stat()
    except FileNotFoundError:
        return None
    return status.st_ino, status.st_mtime_ns, status.st_size


def wait_for_new_reader(env, node, pub, topic, known, process):
    """
    Spin until a subscription not in ``known`` (gids) reads ``topic``.

    Discovering it is what matches it with ``pub``; a killed fuser's reader may stay
    in the graph until its lease ends, so a count alone would not tell.
    """
    def matched():
        readers = node.get_subscriptions_info_by_topic(topic)
        fresh = [r for r in readers if bytes(r.endpoint_gid) not in known]
        return bool(fresh) and pub.get_subscription_count() >= 1
    assert env.spin_until(matched, DEADLINE_S), \
        'the fuser never subscribed: ' + process.stderr_path.read_text()[-3000:]


KILL_STATS = []
"""Sizes of the temporary files each SIGKILL left (none or one), for reports."""


def test_sigkill_during_autosave_never_tears_the_file_and_restart_publishes_it(
        env, start_fuser, tmp_path):
    directory = tmp_path / 'maps'
    directory.mkdir()
    path = directory / 'map.json'
    overrides = persistence_params(path, 'autosave_period_s:=0.05')
    rng = np.random.default_rng(20240611)
    tester = env.node('flooder')
    pub = tester.create_publisher(PointCloud2, f'{start_fuser.namespace}/landmarks',
                                  QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    # 2000 landmarks: a save takes about as long as the autosave period, so a kill
    # at a random moment often lands in the middle of one.
    count = 2000
    ids = np.arange(count)
    base = rng.uniform(-100.0, 100.0, (count, 2))
    cov = np.broadcast_to(C, (count, 2, 2))
    observations = np.zeros(count, np.int64)
    stamp = 0.0
    topic = f'{start_fuser.namespace}/landmarks'
    for _ in range(3):
        before = set(temporary_files(directory))
        version = file_version(path)
        readers = {bytes(i.endpoint_gid) for i in tester.get_subscriptions_info_by_topic(topic)}
        process = start_fuser(*overrides)
        wait_for_new_reader(env, tester, pub, topic, readers, process)
        kill_after = rng.uniform(0.0, 0.4)
        saved_at = None
        # The first save of a fuser under this flood comes some seconds after its start
        # (the first process fuses 2000 new landmarks per message into an empty map):
        # the deadline is on the save, not on the start, and grows with the run queue.
        load = max(1.0, os.getloadavg()[0] / (os.cpu_count() or 1))
        deadline = time.monotonic() + 3 * DEADLINE_S * load
        # Flood until this fuser has saved once, then for a random while more: a new
        # file version is a new save (os.replace), and it only saves after fusing new rows.
        while saved_at is None or time.monotonic() - saved_at < kill_after:
            assert process.poll() is None, process.stderr_path.read_text()
            assert time.monotonic() < deadline, \
                'the fuser never saved: ' + process.stderr_path.read_text()[-3000:]
            if saved_at is None and file_version(path) != version:
                saved_at = time.monotonic()
            stamp += 0.01
            pub.publish(landmark_message(header(stamp, 'map'), ids,
                                         base + rng.normal(0.0, 0.05, (count, 2)), cov))
            env.executor.spin_once(timeout_sec=0.02)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=10.0)

        document = map_file.load(str(path), 'map')    # never torn
        records = document['landmarks']
        assert [r['id'] for r in records] == ids.tolist()
        saved = np.array([r['observations'] for r in records])
        assert np.all(saved > observations), 'the restarted fuser did not continue the map'
        observations = saved
        new = sorted(set(temporary_files(directory)) - before)
        KILL_STATS.append([(directory / name).stat().st_size for name in new])
        assert len(new) <= 1, f'one kill left {new}'

    # Restarted on the same file without new data, the fuser publishes the saved map.
    document = map_file.load(str(path), 'map')
    maps = Collector(tester, PointCloud2, f'{start_fuser.namespace}/fused_landmarks', LATCHED)
    process = start_fuser(*overrides)
    assert env.spin_until(lambda: maps.messages, DEADLINE_S), \
        'no map from the restarted fuser: ' + process.stderr_path.read_text()
    assert_map_equals_file(decode(maps.messages[0]), document)
    process.send_signal(signal.SIGINT)
    assert process.wait(timeout=15.0) == 0
    assert 'Traceback' not in process.stderr_path.read_text()
    assert map_file.load(str(path), 'map')['landmarks'] == document['landmarks']


def test_save_service_and_sigint_write_the_latest_map(env, start_fuser, tmp_path):
    path = tmp_path / 'map.json'
    process = start_fuser(*persistence_params(path, 'autosave_period_s:=0.0'))
    tester = env.node('tester')
    pub = tester.create_publisher(PointCloud2, f'{start_fuser.namespace}/landmarks', RELIABLE)
    maps = Collector(tester, PointCloud2, f'{start_fuser.namespace}/fused_landmarks', LATCHED)
    assert wait_for_match(env, [pub], [maps.subscription], DEADLINE_S), \
        'no DDS match with the fuser process: ' + process.stderr_path.read_text()
    save = tester.create_client(Trigger, f'{start_fuser.namespace}{FUSER}/save')

    pub.publish(landmark_message(header(1.0, 'map'), [1, 2, 3],
                                 [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]], [C] * 3))
    assert env.spin_until(lambda: maps.messages and len(decode(maps.messages[-1]).ids) == 3,
                          DEADLINE_S)
    response = call(env, save)
    assert response.success and response.message == f'saved 3 landmarks to {path}'
    first = map_file.load(str(path), 'map')
    assert first['fusion'] == 'independent'
    assert_map_equals_file(decode(maps.messages[-1]), first)

    pub.publish(landmark_message(header(2.0, 'map'), [2, 4],
                                 [[2.01, 1.99], [4.0, 4.0]], [C] * 2))
    assert env.spin_until(lambda: len(decode(maps.messages[-1]).ids) == 4, DEADLINE_S)
    latest = decode(maps.messages[-1])
    assert latest.observations.tolist() == [1, 2, 1, 1]
    assert map_file.load(str(path), 'map')['landmarks'] == first['landmarks']  # no autosave
    process.send_signal(signal.SIGINT)
    assert process.wait(timeout=15.0) == 0
    assert 'Traceback' not in process.stderr_path.read_text()
    assert_map_equals_file(latest, map_file.load(str(path), 'map'))


@pytest.mark.parametrize('kind', ['garbage', 'other_version'])
def test_unusable_map_file_is_moved_aside_and_the_fuser_starts_empty(
        env, start_fuser, tmp_path, kind):
    path = tmp_path / 'map.json'
    if kind == 'garbage':
        text = 'this is {not: a map\n\x00\x01'
    else:
        record = {'id': 99, 'mean': [1.0, 1.0], 'covariance': C.tolist(),
                  'covariance_dependent': ZERO2.tolist(), 'observations': 3,
                  'sources': ['/landmarks'], 'first_stamp': 1.0, 'last_stamp': 2.0}
        text = json.dumps({'format': map_file.FORMAT, 'version': map_file.VERSION + 1,
                           'world_frame': 'map', 'fusion': 'independent',
                           'landmarks': [record]})
    path.write_text(text)
    tester = env.node('tester')
    diagnostics = Collector(tester, DiagnosticArray, '/diagnostics')
    maps = Collector(tester, PointCloud2, f'{start_fuser.namespace}/fused_landmarks', LATCHED)
    pub = tester.create_publisher(PointCloud2, f'{start_fuser.namespace}/landmarks', RELIABLE)
    process = start_fuser(*persistence_params(path, 'autosave_period_s:=0.05',
                                              'diagnostics_period_s:=0.1'))
    assert wait_for_match(env, [pub], [maps.subscription, diagnostics.subscription],
                          DEADLINE_S), process.stderr_path.read_text()

    def fuser_values():
        for array in reversed(diagnostics.messages):
            for status in array.status:
                if status.name == start_fuser.namespace + FUSER:
                    return values_of(status)
        return None
    assert env.spin_until(lambda: fuser_values() is not None, DEADLINE_S)
    assert fuser_values()['landmarks'] == '0'
    assert fuser_values()['map_file_rejected'] == '1'
    aside = list(tmp_path.glob('map.json.bad-*'))
    assert len(aside) == 1 and aside[0].read_text() == text
    assert not path.exists()
    assert not maps.messages                       # nothing loaded, nothing published

    # It works and started empty: one landmark in, the map and the new file hold it alone.
    pub.publish(landmark_message(header(1.0, 'map'), [5], [[5.0, 5.0]], [C]))
    assert env.spin_until(lambda: maps.messages, DEADLINE_S)
    assert_rows(decode(maps.messages[-1]), [(5, (5.0, 5.0), C, ZERO2, 1)])
    assert env.spin_until(lambda: path.exists(), DEADLINE_S)
    assert [r['id'] for r in map_file.load(str(path), 'map')['landmarks']] == [5]
    assert aside[0].read_text() == text
    process.send_signal(signal.SIGINT)
    assert process.wait(timeout=15.0) == 0
    stderr = process.stderr_path.read_text()
    assert 'unusable' in stderr and str(path) in stderr and 'Traceback' not in stderr


def test_temporary_file_left_by_a_killed_save_is_cleaned_up(ros_env, tmp_path):
    path = tmp_path / 'map.json'
    map_file.save(str(path), [], 'map', 'independent')
    stale = tmp_path / '.map.json.k1ll3d.tmp'       # as mkstemp names them
    stale.write_text(path.read_text()[:20])          # a save cut short
    env = ros_env()
    node = env.add(LandmarkFuser(context=env.context, parameter_overrides=params({
        'map_file': str(path), 'fusion': 'independent', 'min_observations': 1})))
    node.fuser.map.update([1], [[1.0, 1.0]], [C], source='/landmarks')
    assert node.fuser.save()
    assert temporary_files(tmp_path) == []


# 7. Parameters ----------------------------------------------------------------------------------

def test_shipped_yaml_gives_its_values(ros_env):
    env = ros_env(args=['--ros-args', '--params-file', str(SHIPPED_YAML)])
    node = env.add(LandmarkFuser(context=env.context))
    document = yaml.safe_load(SHIPPED_YAML.read_text())
    (key, section), = document.items()
    assert key == '/**/landmark_fuser'
    values = section['ros__parameters']
    assert set(values) == {spec.name for spec in fields(FuserConfig)} - DEPRECATED_PARAMETERS
    for name, value in values.items():
        actual = node.get_parameter(name).value
        actual = list(actual) if isinstance(value, list) else actual
        assert actual == value and type(actual) is type(value), name
        assert getattr(node.config, name) == (tuple(value) if isinstance(value, list)
                                              else value), name
    assert list(node.sources) == values['input_topics']


@pytest.mark.parametrize('override, message', [
    ('fusion:=magic', 'fusion must be one of'),
    ("input_topics:=['/a','/a']", 'must not repeat'),
    ('min_observations:=0', 'min_observations'),
])
def test_invalid_parameter_makes_the_process_exit_with_code_2(env, override, message):
    process_env = dict(os.environ, ROS_DOMAIN_ID=str(env.domain_id),
                       ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    result = subprocess.run(fuser_command() + ['--ros-args', '-p', override],
                            env=process_env, capture_output=True, text=True, timeout=30.0)
    assert result.returncode == 2, result.stderr
    assert 'Traceback' not in result.stderr, result.stderr
    assert 'landmark_fuser: invalid parameters' in result.stderr and message in result.stderr


def test_input_topics_that_resolve_to_one_topic_are_refused_or_fused_once(env):
    ns = unique_namespace(env)
    try:
        node = env.add(LandmarkFuser(context=env.context, namespace=ns, parameter_overrides=params(
            {'input_topics': ['a/landmarks', f'{ns}/a/landmarks'], 'min_observations': 1,
             'fusion': 'independent', 'publish_rate_hz': 50.0})))
    except ValueError:
        return                                     # refused, as a literal repeat is
    tester = env.node('tester')
    pub = tester.create_publisher(PointCloud2, f'{ns}/a/landmarks', RELIABLE)
    maps = Collector(tester, PointCloud2, f'{ns}/fused_landmarks', LATCHED)
    assert env.spin_until(lambda: pub.get_subscription_count() >= 1
                          and maps.subscription.get_publisher_count() >= 1, DEADLINE_S)
    pub.publish(landmark_message(header(1.0, 'map'), [1], [[1.0, 1.0]], [C]))
    sources = node.sources.values()
    assert env.spin_until(lambda: sum(s.counts['messages_in'] for s in sources) >= 1
                          and not any(s.queue for s in sources) and maps.messages, DEADLINE_S)
    # Every subscription has had its copy and every queue is fused.
    assert env.spin_until(lambda: sum(s.counts['messages_in'] for s in sources) == len(sources)
                          and not any(s.queue for s in sources), DEADLINE_S)
    ids, m, P, _, observations = node.fuser.map.snapshot()
    assert ids.tolist() == [1] and observations.tolist() == [1], 'fused more than once'
    np.testing.assert_array_equal(P[0], C)


@pytest.mark.parametrize('burst', [1, 16])
def test_one_callback_takes_the_clouds_waiting_on_every_input_topic(env, monkeypatch, burst):
    from landmark_ros.ros import fast_io
    a, b, c = 'a/landmarks', 'b/landmarks', 'c/landmarks'
    rig = FuserRig(env, topics=(a, b, c), min_observations=1, max_batch_messages=burst)
    subscription = rig.node.landmark_inputs.subscriptions

    def cloud(stamp, landmark):
        return landmark_message(header(stamp, 'map'), [landmark], [[1.0 * landmark, 0.0]], [C])

    # Stand-in for the subscriptions' queues while a's callback runs: two clouds wait
    # on a, two on b, none on c.
    waiting = {subscription[a]: [cloud(2.0, 2), cloud(3.0, 3)],
               subscription[b]: [cloud(1.5, 12), cloud(2.5, 13)]}
    taken = []

    def take_waiting(sub, msg_type, limit, raw=False, infos=None):
        taken.append((sub, limit))
        queue = waiting.get(sub, [])
        out, waiting[sub] = queue[:limit], queue[limit:]
        return out

    monkeypatch.setattr(fast_io, 'take_waiting', take_waiting)
    monkeypatch.setattr(fast_io, '_read_cloud', lambda cloud: cloud)    # messages, not bytes
    rig.node.landmark_inputs.receive(cloud(1.0, 1), a)
    sources = rig.node.sources
    expected = {a: [1] + [2, 3][:burst - 1], b: [12, 13][:burst], c: []}
    assert {topic: [int(item.ids[0]) for item in sources[topic].queue]
            for topic in (a, b, c)} == expected
    assert {topic: sources[topic].counts['messages_in'] for topic in (a, b, c)} == {
        topic: len(ids) for topic, ids in expected.items()}
    first = [(subscription[a], burst - 1), (subscription[b], burst), (subscription[c], burst)]
    # More than one cloud: another round, of the room left per input, finds nothing.
    again = [(subscription[t], burst - len(expected[t])) for t in (a, b, c)
             if len(expected[t]) < burst]
    assert taken == first + again
    rig.node.fuse_queued()
    assert sorted(rig.node.fuser.snapshot()[0].tolist()) == sorted(sum(expected.values(), []))


class _Arrivals:
    """Subscription queues for ``take_waiting``: clouds arrive while a round is processed."""

    def __init__(self, queues, arrivals):
        self.queues, self.arrivals, self.taken = queues, list(arrivals), []

    def take_waiting(self, sub, msg_type, limit, raw=False, infos=None):
        self.taken.append((sub, limit))
        queue = self.queues.get(sub, [])
        out, self.queues[sub] = queue[:limit], queue[limit:]
        return out

    def patch(self, monkeypatch, node):
        from landmark_ros.ros import fast_io
        monkeypatch.setattr(fast_io, 'take_waiting', self.take_waiting)
        monkeypatch.setattr(fast_io, '_read_cloud', lambda cloud: cloud)  # messages, not bytes
        add = node.fuser.add_landmark_bursts

        def add_then_arrive(bursts, now):
            add(bursts, now)
            if self.arrivals:           # what arrives while this round is processed
                for sub, clouds in self.arrivals.pop(0).items():
                    self.queues.setdefault(sub, []).extend(clouds)
        monkeypatch.setattr(node.fuser, 'add_landmark_bursts', add_then_arrive)


def _cloud(stamp, landmark):
    return landmark_message(header(stamp, 'map'), [landmark], [[1.0 * landmark, 0.0]], [C])


def _queued_ids(node, topics):
    return {topic: [int(item.ids[0]) for item in node.sources[topic].queue] for topic in topics}


def test_clouds_arriving_during_a_burst_are_taken_in_further_rounds_up_to_the_cap(
        env, monkeypatch):
    a, b, c = 'a/landmarks', 'b/landmarks', 'c/landmarks'
    # A long update period: the rounds' time budget (a quarter of it) never ends them,
    # however loaded the machine, and no update empties the queues meanwhile.
    rig = FuserRig(env, topics=(a, b, c), min_observations=1, max_batch_messages=4,
                   update_period_s=10.0)
    sub = rig.node.landmark_inputs.subscriptions
    # Round 1 takes a: 1 + 2, b: 1. Meanwhile 3 arrive on a, 1 on b, 2 on c; round 2
    # takes a: 1 (its cap of 4), b: 1, c: 2; meanwhile 2 more on b and 1 on c; round 3
    # takes b: 2 (cap), c: 1; then one arrives on c: round 4 takes it alone, and the
    # callback stops there (a round of one cloud: the inputs are not busy).
    arrivals = _Arrivals(
        {sub[a]: [_cloud(2.0, 2), _cloud(3.0, 3)], sub[b]: [_cloud(1.5, 11)]},
        [{sub[a]: [_cloud(4.0, 4), _cloud(5.0, 5), _cloud(6.0, 6)], sub[b]: [_cloud(2.5, 12)],
          sub[c]: [_cloud(1.0, 21), _cloud(2.0, 22)]},
         {sub[b]: [_cloud(3.5, 13), _cloud(4.5, 14)], sub[c]: [_cloud(3.0, 23)]},
         {sub[c]: [_cloud(4.0, 24)]},
         {sub[c]: [_cloud(5.0, 25)]}])
    arrivals.patch(monkeypatch, rig.node)
    rig.node.landmark_inputs.receive(_cloud(1.0, 1), a)
    assert _queued_ids(rig.node, (a, b, c)) == {a: [1, 2, 3, 4], b: [11, 12, 13, 14],
                                                c: [21, 22, 23, 24]}
    assert [len(arrivals.queues[sub[t]]) for t in (a, b, c)] == [2, 0, 1]   # left to a wait
    assert arrivals.taken == [(sub[a], 3), (sub[b], 4), (sub[c], 4),
                              (sub[a], 1), (sub[b], 3), (sub[c], 4),
                              (sub[b], 2), (sub[c], 2),
                              (sub[c], 1)]
    assert {t: rig.node.sources[t].counts['messages_in'] for t in (a, b, c)} == {
        a: 4, b: 4, c: 4}


def test_a_lone_cloud_takes_no_second_round(env, monkeypatch):
    a, b = 'a/landmarks', 'b/landmarks'
    rig = FuserRig(env, topics=(a, b), min_observations=1, max_batch_messages=16)
    sub = rig.node.landmark_inputs.subscriptions
    arrivals = _Arrivals({}, [{sub[b]: [_cloud(2.0, 12)]}])
    arrivals.patch(monkeypatch, rig.node)
    rig.node.landmark_inputs.receive(_cloud(1.0, 1), a)
    assert _queued_ids(rig.node, (a, b)) == {a: [1], b: []}
    assert arrivals.taken == [(sub[a], 15), (sub[b], 16)]


def test_further_rounds_stop_at_a_quarter_of_the_update_period(env, monkeypatch):
    from landmark_ros.ros import fast_io
    a, b = 'a/landmarks', 'b/landmarks'
    rig = FuserRig(env, topics=(a, b), min_observations=1, max_batch_messages=16,
                   update_period_s=0.04)
    sub = rig.node.landmark_inputs.subscriptions
    arrivals = _Arrivals({sub[b]: [_cloud(1.5, 11)]},
                         [{sub[b]: [_cloud(2.5, 12), _cloud(3.5, 13)]}] * 3)
    arrivals.patch(monkeypatch, rig.node)
    # Wall time read at the start, then after each round: 9 ms, then just over 10 ms
    # (the budget: a quarter of 40 ms) after the start.
    clock = iter([100.0, 100.009, 100.0101])

    class FakeTime:
        monotonic = staticmethod(lambda: next(clock))
    monkeypatch.setattr(fast_io, 'time', FakeTime)
    rig.node.landmark_inputs.receive(_cloud(1.0, 1), a)
    assert _queued_ids(rig.node, (a, b)) == {a: [1], b: [11, 12, 13]}
    assert len(arrivals.taken) == 4     # round 1 (2 takes), round 2 (2), none after
