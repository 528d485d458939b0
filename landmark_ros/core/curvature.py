"""
Curvature of a least-squares fit: how far a Gaussian describes a landmark placed from views.

A landmark placed from range-only or bearing-only views by weighted least squares
(``partial.initialise``) gets the covariance ``(J^T W J)^-1`` of the linearised model.
That is the right description of its error only while the model is nearly linear over
the confidence region. Ranges from a short stretch of path give a long, curved valley
(a banana): the Gaussian lies along its tangent, the true landmark somewhere along the
curve, many standard deviations off the tangent. The relative curvatures of Bates and
Watts measure this from first and second derivatives at the solution.

Symbols
-------
m : landmark in the world ``(x, y)`` [m], shape (2,) or (N, 2).
s : sensor pose in the world ``(x, y, theta)``, shape (3,) or (N, 3).
J : rows ``J_h_m`` of ``N`` scalar views, shape (N, 2).
H_h_m : second derivatives ``d^2 h / d m^2`` of each view, shape (N, 2, 2).
R : variance of each view (the least-squares weights are ``1 / R``), shape (N,).
"""

import math
from typing import Tuple

from landmark_ros.core import sensors
import numpy as np
from numpy.typing import ArrayLike, NDArray

CONFIDENCE_RADIUS_95 = math.sqrt(-2.0 * math.log(0.05))
"""Radius of the 95 % confidence region of two parameters in standard deviations:
``sqrt(chi2_2(0.95))`` (2.448; the 2-dof chi-square quantile is ``-2 log(1 - p)``)."""

_DIRECTIONS = 90
"""Unit directions of the half circle on which the largest curvature is searched."""


def observe_hessians(pose: ArrayLike, m: ArrayLike) -> NDArray[np.float64]:
    """
    Return the second derivatives of range and bearing with respect to the landmark.

    With ``d = m - pose_xy`` and ``r = |d|``: the range ``r`` has
    ``(r^2 I - d d^T) / r^3``; the bearing ``atan2(d_y, d_x) - theta`` has
    ``[[2 d_x d_y, d_y^2 - d_x^2], [d_y^2 - d_x^2, -2 d_x d_y]] / r^4``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        Sensor pose (x, y, theta).
    m : array_like, shape (2,) or (N, 2) [m]
        Landmark in the world.

    Returns
    -------
    ndarray, shape (2, 2, 2) or (N, 2, 2, 2)
        ``[..., k, i, j] = d^2 z_k / d m_i d m_j``, ``k`` 0 the range [1/m], 1 the
        bearing [rad/m^2].

    Raises
    ------
    ValueError
        If the landmark is closer than ``sensors.MIN_RANGE`` to the sensor.

    """
    pose = np.asarray(pose, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    d = m - pose[..., :2]
    r2 = np.sum(d * d, axis=-1)
    r = np.sqrt(r2)
    sensors.check_range(r)
    dx, dy = d[..., 0], d[..., 1]
    eye = np.broadcast_to(np.eye(2), d.shape[:-1] + (2, 2))
    range_h = (eye * r2[..., None, None] - d[..., :, None] * d[..., None, :]) / (
        r2 * r)[..., None, None]
    off = dy * dy - dx * dx
    bearing_h = np.stack([np.stack([2.0 * dx * dy, off], axis=-1),
                          np.stack([off, -2.0 * dx * dy], axis=-1)], axis=-2) / (
        r2 * r2)[..., None, None]
    return np.stack([range_h, bearing_h], axis=-3)


def relative_curvatures(J: ArrayLike, H_h_m: ArrayLike, R: ArrayLike) -> Tuple[float, float]:
    """
    Return the largest parameter-effects and intrinsic curvature of a weighted fit.

    In whitened measurement space (each residual over ``sqrt(R)``) a step of the two
    parameters that moves the prediction by one standard deviation along the
    tangent plane (``|W^1/2 J delta| = 1``) has the acceleration
    ``a_i = delta^T H_i delta / sqrt(R_i)``; its component in the tangent plane is
    the parameter-effects curvature (the Gaussian's straight axes against the
    curved lines of constant parameter: the banana), the rest the intrinsic
    curvature (the expectation surface bending away from its tangent plane). Both
    are maximised over the directions of ``delta`` (90 directions of a half
    circle). A curvature ``gamma`` is the inverse of a radius of curvature in
    standard deviations: the second-order error of the linearisation at ``k``
    standard deviations from the solution is ``gamma k^2 / 2``. Source: Bates and
    Watts, "Relative curvature measures of nonlinearity", J. R. Stat. Soc. B 42(1),
    1980 (here with known variances, so no residual scale).

    Parameters
    ----------
    J : array_like, shape (N, 2)
        Jacobian rows of the views at the solution.
    H_h_m : array_like, shape (N, 2, 2)
        Their second derivatives (``observe_hessians`` of the view's kind).
    R : array_like, shape (N,)
        Variances of the views (positive).

    Returns
    -------
    parameter_effects, intrinsic : float
        Largest curvatures [1 / standard deviation]; ``inf`` when ``J`` has rank
        below 2.

    """
    w = 1.0 / np.sqrt(np.asarray(R, dtype=np.float64))
    J_w = np.asarray(J, dtype=np.float64) * w[:, None]
    H_w = np.asarray(H_h_m, dtype=np.float64) * w[:, None, None]
    Q, upper = np.linalg.qr(J_w)
    singular = np.abs(np.diag(upper))
    if not singular.min() > 1e-12 * max(singular.max(), 1e-300):
        return math.inf, math.inf
    angle = np.linspace(0.0, math.pi, _DIRECTIONS, endpoint=False)
    u = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    delta = np.linalg.solve(upper, u.T).T               # (K, 2): one standard deviation
    a = np.einsum('ki,nij,kj->kn', delta, H_w, delta)   # (K, N) accelerations
    tangent = a @ Q                                     # (K, 2)
    normal = a - tangent @ Q.T
    return (float(np.linalg.norm(tangent, axis=1).max()),
            float(np.linalg.norm(normal, axis=1).max()))
