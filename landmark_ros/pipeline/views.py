"""
Partial observations in the pipeline: range-only and bearing-only views (ROS-free).

The observer side turns observation rows that carry only a range or only a bearing
(a cloud without the other column, or a NaN in it) into *constraints*: one scalar
view each, with the sensor pose in the world and its covariance
(``core.partial.views_from_robot``), published on ``landmark_constraints``. The fuser
side checks constraint rows, buffers the views of each landmark ID until
``core.partial.initialise`` places it, inserts it into the ``LandmarkMap``
(``LandmarkMap.set_estimate``) and from then on updates it with each new view by
``core.partial.update`` with the map's fusion method (1-dof gate). Range-bearing rows of
the same landmark keep going through ``LandmarkMap.update``: a landmark may mix kinds.

Symbols as in ``core.partial``: ``kind`` (``RANGE`` 0, ``BEARING`` 1), ``s`` and
``P_s`` the sensor pose in the world (x [m], y [m], theta [rad]) and its covariance,
``y`` the measured value (range [m] or bearing [rad]), ``R`` the variance of the
independent noise, ``R_bias`` that of a sensor bias. Time is integer nanoseconds.
"""

from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Deque, Dict, Iterable, List, Optional, Tuple

from landmark_ros.core.partial import (BEARING, GATED, Initialisation, initialise,
                                       InitialiseParams, RANGE, TOO_CLOSE, update, UPDATED,
                                       Views, views_from_robot)
from landmark_ros.core.sensors import MIN_RANGE
from landmark_ros.fusion.landmark_map import LandmarkMap
from landmark_ros.pipeline.rows import first_problems, MAX_ID, UNKNOWN_ID
import numpy as np
from numpy.typing import NDArray

CONSTRAINT_COLUMNS = (
    'id', 'kind', 'value', 'variance', 'variance_dep', 'sensor_x', 'sensor_y', 'sensor_theta',
    'sensor_cov_xx', 'sensor_cov_xy', 'sensor_cov_xt', 'sensor_cov_yy', 'sensor_cov_yt',
    'sensor_cov_tt', 'view_group')
"""Columns of a ``landmark_constraints`` row, in wire order (``ros.schemas``)."""

_COV_INDEX = (('sensor_cov_xx', 0, 0), ('sensor_cov_xy', 0, 1), ('sensor_cov_xt', 0, 2),
              ('sensor_cov_yy', 1, 1), ('sensor_cov_yt', 1, 2), ('sensor_cov_tt', 2, 2))

VIEW_SOURCE = 'partial_views'
"""Source name of the synthetic per-source sum a landmark's estimate is collapsed into
(split CI) when views initialise or update it."""

NOT_PROBLEMS = frozenset({'constraints_in', 'views_fused', 'views_initialised_with',
                          'landmarks_initialised'})
"""Counters of the views that are throughput, not rejections."""


@dataclass(frozen=True)
class Constraints:
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
        """Return the number of constraints ``K``."""
        return len(self.ids)

    def columns(self) -> Dict[str, NDArray[Any]]:
        """Return the rows as ``CONSTRAINT_COLUMNS`` columns, shape (K,) each."""
        out: Dict[str, NDArray[Any]] = {'id': self.ids, 'view_group': self.view_group}
        if self.views is None:
            out.update({name: np.zeros(0) for name in CONSTRAINT_COLUMNS[2:-1]})
            out['kind'] = np.zeros(0, np.int64)
        else:
            v = self.views
            out.update({'kind': v.kind, 'value': v.y, 'variance': v.R,
                        'variance_dep': v.R_bias, 'sensor_x': v.s[:, 0],
                        'sensor_y': v.s[:, 1], 'sensor_theta': v.s[:, 2]})
            out.update({name: v.P_s[:, i, j] for name, i, j in _COV_INDEX})
        return {name: out[name] for name in CONSTRAINT_COLUMNS}


def no_constraints() -> Constraints:
    """Return an empty ``Constraints``."""
    return Constraints(np.empty(0, np.int64), None, np.empty(0, np.int64))


# --- Observer side ---------------------------------------------------------------------------

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


