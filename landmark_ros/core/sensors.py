"""
Sensor models: range-bearing, range-only and bearing-only, with Jacobians.

Symbols
-------
pose : sensor pose in the world, shape (3,) or (N, 3).
m : landmark position in the world, shape (2,) or (N, 2) [m].
z : observation ``(range [m], bearing [rad])``, shape (2,) or (N, 2).
p : the same point in Cartesian sensor coordinates, shape (2,) or (N, 2) [m].

``h`` is ``observe`` (predict ``z`` from ``pose`` and ``m``), ``g`` is
``landmark_from_observation`` (its inverse in ``m``). Range-only and bearing-only
observations have shape (1,) or (N, 1) so that every model is a vector model.

"""

from typing import Tuple

from landmark_ros.core.arrays import as_vectors, batch_shape, matrix
from landmark_ros.core.pose2 import wrap_angle
import numpy as np
from numpy.typing import ArrayLike, NDArray


MIN_RANGE = 1e-6
"""Smallest range [m] the models accept: the bearing is undefined at zero range."""


def check_range(r: ArrayLike, name: str = 'range') -> None:
    """
    Raise if any range is below ``MIN_RANGE`` (at or near zero, or negative).

    Parameters
    ----------
    r : ndarray [m]
        Range.
    name : str
        Name used in error messages.

    Raises
    ------
    ValueError
        Naming the first offending index and value.

    """
    too_short = np.asarray(r) < MIN_RANGE
    if too_short.any():
        bad = np.flatnonzero(too_short)
        value = np.asarray(r).reshape(-1)[bad[0]]
        raise ValueError(
            f'{name} must be at least {MIN_RANGE} m (the bearing and its Jacobian are '
            f'undefined at zero range): {bad.size} value(s) below, first at index '
            f'{bad[0]}: {value!r}')


def range_noise_variance(r: ArrayLike, variance: float, variance_per_m2: float = 0.0,
                         variance_per_m4: float = 0.0) -> NDArray[np.float64]:
    """
    Return the range noise variance at range ``r``, shape of ``r`` [m^2].

    ``variance + variance_per_m2 r^2 + variance_per_m4 r^4``: standard deviations ``a``,
    ``k r`` and ``c r^2`` added in quadrature, given as ``a^2``, ``k^2`` and ``c^2`` (the
    range model of ``observer`` and ``localizer``; ``mrclam.range_calibration`` fits it).
    """
    r2 = np.square(np.asarray(r, dtype=np.float64))
    return variance + r2 * (variance_per_m2 + variance_per_m4 * r2)


def polar_to_cartesian(z: ArrayLike) -> NDArray[np.float64]:
    """
    Convert ``(range, bearing)`` to ``(x, y)``.

    Parameters
    ----------
    z : array_like, shape (2,) or (N, 2)
        Range-bearing observation (range [m], bearing [rad]).

    Returns
    -------
    p : ndarray, shape (2,) or (N, 2) [m]

    Raises
    ------
    ValueError
        If a range is below ``MIN_RANGE``.

    """
    z = as_vectors(z, 2, 'z')
    check_range(z[..., 0])
    return np.stack([z[..., 0] * np.cos(z[..., 1]), z[..., 0] * np.sin(z[..., 1])], axis=-1)


def polar_to_cartesian_jacobian(z: ArrayLike) -> NDArray[np.float64]:
    """
    Return the Jacobian of ``polar_to_cartesian``.

    Parameters
    ----------
    z : array_like, shape (2,) or (N, 2)
        Range-bearing observation (range [m], bearing [rad]).

    Returns
    -------
    J_p_z : ndarray, shape (2, 2) or (N, 2, 2)

    Raises
    ------
    ValueError
        If a range is below ``MIN_RANGE``.

    """
    z = as_vectors(z, 2, 'z')
    check_range(z[..., 0])
    r, cos, sin = z[..., 0], np.cos(z[..., 1]), np.sin(z[..., 1])
    return matrix([[cos, -r * sin], [sin, r * cos]], batch_shape(z))


def cartesian_to_polar(p: ArrayLike) -> NDArray[np.float64]:
    """
    Convert ``(x, y)`` to ``(range, bearing)``.

    Parameters
    ----------
    p : array_like, shape (2,) or (N, 2) [m]
        Point in Cartesian sensor coordinates.

    Returns
    -------
    z : ndarray, shape (2,) or (N, 2)

    Raises
    ------
    ValueError
        If a point is closer than ``MIN_RANGE`` to the origin.

    """
    p = as_vectors(p, 2, 'p')
    r = np.hypot(p[..., 0], p[..., 1])
    check_range(r)
    return np.stack([r, wrap_angle(np.arctan2(p[..., 1], p[..., 0]))], axis=-1)


def cartesian_to_polar_jacobian(p: ArrayLike) -> NDArray[np.float64]:
    """
    Return the Jacobian of ``cartesian_to_polar``.

    Parameters
    ----------
    p : array_like, shape (2,) or (N, 2) [m]
        Point in Cartesian sensor coordinates.

    Returns
    -------
    J_z_p : ndarray, shape (2, 2) or (N, 2, 2)

    Raises
    ------
    ValueError
        If a point is closer than ``MIN_RANGE`` to the origin.

    """
    p = as_vectors(p, 2, 'p')
    x, y = p[..., 0], p[..., 1]
    r2 = x * x + y * y
    r = np.sqrt(r2)
    check_range(r)
    return matrix([[x / r, y / r], [-y / r2, x / r2]], batch_shape(p))


