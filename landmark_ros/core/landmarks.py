"""
The chapter's operations on uncertain poses and landmarks.

Each function returns an estimate and its first-order covariance, propagated
through the Jacobians of ``pose2`` and ``sensors``. Inputs are independent.

Symbols
-------
pose, p1, p2 : robot poses in the world, shape (3,) or (N, 3).
P_pose, P1, P2 : their covariances, shape (3, 3) or (N, 3, 3).
sensor_pose : the sensor in the robot frame, shape (3,) or (N, 3), exact.
z : range-bearing observation, shape (2,) or (N, 2); R its noise covariance.
m : landmark in the world, shape (2,) or (N, 2); P_m its covariance.

"""

from typing import Optional, Tuple, Union

from landmark_ros.core import pose2, sensors
from landmark_ros.core.arrays import (as_matrices, as_vectors, common_batch_shape, sandwich,
                                      symmetric_2x2, to_batch)
import numpy as np
from numpy.typing import ArrayLike, NDArray


def sensor_in_world(
        pose: ArrayLike, P_pose: ArrayLike, sensor_pose: Optional[ArrayLike] = None,
) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Compose an exactly known sensor mounting into an uncertain robot pose.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    P_pose : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the pose.
    sensor_pose : array_like, shape (3,) or (N, 3), optional
        Sensor pose in the robot frame; ``None`` means the robot origin.

    Returns
    -------
    s : ndarray, shape (3,) or (N, 3)
        Sensor pose in the world.
    P_s : ndarray, shape (3, 3) or (N, 3, 3)

    """
    pose = as_vectors(pose, 3, 'pose')
    P_pose = as_matrices(P_pose, 3, 'P_pose')
    if sensor_pose is not None:
        sensor_pose = as_vectors(sensor_pose, 3, 'sensor_pose')
        J_s_pose, _ = pose2.compose_jacobians(pose, sensor_pose)
        pose, P_pose = pose2.compose(pose, sensor_pose), sandwich(J_s_pose, P_pose)
    shape = common_batch_shape([pose, sensor_pose], [P_pose])
    return to_batch(shape, pose, 1), to_batch(shape, P_pose, 2)


def polar_covariance(
        r: Union[float, NDArray[np.float64]], angle: Union[float, NDArray[np.float64]],
        R: NDArray[np.float64],
) -> NDArray[np.float64]:
    """
    Return the Cartesian covariance of a polar measurement ``(r, angle)``.

    ``J R J^T`` with ``J = [[cos, -r sin], [sin, r cos]]``, the Jacobian of
    ``sensors.polar_to_cartesian``, in closed form.

    Parameters
    ----------
    r : ndarray, shape () or (N,) [m]
        Range.
    angle : ndarray, shape () or (N,) [rad]
        The bearing in the frame the result is wanted in.
    R : ndarray, shape (2, 2) or (N, 2, 2)
        Covariance of ``(r, angle)``.

    Returns
    -------
    ndarray, shape (2, 2) or (N, 2, 2) [m^2]

    """
    cos, sin = np.cos(angle), np.sin(angle)
    return symmetric_2x2(*_polar_terms(cos, sin, r * cos, r * sin, R))


def lever_arm_covariance(
        e: NDArray[np.float64], P_pose: NDArray[np.float64],
) -> NDArray[np.float64]:
    """
    Return the covariance a pose error gives a point rigidly attached to the robot.

    A world point ``m`` fixed in the robot frame moves with the pose as
    ``J_m_pose = [[1, 0, -e_y], [0, 1, e_x]]`` where ``e = m - (x, y)`` is the lever
    arm from the robot origin; this returns ``J_m_pose P_pose J_m_pose^T`` in closed
    form.

    Parameters
    ----------
    e : ndarray, shape (2,) or (N, 2) [m]
        Lever arm from the robot origin to the point, in the world frame.
    P_pose : ndarray, shape (3, 3) or (N, 3, 3)
        Covariance of the pose.

    Returns
    -------
    ndarray, shape (2, 2) or (N, 2, 2) [m^2]

    """
    return symmetric_2x2(*_lever_arm_terms(e[..., 0], e[..., 1], P_pose))


def _lever_arm_terms(ex, ey, P_pose):
    # J = [[1, 0, -ey], [0, 1, ex]]; few operations, since small batches pay per call.
    xx, xy, yy = P_pose[..., 0, 0], P_pose[..., 0, 1], P_pose[..., 1, 1]
    xt, yt, tt = P_pose[..., 0, 2], P_pose[..., 1, 2], P_pose[..., 2, 2]
    ey_tt = ey * tt
    return (xx + ey * (ey_tt - 2.0 * xt),
            xy + ex * (xt - ey_tt) - ey * yt,
            yy + ex * (ex * tt + 2.0 * yt))


def _polar_terms(cos, sin, dx, dy, R):
    # J = [u w] with u = (cos, sin) and w = r (-sin, cos) = (-dy, dx).
    rr, rb, bb = R[..., 0, 0], 0.5 * (R[..., 0, 1] + R[..., 1, 0]), R[..., 1, 1]
    rr_cos, rr_sin, bb_dx, bb_dy = rr * cos, rr * sin, bb * dx, bb * dy
    return (cos * (rr_cos - 2.0 * rb * dy) + bb_dy * dy,
            cos * rr_sin + rb * (cos * dx - sin * dy) - bb_dx * dy,
            sin * (rr_sin + 2.0 * rb * dx) + bb_dx * dx)


def _world_terms(pose, P_pose, z, R, sensor_pose, R_extra=None):
    # landmark_from_observation and the sandwiches of its Jacobians (composed with the
    # mounting) in closed form, sharing cos and sin: the observer's hot path. The tests
    # check it against the generic Jacobians.
    s = pose if sensor_pose is None else pose2.compose(pose, sensor_pose)
    r = z[..., 0]
    angle = s[..., 2] + z[..., 1]
    cos, sin = np.cos(angle), np.sin(angle)
    dx, dy = r * cos, r * sin
    m = np.stack([s[..., 0] + dx, s[..., 1] + dy], axis=-1)
    if sensor_pose is None:
        pose_terms = _lever_arm_terms(dx, dy, P_pose)
    else:
        pose_terms = _lever_arm_terms(m[..., 0] - pose[..., 0], m[..., 1] - pose[..., 1], P_pose)
    if R_extra is not None:
        return (m, pose_terms, _polar_terms(cos, sin, dx, dy, R),
                _polar_terms(cos, sin, dx, dy, R_extra))
    return m, pose_terms, _polar_terms(cos, sin, dx, dy, R)


def _shape(pose, P_pose, z, R, sensor_pose, R_bias=None):
    return common_batch_shape([pose, z, sensor_pose], [P_pose, R, R_bias])


def _checked(pose, P_pose, z, R, sensor_pose):
    pose = as_vectors(pose, 3, 'pose')
    P_pose = as_matrices(P_pose, 3, 'P_pose')
    z = as_vectors(z, 2, 'z')
    R = as_matrices(R, 2, 'R')
    if sensor_pose is not None:
        sensor_pose = as_vectors(sensor_pose, 3, 'sensor_pose')
    sensors.check_range(z[..., 0])
    return pose, P_pose, z, R, sensor_pose


def landmark_to_world_parts(
        pose: ArrayLike, P_pose: ArrayLike, z: ArrayLike, R: ArrayLike,
        sensor_pose: Optional[ArrayLike] = None,
) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """
    Place an observed landmark in the world, keeping the two covariance terms apart.

    The pose term is shared by every observation made from the same pose (correlated
    errors); the sensor term is independent per observation. Their sum is the
    covariance ``landmark_to_world`` returns.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    P_pose : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the pose.
    z : array_like, shape (2,) or (N, 2)
        Range-bearing observation (range [m], bearing [rad]).
    R : array_like, shape (2, 2) or (N, 2, 2)
        Covariance of the observation noise.
    sensor_pose : array_like, shape (3,) or (N, 3), optional
        Sensor pose in the robot frame; ``None`` means the robot origin.

    Returns
    -------
    m : ndarray, shape (2,) or (N, 2)
    P_m_pose : ndarray, shape (2, 2) or (N, 2, 2)
        ``J_m_pose P_pose J_m_pose^T``.
    P_m_sensor : ndarray, shape (2, 2) or (N, 2, 2)
        ``J_m_z R J_m_z^T``.

    Raises
    ------
    ValueError
        If a range is below ``sensors.MIN_RANGE`` or a shape is wrong.

    """
    args = _checked(pose, P_pose, z, R, sensor_pose)
    m, pose_terms, sensor_terms = _world_terms(*args)
    shape = _shape(*args)
    return (to_batch(shape, m, 1), to_batch(shape, symmetric_2x2(*pose_terms), 2),
            to_batch(shape, symmetric_2x2(*sensor_terms), 2))


def landmark_to_world_dependent(
        pose: ArrayLike, P_pose: ArrayLike, z: ArrayLike, R: ArrayLike,
        R_bias: Optional[ArrayLike] = None,
        sensor_pose: Optional[ArrayLike] = None,
) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """
    Place observed landmarks in the world with their covariance and its dependent part.

    The dependent part is what errors shared between observations contribute: the
    pose term (every observation from that pose shares it) and a sensor bias term
    ``J_m_z R_bias J_m_z^T`` (a bias shared by all observations of the sensor). The
    total adds the independent noise term ``J_m_z R J_m_z^T``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Robot pose (x, y, theta).
    P_pose : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the pose.
    z : array_like, shape (2,) or (N, 2)
        Range-bearing observation (range [m], bearing [rad]).
    R : array_like, shape (2, 2) or (N, 2, 2)
        Covariance of the independent observation noise.
    R_bias : array_like, shape (2, 2) or (N, 2, 2), optional
        Covariance of the sensor bias; ``None`` for none.
    sensor_pose : array_like, shape (3,) or (N, 3), optional
        Sensor pose in the robot frame; ``None`` means the robot origin.

    Returns
    -------
    m : ndarray, shape (2,) or (N, 2)
    P_m : ndarray, shape (2, 2) or (N, 2, 2)
        Total covariance: pose, bias and noise terms.
    P_m_dep : ndarray, shape (2, 2) or (N, 2, 2)
        Pose and bias terms.

    Raises
    ------
    ValueError
        If a range is below ``sensors.MIN_RANGE`` or a shape is wrong.

    """
    pose, P_pose, z, R, sensor_pose = _checked(pose, P_pose, z, R, sensor_pose)
    if R_bias is not None:
        # The bias and the noise enter the same way: fold the bias into the noise for
        # the total, and evaluate it alone for the dependent part (same cos and sin).
        R_bias = as_matrices(R_bias, 2, 'R_bias')
        m, dep, total_sensor, bias = _world_terms(pose, P_pose, z, R + R_bias, sensor_pose,
                                                  R_bias)
        total = symmetric_2x2(*(d + n for d, n in zip(dep, total_sensor)))
        dep = tuple(d + b for d, b in zip(dep, bias))
    else:
        m, dep, noise = _world_terms(pose, P_pose, z, R, sensor_pose)
        total = symmetric_2x2(*(d + n for d, n in zip(dep, noise)))
    shape = _shape(pose, P_pose, z, R, sensor_pose, R_bias)
    return (to_batch(shape, m, 1), to_batch(shape, total, 2),
            to_batch(shape, symmetric_2x2(*dep), 2))


_BLOCK = 16384
"""Rows per block in ``landmark_to_world``: keeps the temporaries in the CPU cache."""


def landmark_to_world(
        pose: ArrayLike, P_pose: ArrayLike, z: ArrayLike, R: ArrayLike,
        sensor_pose: Optional[ArrayLike] = None,
) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Place an observed landmark in the world with its covariance.

    ``m = g(pose (+) sensor_pose, z)`` and
    ``P_m = J_m_pose P_pose J_m_pose^T + J_m_z R J_m_z^T``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    P_pose : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the pose.
    z : array_like, shape (2,) or (N, 2)
        Range-bearing observation (range [m], bearing [rad]).
    R : array_like, shape (2, 2) or (N, 2, 2)
        Covariance of the observation noise.
    sensor_pose : array_like, shape (3,) or (N, 3), optional
        Sensor pose in the robot frame; ``None`` means the robot origin.

    Returns
    -------
    m : ndarray, shape (2,) or (N, 2)
    P_m : ndarray, shape (2, 2) or (N, 2, 2)

    Raises
    ------
    ValueError
        If a range is below ``sensors.MIN_RANGE`` or a shape is wrong.

    """
    args = _checked(pose, P_pose, z, R, sensor_pose)
    shape = _shape(*args)
    if not shape or shape[0] <= _BLOCK:
        m, (pxx, pxy, pyy), (sxx, sxy, syy) = _world_terms(*args)
        return (to_batch(shape, m, 1),
                to_batch(shape, symmetric_2x2(pxx + sxx, pxy + sxy, pyy + syy), 2))
    count = shape[0]
    batched = [a is not None and a.ndim == d + 1 and len(a) > 1
               for a, d in zip(args, (1, 2, 1, 2, 1))]
    m = np.empty((count, 2))
    P_m = np.empty((count, 2, 2))
    for start in range(0, count, _BLOCK):
        rows = slice(start, start + _BLOCK)
        block = [a[rows] if batch else a for a, batch in zip(args, batched)]
        m[rows], (pxx, pxy, pyy), (sxx, sxy, syy) = _world_terms(*block)
        P_m[rows, 0, 0] = pxx + sxx
        P_m[rows, 0, 1] = P_m[rows, 1, 0] = pxy + sxy
        P_m[rows, 1, 1] = pyy + syy
    return m, P_m


