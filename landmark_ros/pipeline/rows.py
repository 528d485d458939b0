"""Observation rows to world-frame landmarks: noise, row checks, core call (ROS-free)."""

from collections import Counter
from typing import Any, Mapping, Optional, Sequence, Tuple

from landmark_ros.core.covariance import (COVARIANCE_ASYMMETRIC, COVARIANCE_NOT_PSD,
                                          COVARIANCE_PROBLEMS, COVARIANCE_RANGE_PROBLEMS,
                                          covariance_range_status, covariance_status,
                                          MAX_CONDITION, MAX_VARIANCE, MIN_VARIANCE)
from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.core.sensors import MIN_RANGE
import numpy as np
from numpy.typing import NDArray


MAX_ID = 2 ** 32 - 1
"""Largest ID a row may carry (the UINT32 range); it is ``UNKNOWN_ID``."""

UNKNOWN_ID = MAX_ID
"""The ID of a row without one (4294967295): the fuser associates it by position."""

MAX_LABEL_ID = UNKNOWN_ID - 1
"""Largest ID of a landmark (a labelled row, a map record, an allocated ID)."""


NOISE_FIELDS = ('range_variance', 'bearing_variance', 'range_bearing_covariance')


def first_problems(
        count: int, checks: Sequence[Tuple[str, NDArray[np.bool_]]]
) -> Tuple[NDArray[np.bool_], Counter[str]]:
    """
    Combine row checks: each bad row is counted once, under its first problem.

    Parameters
    ----------
    count : int
        Number of rows.
    checks : list of (str, ndarray of bool, shape (N,))
        Reason names and where they apply, in order of precedence.

    Returns
    -------
    valid : ndarray of bool, shape (N,)
    reasons : collections.Counter
        Rows per reason.

    """
    valid = np.ones(count, dtype=bool)
    reasons: Counter[str] = Counter()
    for name, bad in checks:
        new = bad & valid
        if new.any():
            reasons[name] = int(new.sum())
            valid &= ~new
    return valid, reasons


def observation_noise(columns: Mapping[str, NDArray[Any]], range_variance: float,
                      bearing_variance: float,
                      range_variance_per_m2: float = 0.0) -> NDArray[np.float64]:
    """
    Return the noise covariance ``R`` of range-bearing observations.

    Rows take ``range_variance``, ``bearing_variance`` and ``range_bearing_covariance``
    from their columns when present and not NaN, else the defaults (no correlation).
    The default range variance is ``range_variance + range_variance_per_m2 * range^2``:
    a constant part and one proportional to the range.

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

    Returns
    -------
    R : ndarray, shape (2, 2) or (N, 2, 2)
        One matrix shared by all rows when the cloud has no noise fields and the
        range variance does not depend on the range.

    """
    per_row = any(name in columns for name in NOISE_FIELDS)
    if not per_row and not range_variance_per_m2:
        return np.array([[range_variance, 0.0], [0.0, bearing_variance]])
    count = len(columns['range'])
    default_rr = range_variance
    if range_variance_per_m2:
        default_rr = range_variance + range_variance_per_m2 * columns['range'] ** 2

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
    if valid.all():
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