def constraints_from_rows(columns: Dict[str, NDArray[Any]], R: NDArray[np.float64],
                          pose: NDArray[np.float64], P_pose: NDArray[np.float64],
                          sensor_pose: Optional[NDArray[np.float64]],
                          R_bias: Optional[NDArray[np.float64]],
                          view_group: int, stamp_ns: int = 0,
                          correlated: Optional[CorrelatedNoise] = None
                          ) -> Tuple[Constraints, Counter[str]]:
    """
    Turn the partial rows of one message into checked constraints.

    Parameters
    ----------
    columns : dict of str to ndarray, shape (K,)
        The partial rows only: ``id``, ``range`` [m], ``bearing`` [rad], one of them NaN.
    R : ndarray, shape (2, 2) or (K, 2, 2)
        Noise covariance of the rows (``rows.observation_noise``); the diagonal entry
        of the measured column is the view's variance.
    pose : ndarray, shape (3,)
        Robot pose in the world.
    P_pose : ndarray, shape (3, 3)
        Its covariance.
    sensor_pose : ndarray, shape (3,), optional
        Sensor pose in the robot frame; None means the robot origin.
    R_bias : ndarray, shape (2, 2), optional
        Covariance of the sensor bias; its diagonal gives ``R_bias`` of the views.
    view_group : int
        In [0, 2^32 - 1]: the number every view of this pose gets.
    stamp_ns : int
        Stamp of the message [ns] (for ``correlated``).
    correlated : CorrelatedNoise, optional
        Time-correlated noise: the valid views' variances are multiplied by its
        ``factors`` (and their stamps remembered); None keeps them.

    Returns
    -------
    Constraints
    reasons : collections.Counter
        Rows rejected, by reason (``invalid_id``, ``range_not_positive``,
        ``variance_not_positive``, ``observation_nonfinite``).

    """
    ids = np.asarray(columns['id'])
    r = np.asarray(columns['range'], dtype=np.float64)
    b = np.asarray(columns['bearing'], dtype=np.float64)
    count = len(ids)
    kind = np.where(np.isnan(r), BEARING, RANGE)
    y = np.where(kind == RANGE, r, b)
    R = np.broadcast_to(R, (count, 2, 2))
    variance = np.where(kind == RANGE, R[:, 0, 0], R[:, 1, 1])
    bias = np.zeros(count) if R_bias is None else np.where(kind == RANGE, R_bias[0, 0],
                                                           R_bias[1, 1])
    with np.errstate(invalid='ignore'):
        valid, reasons = first_problems(count, [
            ('observation_nonfinite', ~np.isfinite(y)),
            ('range_not_positive', (kind == RANGE) & ~(y >= MIN_RANGE)),
            ('invalid_id', (ids < 0) | (ids > MAX_ID)),
            # Views are gathered by ID: no association of partial rows (yet).
            ('partial_without_id', ids == UNKNOWN_ID),
            ('variance_not_positive', ~(variance > 0.0) | ~np.isfinite(variance)),
        ])
    if not valid.any():
        return no_constraints(), reasons
    variance = variance[valid]
    if correlated is not None:
        variance = variance * correlated.factors(stamp_ns, ids[valid], kind[valid])
    views = views_from_robot(kind[valid], pose, P_pose, y[valid], variance,
                             bias[valid], sensor_pose)
    return Constraints(ids[valid].astype(np.int64), views,
                       np.full(int(valid.sum()), view_group, np.int64)), reasons


# --- Fuser side ------------------------------------------------------------------------------

