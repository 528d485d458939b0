"""
The observer's row maths: noise, checks, world-frame landmarks (ROS-free).

Observation rows (range [m], bearing [rad], landmark ID, optional noise columns) are
checked, given their noise covariance ``R`` and placed in the world with
``core.landmarks.landmark_to_world_dependent``; only landmarks whose covariances the
core handles leave the observer.
"""

from collections import Counter
from typing import Any, Mapping, Optional, Tuple

from landmark_ros.core.covariance import (COVARIANCE_PROBLEMS, COVARIANCE_RANGE_PROBLEMS,
                                          covariance_status)
from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.core.sensors import MIN_RANGE, range_noise_variance
from landmark_ros.pipeline.limits import landmark_problems, MAX_COORDINATE
from landmark_ros.pipeline.rows import first_problems, in_range_fast, MAX_ID, range_status
import numpy as np
from numpy.typing import NDArray

NOISE_FIELDS = ('range_variance', 'bearing_variance', 'range_bearing_covariance')


def observation_noise(columns: Mapping[str, NDArray[Any]], range_variance: float,
                      bearing_variance: float,
                      range_variance_per_m2: float = 0.0,
                      range_variance_per_m4: float = 0.0) -> NDArray[np.float64]:
    """
    Return the noise covariance ``R`` of range-bearing observations.

    Rows take ``range_variance``, ``bearing_variance`` and ``range_bearing_covariance``
    from their columns when present and not NaN, else the defaults (no correlation).
    The default range variance is ``range_variance + range_variance_per_m2 * range^2
    + range_variance_per_m4 * range^4``: a constant part, one whose standard deviation
    is proportional to the range and one whose standard deviation is proportional to
    its square.

    Parameters
    ----------
    columns : dict of ndarray, shape (N,)
        Fields of the rows by name; 'range' is required.
    range_variance : float [m^2]
        Default range variance, constant part.
    bearing_variance : float [rad^2]
        Default bearing variance.
    range_variance_per_m2 : float
        Default range variance per squared metre of range [m^2 / m^2].
    range_variance_per_m4 : float
        Default range variance per fourth power of the range [m^2 / m^4].

    Returns
    -------
    R : ndarray, shape (2, 2) or (N, 2, 2)
        One matrix shared by all rows when the cloud has no noise fields and the
        range variance does not depend on the range.

    """
    per_row = any(name in columns for name in NOISE_FIELDS)
    if not per_row and not (range_variance_per_m2 or range_variance_per_m4):
        return np.array([[range_variance, 0.0], [0.0, bearing_variance]])
    count = len(columns['range'])
    default_rr = range_variance
    if range_variance_per_m2 or range_variance_per_m4:
        default_rr = range_noise_variance(columns['range'], range_variance,
                                          range_variance_per_m2, range_variance_per_m4)

    def column(name, default):
        values = columns.get(name)
        if values is None:
            return np.broadcast_to(default, (count,))
        return np.where(np.isnan(values), default, values)

    R = np.empty((count, 2, 2))
    R[:, 0, 0] = column('range_variance', default_rr)
    R[:, 1, 1] = column('bearing_variance', bearing_variance)
    R[:, 0, 1] = R[:, 1, 0] = column('range_bearing_covariance', 0.0)
    return R


def row_problems(ids: NDArray[np.integer[Any]], z: NDArray[np.float64],
                 R: NDArray[np.float64]) -> Tuple[NDArray[np.bool_], Counter[str]]:
    """
    Find the rows that cannot be used, and why.

    Parameters
    ----------
    ids : ndarray of int, shape (N,)
        Landmark IDs.
    z : ndarray, shape (N, 2)
        Range [m] and bearing [rad].
    R : ndarray, shape (2, 2) or (N, 2, 2)
        Noise covariance, shared (already valid) or per row.

    Returns
    -------
    valid : ndarray of bool, shape (N,)
    reasons : collections.Counter
        Rejected rows per reason (each row counted once, under its first problem).

    """
    r = z[:, 0]
    valid = np.isfinite(r + z[:, 1]) & (r >= MIN_RANGE) & (ids >= 0) & (ids <= MAX_ID)
    status = None
    if R.ndim == 3:
        status = np.atleast_1d(covariance_status(R))
        valid &= status == 0
    if np.count_nonzero(valid) == len(valid):
        return valid, Counter()
    checks = [
        ('observation_nonfinite', ~np.all(np.isfinite(z), axis=1)),
        ('range_not_positive', ~(r >= MIN_RANGE)),
        ('invalid_id', (ids < 0) | (ids > MAX_ID)),
    ]
    if status is not None:
        checks.append(('negative_variance', (R[:, 0, 0] < 0.0) | (R[:, 1, 1] < 0.0)))
        checks += [(f'noise_{name}', status == code)
                   for code, name in COVARIANCE_PROBLEMS.items()]
    return first_problems(len(ids), checks)


