"""
Planar motion from wheel odometry, with its noise (ROS-free, scalar and fast).

Symbols
-------
x, P
    Pose ``(x [m], y [m], theta [rad])`` of the robot in the map frame and its 3x3
    covariance.
delta
    The motion between two odometry messages in the frame of the first:
    ``(dx [m], dy [m], dtheta [rad])``, so that ``x_next = x (+) delta``.
Q
    Covariance of ``delta``, 3x3.
alphas
    The four parameters of the odometry motion model of Probabilistic Robotics
    (Thrun, Burgard, Fox), ch. 5.4: the motion is ``rot1`` (turn towards the end point),
    ``trans`` (straight), ``rot2`` (turn to the end heading), with independent errors

    - ``var(rot1) = a1 rot1^2 + a2 trans^2``
    - ``var(trans) = a3 trans^2 + a4 (rot1^2 + rot2^2)``
    - ``var(rot2) = a1 rot2^2 + a2 trans^2``

    ``a1`` [rad^2/rad^2] rotation from rotation, ``a2`` [rad^2/m^2] rotation from
    translation, ``a3`` [m^2/m^2] translation from translation, ``a4`` [m^2/rad^2]
    translation from rotation. The model applies to the motion between two consecutive
    odometry messages: the variances are quadratic in the step, so halving the step
    length quarters them, and the same drive reported at twice the rate, or with
    irregular stamps, gets a different covariance. ``step_noise_scale`` makes the model
    white in time: the alphas describe a step of a fixed period, a step of ``dt`` has
    its variances scaled by ``period / dt`` (constant speed: variance growing linearly
    with time, the same at any rate).

The functions take and return plain floats and small arrays: one odometry message costs a
few microseconds. ``compose``-style results agree with ``landmark_ros.core.pose2`` (tests).
"""

import math
from typing import Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray

_TWO_PI = 2.0 * math.pi


def wrap(angle: float) -> float:
    """Return ``angle`` wrapped to ``[-pi, pi)`` [rad]."""
    return (angle + math.pi) % _TWO_PI - math.pi


def delta_from_twist(v: float, w: float, dt: float) -> NDArray[np.float64]:
    """
    Return the motion of a constant twist held for ``dt``: an arc (a line when ``w`` = 0).

    Parameters
    ----------
    v : float
        Forward speed [m/s].
    w : float
        Yaw rate [rad/s].
    dt : float
        Duration [s], non-negative.

    Returns
    -------
    delta : ndarray, shape (3,)
        ``(dx, dy, dtheta)`` in the frame at the start.

    """
    dth = w * dt
    if abs(dth) < 1e-9:
        return np.array([v * dt, 0.5 * v * dt * dth, dth])
    radius = v / w
    return np.array([radius * math.sin(dth), radius * (1.0 - math.cos(dth)), dth])


def decompose(delta: Sequence[float]) -> Tuple[float, float, float]:
    """
    Return ``(rot1, trans, rot2)`` of a motion ``delta`` (Probabilistic Robotics 5.4).

    A motion without translation is a pure ``rot1``; a negative forward motion (reversing)
    gives ``trans < 0`` with ``rot1`` the small turn, not a half turn.
    """
    dx, dy, dth = float(delta[0]), float(delta[1]), float(delta[2])
    trans = math.hypot(dx, dy)
    if trans < 1e-9:
        return dth, 0.0, 0.0
    rot1 = math.atan2(dy, dx)
    if abs(rot1) > 0.5 * math.pi:  # reversing: drive backwards instead of turning round
        rot1 = wrap(rot1 + math.pi)
        trans = -trans
    return rot1, trans, wrap(dth - rot1)


def odometry_noise(delta: Sequence[float], alphas: Sequence[float]) -> NDArray[np.float64]:
    """
    Return ``Q``, the covariance of ``delta`` under the odometry model of ch. 5.4.

    Parameters
    ----------
    delta : sequence of 3 float
        The motion ``(dx, dy, dtheta)``.
    alphas : sequence of 4 float
        ``(a1, a2, a3, a4)``, non-negative (module docstring).

    Returns
    -------
    Q : ndarray, shape (3, 3)
        ``J Sigma J^T`` with ``Sigma = diag(var rot1, var trans, var rot2)`` and ``J``
        the Jacobian of ``delta = (trans cos rot1, trans sin rot1, rot1 + rot2)``.

    """
    a1, a2, a3, a4 = alphas
    rot1, trans, rot2 = decompose(delta)
    t2, r1, r2 = trans * trans, rot1 * rot1, rot2 * rot2
    v1 = a1 * r1 + a2 * t2  # var(rot1)
    vt = a3 * t2 + a4 * (r1 + r2)  # var(trans)
    v2 = a1 * r2 + a2 * t2  # var(rot2)
    c, s = math.cos(rot1), math.sin(rot1)
    # J Sigma J^T, J = d(dx, dy, dth) / d(rot1, trans, rot2)
    # = [[-trans s, c, 0], [trans c, s, 0], [1, 0, 1]], written out
    ts, tc = trans * s, trans * c
    q00 = ts * ts * v1 + c * c * vt
    q01 = -ts * tc * v1 + c * s * vt
    q11 = tc * tc * v1 + s * s * vt
    return np.array([[q00, q01, -ts * v1], [q01, q11, tc * v1], [-ts * v1, tc * v1, v1 + v2]])


