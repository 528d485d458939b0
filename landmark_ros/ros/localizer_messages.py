"""Messages of ``landmark_localizer``: odometry in, pose and map-to-odom correction out."""

import math

from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from landmark_ros.localizer.update import BEARING, RANGE, RANGE_BEARING
from landmark_ros.ros.conversions import (InputError, planar_pose_covariance, pose_from_msg,
                                          set_planar_pose, yaw_from_quaternion)
import numpy as np

_TWIST_INDICES = np.ix_([0, 1, 5], [0, 1, 5])


def odometry_motion(msg, previous, odom_frame):
    """
    Return the odometry pose (3,) or None, the twist (2,) and the motion covariance.

    The pose counts when the message maintains one (a pose in ``odom_frame`` that is
    not the origin or was not the origin before): then the localizer takes the delta
    of consecutive poses. The twist (forward speed, yaw rate) serves otherwise. The
    motion covariance is the twist covariance (vx, vy, yaw rate) times dt^2 when it is
    not zero, else None (the odometry model of the config).

    Parameters
    ----------
    msg : nav_msgs.msg.Odometry
        The message.
    previous : tuple (stamp_ns, bool) or None
        The previous message's stamp and whether it held a pose.
    odom_frame : str
        The odometry frame ('' accepts any).

    Raises
    ------
    InputError
        ``odometry_nonfinite`` or ``odometry_wrong_frame``.

    """
    if odom_frame and msg.header.frame_id != odom_frame:
        raise InputError('odometry_wrong_frame',
                         f"odometry in '{msg.header.frame_id}', expected '{odom_frame}'")
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    pose = np.array([p.x, p.y, yaw_from_quaternion(q.x, q.y, q.z, q.w)])
    twist = np.array([msg.twist.twist.linear.x, msg.twist.twist.angular.z])
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(twist))):
        raise InputError('odometry_nonfinite', f'pose {pose.tolist()} twist {twist.tolist()}')
    has_pose = bool(np.any(pose)) or bool(previous and previous[1])
    Q = None
    covariance = np.asarray(msg.twist.covariance, dtype=np.float64)
    if previous is not None and covariance.size == 36 and np.any(covariance):
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        dt = max(stamp - previous[0], 0) * 1e-9
        Q = covariance.reshape(6, 6)[_TWIST_INDICES] * dt * dt
    return (pose if has_pose else None), twist, Q, has_pose


def observation_rows(columns):
    """
    Return ids (N,), z (N, 2), kind (N,) and R (N, 2, 2) or None from cloud columns.

    A row with a finite range and bearing is range-bearing; with only one of them it is
    a partial observation (range-only or bearing-only); with neither it is dropped (its
    kind is -1). Rows without an ``id`` field take ``UNKNOWN_ID``.
    """
    n = len(next(iter(columns.values()))) if columns else 0
    r = columns.get('range', np.full(n, np.nan))
    b = columns.get('bearing', np.full(n, np.nan))
    ids = columns.get('id', np.full(n, 0xFFFFFFFF, np.int64))
    has_r, has_b = np.isfinite(r), np.isfinite(b)
    kind = np.where(has_r & has_b, RANGE_BEARING,
                    np.where(has_r, RANGE, np.where(has_b, BEARING, -1)))
    R = None
    if 'range_variance' in columns and 'bearing_variance' in columns:
        R = np.zeros((n, 2, 2))
        R[:, 0, 0], R[:, 1, 1] = columns['range_variance'], columns['bearing_variance']
        if 'range_bearing_covariance' in columns:
            R[:, 0, 1] = R[:, 1, 0] = columns['range_bearing_covariance']
    return ids, np.column_stack([r, b]), kind, R


def pose_message(header, x, P, out=None):
    """Return a PoseWithCovarianceStamped of pose ``x`` (3,) with covariance ``P`` (3, 3)."""
    msg = out if out is not None else PoseWithCovarianceStamped()
    msg.header = header
    set_planar_pose(msg.pose.pose, x)
    msg.pose.covariance = planar_pose_covariance(P)
    return msg


def transform_message(header, child_frame, x):
    """Return a TransformStamped of the planar pose ``x`` (3,) of ``child_frame``."""
    msg = TransformStamped()
    msg.header = header
    msg.child_frame_id = child_frame
    msg.transform.translation.x, msg.transform.translation.y = float(x[0]), float(x[1])
    msg.transform.rotation.z = math.sin(x[2] / 2.0)
    msg.transform.rotation.w = math.cos(x[2] / 2.0)
    return msg


def initial_pose(msg, map_frame):
    """Return the pose and covariance of an ``initialpose`` message (``pose_from_msg``)."""
    return pose_from_msg(msg, map_frame)
