"""
Row checks shared by the observer, the fuser and the localizer (ROS-free).

The ID range (``MAX_ID``, ``UNKNOWN_ID``, ``MAX_LABEL_ID``), the combination of row
checks into named rejection reasons (``first_problems``), the fast covariance range
test (``range_status``) and the checks of landmark rows (``landmark_row_problems``:
what a fuser or a localizer may take from another node or a map file).
"""

from collections import Counter
from typing import Any, Sequence, Tuple

from landmark_ros.core.covariance import (COVARIANCE_ASYMMETRIC, COVARIANCE_NOT_PSD,
                                          COVARIANCE_RANGE_PROBLEMS,
                                          covariance_range_status, covariance_status,
                                          MAX_CONDITION, MAX_VARIANCE, MIN_VARIANCE)
from landmark_ros.pipeline.limits import landmark_problems
import numpy as np
from numpy.typing import NDArray

MAX_ID = 2 ** 32 - 1
"""Largest ID a row may carry (the UINT32 range); it is ``UNKNOWN_ID``."""

UNKNOWN_ID = MAX_ID
"""The ID of a row without one (4294967295): the fuser associates it by position."""

MAX_LABEL_ID = UNKNOWN_ID - 1
"""Largest ID of a landmark (a labelled row, a map record, an allocated ID)."""


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
        rejected = int(np.count_nonzero(new))  # cheaper than any() then sum()
        if rejected:
            reasons[name] = rejected
            valid &= ~new
    return valid, reasons


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
    # Entries 00, 01, 10, 11 as contiguous rows: a few times faster than (N, 2, 2) axes.
    p, q = (np.reshape(x, (-1, 4)).T.copy() for x in (P, P_dep))
    with np.errstate(invalid='ignore', over='ignore', divide='ignore'):
        finite = np.isfinite(m[:, 0] + m[:, 1] + (p[0] + p[1] + p[2] + p[3])
                             + (q[0] + q[1] + q[2] + q[3]))
        # Scaled to unit size, so that huge and tiny covariances compare alike.
        scale = np.maximum(np.maximum(np.abs(p[0]), np.abs(p[1])),
                           np.maximum(np.abs(p[2]), np.abs(p[3])))
        unit, dep = p / scale, q / scale
        a, b, c = unit[0], unit[1], unit[3]
        definite = (a > 0.0) & (a * c - b * b > 1e-12) & (np.abs(b - unit[2]) <= 1e-9)
        dependent = _psd_2x2(dep) & _psd_2x2(unit - dep)
        in_range = range_status(P, finite & definite) == 0
        valid = finite & definite & in_range & dependent & (ids >= 0) & (ids <= MAX_ID)
        valid &= ~landmark_problems(m)[0][1]
        if np.count_nonzero(valid) == len(valid):
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
    return first_problems(len(ids), checks + landmark_problems(m))


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
    status = np.zeros(len(P), np.int64)
    slow = usable & ~in_range_fast(P)
    if np.count_nonzero(slow):
        status[slow] = np.atleast_1d(covariance_range_status(P.compress(slow, axis=0)))
    return status


def in_range_fast(P: NDArray[np.float64]) -> NDArray[np.bool_]:
    """
    Return where symmetric 2x2 covariances pass ``range_status``'s sufficient test.

    Diagonal inside ``[MIN_VARIANCE, MAX_VARIANCE]`` and ``trace^2 <= MAX_CONDITION
    det``: True implies status 0; False (NaN included) says nothing.

    Parameters
    ----------
    P : ndarray, shape (N, 2, 2)
        Covariances [m^2]; only the entries 00, 01 and 11 are read.

    Returns
    -------
    ndarray of bool, shape (N,)

    """
    a, b, c = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    with np.errstate(invalid='ignore', over='ignore'):
        trace = a + c
        return (np.minimum(a, c) >= MIN_VARIANCE) & (np.maximum(a, c) <= MAX_VARIANCE) & (
            trace * trace <= MAX_CONDITION * (a * c - b * b))


def _psd_2x2(P, tol=1e-9):
    """Return where unit-scaled 2x2 matrices (entries 00, 01, 10, 11 as rows) are PSD."""
    a, b, c = P[0], 0.5 * (P[1] + P[2]), P[3]
    return (a >= -tol) & (c >= -tol) & (a * c - b * b >= -tol) & (np.abs(P[1] - P[2]) <= tol)
