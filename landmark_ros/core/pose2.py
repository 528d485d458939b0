"""
Poses in the plane: composition (+), inverse composition (-) and Jacobians.

Symbols
-------
a, b : pose, shape (3,) or (N, 3), ``(x [m], y [m], theta [rad])``.
c : ``a (+) b``, the pose ``b`` given in the frame of ``a``, expressed in the
    frame ``a`` is given in.
p : point, shape (2,) or (N, 2), in the frame of ``pose``.
m : ``pose (+) p``, the same point in the frame ``pose`` is given in.

"""

import math
from typing import overload, Tuple, Union

from landmark_ros.core.arrays import as_vectors, batch_shape, matrix
import numpy as np
from numpy.typing import ArrayLike, NDArray


TWO_PI = 2.0 * math.pi


@overload
def wrap_angle(angle: float) -> float:
    ...


@overload
def wrap_angle(angle: Union[float, ArrayLike]) -> Union[float, NDArray[np.float64]]:
    ...


def wrap_angle(angle: Union[float, ArrayLike]) -> Union[float, NDArray[np.float64]]:
    """
    Wrap angles to ``[-pi, pi)``.

    Parameters
    ----------
    angle : float or ndarray [rad]
        Angles to wrap.

    Returns
    -------
    float or ndarray [rad], same shape

    """
    if isinstance(angle, (float, int)):
        # Plain floats stay plain floats, and are much faster than numpy scalars.
        wrapped = math.fmod(angle + math.pi, TWO_PI)
        wrapped = (wrapped + TWO_PI if wrapped < 0.0 else wrapped) - math.pi
        return wrapped - TWO_PI if wrapped >= math.pi else wrapped
    wrapped = np.mod(np.asarray(angle, dtype=np.float64) + np.pi, TWO_PI) - np.pi
    # mod() can round a tiny negative input up to exactly 2 pi.
    return np.where(wrapped >= np.pi, wrapped - TWO_PI, wrapped)[()]


