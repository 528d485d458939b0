"""
The team's fuser: landmark batches of several sources in, one fused map out (ROS-free).

The ``landmark_fuser`` node, the MRCLAM replay, the Monte Carlo study and the
benchmarks all drive this one object. Rows are checked (``rows.landmark_row_problems``)
and queued per source in bounded queues; ``fuse_queued`` fuses everything queued, in
arrival order, with one ``LandmarkMap.update`` (a batch gives the map its rows would
give one by one). Partial observations (range-only, bearing-only rows of the partial
sources, ``add_partial_observations``) are checked by ``partial.partial_row_problems`` and
handled by ``partial.PartialFusion`` on the same map, before the queued landmark rows of the
same ``fuse_queued``. Time is integer nanoseconds throughout.
"""

from collections import Counter
import itertools
from typing import Any, Dict, List, Optional, Sequence, Tuple

from landmark_ros.core.arrays import unique_inverse
from landmark_ros.fuser import persistence, publishing
from landmark_ros.fuser.change_detection import detect_moves, move_detector
from landmark_ros.fuser.partial import (NOT_PROBLEMS as PARTIAL_COUNTS,
                                        partial_row_problems, PartialFusion, views_from_columns)
from landmark_ros.fuser.sources import LandmarkMessage, Queued, shard_of_position, Source
from landmark_ros.fuser.tracks import Tracker
from landmark_ros.fusion.landmark_map import MapSnapshot, UpdateResult
from landmark_ros.fusion.moves import MovingLandmarkMap
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.counters import Counters, Logger, Status
from landmark_ros.pipeline.rows import landmark_row_problems, UNKNOWN_ID
import numpy as np
from numpy.typing import NDArray

NOT_PROBLEMS = frozenset({'landmarks_confirmed', 'saves', 'other_shard'}) | PARTIAL_COUNTS
"""Fuser counters that do not make its status a warning (a re-initialisation does)."""


class _Quiet:
    """A logger that drops everything (the default when none is given)."""

    def info(self, text: str) -> None:
        """Drop an info line."""

    def warning(self, text: str) -> None:
        """Drop a warning."""

    def error(self, text: str) -> None:
        """Drop an error."""


def _per_message(flags: NDArray[np.bool_], bounds: NDArray[np.int64]) -> List[int]:
    """Return the count of ``flags`` in each message (rows ``bounds[k]:bounds[k + 1]``)."""
    total = np.concatenate([[0], np.cumsum(flags)])
    return (total[bounds[1:]] - total[bounds[:-1]]).tolist()