def bias_covariance(R_bias: Optional[NDArray[np.float64]], range_scale_variance: float,
                    r: NDArray[np.float64]) -> Optional[NDArray[np.float64]]:
    """
    Return the covariance of the sensor bias of each row: an offset and a scale error.

    The shared range error of a row at range ``r`` is ``b + s r`` (an offset ``b`` of
    variance ``R_bias[0, 0]`` and a scale error ``s`` of variance
    ``range_scale_variance``, independent), so its variance is
    ``R_bias[0, 0] + range_scale_variance r^2``; the bearing terms are ``R_bias``'s.

    Parameters
    ----------
    R_bias : ndarray, shape (2, 2), optional
        Covariance of the offsets (range [m^2], bearing [rad^2]); None: zero.
    range_scale_variance : float
        Variance of the relative range error ``s`` (dimensionless).
    r : ndarray, shape (N,)
        Range of each row [m].

    Returns
    -------
    ndarray, shape (2, 2) or (N, 2, 2), or None
        ``R_bias`` itself without a scale error (None if it is None), else one
        matrix per row.

    """
    if not range_scale_variance:
        return R_bias
    out = np.zeros((len(r), 2, 2))
    if R_bias is not None:
        out[:] = R_bias
    out[:, 0, 0] += range_scale_variance * np.square(r)
    return out


def landmarks_from_rows(
        ids: NDArray[np.integer[Any]], z: NDArray[np.float64], R: NDArray[np.float64],
        pose: NDArray[np.float64], P_pose: NDArray[np.float64],
        sensor_pose: Optional[NDArray[np.float64]] = None,
        R_bias: Optional[NDArray[np.float64]] = None,
        range_scale_variance: float = 0.0,
) -> Tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
           Counter[str]]:
    """
    Turn the valid observation rows into world-frame landmarks.

    Parameters
    ----------
    ids : ndarray of int, shape (N,)
        Landmark IDs.
    z : ndarray, shape (N, 2)
        Range-bearing observation (range [m], bearing [rad]).
    R : ndarray, shape (2, 2) or (N, 2, 2)
        Covariance of the observation noise.
    pose : ndarray, shape (3,) or (N, 3)
        Robot pose in the world, one for all rows or one per row.
    P_pose : ndarray, shape (3, 3) or (N, 3, 3)
        Covariance of the pose.
    sensor_pose : ndarray, shape (3,), optional
        Sensor pose in the robot frame; ``None`` means the robot origin.
    R_bias : ndarray, shape (2, 2), optional
        Covariance of the sensor bias, shared by all observations.
    range_scale_variance : float
        Variance of a range scale error shared by all observations (``bias_covariance``:
        the dependent range variance of a row grows by it times the range squared).

    Returns
    -------
    kept : ndarray of bool, shape (N,)
        The rows the results are for (``K`` of them).
    m : ndarray, shape (K, 2)
    P_m : ndarray, shape (K, 2, 2)
        Total covariance.
    P_dep : ndarray, shape (K, 2, 2)
        Its dependent part (pose and bias terms).
    reasons : collections.Counter
        Rows rejected, by reason; ``K`` plus their total is ``N``.

    """
    kept, reasons = row_problems(ids, z, R)
    if reasons:  # compress(): boolean indexing of (N, 2, 2) rows is several times slower
        z = z.compress(kept, axis=0)
        R = R.compress(kept, axis=0) if R.ndim == 3 else R
        pose = pose.compress(kept, axis=0) if pose.ndim == 2 else pose
        P_pose = P_pose.compress(kept, axis=0) if P_pose.ndim == 3 else P_pose
    R_bias = bias_covariance(R_bias, range_scale_variance, z[:, 0])
    with np.errstate(over='ignore', invalid='ignore'):  # huge ranges: caught below
        m, P_m, P_dep = landmark_to_world_dependent(pose, P_pose, z, R, R_bias, sensor_pose)
        if _all_pass(m, P_m, P_dep):
            return kept, m, P_m, P_dep, reasons
        if all(np.count_nonzero(np.isfinite(x)) == x.size for x in (m, P_m, P_dep)):
            finite = np.ones(len(m), bool)
        else:
            finite = np.isfinite(m.sum(axis=1) + P_m.sum(axis=(1, 2)) + P_dep.sum(axis=(1, 2)))
    # Only covariances the core handles leave the observer (core.gaussian's range).
    status = range_status(P_m, finite)
    far = finite & landmark_problems(m)[0][1]
    good = finite & (status == 0) & ~far
    if np.count_nonzero(good) < len(good):
        reasons['result_nonfinite'] += int((~finite).sum())
        if np.count_nonzero(far):
            reasons['result_landmark_out_of_range'] += int(far.sum())
        for code, name in COVARIANCE_RANGE_PROBLEMS.items():
            count = int((finite & (status == code)).sum())
            if count:
                reasons[f'result_{name}'] += count
        kept[np.flatnonzero(kept)[~good]] = False
        m, P_m, P_dep = (x.compress(good, axis=0) for x in (m, P_m, P_dep))
    return kept, m, P_m, P_dep, reasons


def _all_pass(m: NDArray[np.float64], P_m: NDArray[np.float64],
              P_dep: NDArray[np.float64]) -> bool:
    """
    Return True when every placed row passes ``landmarks_from_rows``' result checks.

    A sufficient test (most messages, about half the cost of the checks): every
    coordinate within ``limits.MAX_COORDINATE`` (so finite and not out of range), the
    covariances finite, and ``range_status``'s fast test passed by every row. False
    says nothing: the checks run row by row.
    """
    return (np.count_nonzero(np.abs(m) <= MAX_COORDINATE) == m.size
            and np.count_nonzero(np.isfinite(P_m)) == P_m.size
            and np.count_nonzero(np.isfinite(P_dep)) == P_dep.size
            and np.count_nonzero(in_range_fast(P_m)) == len(P_m))