def landmarks_from_rows(
        ids: NDArray[np.integer[Any]], z: NDArray[np.float64], R: NDArray[np.float64],
        pose: NDArray[np.float64], P_pose: NDArray[np.float64],
        sensor_pose: Optional[NDArray[np.float64]] = None,
        R_bias: Optional[NDArray[np.float64]] = None,
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
    if reasons:
        z = z[kept]
        R = R[kept] if R.ndim == 3 else R
        pose = pose[kept] if pose.ndim == 2 else pose
        P_pose = P_pose[kept] if P_pose.ndim == 3 else P_pose
    with np.errstate(over='ignore', invalid='ignore'):  # huge ranges: caught below
        m, P_m, P_dep = landmark_to_world_dependent(pose, P_pose, z, R, R_bias, sensor_pose)
        if np.isfinite(m).all() and np.isfinite(P_m).all() and np.isfinite(P_dep).all():
            finite = np.ones(len(m), bool)
        else:
            finite = np.isfinite(m.sum(axis=1) + P_m.sum(axis=(1, 2)) + P_dep.sum(axis=(1, 2)))
    # Only covariances the core handles leave the observer (core.gaussian's range).
    status = range_status(P_m, finite)
    good = finite & (status == 0)
    if not good.all():
        reasons['result_nonfinite'] += int((~finite).sum())
        for code, name in COVARIANCE_RANGE_PROBLEMS.items():
            count = int((finite & (status == code)).sum())
            if count:
                reasons[f'result_{name}'] += count
        kept[np.flatnonzero(kept)[~good]] = False
        m, P_m, P_dep = m[good], P_m[good], P_dep[good]
    return kept, m, P_m, P_dep, reasons


def landmark_row_problems(
        ids: NDArray[np.integer[Any]], m: NDArray[np.float64], P: NDArray[np.float64],
        P_dep: NDArray[np.float64]) -> Tuple[NDArray[np.bool_], Counter[str]]:
    """
    Find the landmark rows (fuser input) that cannot be fused, and why (vectorised).

    Parameters
    ----------
    ids : ndarray of int, shape (N,)
        Landmark IDs.
    m : ndarray, shape (N, 2)
        Positions [m].
    P : ndarray, shape (N, 2, 2)
        Total covariances; fusion needs them positive definite.
    P_dep : ndarray, shape (N, 2, 2)
        Dependent parts; positive semi-definite and not larger than ``P``.

    Returns
    -------
    valid : ndarray of bool, shape (N,)
    reasons : collections.Counter
        Rejected rows per reason (each row counted once, under its first problem).

    """
    finite = np.isfinite(m.sum(axis=1) + P.sum(axis=(1, 2)) + P_dep.sum(axis=(1, 2)))
    with np.errstate(invalid='ignore', over='ignore', divide='ignore'):
        # Scaled to unit size, so that huge and tiny covariances compare alike.
        scale = np.abs(P).max(axis=(1, 2))
        unit, dep = P / scale[:, None, None], P_dep / scale[:, None, None]
        a, b, c = unit[:, 0, 0], unit[:, 0, 1], unit[:, 1, 1]
        definite = (a > 0.0) & (a * c - b * b > 1e-12) & (np.abs(b - unit[:, 1, 0]) <= 1e-9)
        rest = unit - dep
        dependent = _psd_2x2(dep) & _psd_2x2(rest)
        in_range = range_status(P, finite & definite) == 0
        valid = finite & definite & in_range & dependent & (ids >= 0) & (ids <= MAX_ID)
        if valid.all():
            return valid, Counter()
        total = np.atleast_1d(covariance_status(np.where(finite[:, None, None], P, 0.0)))
        span = np.atleast_1d(covariance_range_status(np.where(finite[:, None, None], P, 1.0)))
    checks = [
        ('landmark_nonfinite', ~finite),
        ('invalid_id', (ids < 0) | (ids > MAX_ID)),
        ('covariance_asymmetric', total == COVARIANCE_ASYMMETRIC),
        ('covariance_not_psd', total == COVARIANCE_NOT_PSD),
    ]
    checks.append(('covariance_singular', ~definite))
    checks += [(name, span == code) for code, name in COVARIANCE_RANGE_PROBLEMS.items()]
    checks.append(('dependent_part_invalid', ~dependent))
    return first_problems(len(ids), checks)


def range_status(P: NDArray[np.float64], usable: NDArray[np.bool_]) -> NDArray[np.int64]:
    """
    Return ``core.covariance.covariance_range_status`` of symmetric 2x2 covariances, fast.

    A sufficient test in a few vector operations passes most rows (diagonal inside
    ``[MIN_VARIANCE, MAX_VARIANCE]`` and ``trace^2 <= MAX_CONDITION det``, which bounds
    the condition number since the largest eigenvalue is below the trace); only the
    others go through the core's exact check.

    Parameters
    ----------
    P : ndarray, shape (N, 2, 2)
        Covariances [m^2].
    usable : ndarray of bool, shape (N,)
        Rows to check; the others get status 0 (they are rejected for another reason).

    Returns
    -------
    ndarray of int, shape (N,)
        0 where in range, else a code of ``COVARIANCE_RANGE_PROBLEMS``.

    """
    a, b, c = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    with np.errstate(invalid='ignore', over='ignore'):
        trace = a + c
        fast = (np.minimum(a, c) >= MIN_VARIANCE) & (np.maximum(a, c) <= MAX_VARIANCE) & (
            trace * trace <= MAX_CONDITION * (a * c - b * b))
    status = np.zeros(len(P), np.int64)
    slow = usable & ~fast
    if slow.any():
        status[slow] = np.atleast_1d(covariance_range_status(P[slow]))
    return status


def _psd_2x2(P, tol=1e-9):
    """Return where unit-scaled symmetric 2x2 matrices are positive semi-definite."""
    a, b, c = P[:, 0, 0], 0.5 * (P[:, 0, 1] + P[:, 1, 0]), P[:, 1, 1]
    return (a >= -tol) & (c >= -tol) & (a * c - b * b >= -tol) & (
        np.abs(P[:, 0, 1] - P[:, 1, 0]) <= tol)
