"""
Partial observations between the observer and the fuser: their rows (ROS-free).

A partial observation is a range-only or a bearing-only measurement of a landmark,
placed in the world with the sensor pose and its covariance (``core.partial.Views``,
one scalar view each). The observer makes them (``observer.partial``), the fuser
buffers, places and fuses them (``fuser.partial``); in between they travel as rows of
``PARTIAL_COLUMNS`` on the ``partial_observations`` topic (``ros.schemas``).

Symbols as in ``core.partial``: ``kind`` (``RANGE`` 0, ``BEARING`` 1), ``s`` and
``P_s`` the sensor pose in the world (x [m], y [m], theta [rad]) and its covariance,
``y`` the measured value (range [m] or bearing [rad]), ``R`` the variance of the
independent noise, ``R_bias`` that of a sensor bias; a range row may carry the
range scale of its camera (``RANGE_SCALE_COLUMNS``, ``Views.range_scale``).
"""

from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

from landmark_ros.core.partial import Views
import numpy as np
from numpy.typing import NDArray

PARTIAL_COLUMNS = (
    'id', 'kind', 'value', 'variance', 'variance_dep', 'sensor_x', 'sensor_y', 'sensor_theta',
    'sensor_cov_xx', 'sensor_cov_xy', 'sensor_cov_xt', 'sensor_cov_yy', 'sensor_cov_yt',
    'sensor_cov_tt', 'view_group')
"""Columns of a ``partial_observations`` row, in wire order (``ros.schemas``)."""

RANGE_SCALE_COLUMNS = ('range_scale_q0', 'range_scale_q1', 'range_scale_q2',
                       'range_scale_bearing_limit')
"""Optional columns after ``PARTIAL_COLUMNS``: ``Views.range_scale`` and its bearing
limit [rad]. Absent, a row has no range scale (zeros and pi)."""

NO_RANGE_SCALE_ROW = (0.0, 0.0, 0.0, float(np.pi))
"""``RANGE_SCALE_COLUMNS`` of a row without a range scale."""

SENSOR_COVARIANCE_COLUMNS = (
    ('sensor_cov_xx', 0, 0), ('sensor_cov_xy', 0, 1), ('sensor_cov_xt', 0, 2),
    ('sensor_cov_yy', 1, 1), ('sensor_cov_yt', 1, 2), ('sensor_cov_tt', 2, 2))
"""The sensor pose covariance columns and their ``(row, column)`` in ``P_s``."""


@dataclass(frozen=True)
class PartialObservations:
    """
    The partial rows of one observation message, as views in the world.

    Attributes
    ----------
    ids : ndarray of int64, shape (K,)
        Landmark IDs.
    views : core.partial.Views or None
        ``K`` views (``kind``, ``s``, ``P_s``, ``y``, ``R``, ``R_bias``); None when
        ``K`` is 0.
    view_group : ndarray of int64, shape (K,)
        Which views share one pose error (same robot, same stamp): the same number.

    """

    ids: NDArray[np.int64]
    views: Optional[Views]
    view_group: NDArray[np.int64]

    def __len__(self) -> int:
        """Return the number of partial observations ``K``."""
        return len(self.ids)

    def columns(self) -> Dict[str, NDArray[Any]]:
        """Return the rows as ``PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS``, shape (K,) each."""
        out: Dict[str, NDArray[Any]] = {'id': self.ids, 'view_group': self.view_group}
        if self.views is None:
            out.update({name: np.zeros(0) for name in PARTIAL_COLUMNS[2:-1]})
            out['kind'] = np.zeros(0, np.int64)
            out.update({name: np.zeros(0) for name in RANGE_SCALE_COLUMNS})
        else:
            v = self.views
            out.update({'kind': v.kind, 'value': v.y, 'variance': v.R,
                        'variance_dep': v.R_bias, 'sensor_x': v.s[:, 0],
                        'sensor_y': v.s[:, 1], 'sensor_theta': v.s[:, 2]})
            out.update({name: v.P_s[:, i, j] for name, i, j in SENSOR_COVARIANCE_COLUMNS})
            out.update(zip(RANGE_SCALE_COLUMNS, (*v.range_scale.T, v.range_scale_bearing_limit)))
        return {name: out[name] for name in PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS}


def no_partial_observations() -> PartialObservations:
    """Return an empty ``PartialObservations``."""
    return PartialObservations(np.empty(0, np.int64), None, np.empty(0, np.int64))


def sensor_covariance(columns: Dict[str, NDArray[Any]]) -> NDArray[np.float64]:
    """Return the sensor pose covariances of partial observation rows, shape (N, 3, 3)."""
    count = len(columns['id'])
    P_s = np.zeros((count, 3, 3))
    for name, i, j in SENSOR_COVARIANCE_COLUMNS:
        P_s[:, i, j] = P_s[:, j, i] = columns[name]
    return P_s


def with_range_scale(columns: Dict[str, NDArray[Any]]) -> Dict[str, NDArray[Any]]:
    """Return partial observation rows with ``RANGE_SCALE_COLUMNS`` (defaults if absent)."""
    count = len(columns['id'])
    missing = {name: np.full(count, value) for name, value in
               zip(RANGE_SCALE_COLUMNS, NO_RANGE_SCALE_ROW) if name not in columns}
    return dict(columns, **missing) if missing else columns


def range_scale(columns: Dict[str, NDArray[Any]]
                ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return ``Views.range_scale`` (N, 3) and its bearing limit (N,) of rows."""
    columns = with_range_scale(columns)
    q = np.stack([np.asarray(columns[name], np.float64) for name in RANGE_SCALE_COLUMNS[:3]],
                 axis=1).reshape(-1, 3)
    return q, np.asarray(columns[RANGE_SCALE_COLUMNS[3]], np.float64)
