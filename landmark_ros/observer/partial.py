"""
The observer's side of partial observations: range-only and bearing-only rows (ROS-free).

Observation rows that carry only a range or only a bearing (a cloud without the other
column, or a NaN in it) become partial observations: one scalar view each, with the
sensor pose in the world and its covariance (``core.partial.views_from_robot``),
published on ``partial_observations`` (rows of ``pipeline.partial_rows``). Time is
integer nanoseconds.
"""

from collections import Counter
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

from landmark_ros.core.partial import BEARING, RANGE, views_from_robot
from landmark_ros.core.range_scale import MIN_SCALE
from landmark_ros.core.sensors import MIN_RANGE
from landmark_ros.pipeline.limits import partial_problems
from landmark_ros.pipeline.partial_rows import (no_partial_observations, NO_RANGE_SCALE_ROW,
                                                PartialObservations, range_scale,
                                                RANGE_SCALE_COLUMNS)
from landmark_ros.pipeline.rows import first_problems, MAX_ID, UNKNOWN_ID
import numpy as np
from numpy.typing import NDArray


def split_partial(
        columns: Dict[str, NDArray[Any]]) -> Tuple[Dict[str, NDArray[Any]], NDArray[np.bool_]]:
    """
    Fill a missing ``range`` or ``bearing`` column with NaN; find the partial rows.

    A row is partial when exactly one of its range and bearing is NaN (a cloud
    without the column is all NaN there); a row with both NaN stays a full row (the
    range-bearing checks reject it as non-finite).

    Parameters
    ----------
    columns : dict of str to ndarray, shape (N,)
        ``id`` and at least one of ``range`` [m] and ``bearing`` [rad].

    Returns
    -------
    columns : dict of str to ndarray, shape (N,)
        With both ``range`` and ``bearing``.
    partial : ndarray of bool, shape (N,)

    """
    count = len(columns['id'])
    if 'range' not in columns or 'bearing' not in columns:
        columns = dict(columns)
        for name in ('range', 'bearing'):
            if name not in columns:
                columns[name] = np.full(count, np.nan)
    r = np.asarray(columns['range'], dtype=np.float64)
    b = np.asarray(columns['bearing'], dtype=np.float64)
    return columns, np.isnan(r) != np.isnan(b)


class CorrelatedNoise:
    """
    Time-correlated sensor noise: the information a view adds after a recent one.

    The noise of a view is modelled as white noise plus a first-order Gauss-Markov
    (exponentially correlated) part holding ``fraction`` of its variance, with
    correlation time ``tau``: two views of one landmark ``dt`` apart by the same
    sensor have errors correlated by ``rho = fraction * exp(-dt / tau)``. The fuser
    treats views as independent, so each view's variance is inflated so that a run of
    views carries the information of the correlated sequence: the correlated part by
    ``(1 + rho1) / (1 - rho1) = coth(dt / (2 tau))`` with ``rho1 = exp(-dt / tau)``
    and ``dt`` the time since the previous view of the landmark (of that kind) by this
    sensor, the white part as it is. The factor is the variance of the mean of a
    first-order autoregressive sequence relative to independent samples (Bayley and
    Hammersley, "The effective number of independent observations in an autocorrelated
    time series", J. R. Stat. Soc. Suppl. 8(2), 1946). The first view of a landmark,
    or one after a long gap, keeps its variance (factor 1).

    Parameters
    ----------
    range_fraction, bearing_fraction : float
        In [0, 1): share of the range (bearing) noise variance that is correlated.
    correlation_time_s : float
        ``tau`` [s]; 0 means white noise (factor 1 always).
    max_landmarks : int
        Landmarks remembered; beyond, the least recently seen are forgotten (their
        next view counts as a first one).

    """

    def __init__(self, range_fraction: float, bearing_fraction: float,
                 correlation_time_s: float, max_landmarks: int = 100000) -> None:
        self.fraction = np.array([range_fraction, bearing_fraction], dtype=np.float64)
        self.tau_ns = float(correlation_time_s) * 1e9
        self.max_landmarks = int(max_landmarks)
        self.last_ns: Dict[Tuple[int, int], int] = {}

    @property
    def enabled(self) -> bool:
        """Return whether the noise is correlated at all."""
        return self.tau_ns > 0.0 and bool(self.fraction.any())

    def factors(self, stamp_ns: int, ids: NDArray[np.int64],
                kinds: NDArray[np.int64]) -> NDArray[np.float64]:
        """
        Return the variance factor of each view and remember the views' stamps.

        Parameters
        ----------
        stamp_ns : int
            Stamp of the views [ns].
        ids, kinds : ndarray of int, shape (K,)
            Landmark IDs and view kinds (``RANGE``, ``BEARING``).

        Returns
        -------
        ndarray, shape (K,)
            ``(1 - f) + f coth(dt / (2 tau))`` (at least 1); 1 for a first view. Two
            views of one landmark in one message (``dt`` 0) are capped at
            ``dt = 1 ns``.

        """
        count = len(ids)
        if not self.enabled or not count:
            return np.ones(count)
        gaps = np.full(count, np.inf)
        for k, key in enumerate(zip(np.asarray(ids).tolist(), np.asarray(kinds).tolist())):
            last = self.last_ns.pop(key, None)  # re-inserted below: most recent last
            if last is not None:
                gaps[k] = max(abs(int(stamp_ns) - last), 1)
            self.last_ns[key] = int(stamp_ns)
        while len(self.last_ns) > self.max_landmarks:
            del self.last_ns[next(iter(self.last_ns))]
        f = self.fraction[np.asarray(kinds, np.int64)]
        with np.errstate(divide='ignore', over='ignore'):
            coth = 1.0 / np.tanh(gaps / (2.0 * self.tau_ns))
        return (1.0 - f) + f * coth


