"""
Plausible ranges of measured quantities: one table, applied the same on every path (ROS-free).

Finite is not plausible: a bearing of 1e17 rad is finite and places a landmark in an
arbitrary direction, a variance of 1e-200 is positive and makes a covariance the core
cannot invert. Each quantity that enters the observer, the fuser or the map file has
one entry in ``LIMITS`` (what it is, its unit, the accepted closed interval and the
named reason a value outside it is counted under); the checks below are the only
implementation, used by the observer (range-bearing, range-only and bearing-only
rows, poses), the fuser (landmark and partial observation rows) and the map-file
loader, so the live path and the loader accept the same values. ``LIMITS`` is the
source of the bad-input table in the docs (``markdown()``). Configured noise
(``ObserverConfig``: ``range_stddev`` <= 1000 m, ``bearing_stddev`` <= pi rad) stays
within ``MAX_VARIANCE`` by its parameter ranges; ``sensor_pose`` is checked here.

NaN and infinity are not judged here: each path rejects them first under its own
``*_nonfinite`` reason. Variances are checked against the covariance checks' own
bounds (``core.covariance.MIN_VARIANCE``, ``MAX_VARIANCE``) so that nothing passes a
row check and fails a later one.

Odometry that carries no pose (a twist-only message: position and yaw zero, pose
covariance all zero) is refused as ``odometry_pose_missing``: an exact pose at the
origin is what such a message says, not what the robot did.
"""

from dataclasses import dataclass
import math
from typing import Any, Dict, List, Mapping, Tuple

from landmark_ros.core.covariance import MAX_VARIANCE, MIN_VARIANCE
from landmark_ros.core.sensors import MIN_RANGE
import numpy as np
from numpy.typing import NDArray

MAX_ANGLE = 4.0 * math.pi
"""Largest magnitude of a measured angle (bearing, yaw) [rad]: two turns."""

MAX_RANGE = 1.0e4
"""Largest range a sensor row may carry [m] (10 km: beyond any landmark sensor)."""

MAX_COORDINATE = 1.0e7
"""Largest magnitude of a world coordinate (pose, landmark, sensor position) [m]."""


@dataclass(frozen=True)
class Limit:
    """One plausible range: quantity, unit, closed interval ``[low, high]``, reason."""

    quantity: str
    unit: str
    low: float
    high: float
    reason: str
    where: str


LIMITS: Tuple[Limit, ...] = (
    Limit('range', 'm', MIN_RANGE, MAX_RANGE, 'range_out_of_range',
          'observation rows (range-bearing and range-only), partial observation rows'),
    Limit('bearing', 'rad', -MAX_ANGLE, MAX_ANGLE, 'bearing_out_of_range',
          'observation rows (range-bearing and bearing-only), partial observation rows'),
    Limit('range_variance, bearing_variance (per row)', 'm^2, rad^2', MIN_VARIANCE,
          MAX_VARIANCE, 'noise_variance_out_of_range', 'observation rows'),
    Limit('|range_bearing_covariance| (per row)', 'm rad', 0.0, MAX_VARIANCE,
          'noise_variance_out_of_range', 'observation rows'),
    Limit('partial observation variance', 'm^2 or rad^2', MIN_VARIANCE, MAX_VARIANCE,
          'variance_out_of_range', 'partial observation rows, waiting partial '
          'observations in the map file'),
    Limit('pose x, y', 'm', -MAX_COORDINATE, MAX_COORDINATE, 'pose_out_of_range',
          'poses, odometry, sensor poses of partial observations'),
    Limit('pose yaw', 'rad', -MAX_ANGLE, MAX_ANGLE, 'pose_out_of_range',
          'poses, odometry, sensor poses of partial observations'),
    Limit('pose variances (x, y, yaw diagonal)', 'm^2, rad^2', 0.0, MAX_VARIANCE,
          'pose_variance_out_of_range', 'poses, odometry'),
    Limit('landmark x, y', 'm', -MAX_COORDINATE, MAX_COORDINATE, 'landmark_out_of_range',
          'landmark rows, fused landmarks, map-file landmarks and tracks'),
    Limit('sensor_pose x, y (configured)', 'm', -MAX_RANGE, MAX_RANGE, 'ValueError at start',
          'observer parameters'),
    Limit('sensor_pose yaw (configured)', 'rad', -MAX_ANGLE, MAX_ANGLE, 'ValueError at start',
          'observer parameters'),
    Limit('landmark covariance diagonal', 'm^2', MIN_VARIANCE, MAX_VARIANCE,
          'covariance_too_small / covariance_too_large',
          'observer results, landmark rows, fused landmarks, map file'),
)
"""Every plausible range, for the docs table (``docs/bad-input.md``)."""


def outside(values: NDArray[Any], low: float, high: float) -> NDArray[np.bool_]:
    """
    Return where finite ``values`` lie outside ``[low, high]`` (NaN and inf: False).

    Parameters
    ----------
    values : ndarray
        Any shape.
    low, high : float
        The closed interval.

    Returns
    -------
    ndarray of bool, the shape of ``values``

    """
    with np.errstate(invalid='ignore'):
        return _outside(values, low, high)


def _outside(values, low, high):
    """Return ``outside(values, low, high)``; the caller silences 'invalid' (NaN)."""
    values = np.asarray(values, dtype=np.float64)
    return np.asarray(np.isfinite(values) & ((values < low) | (values > high)))