def compose(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """
    Compose two poses: ``c = a (+) b``.

    Parameters
    ----------
    a : array_like, shape (3,) or (N, 3)
        First pose.
    b : array_like, shape (3,) or (N, 3)
        Second pose.

    Returns
    -------
    c : ndarray, shape (3,) or (N, 3)

    """
    a = as_vectors(a, 3, 'a')
    b = as_vectors(b, 3, 'b')
    cos, sin = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([
        a[..., 0] + cos * b[..., 0] - sin * b[..., 1],
        a[..., 1] + sin * b[..., 0] + cos * b[..., 1],
        wrap_angle(a[..., 2] + b[..., 2]),
    ], axis=-1)


def compose_jacobians(
        a: ArrayLike, b: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``a (+) b``.

    Parameters
    ----------
    a : array_like, shape (3,) or (N, 3)
        First pose.
    b : array_like, shape (3,) or (N, 3)
        Second pose.

    Returns
    -------
    J_c_a : ndarray, shape (3, 3) or (N, 3, 3)
    J_c_b : ndarray, shape (3, 3) or (N, 3, 3)

    """
    a = as_vectors(a, 3, 'a')
    b = as_vectors(b, 3, 'b')
    shape = batch_shape(a, b)
    cos, sin = np.cos(a[..., 2]), np.sin(a[..., 2])
    bx, by = b[..., 0], b[..., 1]
    J_c_a = matrix([
        [1.0, 0.0, -sin * bx - cos * by],
        [0.0, 1.0, cos * bx - sin * by],
        [0.0, 0.0, 1.0],
    ], shape)
    J_c_b = matrix([
        [cos, -sin, 0.0],
        [sin, cos, 0.0],
        [0.0, 0.0, 1.0],
    ], shape)
    return J_c_a, J_c_b


def inverse(a: ArrayLike) -> NDArray[np.float64]:
    """
    Invert a pose: ``(-) a``, so that ``a (+) ((-) a) = 0``.

    Parameters
    ----------
    a : array_like, shape (3,) or (N, 3)
        First pose.

    Returns
    -------
    ndarray, shape (3,) or (N, 3)

    """
    a = as_vectors(a, 3, 'a')
    x, y, theta = a[..., 0], a[..., 1], a[..., 2]
    cos, sin = np.cos(theta), np.sin(theta)
    return np.stack([-x * cos - y * sin, x * sin - y * cos, wrap_angle(-theta)], axis=-1)


def inverse_jacobian(a: ArrayLike) -> NDArray[np.float64]:
    """
    Return the Jacobian of ``(-) a`` with respect to ``a``.

    Parameters
    ----------
    a : array_like, shape (3,) or (N, 3)
        First pose.

    Returns
    -------
    J_inv_a : ndarray, shape (3, 3) or (N, 3, 3)

    """
    a = as_vectors(a, 3, 'a')
    x, y, theta = a[..., 0], a[..., 1], a[..., 2]
    cos, sin = np.cos(theta), np.sin(theta)
    return matrix([
        [-cos, -sin, x * sin - y * cos],
        [sin, -cos, x * cos + y * sin],
        [0.0, 0.0, -1.0],
    ], batch_shape(a))


def between(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """
    Return ``(-) a (+) b``: the pose ``b`` seen from the pose ``a``.

    Parameters
    ----------
    a : array_like, shape (3,) or (N, 3)
        First pose.
    b : array_like, shape (3,) or (N, 3)
        Second pose.

    Returns
    -------
    ndarray, shape (3,) or (N, 3)

    """
    a = as_vectors(a, 3, 'a')
    b = as_vectors(b, 3, 'b')
    cos, sin = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([
        cos * dx + sin * dy,
        -sin * dx + cos * dy,
        wrap_angle(b[..., 2] - a[..., 2]),
    ], axis=-1)


def between_jacobians(
        a: ArrayLike, b: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``(-) a (+) b``.

    Parameters
    ----------
    a : array_like, shape (3,) or (N, 3)
        First pose.
    b : array_like, shape (3,) or (N, 3)
        Second pose.

    Returns
    -------
    J_ab_a : ndarray, shape (3, 3) or (N, 3, 3)
    J_ab_b : ndarray, shape (3, 3) or (N, 3, 3)

    """
    a = as_vectors(a, 3, 'a')
    b = as_vectors(b, 3, 'b')
    cos, sin = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    shape = batch_shape(a, b)
    J_ab_a = matrix([
        [-cos, -sin, -sin * dx + cos * dy],
        [sin, -cos, -cos * dx - sin * dy],
        [0.0, 0.0, -1.0],
    ], shape)
    J_ab_b = matrix([
        [cos, sin, 0.0],
        [-sin, cos, 0.0],
        [0.0, 0.0, 1.0],
    ], shape)
    return J_ab_a, J_ab_b


def transform_point(pose: ArrayLike, point: ArrayLike) -> NDArray[np.float64]:
    """
    Express a point given in the frame of ``pose`` in the outer frame.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    point : array_like, shape (2,) or (N, 2) [m]
        Point in the frame of ``pose``.

    Returns
    -------
    m : ndarray, shape (2,) or (N, 2) [m]

    """
    pose = as_vectors(pose, 3, 'pose')
    point = as_vectors(point, 2, 'point')
    cos, sin = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    return np.stack([
        pose[..., 0] + cos * point[..., 0] - sin * point[..., 1],
        pose[..., 1] + sin * point[..., 0] + cos * point[..., 1],
    ], axis=-1)


def transform_point_jacobians(
        pose: ArrayLike, point: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``pose (+) point``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Pose (x, y, theta).
    point : array_like, shape (2,) or (N, 2) [m]
        Point in the frame of ``pose``.

    Returns
    -------
    J_m_pose : ndarray, shape (2, 3) or (N, 2, 3)
    J_m_point : ndarray, shape (2, 2) or (N, 2, 2)

    """
    pose = as_vectors(pose, 3, 'pose')
    point = as_vectors(point, 2, 'point')
    cos, sin = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    px, py = point[..., 0], point[..., 1]
    shape = batch_shape(pose, point)
    J_m_pose = matrix([
        [1.0, 0.0, -sin * px - cos * py],
        [0.0, 1.0, cos * px - sin * py],
    ], shape)
    J_m_point = matrix([
        [cos, -sin],
        [sin, cos],
    ], shape)
    return J_m_pose, J_m_point
