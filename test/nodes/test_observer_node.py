"""
Launch-free integration tests of the ``landmark_observer`` node.

Each test runs the node and a tester node in a private context and DDS domain
(``RosEnv``), talks to it over real topics and checks the numbers that come out.
Expected landmarks come from ``expected_landmark`` below, an independent closed form
of the chapter's formulas (pinned by the textbook numbers), not from the package.
"""

from dataclasses import fields
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.nodes.observer import LandmarkObserver
from landmark_ros.pipeline.config import DEPRECATED_PARAMETERS, ObserverConfig
from landmark_ros.ros.schemas import observation_message
import numpy as np
import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter
from rigs import decode, NOT_BEFORE_S, ObserverRig, values_of
from rosutil import Collector, header, pose_message, wait_for_match
from sensor_msgs.msg import PointCloud2, PointField
from visualization_msgs.msg import Marker, MarkerArray
import yaml

REPO_ROOT = Path(__file__).resolve().parents[2]
SHIPPED_YAML = REPO_ROOT / 'config' / 'observer.yaml'
NAN, INF = float('nan'), float('inf')
ZERO3 = np.zeros((3, 3))

# The textbook exercise: pose p1, observation z of landmark 7, noise R.
P1 = np.array([1.0, 2.0, 0.5])
P1_CASE2 = np.diag([0.08, 0.6, 0.02])
Z = np.array([4.0, 0.7])
R_TEXTBOOK = np.diag([0.25, 0.04])
TEXTBOOK_PARAMS = {'range_stddev': 0.5, 'bearing_stddev': 0.2}
M_TEXTBOOK = np.array([2.44943102, 5.72815634])
PM_CASE1 = np.array([[0.58879177, -0.13171532], [-0.13171532, 0.30120823]])
PM_CASE2 = np.array([[0.94677477, -0.23978943], [-0.23978943, 0.94322523]])

LANDMARK_NAMES = ['x', 'y', 'z', 'id', 'mean_x', 'mean_y', 'cov_xx', 'cov_xy', 'cov_yy',
                  'cov_dep_xx', 'cov_dep_xy', 'cov_dep_yy']
LANDMARK_FORMATS = ['<f4'] * 3 + ['<u4'] + ['<f8'] * 8
THROUGHPUT = {'poses_in', 'observation_messages_in', 'observations_in', 'landmarks_out'}
POINT_FIELD_TYPES = {
    np.dtype(np.int8): PointField.INT8, np.dtype(np.uint8): PointField.UINT8,
    np.dtype(np.int16): PointField.INT16, np.dtype(np.uint16): PointField.UINT16,
    np.dtype(np.int32): PointField.INT32, np.dtype(np.uint32): PointField.UINT32,
    np.dtype(np.float32): PointField.FLOAT32, np.dtype(np.float64): PointField.FLOAT64,
}


# Reference values ---------------------------------------------------------------------