def _offsets(pose, m):
    pose = as_vectors(pose, 3, 'pose')
    m = as_vectors(m, 2, 'm')
    dx, dy = m[..., 0] - pose[..., 0], m[..., 1] - pose[..., 1]
    r2 = dx * dx + dy * dy
    r = np.sqrt(r2)
    check_range(r, 'range from pose to landmark')
    return pose, dx, dy, r, r2, batch_shape(pose, m)


def observe(pose: ArrayLike, m: ArrayLike) -> NDArray[np.float64]:
    """
    Predict the range-bearing observation of ``m`` from ``pose``: ``z = h(pose, m)``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    m : array_like, shape (2,) or (N, 2) [m]
        Landmark position in the world.

    Returns
    -------
    z : ndarray, shape (2,) or (N, 2)

    Raises
    ------
    ValueError
        If the landmark is closer than ``MIN_RANGE`` to the sensor.

    """
    pose, dx, dy, r, _, _ = _offsets(pose, m)
    return np.stack([r, wrap_angle(np.arctan2(dy, dx) - pose[..., 2])], axis=-1)


def observe_jacobians(
        pose: ArrayLike, m: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``observe``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    m : array_like, shape (2,) or (N, 2) [m]
        Landmark position in the world.

    Returns
    -------
    J_z_pose : ndarray, shape (2, 3) or (N, 2, 3)
    J_z_m : ndarray, shape (2, 2) or (N, 2, 2)

    Raises
    ------
    ValueError
        If the landmark is closer than ``MIN_RANGE`` to the sensor.

    """
    _, dx, dy, r, r2, shape = _offsets(pose, m)
    J_z_m = matrix([[dx / r, dy / r], [-dy / r2, dx / r2]], shape)
    J_z_pose = np.concatenate([-J_z_m, matrix([[0.0], [-1.0]], shape)], axis=-1)
    return J_z_pose, J_z_m


def observe_range(pose: ArrayLike, m: ArrayLike) -> NDArray[np.float64]:
    """
    Predict a range-only observation: ``z = (range,)``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    m : array_like, shape (2,) or (N, 2) [m]
        Landmark position in the world.

    Returns
    -------
    z : ndarray, shape (1,) or (N, 1) [m]

    Raises
    ------
    ValueError
        If the landmark is closer than ``MIN_RANGE`` to the sensor.

    """
    return observe(pose, m)[..., :1]


def observe_range_jacobians(
        pose: ArrayLike, m: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``observe_range``.

    Returns
    -------
    J_z_pose : ndarray, shape (1, 3) or (N, 1, 3)
    J_z_m : ndarray, shape (1, 2) or (N, 1, 2)

    """
    J_z_pose, J_z_m = observe_jacobians(pose, m)
    return J_z_pose[..., :1, :], J_z_m[..., :1, :]


def observe_bearing(pose: ArrayLike, m: ArrayLike) -> NDArray[np.float64]:
    """
    Predict a bearing-only observation: ``z = (bearing,)``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    m : array_like, shape (2,) or (N, 2) [m]
        Landmark position in the world.

    Returns
    -------
    z : ndarray, shape (1,) or (N, 1) [rad]

    Raises
    ------
    ValueError
        If the landmark is closer than ``MIN_RANGE`` to the sensor.

    """
    return observe(pose, m)[..., 1:]


def observe_bearing_jacobians(
        pose: ArrayLike, m: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``observe_bearing``.

    Returns
    -------
    J_z_pose : ndarray, shape (1, 3) or (N, 1, 3)
    J_z_m : ndarray, shape (1, 2) or (N, 1, 2)

    """
    J_z_pose, J_z_m = observe_jacobians(pose, m)
    return J_z_pose[..., 1:, :], J_z_m[..., 1:, :]


def landmark_from_observation(pose: ArrayLike, z: ArrayLike) -> NDArray[np.float64]:
    """
    Place the landmark seen as ``z`` from ``pose``: ``m = g(pose, z)``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    z : array_like, shape (2,) or (N, 2)
        Range-bearing observation (range [m], bearing [rad]).

    Returns
    -------
    m : ndarray, shape (2,) or (N, 2) [m]

    Raises
    ------
    ValueError
        If a range is below ``MIN_RANGE``.

    """
    pose = as_vectors(pose, 3, 'pose')
    z = as_vectors(z, 2, 'z')
    check_range(z[..., 0])
    angle = pose[..., 2] + z[..., 1]
    return np.stack([
        pose[..., 0] + z[..., 0] * np.cos(angle),
        pose[..., 1] + z[..., 0] * np.sin(angle),
    ], axis=-1)


def landmark_from_observation_jacobians(
        pose: ArrayLike, z: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``landmark_from_observation``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    z : array_like, shape (2,) or (N, 2)
        Range-bearing observation (range [m], bearing [rad]).

    Returns
    -------
    J_m_pose : ndarray, shape (2, 3) or (N, 2, 3)
    J_m_z : ndarray, shape (2, 2) or (N, 2, 2)

    Raises
    ------
    ValueError
        If a range is below ``MIN_RANGE``.

    """
    pose = as_vectors(pose, 3, 'pose')
    z = as_vectors(z, 2, 'z')
    check_range(z[..., 0])
    r, angle = z[..., 0], pose[..., 2] + z[..., 1]
    cos, sin = np.cos(angle), np.sin(angle)
    shape = batch_shape(pose, z)
    J_m_pose = matrix([[1.0, 0.0, -r * sin], [0.0, 1.0, r * cos]], shape)
    J_m_z = matrix([[cos, -r * sin], [sin, r * cos]], shape)
    return J_m_pose, J_m_z
