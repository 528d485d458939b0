"""The records of ``localizer.Localizer``: sightings, filter steps and pose estimates."""

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Deque, Dict, List, Optional, Sequence, Tuple

from landmark_ros.localizer.update import UpdateResult
import numpy as np
from numpy.typing import NDArray


@dataclass
class Batch:
    """Sightings at one stamp, with the landmarks they refer to."""

    stamp_ns: int
    m: NDArray[np.float64]
    """Landmark (or other robot) positions, shape (N, 2)."""
    P_m: NDArray[np.float64]
    """Their covariances, shape (N, 2, 2)."""
    z: NDArray[np.float64]
    """Observations (range, bearing), shape (N, 2)."""
    R: NDArray[np.float64]
    """Sensor noise, shape (N, 2, 2)."""
    kind: NDArray[np.int64]
    """``update.RANGE_BEARING``, ``RANGE`` or ``BEARING`` per row, shape (N,)."""
    correlation: Optional[str] = None
    """Overrides the config's (``'split_ci'`` for other robots)."""
    label: str = 'rows'
    """Counter prefix: ``rows`` (landmarks) or ``robot_rows`` (other robots)."""
    shared: Optional[NDArray[np.float64]] = None
    """Per row, how many sightings share its time-correlated error (>= 1), shape (N,)."""
    shared_bias: Optional[NDArray[np.float64]] = None
    """Per row, how many sightings (any landmark) share the sensor bias, shape (N,)."""
    result: Optional[UpdateResult] = None
    alternatives: Optional[Dict[int, Tuple[NDArray[np.float64], NDArray[np.float64],
                                           NDArray[np.float64], NDArray[np.int64]]]] = None
    """Rows whose landmark is one of several: row -> candidates (C, 2), their
    covariances (C, 2, 2), probabilities (C,) and IDs (C,) (``localizer.mixture``)."""
    landmarks: Optional[NDArray[np.int64]] = None
    """Map IDs of the rows, shape (N,) (None: not map landmarks)."""


@dataclass
class Step:
    """One odometry step: its motion, the state before and after its updates."""

    stamp_ns: int
    delta: NDArray[np.float64]
    Q: NDArray[np.float64]
    odom: NDArray[np.float64]
    x_prior: NDArray[np.float64]
    P_prior: NDArray[np.float64]
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    batches: List[Batch] = field(default_factory=list)
    C_prior: Optional[NDArray[np.float64]] = None
    """Cross-covariance with the consider landmarks before the updates (``consider``)."""
    C: Optional[NDArray[np.float64]] = None
    """The same after them."""


@dataclass(frozen=True)
class Estimate:
    """The pose at one stamp."""

    stamp_ns: int
    x: NDArray[np.float64]
    P: NDArray[np.float64]


def count_shared(sightings: Dict[Any, Deque[int]], stamp_ns: int, ids: Sequence[Any],
                 tau_ns: int) -> NDArray[np.float64]:
    """
    Return per row the sightings of its landmark within the correlation time, shape (N,).

    The time-correlated part of the noise (``*_correlated_fraction``, correlation
    time ``tau_ns``, ``noise_correlation_time_s``) repeats across the sightings of a
    landmark made within that time: n sightings that share one error carry the
    information of one, so each counts with its correlated variance times n (the
    sightings of the trailing correlation time, this one included). Without a
    correlation time the count is 1. In steady state (a landmark seen at a steady rate)
    each sighting weighs 1/n and the sightings of one correlation time weigh one; right
    after a first encounter the k-th weighs 1/k, so the first n weigh the harmonic sum
    H(n) (about 5 for 100): over-confident by that factor at most. ``sightings`` (the
    stamps per landmark key) is updated with this stamp.
    """
    shared = np.ones(len(ids))
    if tau_ns <= 0:
        return shared
    for row, landmark in enumerate(ids.tolist() if hasattr(ids, 'tolist') else ids):
        seen = sightings.setdefault(landmark, deque())
        seen.append(stamp_ns)
        while seen and seen[0] <= stamp_ns - tau_ns:
            seen.popleft()
        shared[row] = sum(1 for t in seen if t <= stamp_ns)
    return shared