def constraint_row_problems(
        columns: Dict[str, NDArray[Any]]) -> Tuple[NDArray[np.bool_], Counter[str]]:
    """
    Find the constraint rows (fuser input) that cannot be used, and why.

    Parameters
    ----------
    columns : dict of str to ndarray, shape (N,)
        ``CONSTRAINT_COLUMNS``.

    Returns
    -------
    valid : ndarray of bool, shape (N,)
    reasons : collections.Counter
        Rejected rows per reason (each counted once, under its first problem):
        ``constraint_nonfinite``, ``invalid_id``, ``invalid_kind``,
        ``range_not_positive``, ``variance_not_positive``, ``variance_dep_negative``,
        ``sensor_covariance_not_psd``.

    """
    ids = np.asarray(columns['id'])
    count = len(ids)
    kind = np.asarray(columns['kind'])
    reals = np.stack([np.asarray(columns[name], dtype=np.float64)
                      for name in CONSTRAINT_COLUMNS[2:-1]], axis=1) if count else np.zeros(
        (0, 12))
    finite = np.all(np.isfinite(reals), axis=1)
    P_s = sensor_covariance(columns)
    with np.errstate(invalid='ignore'):
        scale = np.maximum(np.abs(np.where(finite[:, None, None], P_s, 0.0)).max(
            axis=(1, 2)), 1e-300) if count else np.zeros(0)
        psd = np.ones(count, bool)
        if count and finite.any():
            psd[finite] = np.linalg.eigvalsh(P_s[finite])[:, 0] >= -1e-9 * scale[finite]
        value = np.asarray(columns['value'], dtype=np.float64)
        return first_problems(count, [
            ('constraint_nonfinite', ~finite),
            ('invalid_id', (ids < 0) | (ids >= UNKNOWN_ID)),
            ('invalid_kind', (kind != RANGE) & (kind != BEARING)),
            ('range_not_positive', (kind == RANGE) & ~(value >= MIN_RANGE)),
            ('variance_not_positive', ~(np.asarray(columns['variance']) > 0.0)),
            ('variance_dep_negative', ~(np.asarray(columns['variance_dep']) >= 0.0)),
            ('sensor_covariance_not_psd', ~psd),
        ])


def sensor_covariance(columns: Dict[str, NDArray[Any]]) -> NDArray[np.float64]:
    """Return the sensor pose covariances of constraint rows, shape (N, 3, 3)."""
    count = len(columns['id'])
    P_s = np.zeros((count, 3, 3))
    for name, i, j in _COV_INDEX:
        P_s[:, i, j] = P_s[:, j, i] = columns[name]
    return P_s


def views_from_columns(columns: Dict[str, NDArray[Any]]) -> Views:
    """
    Return the views of checked constraint rows.

    Raises
    ------
    ValueError
        As ``core.partial.Views`` does (rows that ``constraint_row_problems`` passes
        do not raise).

    """
    s = np.stack([columns['sensor_x'], columns['sensor_y'], columns['sensor_theta']], axis=1)
    return Views(np.asarray(columns['kind']).astype(np.int64), s, sensor_covariance(columns),
                 columns['value'], columns['variance'], columns['variance_dep'])


@dataclass(frozen=True)
class _View:
    source: str
    stamp_ns: int
    group: int
    views: Views            # one view


@dataclass
class ViewResult:
    """What ``PartialViews.fuse`` did: counts by source and the landmarks it changed."""

    changed_ids: List[int]
    counts: Dict[str, Counter[str]]


def parse_waiting_records(records: Any) -> List[Tuple[int, _View]]:
    """
    Check saved waiting views (``PartialViews.waiting_records``) and return them.

    Returns
    -------
    list of (int, _View)
        Landmark ID and view, in the saved order (for ``PartialViews.restore``).

    Raises
    ------
    ValueError
        If a record lacks a field or has a wrong type, or its row fails the checks
        of a live constraint row (``constraint_row_problems``); nothing is loaded.

    """
    if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
        raise ValueError('waiting_views must be a list of objects')
    if not records:
        return []
    names = CONSTRAINT_COLUMNS + ('source', 'stamp_ns')
    for record in records:
        missing = [name for name in names if name not in record]
        if missing:
            raise ValueError(f'waiting view without {missing}')
        for name in names:
            value = record[name]
            if name == 'source':
                if not isinstance(value, str):
                    raise ValueError(f'waiting view source {value!r} is not a string')
            elif isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f'waiting view {name} {value!r} is not a number')
            elif name in ('id', 'kind', 'view_group', 'stamp_ns') and not isinstance(
                    value, int):
                raise ValueError(f'waiting view {name} {value!r} is not an integer')
    try:
        columns = {name: np.array([r[name] for r in records],
                                  np.int64 if name in ('id', 'kind', 'view_group') else
                                  np.float64) for name in CONSTRAINT_COLUMNS}
    except OverflowError as error:
        raise ValueError(f'waiting view number out of range: {error}') from None
    valid, reasons = constraint_row_problems(columns)
    if not valid.all():
        raise ValueError(f'invalid waiting views: {dict(reasons)}')
    views = views_from_columns(columns)
    return [(int(r['id']), _View(r['source'], int(r['stamp_ns']), int(r['view_group']),
                                 views[k])) for k, r in enumerate(records)]


