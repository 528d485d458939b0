"""
The fuser's side of partial observations: check, buffer, place, update (ROS-free).

The fuser checks partial observation rows (``pipeline.partial_rows``: range-only and
bearing-only views of landmark IDs, from the observers' ``partial_observations``
topics), buffers the views of each landmark ID until ``core.partial.initialise``
places it, inserts it into the ``LandmarkMap`` (``LandmarkMap.set_estimate``) and from
then on updates it with each new view by ``core.partial.update`` with the map's fusion
method (1-dof gate). Range-bearing rows of the same landmark keep going through
``LandmarkMap.update``: a landmark may mix kinds.

Symbols as in ``core.partial`` (see ``pipeline.partial_rows``). Time is integer
nanoseconds.
"""

from collections import Counter, deque
from dataclasses import dataclass, replace
from typing import Any, Deque, Dict, Iterable, List, Optional, Tuple

from landmark_ros.core.partial import (BEARING, GATED, Initialisation, initialise,
                                       InitialiseParams, RANGE, range_scale_valid, TOO_CLOSE,
                                       update, update_consider, UPDATED, UpdateResult, Views)
from landmark_ros.core.sensors import MIN_RANGE
from landmark_ros.fuser.partial_consider import (BiasCrosses, CONSIDERED_KINDS, Crosses,
                                                 Estimate, psd_part)
from landmark_ros.fuser.partial_sources import SourceLedger
from landmark_ros.fusion.landmark_map import LandmarkMap
from landmark_ros.pipeline.limits import partial_problems
from landmark_ros.pipeline.partial_rows import (NO_RANGE_SCALE_ROW, PARTIAL_COLUMNS,
                                                PartialObservations, range_scale,
                                                RANGE_SCALE_COLUMNS, sensor_covariance)
from landmark_ros.pipeline.rows import first_problems, landmark_row_problems, UNKNOWN_ID
import numpy as np
from numpy.typing import NDArray

PARTIAL_SOURCE = 'partial_views'
"""Source name of the synthetic per-source sum a landmark's estimate is collapsed into
(split CI) when views initialise or update it."""

NOT_PROBLEMS = frozenset({'partial_in', 'partial_fused', 'landmarks_initialised'})
"""Counters of the partial observations that are throughput, not rejections."""