def observation_problems(columns: Mapping[str, NDArray[Any]],
                         count: int) -> List[Tuple[str, NDArray[np.bool_]]]:
    """
    Return the plausibility checks of observation rows, for ``rows.first_problems``.

    Parameters
    ----------
    columns : dict of str to ndarray, shape (N,)
        ``range`` [m], ``bearing`` [rad] and the optional per-row noise fields (NaN:
        the configured default, not judged here).
    count : int
        Number of rows ``N``.

    Returns
    -------
    list of (str, ndarray of bool, shape (N,))
        ``range_out_of_range`` (above ``MAX_RANGE``; too small is ``range_not_positive``
        on each path), ``bearing_out_of_range``, ``noise_variance_out_of_range``.

    """
    none = np.zeros(count, bool)
    with np.errstate(invalid='ignore'):  # once per message, not once per column
        checks = [
            ('range_out_of_range', _outside(columns['range'], -np.inf, MAX_RANGE)
             if 'range' in columns else none),
            ('bearing_out_of_range', _outside(columns['bearing'], -MAX_ANGLE, MAX_ANGLE)
             if 'bearing' in columns else none),
        ]
        noise = none.copy()
        for name in ('range_variance', 'bearing_variance'):
            if name in columns:    # zero and negative: the covariance checks' own reasons
                values = np.asarray(columns[name], dtype=np.float64)
                noise |= _outside(values, MIN_VARIANCE, MAX_VARIANCE) & (values > 0.0)
        if 'range_bearing_covariance' in columns:
            noise |= _outside(columns['range_bearing_covariance'], -MAX_VARIANCE,
                              MAX_VARIANCE)
    checks.append(('noise_variance_out_of_range', noise))
    return checks


def pose_problem(pose: NDArray[np.float64], P_pose: NDArray[np.float64]) -> Tuple[str, str]:
    """
    Return ``(reason, detail)`` of an implausible finite pose, or ``('', '')``.

    Parameters
    ----------
    pose : ndarray, shape (3,)
        (x [m], y [m], yaw [rad]).
    P_pose : ndarray, shape (3, 3)
        Its covariance (already symmetric positive semi-definite).

    """
    if outside(pose[:2], -MAX_COORDINATE, MAX_COORDINATE).any() or outside(
            pose[2], -MAX_ANGLE, MAX_ANGLE):
        return 'pose_out_of_range', (f'pose {np.asarray(pose).tolist()} outside '
                                     f'|x|, |y| <= {MAX_COORDINATE:g} m, |yaw| <= '
                                     f'{MAX_ANGLE:.4g} rad')
    if outside(np.diagonal(P_pose), 0.0, MAX_VARIANCE).any():
        return 'pose_variance_out_of_range', (f'pose variances {np.diagonal(P_pose).tolist()}'
                                              f' above {MAX_VARIANCE:g}')
    return '', ''


def odometry_pose_missing(pose: NDArray[np.float64], P_pose: NDArray[np.float64]) -> bool:
    """Return True for the pose of a twist-only odometry message (origin, zero covariance)."""
    return not np.any(pose) and not np.any(P_pose)


def partial_problems(columns: Mapping[str, NDArray[Any]], kind: NDArray[Any],
                     value: NDArray[Any], variance: NDArray[Any],
                     range_kind: int) -> List[Tuple[str, NDArray[np.bool_]]]:
    """
    Return the plausibility checks of partial observation rows (fuser input, map file).

    Parameters
    ----------
    columns : dict of str to ndarray, shape (N,)
        ``sensor_x``, ``sensor_y`` [m], ``sensor_theta`` [rad] where present.
    kind, value, variance : ndarray, shape (N,)
        Kind (``range_kind`` for a range), measured value and its variance.
    range_kind : int
        The kind code of a range (``core.partial.RANGE``).

    Returns
    -------
    list of (str, ndarray of bool, shape (N,))
        ``range_out_of_range``, ``bearing_out_of_range``, ``variance_out_of_range``,
        ``pose_out_of_range`` (the sensor pose).

    """
    is_range = np.asarray(kind) == range_kind
    count = len(is_range)
    sensor = np.zeros(count, bool)
    for name, limit in (('sensor_x', MAX_COORDINATE), ('sensor_y', MAX_COORDINATE),
                        ('sensor_theta', MAX_ANGLE)):
        if name in columns:
            sensor |= outside(columns[name], -limit, limit)
    return [
        ('range_out_of_range', is_range & outside(value, -np.inf, MAX_RANGE)),
        ('bearing_out_of_range', ~is_range & outside(value, -MAX_ANGLE, MAX_ANGLE)),
        ('variance_out_of_range', outside(variance, MIN_VARIANCE, MAX_VARIANCE)),
        ('pose_out_of_range', sensor),
    ]


def landmark_problems(m: NDArray[np.float64]) -> List[Tuple[str, NDArray[np.bool_]]]:
    """Return the plausibility check of landmark positions ``m``, shape (N, 2) [m]."""
    far = outside(m, -MAX_COORDINATE, MAX_COORDINATE).reshape(len(m), 2)
    return [('landmark_out_of_range', far[:, 0] | far[:, 1])]


def markdown() -> str:
    """Return ``LIMITS`` as a Markdown table (the source of the docs' bad-input table)."""
    head = ['quantity', 'unit', 'low', 'high', 'reason', 'where']
    lines = ['| ' + ' | '.join(head) + ' |', '|' + ' --- |' * len(head)]
    lines += ['| ' + ' | '.join(row[key] for key in head) + ' |' for row in table()]
    return '\n'.join(lines) + '\n'


def table() -> List[Dict[str, str]]:
    """Return ``LIMITS`` as rows of strings (quantity, unit, low, high, reason, where)."""
    return [{'quantity': limit.quantity, 'unit': limit.unit, 'low': f'{limit.low:.6g}',
             'high': f'{limit.high:.6g}', 'reason': limit.reason, 'where': limit.where}
            for limit in LIMITS]
