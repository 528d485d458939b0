"""Tests of pipeline.pose_buffer: interpolation and lookup by stamp."""

import math

from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.pipeline import pose_buffer
import numpy as np
import pytest


# --- pose_buffer ---------------------------------------------------------------------------------

S = 1_000_000_000   # ns per second


def _cov(k):
    return np.diag([0.01, 0.02, 0.001]) * (1 + k)


def _buffer(stamps, poses, duration=100 * S, gap=S // 10, max_size=10000):
    buf = pose_buffer.PoseBuffer(duration, gap, max_size)
    for k, (stamp, pose) in enumerate(zip(stamps, poses)):
        buf.add(stamp, np.array(pose, float), _cov(k))
    return buf


def test_interpolate_position_linear_and_covariance_linear():
    p0, p1 = np.array([0.0, 1.0, 0.1]), np.array([2.0, -3.0, 0.5])
    for f in (0.0, 0.25, 0.5, 1.0):
        pose, P = pose_buffer.interpolate(p0, _cov(0), p1, _cov(3), f)
        np.testing.assert_allclose(pose, [2.0 * f, 1.0 - 4.0 * f, 0.1 + 0.4 * f], rtol=0,
                                   atol=1e-15)
        np.testing.assert_allclose(P, (1 - f) * _cov(0) + f * _cov(3), rtol=0, atol=1e-15)


@pytest.mark.parametrize('theta0, theta1, f, expected', [
    (3.0, -3.0, 0.5, math.pi),                       # across +-pi, not through 0
    (-3.0, 3.0, 0.5, math.pi),
    (3.0, -3.0, 0.25, 3.0 + 0.25 * (2 * math.pi - 6.0)),
    (-3.1, 3.1, 0.5, math.pi),
    (0.2, -0.2, 0.5, 0.0),
    (-math.pi, math.pi - 1e-9, 0.5, -math.pi),
    (1.0, 1.0 + 3.0, 0.5, 2.5),
])
def test_interpolate_yaw_on_the_shortest_arc(theta0, theta1, f, expected):
    pose, _ = pose_buffer.interpolate(np.array([0.0, 0.0, theta0]), _cov(0),
                                      np.array([0.0, 0.0, theta1]), _cov(1), f)
    assert -math.pi <= pose[2] < math.pi
    assert abs(wrap_angle(pose[2] - expected)) < 1e-9


def test_lookup_statuses():
    buf = pose_buffer.PoseBuffer(100 * S, S // 10)
    assert buf.lookup(5 * S).status == pose_buffer.WAIT          # empty
    assert buf.newest_ns is None and len(buf) == 0
    poses = [[0.0, 0.0, 0.0], [1.0, 2.0, 0.5], [3.0, 2.0, 1.0]]
    buf = _buffer([10 * S, 11 * S, 13 * S], poses)
    assert buf.newest_ns == 13 * S and len(buf) == 3
    found = buf.lookup(11 * S)                                    # exact stamp
    assert found.status == pose_buffer.FOUND
    np.testing.assert_array_equal(found.pose, poses[1])
    np.testing.assert_array_equal(found.P_pose, _cov(1))
    mid = buf.lookup(12 * S)                                      # interpolated
    assert mid.status == pose_buffer.FOUND
    np.testing.assert_allclose(mid.pose, [2.0, 2.0, 0.75], rtol=0, atol=1e-15)
    np.testing.assert_allclose(mid.P_pose, 0.5 * (_cov(1) + _cov(2)), rtol=0, atol=1e-15)
    quarter = buf.lookup(10 * S + S // 4)
    np.testing.assert_allclose(quarter.pose, [0.25, 0.5, 0.125], rtol=0, atol=1e-15)
    # Newer than every pose: wait, also just after the newest.
    assert buf.lookup(13 * S + 1).status == pose_buffer.WAIT
    assert buf.lookup(20 * S).status == pose_buffer.WAIT
    # Older than the buffer: the oldest pose within the gap, else too old.
    early = buf.lookup(10 * S - S // 10)
    assert early.status == pose_buffer.FOUND
    np.testing.assert_array_equal(early.pose, poses[0])
    assert buf.lookup(10 * S - S // 10 - 1).status == pose_buffer.TOO_OLD
    assert buf.lookup(0).status == pose_buffer.TOO_OLD
    assert buf.lookup(0).pose is None


def test_lookup_final_takes_the_newest_within_the_gap():
    poses = [[0.0, 0.0, 0.0], [1.0, 2.0, 0.5]]
    buf = _buffer([10 * S, 11 * S], poses)
    late = buf.lookup(11 * S + S // 10, final=True)
    assert late.status == pose_buffer.FOUND
    np.testing.assert_array_equal(late.pose, poses[1])
    np.testing.assert_array_equal(late.P_pose, _cov(1))
    assert buf.lookup(11 * S + S // 10).status == pose_buffer.WAIT
    assert buf.lookup(11 * S + S // 10 + 1, final=True).status == pose_buffer.WAIT
    # final changes nothing inside the buffer.
    np.testing.assert_array_equal(buf.lookup(10 * S, final=True).pose, poses[0])


def test_lookup_returns_copies():
    buf = _buffer([S, 2 * S], [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    found = buf.lookup(S)
    found.pose[:] = 99.0
    found.P_pose[:] = 99.0
    again = buf.lookup(S)
    np.testing.assert_array_equal(again.pose, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(again.P_pose, _cov(0))


def test_trimming_by_duration_and_size():
    buf = pose_buffer.PoseBuffer(5 * S, 0)
    for k in range(11):
        buf.add(k * S, np.array([k, 0.0, 0.0]), _cov(0))
    assert len(buf) == 6                         # stamps 5..10 s: newest - duration kept
    assert buf.lookup(5 * S).status == pose_buffer.FOUND
    assert buf.lookup(5 * S - 1).status == pose_buffer.TOO_OLD
    buf = pose_buffer.PoseBuffer(100 * S, 0, max_size=4)
    for k in range(10):
        buf.add(k * S, np.array([k, 0.0, 0.0]), _cov(0))
    assert len(buf) == 4
    np.testing.assert_array_equal(buf.lookup(6 * S).pose, [6.0, 0.0, 0.0])
    assert buf.lookup(5 * S).status == pose_buffer.TOO_OLD
    buf.clear()
    assert len(buf) == 0 and buf.lookup(6 * S).status == pose_buffer.WAIT


def test_add_refuses_non_increasing_stamps():
    buf = _buffer([S, 2 * S], [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    for stamp in (2 * S, S, 0):
        with pytest.raises(ValueError, match='not newer'):
            buf.add(stamp, np.zeros(3), _cov(0))
    assert len(buf) == 2 and buf.newest_ns == 2 * S
    buf.add(2 * S + 1, np.zeros(3), _cov(0))
    assert len(buf) == 3


def test_integer_stamps_are_exact_at_large_values():
    base = 1_700_000_000 * S     # a wall-clock time in ns: beyond float64's exact integers
    buf = _buffer([base, base + 2], [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    mid = buf.lookup(base + 1)
    assert mid.status == pose_buffer.FOUND
    np.testing.assert_allclose(mid.pose, [1.0, 0.0, 0.0], rtol=0, atol=1e-15)
    assert buf.lookup(base + 3).status == pose_buffer.WAIT