def step_noise_scale(dt, period_s: float):
    """
    Return the factor of a step's model covariance: ``period_s / dt``, 1 for period 0.

    With ``period_s`` > 0 the alphas describe a step of that duration and the odometry
    error is white in time: at constant speed a step of ``dt`` has the model variance
    ``a v^2 dt^2`` times ``period_s / dt``, linear in ``dt``, so cutting a motion into
    more steps leaves its total variance unchanged. With ``period_s`` = 0 the alphas
    apply per step whatever its length (Probabilistic Robotics, ch. 5.4, as written).

    Parameters
    ----------
    dt : float or ndarray, shape (N,)
        Step durations [s]; a step of ``dt <= 0`` (no motion) gets factor 0.
    period_s : float
        The step duration the alphas describe [s], >= 0.

    Returns
    -------
    float or ndarray, shape (N,)

    """
    if period_s <= 0.0:
        return 1.0 if np.ndim(dt) == 0 else np.ones(np.shape(dt))
    dt = np.asarray(dt, dtype=np.float64)
    out = np.divide(period_s, dt, out=np.zeros_like(dt), where=dt > 0.0)
    return float(out) if out.ndim == 0 else out


def scale_motion(delta: Sequence[float], dt: float, speed_scale: float = 1.0,
                 yaw_rate_scale: float = 1.0, speed_scale_per_yaw_rate: float = 0.0,
                 yaw_per_m: float = 0.0) -> NDArray[np.float64]:
    """
    Return the true motion of an odometry motion: its systematic error removed.

    Parameters
    ----------
    delta : sequence of 3 float
        The odometry's motion ``(dx, dy, dtheta)`` over ``dt``.
    dt : float
        Its duration [s], > 0 (``speed_scale_per_yaw_rate`` needs the yaw rate).
    speed_scale : float
        True distance per odometry distance when not turning (wheel radius error).
    yaw_rate_scale : float
        True turn per odometry turn (wheel base error).
    speed_scale_per_yaw_rate : float
        Change of the speed scale per rad/s of the odometry's yaw rate ``|dtheta| / dt``
        [s/rad]: a drive that keeps the commanded turn rate and gives up forward speed.
        The speed scale is held at zero or above.
    yaw_per_m : float
        Turn per metre of odometry distance [rad/m], a veer while driving (unequal
        wheels; Borenstein and Feng's systematic odometry errors, 1996).

    Returns
    -------
    ndarray, shape (3,)
        ``(s dx, s dy, yaw_rate_scale dtheta + yaw_per_m hypot(dx, dy))``, ``s =
        max(0, speed_scale + speed_scale_per_yaw_rate |dtheta| / dt)``.

    """
    s = speed_scale
    if speed_scale_per_yaw_rate and dt > 0.0:
        s = max(0.0, s + speed_scale_per_yaw_rate * abs(float(delta[2])) / dt)
    if s == 1.0 and yaw_rate_scale == 1.0 and not yaw_per_m:
        return np.asarray(delta, dtype=np.float64)
    out = np.asarray(delta, dtype=np.float64) * np.array([s, s, yaw_rate_scale])
    if yaw_per_m:
        out[2] += yaw_per_m * math.hypot(float(delta[0]), float(delta[1]))
    return out


def scale_twists(twists: NDArray[np.float64], scales: Sequence[float]) -> NDArray[np.float64]:
    """
    Return odometry twists (K, 2) with the systematic error of ``scale_motion`` removed.

    ``scales``: ``(speed_scale, yaw_rate_scale[, speed_scale_per_yaw_rate[,
    yaw_per_m]])``; the batch form for twists (speed [m/s], yaw rate [rad/s]).
    """
    twists = np.asarray(twists, dtype=np.float64).reshape(-1, 2)
    speed, yaw = float(scales[0]), float(scales[1])
    per = float(scales[2]) if len(scales) > 2 else 0.0
    veer = float(scales[3]) if len(scales) > 3 else 0.0
    s = np.maximum(0.0, speed + per * np.abs(twists[:, 1])) if per else speed
    return np.stack([twists[:, 0] * s, twists[:, 1] * yaw + veer * np.abs(twists[:, 0])],
                    axis=1)