class PartialViews:
    """
    Buffer the views of landmarks until they are placed, then update with them.

    Parameters
    ----------
    landmark_map : fusion.landmark_map.LandmarkMap
        The fused map the landmarks go into (and whose fusion method the updates use).
    min_triangulation_angle_deg : float
        ``core.partial.InitialiseParams.min_triangulation_angle_deg`` [deg].
    max_views : int
        Views kept per waiting landmark; the oldest is dropped beyond (counted
        ``views_dropped``).
    gate_probability : float
        Probability of the 1-dof chi-square gate of the updates.
    max_consecutive_rejections : int
        Views of a placed landmark gated in a row after which it is placed again from
        its recent views (``max_views`` of them, gated or not), counted
        ``landmarks_reinitialised``: a range-only landmark placed on the mirror side of
        a straight robot path, or a moved one.
    max_curvature_ratio : float
        ``core.partial.InitialiseParams.max_curvature_ratio``; 0 turns the rule off.

    Notes
    -----
    A waiting landmark is tried again with every new view (``initialise`` on its
    buffer, at least two views). The initialisation's covariance accounts for the
    views that share errors: the views of one source share its bias, the views of one
    ``view_group`` of a source share its pose error (``core.partial.initialise``
    with ``bias_group`` and ``pose_group``).

    """

    def __init__(self, landmark_map: LandmarkMap, min_triangulation_angle_deg: float = 5.0,
                 max_views: int = 50, gate_probability: float = 0.999,
                 max_consecutive_rejections: int = 5, max_curvature_ratio: float = 0.5) -> None:
        self.map = landmark_map
        self.params = InitialiseParams(min_triangulation_angle_deg=min_triangulation_angle_deg,
                                       max_curvature_ratio=max_curvature_ratio or None)
        self.max_views = int(max_views)
        self.gate_probability = gate_probability
        self.max_consecutive_rejections = int(max_consecutive_rejections)
        self.queue: Deque[Tuple[str, int, NDArray[np.int64], Views, NDArray[np.int64]]] = deque()
        self.waiting: Dict[int, Deque[_View]] = {}
        self.recent: Dict[int, Deque[_View]] = {}
        self.streak: Counter[int] = Counter()
        self.wait_reasons: Counter[str] = Counter()

    def reset(self) -> None:
        """Forget the queued and waiting views."""
        self.queue.clear()
        self.waiting.clear()
        self.recent.clear()
        self.streak.clear()

    def waiting_records(self) -> List[Dict[str, Any]]:
        """
        Return the views of the landmarks still waiting to be placed, for the map file.

        Returns
        -------
        list of dict
            One per view, oldest first per landmark: ``CONSTRAINT_COLUMNS`` (plain
            numbers) plus ``source`` and ``stamp_ns`` [ns].

        """
        records = []
        for landmark_id, buffer in self.waiting.items():
            for b in buffer:
                columns = Constraints(np.array([landmark_id], np.int64), b.views,
                                      np.array([b.group], np.int64)).columns()
                record: Dict[str, Any] = {name: values[0].item()
                                          for name, values in columns.items()}
                record.update(source=b.source, stamp_ns=int(b.stamp_ns))
                records.append(record)
        return records

    def restore(self, parsed: List[Tuple[int, _View]]) -> int:
        """
        Put checked saved views (``parse_waiting_records``) back into the buffers.

        Views of a landmark the map already holds are left out (it was placed).
        Landmarks are not placed here: the next view of each tries again.

        Returns
        -------
        int
            Views restored.

        """
        restored = 0
        for landmark_id, view in parsed:
            if self.map.estimate(landmark_id) is not None:
                continue
            self.waiting.setdefault(landmark_id, deque(maxlen=self.max_views)).append(view)
            restored += 1
        return restored

    def add(self, source: str, stamp_ns: int, ids: NDArray[np.int64], views: Views,
            groups: NDArray[np.int64]) -> None:
        """Queue checked views (``fuse`` takes them in arrival order)."""
        self.queue.append((source, int(stamp_ns), np.asarray(ids, np.int64), views,
                           np.asarray(groups, np.int64)))

    def _initialise(self, buffer: Iterable[_View]) -> Initialisation:
        """Place a landmark from views: a source shares its bias, a view group its pose."""
        buffer = list(buffer)
        sources = [b.source for b in buffer]
        index = {name: k for k, name in enumerate(dict.fromkeys(sources))}
        bias_group = np.array([index[name] for name in sources], np.int64)
        pose_group = np.array([index[b.source] * (1 << 33) + b.group for b in buffer], np.int64)
        return initialise(Views.concatenate(b.views for b in buffer), self.params,
                          bias_group, pose_group)

    def fuse(self) -> ViewResult:
        """
        Take every queued view in arrival order: buffer, initialise or update.

        Returns
        -------
        ViewResult
            Per source: ``views_fused`` (updates and views an initialisation used),
            ``views_gated``, ``views_too_close``, ``views_dropped``,
            ``landmarks_initialised``; the IDs of the landmarks changed.

        """
        counts: Dict[str, Counter[str]] = {}
        changed: List[int] = []
        method = self.map.fusion
        while self.queue:
            source, stamp_ns, ids, views, groups = self.queue.popleft()
            count = counts.setdefault(source, Counter())
            for k, landmark_id in enumerate(ids.tolist()):
                view = views[k]
                estimate = self.map.estimate(landmark_id)
                if estimate is not None:
                    stale = self.waiting.pop(landmark_id, None)
                    if stale:  # range-bearing rows confirmed it first
                        count['views_superseded'] += len(stale)
                    m, P, P_dep = estimate
                    recent = self.recent.setdefault(landmark_id, deque(maxlen=self.max_views))
                    recent.append(_View(source, stamp_ns, int(groups[k]), view))
                    result = update(m, P, view, P_dep, method, self.gate_probability)
                    status = int(result.status[0])
                    self.streak[landmark_id] = self.streak[landmark_id] + 1 if (
                        status == GATED) else 0
                    if self.streak[landmark_id] >= self.max_consecutive_rejections:
                        self.streak[landmark_id] = 0
                        placed = self._initialise(recent)
                        if placed.ok:
                            self.map.set_estimate(landmark_id, placed.m, placed.P_m,
                                                  placed.P_m_dep, VIEW_SOURCE, stamp_ns, 0)
                            count['landmarks_reinitialised'] += 1
                            changed.append(landmark_id)
                    if status == UPDATED:
                        self.map.set_estimate(landmark_id, result.m[0], result.P_m[0],
                                              result.P_m_dep[0], VIEW_SOURCE, stamp_ns, 1)
                        count['views_fused'] += 1
                        changed.append(landmark_id)
                    elif status == GATED:
                        count['views_gated'] += 1
                    elif status == TOO_CLOSE:
                        count['views_too_close'] += 1
                    continue
                buffer = self.waiting.setdefault(landmark_id, deque(maxlen=self.max_views))
                if len(buffer) == buffer.maxlen:
                    counts.setdefault(buffer[0].source, Counter())['views_dropped'] += 1
                buffer.append(_View(source, stamp_ns, int(groups[k]), view))
                if len(buffer) < 2:
                    continue
                placed = self._initialise(buffer)
                if not placed.ok:
                    self.wait_reasons[placed.reason] += 1
                    continue
                self.map.set_estimate(landmark_id, placed.m, placed.P_m, placed.P_m_dep,
                                      VIEW_SOURCE, stamp_ns, len(buffer))
                for b in buffer:
                    counts.setdefault(b.source, Counter())['views_fused'] += 1
                count['landmarks_initialised'] += 1
                self.recent[landmark_id] = self.waiting.pop(landmark_id)
                changed.append(landmark_id)
        return ViewResult(changed, counts)
