"""
Closed-form geometry for the first guess of a landmark from views (``partial``).

Two rays, two circles, a ray and a circle, and linear trilateration of three or more
circles. Private to ``core``: ``partial`` is the interface.
"""

from typing import Tuple, Union

from landmark_ros.core import sensors
from landmark_ros.core.pose2 import wrap_angle
import numpy as np
from numpy.typing import ArrayLike, NDArray

_COLLINEAR = 1e-9
"""Centres whose smaller singular value is below this fraction of the larger are collinear."""


def intersect_rays(
        s1: ArrayLike, phi1: ArrayLike, s2: ArrayLike, phi2: ArrayLike
) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """
    Intersect pairs of rays ``s1 + t1 d(phi1)`` and ``s2 + t2 d(phi2)``.

    Source: the 2D line intersection by cross products (Goldman, "Intersection of two
    lines in three-space", *Graphics Gems*, 1990, specialised to the plane).

    Parameters
    ----------
    s1, s2 : array_like, shape (2,) or (N, 2) [m]
        Ray origins (the sensor positions).
    phi1, phi2 : array_like, shape () or (N,) [rad]
        Ray directions in the world (sensor heading plus bearing).

    Returns
    -------
    point : ndarray, shape (2,) or (N, 2) [m]
        Intersection of the two lines; ``inf`` or NaN for parallel rays.
    t1, t2 : ndarray, shape () or (N,) [m]
        Distances along each ray; the rays cross in front of both where both are
        positive.
    crossing_angle : ndarray, shape () or (N,) [rad]
        Angle between the two lines in [0, pi/2]: 0 for parallel (or opposite) rays,
        where the intersection is undetermined.

    """
    s1, s2 = np.asarray(s1, dtype=np.float64), np.asarray(s2, dtype=np.float64)
    d1 = np.stack([np.cos(phi1), np.sin(phi1)], axis=-1)
    d2 = np.stack([np.cos(phi2), np.sin(phi2)], axis=-1)
    delta = s2 - s1
    cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        t1 = (delta[..., 0] * d2[..., 1] - delta[..., 1] * d2[..., 0]) / cross
        t2 = (delta[..., 0] * d1[..., 1] - delta[..., 1] * d1[..., 0]) / cross
    angle = np.abs(wrap_angle(np.asarray(phi2) - np.asarray(phi1)))
    crossing = np.minimum(angle, np.pi - angle)
    return s1 + t1[..., None] * d1, t1, t2, crossing


def intersect_circles(
        c1: ArrayLike, r1: ArrayLike, c2: ArrayLike, r2: ArrayLike
) -> Tuple[NDArray[np.float64], Union[np.bool_, NDArray[np.bool_]]]:
    """
    Intersect pairs of circles.

    Source: Bourke, "Intersection of two circles", 1997 (the radical line).

    Parameters
    ----------
    c1, c2 : array_like, shape (2,) or (N, 2) [m]
        Centres, at least ``sensors.MIN_RANGE`` apart.
    r1, r2 : array_like, shape () or (N,) [m]
        Radii.

    Returns
    -------
    points : ndarray, shape (2, 2) or (N, 2, 2) [m]
        The two intersections, left then right of the line from ``c1`` to ``c2``.
        Where the circles do not meet (noisy ranges) both are the point of the centre
        line closest to both circles.
    meet : ndarray of bool, shape () or (N,)
        Whether the circles meet.

    Raises
    ------
    ValueError
        If two centres are closer than ``sensors.MIN_RANGE``.

    """
    c1, c2 = np.asarray(c1, dtype=np.float64), np.asarray(c2, dtype=np.float64)
    r1, r2 = np.asarray(r1, dtype=np.float64), np.asarray(r2, dtype=np.float64)
    delta = c2 - c1
    d = np.hypot(delta[..., 0], delta[..., 1])
    sensors.check_range(d, 'distance between circle centres')
    u = delta / d[..., None]
    a = (r1 * r1 - r2 * r2 + d * d) / (2.0 * d)
    h2 = r1 * r1 - a * a
    meet = h2 >= 0.0
    h = np.sqrt(np.maximum(h2, 0.0))
    base = c1 + a[..., None] * u
    left = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    points = np.stack([base + h[..., None] * left, base - h[..., None] * left], axis=-2)
    return points, meet[()]


