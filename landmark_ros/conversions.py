"""Message fields to arrays, with the checks every node needs (no message imports)."""

import math

from landmark_ros.core.gaussian import COVARIANCE_PROBLEMS, covariance_status
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
