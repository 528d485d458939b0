"""The records of ``localizer.Localizer``: sightings, filter steps and pose estimates."""

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

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
                                           NDArray[np.float64]]]] = None
    """Rows whose landmark is one of several: row -> candidates (C, 2), their
    covariances (C, 2, 2) and probabilities (C,) (``localizer.mixture``)."""


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


@dataclass(frozen=True)
class Estimate:
    """The pose at one stamp."""

    stamp_ns: int
    x: NDArray[np.float64]
    P: NDArray[np.float64]