def intersect_ray_circle(
        s: ArrayLike, phi: ArrayLike, c: ArrayLike, r: ArrayLike
) -> Tuple[NDArray[np.float64], NDArray[np.float64], Union[np.bool_, NDArray[np.bool_]]]:
    """
    Intersect rays ``s + t d(phi)`` with circles.

    Source: the quadratic ``|s + t d - c|^2 = r^2`` in ``t``.

    Parameters
    ----------
    s : array_like, shape (2,) or (N, 2) [m]
        Ray origins.
    phi : array_like, shape () or (N,) [rad]
        Ray directions in the world.
    c : array_like, shape (2,) or (N, 2) [m]
        Circle centres.
    r : array_like, shape () or (N,) [m]
        Radii.

    Returns
    -------
    points : ndarray, shape (2, 2) or (N, 2, 2) [m]
        The two intersections of the line, nearer first; where they do not meet, both
        are the point of the line closest to the centre.
    t : ndarray, shape (2,) or (N, 2) [m]
        Their distances along the ray (negative: behind the sensor).
    meet : ndarray of bool, shape () or (N,)

    """
    s, c = np.asarray(s, dtype=np.float64), np.asarray(c, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    d = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    e = s - c
    b = np.sum(d * e, axis=-1)
    disc = b * b - (np.sum(e * e, axis=-1) - r * r)
    meet = disc >= 0.0
    root = np.sqrt(np.maximum(disc, 0.0))
    t = np.stack([-b - root, -b + root], axis=-1)
    return s[..., None, :] + t[..., None] * d[..., None, :], t, meet[()]


def trilaterate(c: ArrayLike, r: ArrayLike) -> Tuple[NDArray[np.float64], float]:
    """
    Place a point from ranges to three or more centres, linearised (no iteration).

    Subtracting the mean of the equations ``|m - c_i|^2 = r_i^2`` cancels ``|m|^2`` and
    leaves the linear system ``2 (c_i - c_mean) . m = ...``, solved by least squares.
    Source: Murphy and Hereman, "Determination of a position in three dimensions
    using trilateration and approximate distances", Colorado School of Mines report
    MCS-95-07, 1995 (here in the plane, centred for conditioning).

    Parameters
    ----------
    c : array_like, shape (N, 2) [m]
        Centres, ``N >= 3``.
    r : array_like, shape (N,) [m]
        Ranges.

    Returns
    -------
    m : ndarray, shape (2,) [m]
        The point; NaN where the centres are collinear (the mirror image of the point
        across their line fits as well).
    spread : float
        Smaller over larger singular value of the centred centres, in [0, 1]: 0 for
        collinear centres.

    Raises
    ------
    ValueError
        If there are fewer than three centres.

    """
    c = np.asarray(c, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] < 3 or c.shape[1] != 2 or r.shape != c.shape[:1]:
        raise ValueError(f'need (N, 2) centres and (N,) ranges with N >= 3, got {c.shape}, '
                         f'{r.shape}')
    mean = c.mean(axis=0)
    c = c - mean
    singular = np.linalg.svd(c, compute_uv=False)
    spread = float(singular[1] / singular[0]) if singular[0] > 0.0 else 0.0
    if spread < _COLLINEAR:
        return np.full(2, np.nan), spread
    q = np.sum(c * c, axis=1) - r * r
    m = np.linalg.lstsq(2.0 * c, q - q.mean(), rcond=None)[0]
    return m + mean, spread