class Fuser:
    """
    Fuse the landmark observations of a team of robots into one map.

    Parameters
    ----------
    config : FuserConfig
        The parameters (fusion method, gate, queues, map file).
    sources : sequence of str
        The source names (the nodes use the resolved input topics).
    logger : object, optional
        With ``info``, ``warning`` and ``error`` methods taking one string (an rclpy
        logger or a ``logging.Logger``).
    partial_sources : sequence of str
        The sources of partial observations (``add_partial_observations``; the nodes use
        the resolved ``partial_observation_topics``); none by default.

    Raises
    ------
    ValueError
        If two sources have the same name.

    """

    def __init__(self, config: FuserConfig, sources: Sequence[str],
                 logger: Optional[Logger] = None,
                 partial_sources: Sequence[str] = ()) -> None:
        sources = list(sources) + list(partial_sources)
        if len(set(sources)) != len(sources):
            raise ValueError(f'input_topics name one topic twice once resolved: {list(sources)}')
        self.config = config
        self.logger = logger or _Quiet()
        for warning in config.deprecations():
            self.logger.warning(warning)
        self.counters = Counters(self.logger.warning, config.log_throttle_s)
        self.map = MovingLandmarkMap(config.fusion, config.gate_probability,
                                     config.min_observations, config.max_consecutive_rejections,
                                     config.source_correlation)
        self.moves = move_detector(config, self.map.threshold)
        """Change detection on the confirmed landmarks (``fuser.change_detection``)."""
        self.sources: Dict[str, Source] = {
            name: Source(name, optional=name in partial_sources) for name in sources}
        self._sequence = itertools.count()
        self._reported: Dict[str, int] = {}
        self.map_changed = False
        """Whether the confirmed map changed since the last ``snapshot`` was taken."""
        self.unsaved = False
        """Whether the map changed since the last save."""
        self._updated: List[NDArray[np.int64]] = []
        self._removed: List[tuple] = []
        self.tracker = Tracker(config)
        """Association of the rows without an ID (``fuser.tracks``)."""
        self.reserved_from = int(config.first_new_id)
        """Start of the IDs this fuser allocates (to ``MAX_LABEL_ID``): a labelled row
        with one is rejected as ``id_reserved``, so an allocated ID never names another
        landmark. Kept in the map file (``first_new_id``): a restart keeps the range."""
        self.association_log: Optional[List[Tuple[str, int, NDArray[np.int64]]]] = None
        """Set to a list to record, per message with rows without an ID, in fuse order,
        ``(source, stamp_ns, ids)``: the ID each such row got (-1: dropped as ambiguous)."""
        self.partial = PartialFusion(self.map, config.min_triangulation_angle_deg,
                                     config.max_views_per_landmark, config.gate_probability,
                                     config.max_consecutive_rejections,
                                     config.max_curvature_ratio)

    def reconfigure(self, config: FuserConfig) -> None:
        """Apply new parameters (those that may change at run time)."""
        self.config = config
        self.counters.throttle_s = config.log_throttle_s
        self.tracker.config = config

    def reject(self, source: str, reason: str, count: int = 1,
               detail: Optional[str] = None) -> None:
        """Count (and log, throttled) input of ``source`` rejected, by reason."""
        self.sources[source].counts[reason] += count
        self.counters.add(reason, count, None if detail is None else f'{source}: {detail}')

    # Input ---------------------------------------------------------------------

    def _arrive(self, source: str, frame_id: Optional[str], now_ns: Optional[int],
                what: str) -> Optional[Source]:
        """Count a message of ``source`` in; return its state, or None if in the wrong frame."""
        state = self.sources[source]
        if now_ns is not None:
            state.last_message_ns = now_ns
        state.counts['messages_in'] += 1
        if frame_id is not None and frame_id != self.config.world_frame:
            self.reject(source, 'wrong_frame', 1,
                        f"{what} in frame '{frame_id}', expected "
                        f"'{self.config.world_frame}': message dropped")
            return None
        return state

    def add_landmarks(self, source: str, message: LandmarkMessage,
                      now_ns: Optional[int] = None) -> int:
        """
        Check the rows of one landmark message of ``source`` and queue the valid ones.

        ``add_landmark_messages`` with one message (``now_ns``: the arrival time [ns]
        for the stale-source check). Returns the number of rows queued.
        """
        return self.add_landmark_messages(source, [message], now_ns)

    def add_landmark_messages(self, source: str, messages: Sequence[LandmarkMessage],
                              now_ns: Optional[int] = None) -> int:
        """
        Check the rows of several landmark messages of one source and queue the valid ones.

        ``add_landmark_bursts`` with one source (parameters and result there): each
        message gets its own frame check, stamp and queue entry, their rows one check.
        """
        return self.add_landmark_bursts([(source, messages)], now_ns)

    def add_landmark_bursts(self, bursts: Sequence[Tuple[str, Sequence[LandmarkMessage]]],
                            now_ns: Optional[int] = None) -> int:
        """
        Check and queue the landmark messages of several sources with one row check.

        What ``add_landmark_messages`` does for each ``(source, messages)`` in turn,
        with the rows of all of them checked in one ``rows.landmark_row_problems``: a
        callback that takes a few messages from each of many robots pays the checks'
        fixed cost once, not once per robot. A source with rejected rows has them
        checked again on their own, so counters and logs stay per source.

        Parameters
        ----------
        bursts : sequence of (str, sequence of LandmarkMessage)
            Sources (each one of the sources) and their messages, oldest first.
        now_ns : int, optional
            Arrival time [ns], for the stale-source check.

        Returns
        -------
        int
            The rows queued.

        """
        taken = []
        for source, messages in bursts:
            kept = [message for message in messages if self._arrive(
                source, message.frame_id, now_ns, 'landmarks') is not None]
            if kept:
                taken.append((source, kept))
        if not taken:
            return 0
        every = [message for _, kept in taken for message in kept]
        ids = np.concatenate([np.asarray(message.ids) for message in every]).astype(
            np.int64, copy=False)
        m, P, P_dep = (np.concatenate([np.asarray(getattr(message, name), np.float64)
                                       for message in every]) for name in ('m', 'P', 'P_dep'))
        valid, _ = landmark_row_problems(ids, m, P, P_dep)
        bounds = np.cumsum([0] + [len(message.ids) for message in every])
        reserved = valid & (ids >= self.reserved_from) & (ids != UNKNOWN_ID)
        if reserved.any():
            valid &= ~reserved
            sources = [source for source, kept in taken for _ in kept]
            for source, count in zip(sources, _per_message(reserved, bounds)):
                if count:
                    self.reject(source, 'id_reserved', count,
                                f'labelled rows with IDs from first_new_id '
                                f'{self.reserved_from} up: those are the IDs of landmarks '
                                'found without an ID')
        # Per message, from one pass over the burst: rows that passed the checks, those
        # of another shard, and those queued (with how many lack an ID).
        passed = _per_message(valid, bounds)
        other = self._other_shard(ids, m)
        if other is not None:
            other &= valid
            valid &= ~other
        other_counts = _per_message(other, bounds) if other is not None else [0] * len(every)
        counts = _per_message(valid, bounds)
        unlabelled = _per_message(valid & (ids == UNKNOWN_ID), bounds)
        queued, index = 0, 0
        for source, kept in taken:
            first, index = index, index + len(kept)
            part = slice(bounds[first], bounds[index])
            state = self.sources[source]
            state.counts['observations_in'] += part.stop - part.start
            if sum(passed[first:index]) < part.stop - part.start:
                # The reasons per source: the rows of a source with problems checked again.
                for reason, count in landmark_row_problems(
                        ids[part], m[part], P[part], P_dep[part])[1].items():
                    self.reject(source, reason, count,
                                f'{count} of {part.stop - part.start} rows rejected')
            if sum(other_counts[first:index]):
                state.counts['other_shard'] += sum(other_counts[first:index])
            for k in range(first, index):
                if counts[k]:
                    rows = slice(bounds[k], bounds[k + 1])
                    keep = slice(None) if counts[k] == rows.stop - rows.start else valid[rows]
                    queued += self._queue(state, every[k], counts[k], unlabelled[k] > 0, (
                        ids[rows][keep], m[rows][keep], P[rows][keep], P_dep[rows][keep]), keep)
        return queued

    def _other_shard(self, ids, m):
        """Return which rows belong to another shard (None when there is one shard)."""
        if self.config.shard_count <= 1:
            return None
        # Rows without an ID go to the shard of their cell (``shard_of_position``).
        cells = shard_of_position(m.reshape(-1, 2), self.config.shard_cell_m,
                                  self.config.shard_count)
        return np.where(ids == UNKNOWN_ID, cells != self.config.shard_index,
                        ids % self.config.shard_count != self.config.shard_index)

    def _queue(self, state: Source, message: LandmarkMessage, count: int, unlabelled: bool,
               columns: Tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64],
                              NDArray[np.float64]], keep: Any) -> int:
        """
        Queue ``count`` checked rows of one message (dropping the oldest of a full queue).

        ``columns``: the rows' ``ids, m, P, P_dep``; ``keep``: which rows of the message
        they are (a mask, or a slice of all).
        """
        if len(state.queue) >= self.config.max_queue_messages:
            dropped = state.queue.popleft()
            self.reject(state.name, 'queue_overflow', len(dropped.ids),
                        f'more than {self.config.max_queue_messages} messages waiting: '
                        'dropped the oldest')
        classes = None if message.classes is None else np.asarray(message.classes,
                                                                  np.int64)[keep]
        state.queue.append(Queued(next(self._sequence), *columns, int(message.stamp_ns),
                                  classes, message.scan, unlabelled))
        return count

    def add_partial_observations(self, source: str, stamp_ns: int,
                                 columns: Dict[str, NDArray[Any]],
                                 frame_id: Optional[str] = None,
                                 now_ns: Optional[int] = None) -> int:
        """
        Check the rows of one partial observation message and queue the valid ones.

        Parameters
        ----------
        source : str
            One of the partial sources.
        stamp_ns : int
            The message stamp [ns].
        columns : dict of str to ndarray, shape (N,)
            ``pipeline.partial_rows.PARTIAL_COLUMNS``.
        frame_id : str, optional
            The message's frame, checked against ``world_frame``; None skips the check.
        now_ns : int, optional
            Arrival time [ns], for the stale-source check.

        Returns
        -------
        int
            The rows queued.

        """
        state = self._arrive(source, frame_id, now_ns, 'partial observations')
        if state is None:
            return 0
        ids = np.asarray(columns['id'])
        state.counts['partial_in'] += len(ids)
        valid, reasons = partial_row_problems(columns)
        reserved = valid & (ids >= self.reserved_from)
        if reserved.any():
            valid &= ~reserved
            reasons['id_reserved'] += int(reserved.sum())
        if self.config.shard_count > 1:
            other = valid & (ids % self.config.shard_count != self.config.shard_index)
            if other.any():
                state.counts['other_shard'] += int(other.sum())
                valid &= ~other
        for reason, count in reasons.items():
            self.reject(source, reason, count, f'{count} of {len(valid)} partial observation '
                        'rows rejected')
        if not valid.any():
            return 0
        if not valid.all():
            columns = {name: np.asarray(values)[valid] for name, values in columns.items()}
        self.partial.add(source, stamp_ns, np.asarray(columns['id']).astype(np.int64),
                         views_from_columns(columns), np.asarray(columns['view_group']))
        return int(valid.sum())

    def _fuse_partial(self) -> None:
        """Take the queued partial observations: buffer, place or update landmarks."""
        if not self.partial.queue:
            return
        result = self.partial.fuse()
        for name, counts in result.counts.items():
            for reason, count in counts.items():
                if reason in ('partial_gated', 'partial_too_close', 'partial_dropped'):
                    self.reject(name, reason, count)
                else:
                    self.sources[name].counts[reason] += count
                    if reason in ('landmarks_initialised', 'landmarks_reinitialised'):
                        self.counters.add(reason, count)
        if result.changed_ids:
            self.map_changed = self.unsaved = True
            self._updated.append(np.unique(np.array(result.changed_ids, np.int64)))

    def queued_messages(self) -> int:
        """Return the number of messages waiting in all queues."""
        return sum(len(state.queue) for state in self.sources.values())

    def fuse_queued(self) -> Optional[UpdateResult]:
        """
        Fuse every queued row, in arrival order, in one batch (queued partial observations first).

        Returns
        -------
        UpdateResult or None
            What the update did; None when nothing was queued.

        """
        self._fuse_partial()
        items = []
        for state in self.sources.values():
            items += [(item, state.name) for item in state.queue]
            state.queue.clear()
        if not items:
            return None
        items.sort(key=lambda entry: entry[0].sequence)
        for item, _ in items:
            if item.classes is not None and item.classes.any():
                self.tracker.note_classes(item.ids, item.classes)
        if not any(item.unlabelled for item, _ in items):
            return self._apply(items)
        # Rows without an ID: message by message, each associated with the map as the
        # messages before it left it; labelled messages in between go in one batch.
        # Expiry (before) and merging (after) go with each such message, so the map
        # does not depend on where the batches begin and end (``fuser.tracks``).
        results, group = [], []
        for item, name in items:
            now_ns = self.tracker.advance(item.stamp_ns)
            if not item.unlabelled:
                group.append((item, name))
                continue
            if group:
                results.append(self._apply(group))
                group = []
            self.tracker.expire(self.map, now_ns, self._counts_of())
            results.append(self._apply(self._associate(item, name)))
            self.tracker.after_update(results[-1], self._counts_of())
            merged = self.tracker.merge(self.map, self.sources[name].counts,
                                        results[-1].changed_ids)
            if merged:
                self.map_changed = self.unsaved = True
                self._updated.append(np.array([keep for _, keep in merged], np.int64))
                self._removed += merged
        if group:
            results.append(self._apply(group))
        self.tracker.expire(self.map, now_ns, self._counts_of())
        return _combine(results)

    def _counts_of(self) -> Dict[str, Counter[str]]:
        return {name: state.counts for name, state in self.sources.items()}

    def _associate(self, item: Queued, name: str) -> List[Tuple[Queued, str]]:
        """Return what of ``item`` goes to the map, IDs given (``Tracker.screen``)."""
        unlabelled = item.ids == UNKNOWN_ID
        classes = item.classes
        if classes is None:
            classes = np.zeros(len(item.ids), np.int64)
        ids = item.ids.copy()
        ids[unlabelled] = self.tracker.associate(
            self.map, name, item.m[unlabelled], item.P[unlabelled], classes[unlabelled],
            item.scan, item.stamp_ns, self.sources[name].counts)
        if self.association_log is not None:
            self.association_log.append((name, item.stamp_ns, ids[unlabelled].copy()))
        keep = ids >= 0
        return [(queued, source if source in self.sources else name)
                for queued, source in self.tracker.screen(
                    self.map, Queued(item.sequence, ids[keep], item.m[keep], item.P[keep],
                                     item.P_dep[keep], item.stamp_ns, None, item.scan),
                    unlabelled[keep], name, self._counts_of())]

    def _apply(self, items: Sequence[Tuple[Queued, str]]) -> UpdateResult:
        """Fuse queued messages (labelled rows only) in one ``LandmarkMap.update``."""
        if not items:
            return UpdateResult()
        lengths = [len(item.ids) for item, _ in items]
        names: Dict[str, int] = {}
        index = [names.setdefault(name, len(names)) for _, name in items]
        rows = [np.concatenate([getattr(item, name) for item, _ in items])
                for name in ('ids', 'm', 'P', 'P_dep')]
        stamps, index = np.repeat([item.stamp_ns for item, _ in items], lengths), np.repeat(
            index, lengths)
        ids, z, P, P_dep = rows
        groups = None if self.moves is None else unique_inverse(ids)
        tested = None if groups is None else self.map.confirmed_ids(groups[0])[groups[1]]
        result = self.map.update(ids, z, P, P_dep, list(names), stamps,
                                 settle=False, source_index=index)  # folded when read
        if self.moves is not None and tested is not None:
            moved = detect_moves(self.moves, self.map, tested, (ids, z, P, P_dep, index, stamps),
                                 result, list(names), groups)
            if moved:
                self.counters.add('landmark_moved', len(moved), f'landmarks {moved} moved: '
                                  'rebuilt from their rows since the change (change detection)')
                self._updated.append(np.array(moved, np.int64))
                self.map_changed = self.unsaved = True
        for name, count in result.accepted.items():
            self.sources[name].counts['fused'] += count
        for name, count in result.rejected.items():
            self.reject(name, 'gated_out', count,
                        'observations outside the chi-square gate of their landmark')
        if result.confirmed:
            self.counters.add('landmarks_confirmed', len(result.confirmed))
        if result.reinitialised:
            self.counters.add('landmarks_reinitialised', len(result.reinitialised),
                              f'landmarks {result.reinitialised} rejected '
                              f'{self.config.max_consecutive_rejections} times in a row were '
                              'rebuilt from their recent observations (moved?)')
        if result.changed:
            self.map_changed = self.unsaved = True
            self._updated.append(result.changed_ids)
            self.tracker.dirty = True
        return result

    # Output --------------------------------------------------------------------

    def snapshot(self) -> MapSnapshot:
        """Return the confirmed map (``LandmarkMap.snapshot``); clears ``map_changed``."""
        self.map_changed = False
        return self.map.snapshot()

    def classes_of(self, ids: NDArray[np.int64]) -> NDArray[np.int64]:
        """Return the class of each landmark ID, shape (K,) (0 when none was given)."""
        return self.tracker.class_of(ids)

    def take_removed(self) -> List[tuple]:
        """
        Return the landmarks taken out of the map since the last call.

        Returns
        -------
        list of (int, int)
            ``(removed ID, ID it is now part of)`` (later merges followed), in the
            order of the merges; the nodes announce them on ``fused_landmark_updates``.

        """
        removed, self._removed = self._removed, []
        return [(drop, self.tracker.resolve(keep)) for drop, keep in removed]

    def removal_rows(self, removed: Sequence[tuple]) -> Tuple[MapSnapshot, NDArray[np.int64]]:
        """Return the rows that announce ``removed`` (``publishing.removal_rows``)."""
        return publishing.removal_rows(self.map, removed, self.tracker.deleted)

    def take_updates(self) -> MapSnapshot:
        """
        Return the confirmed landmarks that changed since the last call.

        Returns
        -------
        MapSnapshot
            Rows (sorted by ID) of the landmarks whose estimate changed; empty when none.

        """
        changed = np.unique(np.concatenate(self._updated)) if self._updated else np.empty(
            0, np.int64)
        self._updated = []
        return self.map.snapshot(changed)

    def reset(self) -> int:
        """Clear the map and the queues; return how many landmarks were cleared."""
        count = len(self.map)
        self.map.reset()
        self.tracker.reset()
        self.partial.reset()
        if self.moves is not None:
            self.moves.reset()
        for state in self.sources.values():
            state.queue.clear()
        self._updated = []
        self._removed = []
        self.map_changed = False
        self.unsaved = True
        return count

    def statuses(self, now_ns: int) -> List[Status]:
        """
        Return the fuser's diagnostics: its own status, then one per source.

        Parameters
        ----------
        now_ns : int
            The caller's clock [ns]; a source silent ``source_timeout_s`` is stale.

        Returns
        -------
        list of Status
            The first has ``name`` '' (the fuser), the others the source name.

        """
        statuses = []
        stale = []
        partial_waiting = Counter(entry[0] for entry in self.partial.queue)
        for state in self.sources.values():
            age = None if state.last_message_ns is None else (
                now_ns - state.last_message_ns) * 1e-9
            is_stale = (not state.optional) if age is None else (
                age > self.config.source_timeout_s)
            if is_stale:
                stale.append(state.name)
            extra = {'age_s': 'never' if age is None else f'{age:.3f}',
                     'stale': str(is_stale).lower(), 'queued_messages': len(state.queue),
                     'queued_partial': partial_waiting[state.name]}
            statuses.append(Status('warn' if is_stale else 'ok',
                                   'stale' if is_stale else 'ok', dict(state.counts), extra,
                                   state.name))
        counts = dict(self.counters.counts)
        problems = sorted(key for key, value in counts.items()
                          if key not in NOT_PROBLEMS and value > self._reported.get(key, 0))
        self._reported = counts
        message = f'{len(self.map)} landmarks'
        if stale:
            message += f"; stale: {', '.join(stale)}"
        if problems:
            message += f"; rejected: {', '.join(problems)}"
        extra = {'landmarks': len(self.map), 'fusion': self.config.fusion,
                 'map_file': self.config.map_file or '(none)'}
        statuses.insert(0, Status('warn' if (stale or problems) else 'ok', message, counts,
                                  extra))
        return statuses

    # Persistence -----------------------------------------------------------------

    def save(self) -> bool:
        """Write ``map_file`` atomically; return whether it worked (``persistence.save``)."""
        return persistence.save(self)

    def load(self) -> None:
        """
        Load ``map_file`` if set: every valid record is kept, the bad ones quarantined.

        See ``persistence.load``: an unparsable file is moved aside and the fuser starts
        empty; otherwise each record and section is checked on its own and what fails
        goes to a quarantine file beside the map (``map_records_rejected``).
        """
        persistence.load(self)


def _combine(results: Sequence[UpdateResult]) -> UpdateResult:
    """Return one ``UpdateResult`` for several updates made one after the other."""
    total = UpdateResult()
    for result in results:
        total.accepted.update(result.accepted)
        total.rejected.update(result.rejected)
        total.confirmed += result.confirmed
        total.reinitialised += result.reinitialised
    changed = [result.changed_ids for result in results if len(result.changed_ids)]
    if changed:
        total.changed_ids = np.unique(np.concatenate(changed))
    return total