def scale_delta(delta: Sequence[float], fraction: float) -> NDArray[np.float64]:
    """
    Return the part ``fraction`` in [0, 1] of a motion, along the same arc.

    The arc through the start and the end with the start heading (the constant twist
    that makes ``delta``) is cut at ``fraction`` of its turn and length.
    """
    dx, dy, dth = float(delta[0]), float(delta[1]), float(delta[2])
    if abs(dth) < 1e-9:
        return np.array([dx * fraction, dy * fraction, dth * fraction])
    # chord of length L at angle dth / 2 to the heading; radius = L / (2 sin(dth / 2))
    chord = math.hypot(dx, dy)
    length = chord * (dth / 2.0) / math.sin(dth / 2.0) if chord else 0.0
    return delta_from_twist(length * fraction, dth * fraction, 1.0)


def predict(x: NDArray[np.float64], P: NDArray[np.float64], delta: Sequence[float],
            Q: NDArray[np.float64]) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return ``x (+) delta`` and its covariance ``J_x P J_x^T + J_d Q J_d^T``.

    Parameters
    ----------
    x : ndarray, shape (3,)
        Pose before the motion.
    P : ndarray, shape (3, 3)
        Its covariance.
    delta : sequence of 3 float
        The motion in the frame of ``x``.
    Q : ndarray, shape (3, 3)
        Covariance of ``delta``.

    Returns
    -------
    x_next : ndarray, shape (3,)
    P_next : ndarray, shape (3, 3)

    """
    c, s = math.cos(x[2]), math.sin(x[2])
    dx, dy, dth = float(delta[0]), float(delta[1]), float(delta[2])
    x_next = np.array([x[0] + c * dx - s * dy, x[1] + s * dx + c * dy, wrap(x[2] + dth)])
    # Written out (numpy on 3x3 costs more than the arithmetic):
    # J_x = [[1, 0, a], [0, 1, b], [0, 0, 1]], J_d = rotation by theta (xy), 1 (theta).
    a, b = -s * dx - c * dy, c * dx - s * dy
    (p00, p01, p02), (_, p11, p12), (_, _, p22) = P.tolist()
    (q00, q01, q02), (_, q11, q12), (_, _, q22) = Q.tolist()
    cc, ss, cs = c * c, s * s, c * s
    n00 = p00 + 2.0 * a * p02 + a * a * p22 + cc * q00 - 2.0 * cs * q01 + ss * q11
    n01 = p01 + a * p12 + b * p02 + a * b * p22 + cs * (q00 - q11) + (cc - ss) * q01
    n11 = p11 + 2.0 * b * p12 + b * b * p22 + ss * q00 + 2.0 * cs * q01 + cc * q11
    n02 = p02 + a * p22 + c * q02 - s * q12
    n12 = p12 + b * p22 + s * q02 + c * q12
    n22 = p22 + q22
    return x_next, np.array([[n00, n01, n02], [n01, n11, n12], [n02, n12, n22]])


def predict_with(x: NDArray[np.float64], P: NDArray[np.float64], delta: Sequence[float],
                 Q: NDArray[np.float64]) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return ``predict`` of a state whose components after the pose are constant.

    The pose block moves as in ``predict``; the other components (the range scale error
    of ``localizer.update``) stay, their cross-covariance with the pose turns with the
    motion: ``J_x P_xs``. A 3-component state is ``predict``.

    Parameters
    ----------
    x : ndarray, shape (n,), n >= 3
        Pose, then the constant components.
    P : ndarray, shape (n, n)
        Its covariance.
    delta : sequence of 3 float
        The motion in the frame of the pose.
    Q : ndarray, shape (3, 3)
        Covariance of ``delta``.

    Returns
    -------
    x_next : ndarray, shape (n,)
    P_next : ndarray, shape (n, n)

    """
    if len(x) == 3:
        return predict(x, P, delta, Q)
    pose, P_pose = predict(x[:3], P[:3, :3], delta, Q)
    x_next, P_next = x.copy(), P.copy()
    x_next[:3], P_next[:3, :3] = pose, P_pose
    P_next[:3, 3:] = _pose_jacobian(x, delta) @ P[:3, 3:]
    P_next[3:, :3] = P_next[:3, 3:].T
    return x_next, P_next


def _pose_jacobian(x, delta):
    """Return ``J_x`` (3, 3) of ``x (+) delta`` with respect to ``x``."""
    c, s = math.cos(x[2]), math.sin(x[2])
    return np.array([[1.0, 0.0, -s * delta[0] - c * delta[1]],
                     [0.0, 1.0, c * delta[0] - s * delta[1]], [0.0, 0.0, 1.0]])