def wrap(angle):
    """Wrap an angle to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def expected_landmark(pose, P_pose, z, R, sensor_pose=(0.0, 0.0, 0.0)):
    """Return the landmark seen as ``z`` from ``pose`` and its first-order covariance."""
    x, y, theta = pose
    dx, dy, dtheta = sensor_pose
    sx = x + math.cos(theta) * dx - math.sin(theta) * dy
    sy = y + math.sin(theta) * dx + math.cos(theta) * dy
    r, bearing = z
    angle = theta + dtheta + bearing
    m = np.array([sx + r * math.cos(angle), sy + r * math.sin(angle)])
    J_pose = np.array([[1.0, 0.0, -(m[1] - y)], [0.0, 1.0, m[0] - x]])
    J_z = np.array([[math.cos(angle), -r * math.sin(angle)],
                    [math.sin(angle), r * math.cos(angle)]])
    return m, J_pose @ np.asarray(P_pose) @ J_pose.T + J_z @ np.asarray(R) @ J_z.T


def interpolated(pose0, P0, pose1, P1_, fraction):
    """Interpolate two poses: x, y linear, yaw along the shortest arc, covariance linear."""
    pose0, pose1 = np.asarray(pose0, float), np.asarray(pose1, float)
    pose = pose0 + fraction * (pose1 - pose0)
    pose[2] = wrap(pose0[2] + fraction * wrap(pose1[2] - pose0[2]))
    return pose, (1.0 - fraction) * np.asarray(P0) + fraction * np.asarray(P1_)


def assert_landmarks(actual, expected, atol=1e-9):
    """Assert decoded landmarks ``(ids, m, P_m)`` equal ``[(id, m, P_m), ...]``."""
    ids, m, P_m = actual[:3]
    assert ids.tolist() == [e[0] for e in expected]
    for i, (_, m_expected, P_expected) in enumerate(expected):
        np.testing.assert_allclose(m[i], m_expected, rtol=0, atol=atol)
        np.testing.assert_allclose(P_m[i], P_expected, rtol=0, atol=atol)


def stamp_tuple(stamp):
    """Return a builtin_interfaces/Time as (sec, nanosec)."""
    return stamp.sec, stamp.nanosec


# Hand-made clouds -----------------------------------------------------------------------

def make_cloud(stamp, columns, frame='laser', bigendian=False, height=1, row_padding=0,
               field_order=None):
    """
    Return a PointCloud2 built by hand.

    ``columns`` is a list of ``(name, numpy dtype, values)``; fields are laid out in
    that order, each aligned to its size, the point padded to 8 bytes. ``row_padding``
    bytes of 0xAB follow every row; ``field_order`` lists the fields in another order.
    """
    order = '>' if bigendian else '<'
    names, formats, offsets, offset = [], [], [], 0
    for name, dtype, _ in columns:
        dtype = np.dtype(dtype).newbyteorder(order)
        offset = -(-offset // dtype.itemsize) * dtype.itemsize
        names.append(name)
        formats.append(dtype)
        offsets.append(offset)
        offset += dtype.itemsize
    step = -(-offset // 8) * 8
    count = len(columns[0][2]) if columns else 0
    rows = np.zeros(count, np.dtype({'names': names, 'formats': formats,
                                     'offsets': offsets, 'itemsize': step}))
    for name, _, values in columns:
        rows[name] = values
    width = count // height if height else 0
    body = np.frombuffer(rows.tobytes(), np.uint8).reshape(height, width * step)
    padding = np.full((height, row_padding), 0xAB, np.uint8)
    msg = PointCloud2(header=header(stamp, frame), height=height, width=width,
                      is_bigendian=bigendian, point_step=step,
                      row_step=width * step + row_padding, is_dense=True)
    msg.fields = [PointField(name=name, offset=off, count=1,
                             datatype=POINT_FIELD_TYPES[np.dtype(dtype)])
                  for name, dtype, off in zip(names, [c[1] for c in columns], offsets)]
    if field_order is not None:
        msg.fields = sorted(msg.fields, key=lambda f: field_order.index(f.name))
    msg.data = np.hstack([body, padding]).tobytes()
    return msg


def noise_rows_cloud(stamp, rows, id_type=np.int32, frame='laser'):
    """Return an observation cloud from ``(id, range, bearing, rv, bv, rbc)`` rows."""
    rows = list(rows)
    columns = list(zip(*rows)) if rows else [()] * 6
    names = ['id', 'range', 'bearing', 'range_variance', 'bearing_variance',
             'range_bearing_covariance']
    types = [id_type] + [np.float64] * 5
    return make_cloud(stamp, [(n, t, list(v)) for n, t, v in zip(names, types, columns)],
                      frame=frame)


def row_R(row, params=(0.25, 0.04)):
    """Return the noise covariance a row stands for: NaN entries take the parameters."""
    _, _, _, rv, bv, rbc = row
    rv = params[0] if math.isnan(rv) else rv
    bv = params[1] if math.isnan(bv) else bv
    rbc = 0.0 if math.isnan(rbc) else rbc
    return np.array([[rv, rbc], [rbc, bv]])


# Fixtures and the test rig ---------------------------------------------------------------

def textbook_rig(env, **params):
    """Return a rig with the textbook noise parameters plus ``params``."""
    return ObserverRig(env, **{**TEXTBOOK_PARAMS, **params})


# 1. Textbook cases ------------------------------------------------------------------------

@pytest.mark.parametrize('noise', ['parameters', 'per_row', 'per_row_nan'])
@pytest.mark.parametrize('case, P_pose, P_expected', [
    ('case1', ZERO3, PM_CASE1), ('case2', P1_CASE2, PM_CASE2)])
def test_textbook_case(env, case, P_pose, P_expected, noise):
    # per_row: the cloud carries R while the parameters are the defaults (0.1, 0.02);
    # per_row_nan: the cloud carries NaN variances, which mean "use the parameters".
    if noise == 'per_row':
        rig, R = ObserverRig(env), R_TEXTBOOK[None]
    else:
        rig = textbook_rig(env)
        R = None if noise == 'parameters' else np.full((1, 2, 2), NAN)
    stamp = 10.123456789
    rig.pose(stamp, P1, P_pose)
    sent = rig.observe(stamp, [7], [Z], R, frame='laser')
    msg, = rig.wait_landmarks()

    # The reference formula reproduces the textbook numbers ...
    m_ref, P_ref = expected_landmark(P1, P_pose, Z, R_TEXTBOOK)
    np.testing.assert_allclose(m_ref, M_TEXTBOOK, rtol=0, atol=1e-8)
    np.testing.assert_allclose(P_ref, P_expected, rtol=0, atol=1e-8)
    # ... and so does the node.
    ids, m, P_m = decode(msg)[:3]
    assert ids.tolist() == [7]
    np.testing.assert_allclose(m[0], M_TEXTBOOK, rtol=0, atol=1e-8)
    np.testing.assert_allclose(P_m[0], P_expected, rtol=0, atol=1e-8)

    assert stamp_tuple(msg.header.stamp) == stamp_tuple(sent.header.stamp)
    assert msg.header.frame_id == 'map'
    # Layout: FLOAT32 x y z at 0, 4, 8 (RViz, PCL), UINT32 id, then little-endian
    # FLOAT64 (the estimate at full precision, covariances), in order, non-overlapping.
    assert [f.name for f in msg.fields] == LANDMARK_NAMES
    assert [f.datatype for f in msg.fields] == \
        [PointField.FLOAT32] * 3 + [PointField.UINT32] + [PointField.FLOAT64] * 8
    assert all(f.count == 1 for f in msg.fields)
    assert msg.is_bigendian is False
    sizes = [4] * 4 + [8] * 8
    offsets = [f.offset for f in msg.fields]
    assert offsets[:3] == [0, 4, 8]
    assert all(offsets[i] + sizes[i] <= offsets[i + 1] for i in range(11))
    assert offsets[-1] + 8 <= msg.point_step
    assert (msg.height, msg.width) == (1, 1)
    assert msg.row_step == msg.point_step and len(msg.data) == msg.row_step
    raw = np.frombuffer(bytes(msg.data), np.dtype({
        'names': LANDMARK_NAMES, 'formats': LANDMARK_FORMATS, 'offsets': offsets,
        'itemsize': msg.point_step}))
    assert raw['id'][0] == 7 and raw['z'][0] == 0.0
    np.testing.assert_allclose([raw['mean_x'][0], raw['mean_y'][0]], M_TEXTBOOK, rtol=0,
                               atol=1e-8)
    assert [raw['x'][0], raw['y'][0]] == [np.float32(v) for v in M_TEXTBOOK]
    np.testing.assert_allclose([raw['cov_xx'][0], raw['cov_xy'][0], raw['cov_yy'][0]],
                               [P_expected[0, 0], P_expected[0, 1], P_expected[1, 1]],
                               rtol=0, atol=1e-8)
    assert rig.counts == {'poses_in': 1, 'observation_messages_in': 1, 'observations_in': 1,
                          'landmarks_out': 1}


def test_non_unit_quaternion_is_normalised(env):
    rig = textbook_rig(env)
    msg = pose_message(10.0, P1, P1_CASE2)
    q = msg.pose.pose.orientation
    q.z, q.w = 3.0 * q.z, 3.0 * q.w
    rig.send_pose(msg)
    rig.observe(10.0, [7], [Z])
    assert_landmarks(decode(rig.wait_landmarks()[0]), [(7, M_TEXTBOOK, PM_CASE2)], atol=1e-8)
    assert rig.problems() == {}


# 2. Interpolation --------------------------------------------------------------------------

POSE_A_COV = np.diag([0.01, 0.02, 0.001])
POSE_B_COV = np.array([[0.05, 0.01, 0.002], [0.01, 0.03, 0.0], [0.002, 0.0, 0.004]])


@pytest.mark.parametrize('pose_a, pose_b, yaw_at_quarter', [
    ((0.0, 0.0, 0.0), (2.0, 0.0, math.pi / 2), math.pi / 8),
    # Across the +-pi wrap the short way is +0.283 rad, not -6 rad.
    ((1.0, 1.0, 3.0), (1.5, 0.5, -3.0), 3.0 + 0.25 * (2.0 * math.pi - 6.0)),
], ids=['turn', 'across_pi'])
def test_interpolates_between_bracketing_poses(env, pose_a, pose_b, yaw_at_quarter):
    rig = textbook_rig(env, max_wait_s=30.0)
    z = np.array([5.0, -0.4])
    rig.pose(10.0, pose_a, POSE_A_COV)
    rig.observe(10.25, [3], [z])
    # Newer than every pose: it waits for a bracketing pose instead of extrapolating.
    rig.assert_no_more_landmarks(0)
    assert len(rig.node.observer.pending) == 1
    rig.pose(11.0, pose_b, POSE_B_COV)
    msg, = rig.wait_landmarks(1)
    pose, P_pose = interpolated(pose_a, POSE_A_COV, pose_b, POSE_B_COV, 0.25)
    assert pose[2] == pytest.approx(wrap(yaw_at_quarter), abs=1e-12)
    assert_landmarks(decode(msg), [(3, *expected_landmark(pose, P_pose, z, R_TEXTBOOK))])
    assert stamp_tuple(msg.header.stamp) == (10, 250_000_000)

    # Stamps equal to a pose stamp take that pose exactly (newest, then an older one).
    rig.observe(11.0, [4], [z])
    rig.observe(10.0, [5], [z])
    _, at_b, at_a = rig.wait_landmarks(3)
    assert_landmarks(decode(at_b), [(4, *expected_landmark(pose_b, POSE_B_COV, z, R_TEXTBOOK))])
    assert_landmarks(decode(at_a), [(5, *expected_landmark(pose_a, POSE_A_COV, z, R_TEXTBOOK))])
    assert rig.problems() == {}


# 3. Waiting for poses ----------------------------------------------------------------------

def test_observation_waits_for_a_late_pose(env):
    rig = textbook_rig(env, max_wait_s=30.0)
    z = np.array([3.0, 1.0])
    rig.observe(10.5, [8], [z])            # before any pose
    rig.assert_no_more_landmarks(0)
    rig.pose(10.0, P1, POSE_A_COV)         # not bracketing yet: keeps waiting
    rig.assert_no_more_landmarks(0)
    assert len(rig.node.observer.pending) == 1
    rig.pose(11.0, (3.0, 2.0, 1.5), POSE_B_COV)
    msg, = rig.wait_landmarks(1)
    pose, P_pose = interpolated(P1, POSE_A_COV, (3.0, 2.0, 1.5), POSE_B_COV, 0.5)
    assert_landmarks(decode(msg), [(8, *expected_landmark(pose, P_pose, z, R_TEXTBOOK))])
    assert rig.problems() == {}


def test_no_pose_in_time_on_diagnostics(env):
    rig = textbook_rig(env, max_wait_s=0.2, diagnostics_period_s=0.1)
    diagnostics = Collector(rig.tester, DiagnosticArray, '/diagnostics')
    assert wait_for_match(env, [rig.node.diagnostics_pub], [diagnostics.subscription])
    assert env.spin_until(lambda: diagnostics.messages)
    first = diagnostics.messages[0].status[0]
    assert (first.level, first.message) == (DiagnosticStatus.WARN, 'no pose received yet')
    rig.pose(10.0, P1, P1_CASE2)
    rig.observe(10.0, [7], [Z])
    rig.wait_landmarks(1)
    rig.observe(12.0, [1, 2, 3], [[1.0, 0.0], [2.0, 0.1], [3.0, 0.2]])  # 2 s past any pose
    sent = time.monotonic()

    def warned():
        return [status for array in diagnostics.messages for status in array.status
                if values_of(status).get('no_pose_in_time') == '3']

    assert env.spin_until(lambda: rig.counts['no_pose_in_time'] == 3, 5.0)
    assert time.monotonic() - sent >= 0.19   # dropped only after max_wait_s
    assert env.spin_until(warned, 5.0), 'no /diagnostics status reporting no_pose_in_time'
    status = warned()[0]
    assert status.name == '/landmark_observer' == rig.node.get_fully_qualified_name()
    assert status.level == DiagnosticStatus.WARN
    assert 'no_pose_in_time 3' in status.message
    assert values_of(status) == {
        'pose_buffer_size': '1', 'pending_messages': '0', 'poses_in': '1',
        'observation_messages_in': '2', 'observations_in': '4', 'landmarks_out': '1',
        'no_pose_in_time': '3'}
    # The next period has no new problem: back to OK, counters unchanged.
    count = len(diagnostics.messages)
    assert env.spin_until(lambda: any(
        s.level == DiagnosticStatus.OK for a in diagnostics.messages[count:] for s in a.status))
    ok = [s for a in diagnostics.messages[count:] for s in a.status
          if s.level == DiagnosticStatus.OK][0]
    assert ok.message == 'ok' and values_of(ok)['no_pose_in_time'] == '3'
    rig.assert_no_more_landmarks(1, within=0.0)


def test_newest_pose_within_max_pose_gap_after_the_wait(env):
    rig = textbook_rig(env, max_wait_s=0.2, max_pose_gap_s=0.1)
    z = np.array([2.0, -0.3])
    rig.pose(10.0, P1, P1_CASE2)
    rig.observe(10.05, [4], [z])            # within max_pose_gap_s of the newest pose
    sent = time.monotonic()
    rig.observe(10.15, [5, 6], [z, z])      # beyond it
    assert len(rig.node.observer.pending) == 2
    msg, = rig.wait_landmarks(1)
    assert time.monotonic() - sent >= 0.15  # only after waiting ~max_wait_s
    assert_landmarks(decode(msg), [(4, *expected_landmark(P1, P1_CASE2, z, R_TEXTBOOK))])
    assert env.spin_until(lambda: rig.counts['no_pose_in_time'] == 2)
    assert rig.problems() == {'no_pose_in_time': 2}
    rig.assert_no_more_landmarks(1, within=0.0)


def test_observation_older_than_the_pose_history(env):
    rig = textbook_rig(env, max_wait_s=30.0, max_pose_gap_s=0.1)
    z = np.array([2.0, 0.4])
    rig.observe(5.0, [1], [z])              # waits: no pose yet
    rig.pose(10.0, P1, P1_CASE2)            # now it is known to be too old
    assert rig.problems() == {'observation_too_old': 1}
    rig.pose(11.0, (2.0, 2.0, 0.6), POSE_B_COV)
    rig.observe(9.5, [2, 3], [z, z])
    assert rig.problems() == {'observation_too_old': 3}
    rig.observe(9.95, [4], [z])             # within max_pose_gap_s: the oldest pose
    msg, = rig.wait_landmarks(1)
    assert_landmarks(decode(msg), [(4, *expected_landmark(P1, P1_CASE2, z, R_TEXTBOOK))])


def test_observation_older_than_the_kept_pose_history(env):
    rig = textbook_rig(env, pose_buffer_s=1.0, max_pose_gap_s=0.1, max_wait_s=30.0)
    z = np.array([2.0, 0.4])
    poses = {10.0: (0.0, 0.0, 0.0), 10.5: (0.5, 0.0, 0.1), 11.0: (1.0, 0.0, 0.2),
             11.5: (1.5, 0.0, 0.3), 12.0: (2.0, 0.0, 0.4)}
    for stamp, pose in poses.items():
        rig.pose(stamp, pose, POSE_A_COV)
    assert len(rig.node.observer.poses) == 3            # 11.0 to 12.0: pose_buffer_s = 1 s
    rig.observe(10.5, [1], [z])                # its pose was dropped from the history
    assert rig.problems() == {'observation_too_old': 1}
    rig.observe(11.25, [2], [z])
    pose, P_pose = interpolated(poses[11.0], POSE_A_COV, poses[11.5], POSE_A_COV, 0.5)
    assert_landmarks(decode(rig.wait_landmarks(1)[0]),
                     [(2, *expected_landmark(pose, P_pose, z, R_TEXTBOOK))])


# 4. Several robots in one process -------------------------------------------------------

def test_namespaced_observers_do_not_mix(env):
    robots = {
        'robot1': (P1, ZERO3, [(7, M_TEXTBOOK, PM_CASE1)]),
        'robot2': ((-3.0, 1.0, -2.0), POSE_B_COV,
                   [(7, *expected_landmark((-3.0, 1.0, -2.0), POSE_B_COV, Z, R_TEXTBOOK))]),
    }
    rigs = {ns: textbook_rig(env, namespace=ns, diagnostics_period_s=0.1) for ns in robots}
    diagnostics = Collector(rigs['robot1'].tester, DiagnosticArray, '/diagnostics')
    assert wait_for_match(env, [r.node.diagnostics_pub for r in rigs.values()],
                          [diagnostics.subscription])
    for ns, rig in rigs.items():
        assert rig.node.get_fully_qualified_name() == f'/{ns}/landmark_observer'
        assert rig.landmarks.subscription.topic_name == f'/{ns}/landmarks'
        pose, P_pose, _ = robots[ns]
        rig.pose(20.0, pose, P_pose)
        rig.observe(20.0, [7], [Z])
    for ns, rig in rigs.items():
        msg, = rig.wait_landmarks(1)
        assert_landmarks(decode(msg), robots[ns][2], atol=1e-8)
        assert rig.counts['observation_messages_in'] == 1 and rig.counts['poses_in'] == 1
    rigs['robot2'].assert_no_more_landmarks(1)
    assert len(rigs['robot1'].landmarks.messages) == 1

    def names():
        return {s.name: s.hardware_id for a in diagnostics.messages for s in a.status}

    assert env.spin_until(lambda: len(names()) == 2)
    assert names() == {'/robot1/landmark_observer': '/robot1',
                       '/robot2/landmark_observer': '/robot2'}


# 5. Parameters: YAML files and run-time changes ------------------------------------------

def yaml_sections(path):
    """Return the single node key of a parameter file and its parameters."""
    document = yaml.safe_load(Path(path).read_text())
    (key, section), = document.items()
    return key, section['ros__parameters']


def param_value(node, name):
    """Return a parameter value, arrays as lists."""
    value = node.get_parameter(name).value
    return list(value) if not isinstance(value, (str, bool, int, float)) else value


def test_shipped_yaml_applies_to_a_namespaced_node(ros_env):
    env = ros_env(args=['--ros-args', '--params-file', str(SHIPPED_YAML),
                        '-r', '__ns:=/robot1'])
    node = env.add(LandmarkObserver(context=env.context))
    assert node.get_fully_qualified_name() == '/robot1/landmark_observer'
    key, values = yaml_sections(SHIPPED_YAML)
    assert key == '/**/landmark_observer'
    assert set(values) == {spec.name for spec in fields(ObserverConfig)} - DEPRECATED_PARAMETERS
    for name, value in values.items():
        assert param_value(node, name) == value, name
        assert type(param_value(node, name)) is type(value), name
        assert getattr(node.config, name) == (tuple(value) if isinstance(value, list)
                                              else value), name


def test_yaml_values_take_effect(ros_env, tmp_path):
    # Same '/**/landmark_observer' key as the shipped file, non-default values.
    key, values = yaml_sections(SHIPPED_YAML)
    values.update(world_frame='odom', sensor_frame='laser', sensor_pose=[0.1, 0.0, 0.0],
                  range_stddev=0.3, bearing_stddev=1, max_wait_s=30)
    path = tmp_path / 'observer.yaml'
    path.write_text(yaml.safe_dump({key: {'ros__parameters': values}}))
    env = ros_env(args=['--ros-args', '--params-file', str(path), '-r', '__ns:=/robot1'])
    rig = ObserverRig(env, node=LandmarkObserver(context=env.context))
    node = rig.node
    assert node.get_parameter('bearing_stddev').value == 1   # an integer in the file
    assert node.config.bearing_stddev == 1.0 and isinstance(node.config.bearing_stddev, float)
    assert node.config.sensor_pose == (0.1, 0.0, 0.0) and node.config.max_wait_s == 30.0

    rig.pose(10.0, P1, P1_CASE2, frame='odom')
    rig.observe(10.0, [7], [Z], frame='laser')
    rig.observe(10.0, [8], [Z], frame='camera')      # not the sensor_frame
    msg, = rig.wait_landmarks(1)
    assert msg.header.frame_id == 'odom'
    R = np.diag([0.09, 1.0])
    assert_landmarks(decode(msg), [(7, *expected_landmark(P1, P1_CASE2, Z, R, (0.1, 0.0, 0.0)))])
    rig.pose(11.0, P1, P1_CASE2, frame='map')        # not the world_frame
    assert rig.problems() == {'observation_wrong_frame': 1, 'pose_wrong_frame': 1}


@pytest.mark.parametrize('line', [
    'range_stddev: -1', 'range_stddev: -1.5', 'max_pending: 0', 'sensor_pose: [1.0, 2.0]',
    'max_pose_gap_s: 20.0'])
def test_invalid_yaml_value_is_refused(ros_env, tmp_path, line):
    key, values = yaml_sections(SHIPPED_YAML)
    values.update(yaml.safe_load(line))
    path = tmp_path / 'observer.yaml'
    path.write_text(yaml.safe_dump({key: {'ros__parameters': values}}))
    env = ros_env(args=['--ros-args', '--params-file', str(path)])
    with pytest.raises((ValueError, InvalidParameterValueException)):
        LandmarkObserver(context=env.context)


def test_parameter_changes_at_run_time(env):
    rig = textbook_rig(env)
    node = rig.node
    rig.pose(10.0, P1, P1_CASE2)
    rig.observe(10.0, [7], [Z])
    rig.wait_landmarks(1)

    result, = node.set_parameters([Parameter('range_stddev', value=0.3)])
    assert result.successful, result.reason
    assert node.config.range_stddev == 0.3
    rig.observe(10.0, [7], [Z])
    R = np.diag([0.09, 0.04])
    expected = [(7, *expected_landmark(P1, P1_CASE2, Z, R))]
    assert_landmarks(decode(rig.wait_landmarks(2)[1]), expected)

    for parameter in (Parameter('range_stddev', value=-0.3),
                      Parameter('range_stddev', value=-1),
                      Parameter('range_stddev', value='wide'),
                      Parameter('world_frame', value='odom'),
                      Parameter('max_pose_gap_s', value=20.0)):
        result, = node.set_parameters([parameter])
        assert not result.successful, parameter.name
        assert result.reason
    assert node.get_parameter('range_stddev').value == 0.3
    assert node.get_parameter('world_frame').value == 'map'
    assert (node.config.range_stddev, node.config.world_frame) == (0.3, 'map')
    rig.observe(10.0, [7], [Z])
    assert_landmarks(decode(rig.wait_landmarks(3)[2]), expected)


def test_max_wait_change_at_run_time_takes_effect(env):
    rig = textbook_rig(env, max_wait_s=30.0, max_pose_gap_s=0.1)
    rig.pose(10.0, P1, P1_CASE2)
    rig.observe(10.05, [7], [Z])            # no bracketing pose: waits up to 30 s
    rig.assert_no_more_landmarks(0)
    result, = rig.node.set_parameters([Parameter('max_wait_s', value=0.1)])
    assert result.successful, result.reason
    msg, = rig.wait_landmarks(1, timeout=3.0)  # now it takes the newest pose
    assert_landmarks(decode(msg), [(7, M_TEXTBOOK, PM_CASE2)], atol=1e-8)
    assert rig.problems() == {}


# 6. Bad inputs ------------------------------------------------------------------------------

GOOD_ROWS = [(1, 4.0, 0.7, NAN, NAN, NAN), (2, 2.5, -1.2, 0.09, 0.01, 0.02)]
BAD_ROWS = {
    # One of range and bearing NaN is a partial row (fuser.partial), not a bad one.
    'observation_nonfinite': [(3, NAN, NAN, NAN, NAN, NAN), (4, 1.0, INF, NAN, NAN, NAN),
                              (5, -INF, 0.2, NAN, NAN, NAN), (6, 2.0, -INF, NAN, NAN, NAN),
                              (7, INF, 0.2, NAN, NAN, NAN)],
    'range_not_positive': [(3, 0.0, 0.1, NAN, NAN, NAN), (4, -2.0, 0.3, NAN, NAN, NAN)],
    'invalid_id': [(-1, 3.0, 0.1, NAN, NAN, NAN), (-2 ** 31, 1.0, 0.0, NAN, NAN, NAN)],
    'negative_variance': [(3, 3.0, 0.1, -0.01, NAN, NAN), (4, 3.0, 0.1, NAN, -1e-6, NAN)],
    'noise_covariance_not_psd': [(3, 3.0, 0.1, 0.25, 0.04, 0.2),
                                 (4, 3.0, 0.1, NAN, NAN, -0.5)],
    'noise_covariance_nonfinite': [(3, 3.0, 0.1, INF, NAN, NAN), (4, 3.0, 0.1, NAN, INF, NAN),
                                   (5, 3.0, 0.1, NAN, NAN, INF)],
    # Finite but implausible (pipeline.limits): refused before the maths.
    'range_out_of_range': [(3, 1e200, 0.3, NAN, NAN, NAN)],
    'bearing_out_of_range': [(3, 3.0, 1e17, NAN, NAN, NAN)],
    'noise_variance_out_of_range': [(3, 3.0, 0.1, 1e-200, NAN, NAN),
                                    (4, 3.0, 0.1, NAN, 1e13, NAN)],
}


def good_row_landmarks(rows=GOOD_ROWS, pose=P1, P_pose=P1_CASE2):
    """Return the expected landmarks of good noise rows."""
    return [(row[0], *expected_landmark(pose, P_pose, row[1:3], row_R(row))) for row in rows]


@pytest.mark.parametrize('reason', [*BAD_ROWS, 'all_mixed'])
def test_bad_rows_are_dropped_and_the_rest_goes_through(env, reason):
    rig = textbook_rig(env)
    bad = sum(BAD_ROWS.values(), []) if reason == 'all_mixed' else BAD_ROWS[reason]
    rows = [GOOD_ROWS[0], *bad, GOOD_ROWS[1]]
    rig.pose(10.0, P1, P1_CASE2)
    rig.send_cloud(noise_rows_cloud(10.0, rows))
    msg, = rig.wait_landmarks(1)
    assert_landmarks(decode(msg), good_row_landmarks())
    expected = ({name: len(v) for name, v in BAD_ROWS.items()} if reason == 'all_mixed'
                else {reason: len(bad)})
    assert rig.problems() == expected
    assert rig.counts['observations_in'] == len(rows)
    assert rig.counts['landmarks_out'] == 2
    # The node keeps working.
    rig.observe(10.0, [7], [Z])
    assert_landmarks(decode(rig.wait_landmarks(2)[1]), [(7, M_TEXTBOOK, PM_CASE2)], atol=1e-8)


def test_all_rows_bad_or_no_rows_give_empty_clouds(env):
    rig = textbook_rig(env)
    rig.pose(10.0, P1, P1_CASE2)
    rig.send_cloud(noise_rows_cloud(10.5, []))
    rig.pose(11.0, P1, P1_CASE2)
    rig.send_cloud(noise_rows_cloud(10.75, BAD_ROWS['range_not_positive']))
    empty, rejected = rig.wait_landmarks(2)
    for msg, stamp in ((empty, (10, 500_000_000)), (rejected, (10, 750_000_000))):
        assert stamp_tuple(msg.header.stamp) == stamp and msg.header.frame_id == 'map'
        assert [f.name for f in msg.fields] == LANDMARK_NAMES
        assert msg.width * msg.height == 0 and len(msg.data) == 0
        ids, m, P_m = decode(msg)[:3]
        assert ids.shape == (0,) and m.shape == (0, 2) and P_m.shape == (0, 2, 2)
    assert rig.problems() == {'range_not_positive': 2}
    assert rig.counts['landmarks_out'] == 0


def good_columns():
    """Return the columns of a valid observation cloud with landmark 7."""
    return [('id', np.uint32, [7]), ('range', np.float64, [Z[0]]),
            ('bearing', np.float64, [Z[1]])]


def without(name):
    """Return a cloud builder that leaves field ``name`` out."""
    return lambda stamp: make_cloud(stamp, [c for c in good_columns() if c[0] != name])


def retyped(name, dtype):
    """Return a cloud builder that stores field ``name`` as ``dtype``."""
    return lambda stamp: make_cloud(
        stamp, [(n, dtype if n == name else t, v) for n, t, v in good_columns()])


def edited(change):
    """Return a cloud builder that applies ``change(msg)`` to a valid cloud."""
    def build(stamp):
        msg = make_cloud(stamp, [(n, t, v * 2) for n, t, v in good_columns()])
        change(msg)
        return msg
    return build


def _set(**attributes):
    def change(msg):
        for name, value in attributes.items():
            setattr(msg, name, value)
    return change


def _field(name, **attributes):
    def change(msg):
        field, = [f for f in msg.fields if f.name == name]
        for key, value in attributes.items():
            setattr(field, key, value)
    return change


def _short_row_step(msg):
    msg.row_step = msg.width * msg.point_step - 8
    msg.data = bytes(msg.data)[:msg.row_step * msg.height]


BAD_MESSAGES = {
    # Without range or bearing a cloud is bearing-only or range-only (fuser.partial).
    'id_float32': ('unsupported_field_type', retyped('id', np.float32)),
    'range_int32': ('unsupported_field_type', retyped('range', np.int32)),
    'bearing_count_2': ('unsupported_field_type', edited(_field('bearing', count=2))),
    'range_variance_uint8': ('unsupported_field_type',
                             lambda stamp: make_cloud(stamp, good_columns() + [
                                 ('range_variance', np.uint8, [1])])),
    'data_short': ('data_length_mismatch',
                   edited(lambda msg: _set(data=bytes(msg.data)[:-1])(msg))),
    'data_long': ('data_length_mismatch',
                  edited(lambda msg: _set(data=bytes(msg.data) + bytes(8))(msg))),
    'row_step_short': ('data_length_mismatch', edited(_short_row_step)),
    'field_overruns_point': ('data_length_mismatch',
                             edited(lambda msg: _field('bearing', offset=msg.point_step - 4)(
                                 msg))),
    'wrong_frame': ('observation_wrong_frame',
                    lambda stamp: make_cloud(stamp, good_columns(), frame='camera')),
}


@pytest.mark.parametrize('case', list(BAD_MESSAGES))
def test_bad_observation_message_is_dropped(env, case):
    reason, build = BAD_MESSAGES[case]
    rig = textbook_rig(env, sensor_frame='laser')
    rig.pose(10.0, P1, P1_CASE2)
    rig.send_cloud(build(10.0))
    assert rig.problems() == {reason: 1}
    assert rig.counts['observations_in'] == 0
    rig.assert_no_more_landmarks(0, within=0.1)
    rig.send_cloud(make_cloud(10.0, good_columns(), frame='laser'))
    assert_landmarks(decode(rig.wait_landmarks(1)[0]), [(7, M_TEXTBOOK, PM_CASE2)], atol=1e-8)


def _orientation(**values):
    def change(msg):
        for key, value in values.items():
            setattr(msg.pose.pose.orientation, key, value)
    return change


def _position(**values):
    def change(msg):
        for key, value in values.items():
            setattr(msg.pose.pose.position, key, value)
    return change


def _covariance(**entries):
    def change(msg):
        for index, value in entries.items():
            msg.pose.covariance[int(index[1:])] = value
    return change


BAD_POSES = {
    'frame': ('pose_wrong_frame', lambda msg: setattr(msg.header, 'frame_id', 'odom')),
    'x_nan': ('pose_nonfinite', _position(x=NAN)),
    'y_inf': ('pose_nonfinite', _position(y=-INF)),
    'zero_quaternion': ('pose_bad_quaternion', _orientation(x=0.0, y=0.0, z=0.0, w=0.0)),
    'nan_quaternion': ('pose_bad_quaternion', _orientation(w=NAN)),
    'inf_quaternion': ('pose_bad_quaternion', _orientation(z=INF)),
    'asymmetric': ('pose_covariance_asymmetric', _covariance(i1=0.05)),
    'asymmetric_yaw': ('pose_covariance_asymmetric', _covariance(i5=0.01, i30=-0.01)),
    'negative_variance': ('pose_covariance_not_psd', _covariance(i35=-0.01)),
    'not_psd': ('pose_covariance_not_psd', _covariance(i1=1.0, i6=1.0)),
    'nan': ('pose_covariance_nonfinite', _covariance(i7=NAN)),
    'inf': ('pose_covariance_nonfinite', _covariance(i0=INF)),
}


@pytest.mark.parametrize('case', list(BAD_POSES))
def test_bad_pose_is_dropped(env, case):
    reason, change = BAD_POSES[case]
    rig = textbook_rig(env, max_wait_s=30.0)
    bad = pose_message(10.0, (5.0, 5.0, 1.0), P1_CASE2)
    change(bad)
    rig.send_pose(bad)
    assert rig.problems() == {reason: 1}
    assert rig.counts['poses_in'] == 0 and len(rig.node.observer.poses) == 0
    rig.observe(10.0, [7], [Z])
    rig.assert_no_more_landmarks(0, within=0.1)   # the bad pose is not used
    rig.pose(10.0, P1, P1_CASE2)                  # same stamp: not out of order
    assert_landmarks(decode(rig.wait_landmarks(1)[0]), [(7, M_TEXTBOOK, PM_CASE2)], atol=1e-8)
    assert rig.problems() == {reason: 1}


def test_big_endian_cloud_with_narrow_types(env):
    rig = textbook_rig(env)
    ids = [7, 300, -5]
    ranges = np.array([4.0, 2.5, 1.0], np.float32)
    bearings = np.array([0.7, -1.3, 0.0], np.float32)
    msg = make_cloud(10.0, [('id', np.int16, ids), ('range', np.float32, ranges),
                            ('bearing', np.float32, bearings)], bigendian=True)
    assert bytes(msg.data)[:2] == b'\x00\x07'   # really big-endian
    rig.pose(10.0, P1, P1_CASE2)
    rig.send_cloud(msg)
    got = decode(rig.wait_landmarks(1)[0])
    z = np.stack([ranges, bearings], axis=1).astype(np.float64)
    assert_landmarks(got, [(i, *expected_landmark(P1, P1_CASE2, z[k], R_TEXTBOOK))
                           for k, i in enumerate(ids[:2])])
    assert rig.problems() == {'invalid_id': 1}


def test_padded_rows_and_height_two(env):
    rig = textbook_rig(env)
    ids = [10, 11, 12, 13]
    z = np.array([[1.0, 0.1], [2.0, -0.2], [3.0, 0.3], [4.0, -0.4]])
    msg = make_cloud(10.0, [('id', np.uint16, ids), ('range', np.float32, z[:, 0]),
                            ('bearing', np.float64, z[:, 1])],
                     height=2, row_padding=8, field_order=['bearing', 'id', 'range'])
    assert (msg.height, msg.width, msg.row_step) == (2, 2, 2 * msg.point_step + 8)
    rig.pose(10.0, P1, P1_CASE2)
    rig.send_cloud(msg)
    got = decode(rig.wait_landmarks(1)[0])
    assert_landmarks(got, [(i, *expected_landmark(P1, P1_CASE2, z[k], R_TEXTBOOK))
                           for k, i in enumerate(ids)])
    assert rig.problems() == {}


def test_backlog_drops_the_oldest_waiting_messages(env):
    rig = textbook_rig(env, max_pending=3, max_wait_s=30.0)
    stamps = [10.0, 10.1, 10.2, 10.3, 10.4]
    for k, stamp in enumerate(stamps):
        rows = k + 1
        rig.observe(stamp, list(range(rows)), [[1.0 + j, 0.1 * j] for j in range(rows)])
    assert rig.problems() == {'backlog_dropped': 1 + 2}
    assert len(rig.node.observer.pending) == 3
    rig.assert_no_more_landmarks(0, within=0.1)
    rig.pose(9.95, P1, P1_CASE2)
    rig.pose(10.5, P1, P1_CASE2)
    messages = rig.wait_landmarks(3)
    assert [stamp_tuple(m.header.stamp) for m in messages] == [
        (10, 200_000_000), (10, 300_000_000), (10, 400_000_000)]
    assert [m.width for m in messages] == [3, 4, 5]
    assert rig.counts['landmarks_out'] == 12 and rig.counts['observations_in'] == 15
    rig.assert_no_more_landmarks(3, within=0.1)


def test_out_of_order_pose_is_dropped(env):
    rig = textbook_rig(env, max_wait_s=30.0, time_jump_s=1.0)
    z = np.array([2.0, 0.5])
    pose_b = (3.0, 1.0, 1.0)
    rig.pose(10.0, P1, POSE_A_COV)
    rig.pose(11.0, pose_b, POSE_B_COV)
    rig.pose(10.5, (50.0, 50.0, 0.0), ZERO3)     # 0.5 s back: dropped
    rig.pose(11.0, pose_b, POSE_B_COV)           # the same pose again: dropped
    assert rig.problems() == {'pose_out_of_order': 1, 'pose_duplicate': 1}
    assert len(rig.node.observer.poses) == 2
    rig.observe(10.5, [1], [z])
    pose, P_pose = interpolated(P1, POSE_A_COV, pose_b, POSE_B_COV, 0.5)
    assert_landmarks(decode(rig.wait_landmarks(1)[0]),
                     [(1, *expected_landmark(pose, P_pose, z, R_TEXTBOOK))])


def test_time_jump_back_clears_history_and_waiting_observations(env):
    rig = textbook_rig(env, max_wait_s=30.0, time_jump_s=1.0)
    z = np.array([2.0, 0.5])
    rig.pose(100.0, (40.0, 40.0, 0.0), ZERO3)
    rig.pose(101.0, (41.0, 40.0, 0.0), ZERO3)
    rig.observe(102.0, [1, 2], [z, z])           # waits for a pose after 102 s
    rig.pose(5.0, P1, POSE_A_COV)               # 96 s back: a bag loop, a sim reset
    assert rig.problems() == {'time_jump_back': 1, 'dropped_on_time_jump': 2}
    assert len(rig.node.observer.pending) == 0 and len(rig.node.observer.poses) == 1
    rig.pose(6.0, (2.0, 2.0, 1.0), POSE_B_COV)
    rig.observe(5.5, [3], [z])
    pose, P_pose = interpolated(P1, POSE_A_COV, (2.0, 2.0, 1.0), POSE_B_COV, 0.5)
    msg, = rig.wait_landmarks(1)
    assert_landmarks(decode(msg), [(3, *expected_landmark(pose, P_pose, z, R_TEXTBOOK))])


# 7. Markers ---------------------------------------------------------------------------------

def test_markers_show_each_landmark_ellipse_and_label(env):
    sigma = 3.0
    rig = textbook_rig(env, marker_rate_hz=50.0, marker_sigma=sigma, marker_lifetime_s=1.5)
    rig.pose(10.0, P1, P1_CASE2)
    rig.observe(10.0, [5], [Z])                 # nobody subscribes: no markers kept
    rig.wait_landmarks(1)
    markers = Collector(rig.tester, MarkerArray, 'landmark_markers')
    assert wait_for_match(env, [rig.node.marker_pub], [markers.subscription])
    assert not env.spin_until(lambda: markers.messages, NOT_BEFORE_S)

    z9 = np.array([2.0, -1.0])
    rig.observe(10.0, [7, 9], [Z, z9])
    assert env.spin_until(lambda: markers.messages)
    array = markers.messages[0]
    expected = {7: (M_TEXTBOOK, PM_CASE2),
                9: expected_landmark(P1, P1_CASE2, z9, R_TEXTBOOK)}
    ellipses = {m.id: m for m in array.markers if m.type == Marker.CYLINDER}
    labels = {m.id: m for m in array.markers if m.type == Marker.TEXT_VIEW_FACING}
    assert len(array.markers) == 4 and set(ellipses) == set(labels) == {7, 9}
    for landmark_id, (m, P_m) in expected.items():
        ellipse, label = ellipses[landmark_id], labels[landmark_id]
        for marker in (ellipse, label):
            assert marker.header.frame_id == 'map' and marker.action == Marker.ADD
            assert stamp_tuple(marker.header.stamp) == (10, 0)
            assert (marker.lifetime.sec, marker.lifetime.nanosec) == (1, 500_000_000)
            np.testing.assert_allclose([marker.pose.position.x, marker.pose.position.y], m,
                                       rtol=0, atol=1e-7)
        assert label.text == str(landmark_id)
        eigenvalues, eigenvectors = np.linalg.eigh(P_m)
        np.testing.assert_allclose([ellipse.scale.x, ellipse.scale.y],
                                   2.0 * sigma * np.sqrt(eigenvalues[::-1]), rtol=1e-7)
        q = ellipse.pose.orientation
        yaw = 2.0 * math.atan2(q.z, q.w)
        major = eigenvectors[:, 1]
        assert abs(math.sin(yaw - math.atan2(major[1], major[0]))) < 1e-6
        assert abs(q.x) < 1e-12 and abs(q.y) < 1e-12


def test_markers_enabled_at_run_time(env):
    rig = textbook_rig(env, marker_rate_hz=0.0)
    markers = Collector(rig.tester, MarkerArray, 'landmark_markers')
    assert wait_for_match(env, [rig.node.marker_pub], [markers.subscription])
    rig.pose(10.0, P1, P1_CASE2)
    rig.observe(10.0, [5], [Z])
    rig.wait_landmarks(1)
    assert not env.spin_until(lambda: markers.messages, NOT_BEFORE_S)   # disabled
    result, = rig.node.set_parameters([Parameter('marker_rate_hz', value=50.0)])
    assert result.successful, result.reason
    rig.observe(10.0, [7], [Z])
    assert env.spin_until(lambda: markers.messages)
    assert sorted((m.id, m.type) for m in markers.messages[0].markers) == [
        (7, Marker.CYLINDER), (7, Marker.TEXT_VIEW_FACING)]


# 8. The console script ----------------------------------------------------------------------

def observer_commands():
    """Return the ways to start the node as its own process, by name."""
    module = [sys.executable, '-m', 'landmark_ros.nodes.observer']
    scripts = [Path(sys.executable).parent / 'landmark_observer',
               REPO_ROOT / '.venv' / 'bin' / 'landmark_observer',
               REPO_ROOT / '.venv' / 'lib' / 'landmark_ros' / 'landmark_observer']
    found = [str(p) for p in scripts if p.is_file() and os.access(p, os.X_OK)]
    return {'module': module, 'console_script': found[:1]}


@pytest.mark.parametrize('how', ['module', 'console_script'])
def test_node_as_a_process_answers_and_exits_cleanly_on_sigint(env, tmp_path, how):
    command = observer_commands()[how]
    if not command:
        pytest.skip('the landmark_observer console script is not installed (pip install -e .)')
    command = command + ['--ros-args', '-r', '__ns:=/robotX', '-p', 'range_stddev:=0.5',
                         '-p', 'bearing_stddev:=0.2', '-p', 'max_wait_s:=5.0']
    tester = env.node('process_tester')
    pose_pub = tester.create_publisher(PoseWithCovarianceStamped, '/robotX/pose', 10)
    obs_pub = tester.create_publisher(PointCloud2, '/robotX/observations', 10)
    landmarks = Collector(tester, PointCloud2, '/robotX/landmarks')
    diagnostics = Collector(tester, DiagnosticArray, '/diagnostics')
    process_env = dict(os.environ, ROS_DOMAIN_ID=str(env.domain_id),
                       ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    stdout, stderr = tmp_path / 'stdout.txt', tmp_path / 'stderr.txt'
    with open(stdout, 'w') as out, open(stderr, 'w') as err:
        process = subprocess.Popen(command, env=process_env, stdout=out, stderr=err,
                                   cwd=tmp_path)
    try:
        assert wait_for_match(env, [pose_pub, obs_pub],
                              [landmarks.subscription, diagnostics.subscription], 20.0), \
            'no DDS match with the observer process: ' + stderr.read_text()
        # Best-effort inputs across processes: resend until the landmark comes back.
        deadline = time.monotonic() + 20.0
        while not landmarks.messages and time.monotonic() < deadline:
            assert process.poll() is None, stderr.read_text()
            pose_pub.publish(pose_message(10.0, P1, P1_CASE2))
            obs_pub.publish(observation_message(header(10.0, 'laser'), [7], [Z]))
            env.spin_until(lambda: landmarks.messages, 0.25)
        assert landmarks.messages, 'no landmarks from the observer process'
        msg = landmarks.messages[0]
        assert msg.header.frame_id == 'map' and stamp_tuple(msg.header.stamp) == (10, 0)
        assert_landmarks(decode(msg), [(7, M_TEXTBOOK, PM_CASE2)], atol=1e-8)
        assert env.spin_until(lambda: any(
            s.name == '/robotX/landmark_observer' for a in diagnostics.messages
            for s in a.status), 10.0)

        process.send_signal(signal.SIGINT)
        returncode = process.wait(timeout=15.0)
        assert returncode == 0, stderr.read_text()
        assert 'Traceback' not in stderr.read_text()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=10.0)


@pytest.mark.parametrize('override', [
    'range_stddev:=-1',       # integer: passes rclpy, refused by ObserverConfig
    'sensor_pose:=[1.0,2.0]',
    'range_stddev:=-1.0',     # double: refused by rclpy's declared range
    'max_pending:=0',
    'max_pending:=many',
])
def test_process_with_an_invalid_parameter_exits_with_code_2(env, override):
    command = [sys.executable, '-m', 'landmark_ros.nodes.observer', '--ros-args',
               '-p', override]
    process_env = dict(os.environ, ROS_DOMAIN_ID=str(env.domain_id),
                       ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    result = subprocess.run(command, env=process_env, capture_output=True, text=True,
                            timeout=30.0)
    assert 'Traceback' not in result.stderr, result.stderr
    assert 'landmark_observer: invalid parameters' in result.stderr
    assert result.returncode == 2