def relative_pose(
        p1: ArrayLike, P1: ArrayLike, p2: ArrayLike, P2: ArrayLike, method: str = 'between',
) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the pose of robot 2 seen from robot 1, ``(-) p1 (+) p2``, with covariance.

    Parameters
    ----------
    p1 : array_like, shape (3,) or (N, 3)
        Pose of robot 1.
    P1 : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the first estimate.
    p2 : array_like, shape (3,) or (N, 3)
        Pose of robot 2.
    P2 : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the second estimate.
    method : {'between', 'composition'}
        ``'between'`` uses the direct inverse composition and its Jacobians;
        ``'composition'`` inverts ``p1`` first, then composes (two chained steps).
        Both give the same result.

    Returns
    -------
    p12 : ndarray, shape (3,) or (N, 3)
    P12 : ndarray, shape (3, 3) or (N, 3, 3)

    Raises
    ------
    ValueError
        If ``method`` is unknown or a shape is wrong.

    """
    p1, p2 = as_vectors(p1, 3, 'p1'), as_vectors(p2, 3, 'p2')
    P1, P2 = as_matrices(P1, 3, 'P1'), as_matrices(P2, 3, 'P2')
    if method == 'between':
        J_12_1, J_12_2 = pose2.between_jacobians(p1, p2)
        p12, P12 = pose2.between(p1, p2), sandwich(J_12_1, P1) + sandwich(J_12_2, P2)
    elif method == 'composition':
        p1_inv = pose2.inverse(p1)
        P1_inv = sandwich(pose2.inverse_jacobian(p1), P1)
        J_12_inv, J_12_2 = pose2.compose_jacobians(p1_inv, p2)
        p12 = pose2.compose(p1_inv, p2)
        P12 = sandwich(J_12_inv, P1_inv) + sandwich(J_12_2, P2)
    else:
        raise ValueError(f"method must be 'between' or 'composition', got {method!r}")
    shape = common_batch_shape([p1, p2], [P1, P2])
    return to_batch(shape, p12, 1), to_batch(shape, P12, 2)


def predict_observation(
        pose: ArrayLike, P_pose: ArrayLike, m: ArrayLike, P_m: ArrayLike,
        sensor_pose: Optional[ArrayLike] = None,
) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Predict the range-bearing observation of an uncertain landmark.

    ``z = h(pose (+) sensor_pose, m)`` and
    ``P_z = J_z_pose P_pose J_z_pose^T + J_z_m P_m J_z_m^T`` (add the sensor noise
    ``R`` to get the innovation covariance).

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    P_pose : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the pose.
    m : array_like, shape (2,) or (N, 2)
        Landmark position in the world.
    P_m : array_like, shape (2, 2) or (N, 2, 2)
        Covariance of the landmark.
    sensor_pose : array_like, shape (3,) or (N, 3), optional
        Sensor pose in the robot frame; ``None`` means the robot origin.

    Returns
    -------
    z : ndarray, shape (2,) or (N, 2)
    P_z : ndarray, shape (2, 2) or (N, 2, 2)

    Raises
    ------
    ValueError
        If the landmark is closer than ``sensors.MIN_RANGE`` to the sensor.

    """
    s, P_s = sensor_in_world(pose, P_pose, sensor_pose)
    m, P_m = as_vectors(m, 2, 'm'), as_matrices(P_m, 2, 'P_m')
    J_z_s, J_z_m = sensors.observe_jacobians(s, m)
    shape = common_batch_shape([s, m], [P_s, P_m])
    return (to_batch(shape, sensors.observe(s, m), 1),
            to_batch(shape, sandwich(J_z_s, P_s) + sandwich(J_z_m, P_m), 2))


def nees(m: ArrayLike, P_m: ArrayLike, m_true: ArrayLike) -> Union[float, NDArray[np.float64]]:
    """
    Return the normalised estimation error squared of estimates against truth.

    Parameters
    ----------
    m : array_like, shape (n,) or (N, n)
        Landmark position in the world.
    P_m : array_like, shape (n, n) or (N, n, n), positive definite
        Covariance of the landmark.
    m_true : array_like, shape (n,) or (N, n)
        True values.

    Returns
    -------
    float or ndarray, shape () or (N,)
        Chi-square with ``n`` degrees of freedom when the estimate is consistent.

    """
    from landmark_ros.core.gating import mahalanobis_sq
    return mahalanobis_sq(np.asarray(m_true), m, P_m)