@dataclass(frozen=True)
class RangeOnlyScale:
    """
    A camera's range scale for rows without a bearing (from ``ObserverConfig``).

    ``coeffs``, ``per_m``: ``core.range_scale``; ``no_bearing``: mean and standard
    deviation of ``c0 + c1 b + c2 b^2`` over the image; ``bearing_limit``: half the
    field of view [rad], 0 when unknown.
    """

    coeffs: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    per_m: float = 0.0
    no_bearing: Tuple[float, float] = (0.0, 0.0)
    bearing_limit: float = 0.0


def range_only_corrected(rows: Dict[str, NDArray[Any]], R: NDArray[np.float64],
                         lens: RangeOnlyScale
                         ) -> Tuple[Dict[str, NDArray[Any]], NDArray[np.float64]]:
    """
    Return partial rows with the mean range scale removed from range-only rows, and R.

    A range-only row is divided by ``g = 1 + s + per_m r`` (``s`` the mean of
    ``lens.no_bearing``) and ``R_rr`` by ``g^2``. What is left depends on the bearing
    of the landmark in the image, which the row lacks. With ``lens.bearing_limit`` and
    ``lens.coeffs`` set, the row carries it as a model (``RANGE_SCALE_COLUMNS``:
    ``q0 = (c0 - s) / g``, ``q1 = c1 / g``, ``q2 = c2 / g``; the fuser evaluates it
    at the landmark's predicted bearing, ``core.partial.Views``); otherwise its spread
    is noise, ``R_rr`` grows by ``(d r / g)^2`` (``d`` the standard deviation). Rows
    whose ``g`` would fall below ``range_scale.MIN_SCALE`` leave everything unchanged;
    bearing-only rows are unchanged.

    Parameters
    ----------
    rows : dict of str to ndarray, shape (K,)
        Partial rows: ``range`` [m], ``bearing`` [rad], one of them NaN.
    R : ndarray, shape (2, 2) or (K, 2, 2)
        Their noise covariance.
    lens : RangeOnlyScale
        The camera's range scale model.

    Returns
    -------
    rows : dict of str to ndarray, shape (K,)
    R : ndarray, shape (2, 2) or (K, 2, 2)

    """
    mean, spread = lens.no_bearing
    modelled = lens.bearing_limit > 0.0 and any(lens.coeffs)
    r = np.asarray(rows['range'], np.float64)
    only = np.isfinite(r) & ~np.isfinite(np.asarray(rows['bearing'], np.float64))
    if not (mean or spread or lens.per_m or modelled) or not only.any():
        return rows, R
    g = np.where(only, 1.0 + mean + lens.per_m * np.where(only, r, 0.0), 1.0)
    if np.any(g < MIN_SCALE):
        return rows, R
    R = np.array(np.broadcast_to(R, (len(r), 2, 2)))
    noise = 0.0 if modelled else (spread * r / g) ** 2
    R[:, 0, 0] = np.where(only, R[:, 0, 0] / g ** 2 + noise, R[:, 0, 0])
    rows = dict(rows, range=np.where(only, r / g, r))
    if modelled:
        c0, c1, c2 = lens.coeffs
        model = ((c0 - mean) / g, c1 / g, c2 / g, np.full(len(r), lens.bearing_limit))
        rows.update({name: np.where(only, value, default) for name, value, default in
                     zip(RANGE_SCALE_COLUMNS, model, NO_RANGE_SCALE_ROW)})
    return rows, R