def predict_cross(x: NDArray[np.float64], C: Optional[NDArray[np.float64]],
                  delta: Sequence[float]) -> Optional[NDArray[np.float64]]:
    """
    Return the cross-covariance of the state with constant states after a motion.

    ``C`` (n, w) is the cross-covariance of the state ``x`` (n,) (pose first) with
    states that do not move (``localizer.consider``); the pose rows turn with the motion
    (``J_x C``), the others stay. None stays None.
    """
    if C is None:
        return None
    C_next = C.copy()
    C_next[:3] = _pose_jacobian(x, delta) @ C[:3]
    return C_next


def between(a: Sequence[float], b: Sequence[float]) -> NDArray[np.float64]:
    """Return ``(-) a (+) b``: the pose ``b`` in the frame of ``a``, shape (3,)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2])])


def compose(a: Sequence[float], b: Sequence[float]) -> NDArray[np.float64]:
    """Return ``a (+) b``, shape (3,)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
                     wrap(a[2] + b[2])])


def inverse(a: Sequence[float]) -> NDArray[np.float64]:
    """Return ``(-) a``, shape (3,)."""
    return between(a, (0.0, 0.0, 0.0))


def odometry_noise_terms(deltas: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return the covariance of each motion for each unit alpha: ``Q = sum_i a_i T[:, i]``.

    The batch form of ``odometry_noise`` (same decomposition), for calibration.

    Parameters
    ----------
    deltas : ndarray, shape (N, 3)
        Motions ``(dx, dy, dtheta)``.

    Returns
    -------
    T : ndarray, shape (N, 4, 3, 3)

    """
    deltas = np.asarray(deltas, dtype=np.float64).reshape(-1, 3)
    dx, dy, dth = deltas[:, 0], deltas[:, 1], deltas[:, 2]
    trans = np.hypot(dx, dy)
    moving = trans >= 1e-9
    rot1 = np.where(moving, np.arctan2(dy, dx), dth)
    back = moving & (np.abs(rot1) > 0.5 * math.pi)
    rot1 = np.where(back, (rot1 + 2.0 * math.pi) % _TWO_PI - math.pi, rot1)
    trans = np.where(back, -trans, trans)
    rot2 = np.where(moving, (dth - rot1 + math.pi) % _TWO_PI - math.pi, 0.0)
    t2, r1, r2 = trans ** 2, rot1 ** 2, rot2 ** 2
    zero = np.zeros_like(t2)
    # variances of (rot1, trans, rot2) per unit alpha: rows a1..a4
    var = np.stack([np.stack([r1, zero, r2], -1), np.stack([t2, zero, t2], -1),
                    np.stack([zero, t2, zero], -1), np.stack([zero, r1 + r2, zero], -1)], 1)
    c, s = np.cos(rot1), np.sin(rot1)
    J = np.zeros((len(deltas), 3, 3))
    J[:, 0, 0], J[:, 0, 1] = -trans * s, c
    J[:, 1, 0], J[:, 1, 1] = trans * c, s
    J[:, 2, 0] = J[:, 2, 2] = 1.0
    return np.einsum('nij,naj,nkj->naik', J, var, J)


def integrate_twists(times: NDArray[np.float64], twists: NDArray[np.float64]
                     ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the dead-reckoned poses from the origin and the step motions.

    Each step holds the previous message's twist until the next stamp (as ``Localizer``).

    Parameters
    ----------
    times : ndarray, shape (K,)
        Stamps [s], increasing.
    twists : ndarray, shape (K, 2)
        Forward speed [m/s], yaw rate [rad/s].

    Returns
    -------
    poses : ndarray, shape (K, 3)
        Pose at each stamp, the first at the origin.
    deltas : ndarray, shape (K - 1, 3)
        Motion of each step in the frame of its start.

    """
    dt = np.diff(times)
    v, w = twists[:-1, 0], twists[:-1, 1]
    dth = w * dt
    small = np.abs(dth) < 1e-9
    safe_w = np.where(small, 1.0, w)
    deltas = np.stack([np.where(small, v * dt, v / safe_w * np.sin(dth)),
                       np.where(small, 0.5 * v * dt * dth, v / safe_w * (1.0 - np.cos(dth))),
                       dth], axis=1)
    heading = np.concatenate([[0.0], np.cumsum(dth)])
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    steps = np.stack([c * deltas[:, 0] - s * deltas[:, 1],
                      s * deltas[:, 0] + c * deltas[:, 1]], axis=1)
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    return np.column_stack([xy, heading]), deltas
