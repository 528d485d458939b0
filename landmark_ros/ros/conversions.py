"""Message fields to arrays, with the checks every node needs (no message imports)."""

import math

from landmark_ros.core.covariance import COVARIANCE_PROBLEMS, covariance_status
from landmark_ros.pipeline.limits import odometry_pose_missing
import numpy as np


POSE_COVARIANCE_INDICES = np.array([[0, 1, 5], [6, 7, 11], [30, 31, 35]])
"""Row-major indices of the (x, y, yaw) block in a 6x6 ROS pose covariance."""


class InputError(ValueError):
    """An input that must be rejected; ``reason`` is its counter name."""

    def __init__(self, reason, detail):
        super().__init__(f'{reason}: {detail}')
        self.reason = reason
        self.detail = detail


def stamp_ns(stamp):
    """Return a ``builtin_interfaces/Time`` as integer nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _split_seconds(seconds):
    sec = math.floor(seconds)
    nanosec = int(round((seconds - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return int(sec), nanosec


def set_stamp(stamp, seconds):
    """Set a ``builtin_interfaces/Time`` to ``seconds``, nanoseconds rounded."""
    stamp.sec, stamp.nanosec = _split_seconds(seconds)


def seconds_to_ns(seconds):
    """Return ``seconds`` as the integer nanoseconds a stamp set by ``set_stamp`` holds."""
    sec, nanosec = _split_seconds(seconds)
    return sec * 1_000_000_000 + nanosec


def set_planar_pose(msg_pose, pose):
    """Set a ``geometry_msgs/Pose`` to a planar pose ``(x, y, yaw)`` (z and roll, pitch 0)."""
    msg_pose.position.x, msg_pose.position.y = float(pose[0]), float(pose[1])
    msg_pose.orientation.z = math.sin(0.5 * float(pose[2]))
    msg_pose.orientation.w = math.cos(0.5 * float(pose[2]))


def planar_pose_covariance(P_pose):
    """Return the row-major 6x6 ROS pose covariance holding a (3, 3) (x, y, yaw) one."""
    covariance = np.zeros(36)
    covariance[POSE_COVARIANCE_INDICES] = P_pose
    return covariance.tolist()


def yaw_from_quaternion(x, y, z, w):
    """
    Return the yaw [rad] of a quaternion after normalising it.

    Raises
    ------
    InputError
        ``pose_bad_quaternion`` if its norm is zero or not finite.

    """
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(norm) or norm < 1e-9:
        raise InputError('pose_bad_quaternion', f'quaternion norm {norm}')
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def pose_from_msg(msg, world_frame):
    """
    Return the planar pose and its covariance from a PoseWithCovarianceStamped.

    Parameters
    ----------
    msg : geometry_msgs.msg.PoseWithCovarianceStamped
        The message to read.
    world_frame : str
        The frame the pose must be given in.

    Returns
    -------
    pose : ndarray, shape (3,)
    P_pose : ndarray, shape (3, 3)

    Raises
    ------
    InputError
        ``pose_wrong_frame``, ``pose_nonfinite``, ``pose_bad_quaternion``,
        ``pose_covariance_wrong_size`` or a ``covariance_*`` problem.

    """
    if msg.header.frame_id != world_frame:
        raise InputError('pose_wrong_frame',
                         f"pose in frame '{msg.header.frame_id}', expected '{world_frame}'")
    position, q = msg.pose.pose.position, msg.pose.pose.orientation
    if not (math.isfinite(position.x) and math.isfinite(position.y)):
        raise InputError('pose_nonfinite', f'position ({position.x}, {position.y})')
    yaw = yaw_from_quaternion(q.x, q.y, q.z, q.w)
    covariance = np.asarray(msg.pose.covariance, dtype=np.float64)
    if covariance.size != 36:
        raise InputError('pose_covariance_wrong_size', f'{covariance.size} entries, not 36')
    P_pose = covariance[POSE_COVARIANCE_INDICES]
    status = int(covariance_status(P_pose))
    if status:
        raise InputError(f'pose_{COVARIANCE_PROBLEMS[status]}',
                         f'(x, y, yaw) block {P_pose.tolist()}')
    return np.array([position.x, position.y, yaw]), P_pose


def pose_from_odometry(msg, world_frame, base_frame=''):
    """
    Return the planar pose and its covariance from a nav_msgs/Odometry message.

    The pose part is read with every check of ``pose_from_msg`` (its header frame must
    be ``world_frame``, its 6x6 row-major covariance gives the (x, y, yaw) block); the
    twist is ignored. A message whose pose is the origin with an all-zero covariance
    carries no pose (twist-only odometry, e.g. wheel encoders): it is refused as
    ``odometry_pose_missing`` instead of being taken as an exact pose at the origin.

    Parameters
    ----------
    msg : nav_msgs.msg.Odometry
        The message to read.
    world_frame : str
        The frame the pose must be given in (``header.frame_id``).
    base_frame : str
        The robot frame ``child_frame_id`` must name; '' accepts any.

    Returns
    -------
    pose : ndarray, shape (3,)
    P_pose : ndarray, shape (3, 3)

    Raises
    ------
    InputError
        ``pose_wrong_child_frame``, ``odometry_pose_missing``, or any reason of
        ``pose_from_msg``.

    """
    pose, P_pose = pose_from_msg(msg, world_frame)
    if odometry_pose_missing(pose, np.asarray(msg.pose.covariance, dtype=np.float64)):
        raise InputError('odometry_pose_missing',
                         'odometry with a zero pose and a zero pose covariance (twist only): '
                         'not a pose; use a pose source (a localizer, a fused odometry)')
    if base_frame and msg.child_frame_id != base_frame:
        raise InputError('pose_wrong_child_frame',
                         f"odometry of frame '{msg.child_frame_id}', expected '{base_frame}'")
    return pose, P_pose