@dataclass(frozen=True)
class SensorMount:
    """Where the sensor sits on the robot and how biased it is (from ``ObserverConfig``)."""

    sensor_pose: Optional[NDArray[np.float64]] = None
    """Sensor pose in the robot frame, shape (3,); None means the robot origin."""
    R_bias: Optional[NDArray[np.float64]] = None
    """Covariance of the sensor bias, shape (2, 2); None means no bias."""
    range_scale_variance: float = 0.0
    """Variance of a shared range scale error (``rows.bias_covariance``)."""


def partial_observations_from_rows(columns: Dict[str, NDArray[Any]], R: NDArray[np.float64],
                                   pose: NDArray[np.float64], P_pose: NDArray[np.float64],
                                   mount: SensorMount, view_group: int, stamp_ns: int = 0,
                                   correlated: Optional[CorrelatedNoise] = None
                                   ) -> Tuple[PartialObservations, Counter[str]]:
    """
    Turn the partial rows of one message into checked partial observations.

    Parameters
    ----------
    columns : dict of str to ndarray, shape (K,)
        The partial rows only: ``id``, ``range`` [m], ``bearing`` [rad], one of them NaN;
        optionally ``RANGE_SCALE_COLUMNS`` (``range_only_corrected``).
    R : ndarray, shape (2, 2) or (K, 2, 2)
        Noise covariance of the rows (``rows.observation_noise``); the diagonal entry
        of the measured column is the view's variance.
    pose : ndarray, shape (3,)
        Robot pose in the world.
    P_pose : ndarray, shape (3, 3)
        Its covariance.
    mount : SensorMount
        Sensor pose in the robot frame and covariance of the sensor bias (its diagonal,
        plus ``range_scale_variance r^2`` for a range, gives ``R_bias`` of the views).
    view_group : int
        In [0, 2^32 - 1]: the number every view of this pose gets.
    stamp_ns : int
        Stamp of the message [ns] (for ``correlated``).
    correlated : CorrelatedNoise, optional
        Time-correlated noise: the valid views' variances are multiplied by its
        ``factors`` (and their stamps remembered); None keeps them.

    Returns
    -------
    PartialObservations
    reasons : collections.Counter
        Rows rejected, by reason (``invalid_id``, ``range_not_positive``,
        ``variance_not_positive``, ``observation_nonfinite``).

    """
    ids = np.asarray(columns['id'])
    r = np.asarray(columns['range'], dtype=np.float64)
    b = np.asarray(columns['bearing'], dtype=np.float64)
    count = len(ids)
    sensor_pose, R_bias = mount.sensor_pose, mount.R_bias
    kind = np.where(np.isnan(r), BEARING, RANGE)
    y = np.where(kind == RANGE, r, b)
    R = np.broadcast_to(R, (count, 2, 2))
    variance = np.where(kind == RANGE, R[:, 0, 0], R[:, 1, 1])
    bias = np.zeros(count) if R_bias is None else np.where(kind == RANGE, R_bias[0, 0],
                                                           R_bias[1, 1])
    if mount.range_scale_variance:
        bias = bias + np.where(kind == RANGE, mount.range_scale_variance * r * r, 0.0)
    with np.errstate(invalid='ignore'):
        valid, reasons = first_problems(count, [
            ('observation_nonfinite', ~np.isfinite(y)),
            ('range_not_positive', (kind == RANGE) & ~(y >= MIN_RANGE)),
            ('invalid_id', (ids < 0) | (ids > MAX_ID)),
            # Views are gathered by ID: no association of partial rows (yet).
            ('partial_without_id', ids == UNKNOWN_ID),
            ('variance_not_positive', ~(variance > 0.0) | ~np.isfinite(variance)),
        ] + partial_problems({}, kind, y, variance, RANGE))
    if not valid.any():
        return no_partial_observations(), reasons
    variance = variance[valid]
    if correlated is not None:
        variance = variance * correlated.factors(stamp_ns, ids[valid], kind[valid])
    q, limit = range_scale(columns)
    views = views_from_robot(kind[valid], pose, P_pose, y[valid], variance,
                             bias[valid], sensor_pose, (q[valid], limit[valid]))
    return PartialObservations(ids[valid].astype(np.int64), views,
                               np.full(int(valid.sum()), view_group, np.int64)), reasons