def partial_row_problems(
        columns: Dict[str, NDArray[Any]]) -> Tuple[NDArray[np.bool_], Counter[str]]:
    """
    Find the partial observation rows (fuser input) that cannot be used, and why.

    Parameters
    ----------
    columns : dict of str to ndarray, shape (N,)
        ``PARTIAL_COLUMNS``.

    Returns
    -------
    valid : ndarray of bool, shape (N,)
    reasons : collections.Counter
        Rejected rows per reason (each counted once, under its first problem):
        ``partial_nonfinite``, ``invalid_id``, ``invalid_kind``,
        ``range_not_positive``, ``variance_not_positive``, ``variance_dep_negative``,
        ``sensor_covariance_not_psd``, ``range_scale_invalid`` (not finite, a bearing
        limit outside (0, pi], a factor below ``range_scale.MIN_SCALE`` inside it), then
        the ``limits.partial_problems``
        (``range_out_of_range``, ``bearing_out_of_range``, ``variance_out_of_range``,
        ``pose_out_of_range``).

    """
    ids = np.asarray(columns['id'])
    count = len(ids)
    kind = np.asarray(columns['kind'])
    reals = np.stack([np.asarray(columns[name], dtype=np.float64)
                      for name in PARTIAL_COLUMNS[2:-1]], axis=1) if count else np.zeros(
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
        plausible = partial_problems(columns, kind, value, columns['variance'], RANGE)
        return first_problems(count, [
            ('partial_nonfinite', ~finite),
            ('invalid_id', (ids < 0) | (ids >= UNKNOWN_ID)),
            ('invalid_kind', (kind != RANGE) & (kind != BEARING)),
            ('range_not_positive', (kind == RANGE) & ~(value >= MIN_RANGE)),
            ('variance_not_positive', ~(np.asarray(columns['variance']) > 0.0)),
            ('variance_dep_negative', ~(np.asarray(columns['variance_dep']) >= 0.0)),
            ('sensor_covariance_not_psd', ~psd),
            ('range_scale_invalid', ~range_scale_valid(*range_scale(columns))),
        ] + plausible)


def views_from_columns(columns: Dict[str, NDArray[Any]]) -> Views:
    """
    Return the views of checked partial observation rows.

    Raises
    ------
    ValueError
        As ``core.partial.Views`` does (rows that ``partial_row_problems`` passes
        do not raise).

    """
    s = np.stack([columns['sensor_x'], columns['sensor_y'], columns['sensor_theta']], axis=1)
    return Views(np.asarray(columns['kind']).astype(np.int64), s, sensor_covariance(columns),
                 columns['value'], columns['variance'], columns['variance_dep'],
                 *range_scale(columns))


@dataclass(frozen=True)
class _Buffered:
    source: str
    stamp_ns: int
    group: int
    views: Views            # one view


@dataclass
class PartialResult:
    """What ``PartialFusion.fuse`` did: counts by source and the landmarks it changed."""

    changed_ids: List[int]
    counts: Dict[str, Counter[str]]


def parse_waiting_records(records: Any) -> List[Tuple[int, _Buffered]]:
    """
    Check saved waiting views (``PartialFusion.waiting_records``) and return them.

    Returns
    -------
    list of (int, _Buffered)
        Landmark ID and view, in the saved order (for ``PartialFusion.restore``).

    Raises
    ------
    ValueError
        If a record lacks a field or has a wrong type, or its row fails the checks
        of a live partial observation row (``partial_row_problems``); nothing is loaded.

    """
    if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
        raise ValueError('waiting_partial_observations must be a list of objects')
    if not records:
        return []
    # Map files written before the range scale lack it: none.
    records = [dict(zip(RANGE_SCALE_COLUMNS, NO_RANGE_SCALE_ROW), **r) for r in records]
    names = PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS + ('source', 'stamp_ns')
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
                                  np.float64) for name in PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS}
    except OverflowError as error:
        raise ValueError(f'waiting view number out of range: {error}') from None
    valid, reasons = partial_row_problems(columns)
    if not valid.all():
        raise ValueError(f'invalid waiting views: {dict(reasons)}')
    views = views_from_columns(columns)
    return [(int(r['id']), _Buffered(r['source'], int(r['stamp_ns']), int(r['view_group']),
                                     views[k])) for k, r in enumerate(records)]


class PartialFusion:
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
        ``partial_dropped``).
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
        self.waiting: Dict[int, Deque[_Buffered]] = {}
        self.recent: Dict[int, Deque[_Buffered]] = {}
        self.streak: Counter[int] = Counter()
        self.wait_reasons: Counter[str] = Counter()
        self.ledger = SourceLedger()
        self.biases = BiasCrosses()

    def reset(self) -> None:
        """Forget the queued and waiting views."""
        self.queue.clear()
        self.waiting.clear()
        self.recent.clear()
        self.streak.clear()
        self.ledger.clear()
        self.biases.clear()

    def waiting_records(self) -> List[Dict[str, Any]]:
        """
        Return the views of the landmarks still waiting to be placed, for the map file.

        Returns
        -------
        list of dict
            One per view, oldest first per landmark: ``PARTIAL_COLUMNS`` and
            ``RANGE_SCALE_COLUMNS`` (plain numbers) plus ``source`` and ``stamp_ns`` [ns].

        """
        records = []
        for landmark_id, buffer in self.waiting.items():
            for b in buffer:
                columns = PartialObservations(np.array([landmark_id], np.int64), b.views,
                                              np.array([b.group], np.int64)).columns()
                record: Dict[str, Any] = {name: values[0].item()
                                          for name, values in columns.items()}
                record.update(source=b.source, stamp_ns=int(b.stamp_ns))
                records.append(record)
        return records

    def restore(self, parsed: List[Tuple[int, _Buffered]]) -> int:
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

    def _initialise(self, buffer: Iterable[_Buffered]) -> Initialisation:
        """Place a landmark from views: a source shares its bias, a view group its pose."""
        buffer = list(buffer)
        sources = [b.source for b in buffer]
        index = {name: k for k, name in enumerate(dict.fromkeys(sources))}
        bias_group = np.array([index[name] for name in sources], np.int64)
        pose_group = np.array([index[b.source] * (1 << 33) + b.group for b in buffer], np.int64)
        return initialise(Views.concatenate(b.views for b in buffer), self.params,
                          bias_group, pose_group)

    def _set(self, count: Counter[str], landmark_id: int,
             estimate: Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
             stamp_ns: int, views: int) -> bool:
        """
        Set a landmark's estimate if it passes the live landmark row checks.

        The checks the map-file loader applies (``rows.landmark_row_problems``): an
        estimate that would not load back is not stored, and is counted as
        ``partial_result_<reason>`` against the observation's source.
        """
        m, P, P_dep = estimate
        _, reasons = landmark_row_problems(np.array([landmark_id], np.int64), m[None],
                                           P[None], P_dep[None])
        if reasons:
            for reason in reasons:
                count[f'partial_result_{reason}'] += 1
            return False
        self.map.set_estimate(landmark_id, m, P, P_dep, PARTIAL_SOURCE, stamp_ns, views)
        self.ledger.forget(landmark_id)    # an update keeps its new parts after this
        self.biases.forget(landmark_id)
        return True

    def _considered(self, landmark_id: int, buffer: Iterable[_Buffered],
                    placed: Initialisation) -> None:
        """Start the bias cross-covariances of a landmark just placed from ``buffer``."""
        if not self._by_source():
            return
        buffer = list(buffer)
        keys = [(b.source, int(b.views.kind[0])) for b in buffer]
        views = Views.concatenate(b.views for b in buffer)
        estimate = self.map.estimate(landmark_id)
        if estimate is not None:
            self.biases.keep(landmark_id, self.biases.placed(views, keys, placed, estimate))

    def _by_source(self, views: Optional[Views] = None) -> bool:
        """Return whether views (a view) split the dependent parts by source (``_update``)."""
        return (self.map.fusion == 'split_covariance_intersection'
                and self.map.source_correlation == 'independent'
                and (views is None or int(views.kind[0]) == BEARING
                     or bool(np.any(views.range_scale))))

    def _update(self, count: Counter[str], seen: _Buffered, landmark_id: int,
                estimate: Estimate) -> List[int]:
        """
        Update a placed landmark with one view; return its ID when it changed.

        With split CI and ``source_correlation: independent`` a view's dependent error
        is shared only with its own source's part of ``P_dep`` (and the part of no known
        source): ``partial_sources.SourceLedger``; its sensor bias, when the landmark
        was placed and updated by views only, is a consider state whose
        cross-covariance is carried (``partial_consider``). Not so a range-only view
        without a range scale model (``Views.range_scale``): it holds the camera's
        scale error at the bearing it could not correct as noise
        (``range_scale_no_bearing``), one lens function for every robot, so views of
        different robots from like bearings share it; it takes all of ``P_dep``.
        """
        by_source = self._by_source(seen.views)
        crosses = (self.biases.current(landmark_id, estimate)
                   if by_source and int(seen.views.kind[0]) in CONSIDERED_KINDS else None)
        result, book = self._step(seen, landmark_id, estimate, by_source, crosses)
        status = int(result.status[0])
        changed = []
        self.streak[landmark_id] = self.streak[landmark_id] + 1 if status == GATED else 0
        if self.streak[landmark_id] >= self.max_consecutive_rejections:
            self.streak[landmark_id] = 0
            recent = list(self.recent[landmark_id])
            placed = self._initialise(recent)
            if placed.ok and self._set(count, landmark_id, (
                    placed.m, placed.P_m, placed.P_m_dep), seen.stamp_ns, 0):
                self._considered(landmark_id, recent, placed)
                count['landmarks_reinitialised'] += 1
                changed.append(landmark_id)
        if status == UPDATED:
            new_dep, keep = book(result)
            if self._set(count, landmark_id, (result.m[0], result.P_m[0], new_dep),
                         seen.stamp_ns, 1):
                count['partial_fused'] += 1
                changed.append(landmark_id)
                keep(self.map.estimate(landmark_id))
        elif status == GATED:
            count['partial_gated'] += 1
        elif status == TOO_CLOSE:
            count['partial_too_close'] += 1
        return changed

    def _step(self, seen: _Buffered, landmark_id: int, estimate: Estimate, by_source: bool,
              crosses: Optional[Crosses]) -> Tuple[UpdateResult, Any]:
        """
        Return the update of a landmark by a view and how to book it.

        ``book(result)`` gives the new ``P_dep`` and ``keep(estimate)``, which holds
        the ledger's parts and the cross-covariances once the map has the estimate.
        """
        m, P, P_dep = estimate
        if crosses is None:
            shared = (self.ledger.shared_part(landmark_id, seen.source, P_dep) if by_source
                      else P_dep)
            result = update(m, P, seen.views, shared, self.map.fusion, self.gate_probability)

            def book(result):
                if not by_source:
                    return result.P_m_dep[0], lambda estimate: None
                new_dep, parts = self.ledger.book(landmark_id, seen.source, P_dep, result)
                return new_dep, lambda estimate: self.ledger.keep(landmark_id, parts)
            return result, book
        key = (seen.source, int(seen.views.kind[0]))
        pose_dep = psd_part(P_dep - crosses.bias_part())   # >= 0 but for rounding
        shared = self.ledger.shared_part(landmark_id, seen.source, pose_dep)
        result, c_key = update_consider(m, P, seen.views, shared,
                                        crosses.c.get(key, np.zeros(2)), self.gate_probability)

        def book_consider(result):
            new_pose, parts = self.ledger.book(landmark_id, seen.source, pose_dep, result)
            after = crosses.after(key, c_key[0], result.L[0], crosses.estimate)

            def keep(estimate):
                self.ledger.keep(landmark_id, parts)
                if estimate is not None:
                    self.biases.keep(landmark_id, replace(after, estimate=estimate))
            return new_pose + after.bias_part(), keep
        return result, book_consider

    def fuse(self) -> PartialResult:
        """
        Take every queued view in arrival order: buffer, initialise or update.

        Returns
        -------
        PartialResult
            Per source: ``partial_fused`` (updates and views an initialisation used),
            ``partial_gated``, ``partial_too_close``, ``partial_dropped``,
            ``landmarks_initialised``; the IDs of the landmarks changed.

        """
        counts: Dict[str, Counter[str]] = {}
        changed: List[int] = []
        while self.queue:
            source, stamp_ns, ids, views, groups = self.queue.popleft()
            count = counts.setdefault(source, Counter())
            for k, landmark_id in enumerate(ids.tolist()):
                view = views[k]
                estimate = self.map.estimate(landmark_id)
                if estimate is not None:
                    stale = self.waiting.pop(landmark_id, None)
                    if stale:  # range-bearing rows confirmed it first
                        count['partial_superseded'] += len(stale)
                    seen = _Buffered(source, stamp_ns, int(groups[k]), view)
                    self.recent.setdefault(landmark_id, deque(maxlen=self.max_views)).append(seen)
                    changed += self._update(count, seen, landmark_id, estimate)
                    continue
                buffer = self.waiting.setdefault(landmark_id, deque(maxlen=self.max_views))
                if len(buffer) == buffer.maxlen:
                    counts.setdefault(buffer[0].source, Counter())['partial_dropped'] += 1
                buffer.append(_Buffered(source, stamp_ns, int(groups[k]), view))
                if len(buffer) < 2:
                    continue
                placed = self._initialise(buffer)
                if not placed.ok:
                    self.wait_reasons[placed.reason] += 1
                    continue
                if not self._set(count, landmark_id, (placed.m, placed.P_m, placed.P_m_dep),
                                 stamp_ns, len(buffer)):
                    continue
                self._considered(landmark_id, buffer, placed)
                for b in buffer:
                    counts.setdefault(b.source, Counter())['partial_fused'] += 1
                count['landmarks_initialised'] += 1
                self.recent[landmark_id] = self.waiting.pop(landmark_id)
                changed.append(landmark_id)
        return PartialResult(changed, counts)
