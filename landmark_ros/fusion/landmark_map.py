"""
A map of landmark estimates fused by ID, with gating and confirmation.

Symbols: ``ids`` landmark IDs (N,); ``z`` observed positions in the world (N, 2) [m];
``R`` their covariances (N, 2, 2) [m^2], ``R_dep`` the dependent part (pose error, sensor
bias: correlated across observations), ``R_ind = R - R_dep`` the independent part. An
estimate is held as ``m, P_ind, P_dep``; ``stamp_ns`` is integer nanoseconds.

An observation of a confirmed landmark is gated by its squared Mahalanobis distance to
the landmark's gate reference (innovation covariance ``P_ref + R``): the estimate after
its last refresh (``records.gate_due``), rebuild, merge, ``set_estimate`` or
``load_records``. A new ID becomes a landmark once ``min_observations`` of its
observations agree; one rejected ``max_consecutive_rejections`` times in a row is rebuilt
from them when they agree (it moved). A batch gives the same map as its rows one by one:
the rows of confirmed landmarks go in passes, each taking every landmark's rows up to its
next refresh or rebuild (``_pass``), when its gate reference changes.
"""

from collections import deque
import copy
from typing import Any, Deque, Dict, List, Mapping, Optional, Sequence, Tuple, Union

from landmark_ros.core.arrays import mahalanobis_sq_2x2, unique_ints, unique_inverse
from landmark_ros.core.gating import chi2_threshold
from landmark_ros.fusion.methods import FUSION_METHODS, make_method, Rows  # noqa: F401
from landmark_ros.fusion.records import (agreeing, Batch, Checkpoint, floored, gate_due,
                                         MapSnapshot, Observation, parse_record, stack,
                                         UpdateResult)
from landmark_ros.fusion.source_sums import entries as _entries, Estimates, SOURCE_BITS
import numpy as np
from numpy.typing import ArrayLike, NDArray

_NO_STAMP = np.iinfo(np.int64).min
"""``first_stamp_ns`` of a landmark that has not had an observation yet."""


class LandmarkMap:
    """
    Fuse world-frame landmark observations of several robots by landmark ID.

    Parameters
    ----------
    fusion : str
        One of ``FUSION_METHODS``.
    gate_probability : float
        Probability mass of the chi-square gate (2 degrees of freedom).
    min_observations : int
        Mutually consistent observations needed before a landmark is confirmed.
    max_consecutive_rejections : int
        Rejections in a row after which a landmark is rebuilt from them.
    source_correlation : str
        ``'unknown'`` or ``'independent'`` (split CI: ``methods.make_method``).

    Raises
    ------
    ValueError
        If ``fusion`` or ``source_correlation`` is unknown or a count is below 1.

    """

    def __init__(self, fusion: str = 'split_covariance_intersection',
                 gate_probability: float = 0.999, min_observations: int = 2,
                 max_consecutive_rejections: int = 5, source_correlation: str = 'unknown'
                 ) -> None:
        if min_observations < 1 or max_consecutive_rejections < 1:
            raise ValueError('min_observations and max_consecutive_rejections must be >= 1')
        self.fusion = fusion
        self._method = make_method(fusion, source_correlation)
        self.source_correlation = source_correlation
        self.threshold = chi2_threshold(2, gate_probability)
        self.min_observations = int(min_observations)
        self.max_consecutive_rejections = int(max_consecutive_rejections)
        self.reset()

    def reset(self) -> None:
        """Forget every landmark."""
        self._count = 0
        self._sorted_ids = np.empty(0, np.int64)
        self._sorted_rows = np.empty(0, np.int64)
        self.ids = np.empty(0, np.int64)
        self.mean = np.empty((0, 2))
        self.cov_ind = np.empty((0, 2, 2))
        self.cov_dep = np.empty((0, 2, 2))
        self.gate = np.empty((0, 5))
        self.confirmed = np.empty(0, bool)
        self.observations = np.empty(0, np.int64)
        self.rejections = np.empty(0, np.int64)
        self.consecutive = np.empty(0, np.int64)
        self.first_stamp_ns = np.empty(0, np.int64)
        self.last_stamp_ns = np.empty(0, np.int64)
        self._seen_by: Dict[str, NDArray[np.bool_]] = {}
        self._buffers: Dict[int, Deque[Observation]] = {}
        self._source_names: List[str] = []
        self._source_codes: Dict[str, int] = {}
        self._method.reset()

    def __len__(self) -> int:
        """Return the number of confirmed landmarks."""
        return int(self.confirmed[:self._count].sum())

    @property
    def source_names(self) -> List[str]:
        """Return the source names, indexed by their codes."""
        return self._source_names

    def source_code(self, name: str) -> int:
        """Return the map's integer code of a source name, registering a new one."""
        code = self._source_codes.get(name)
        if code is None:
            code = self._source_codes[name] = len(self._source_names)
            if code >= 1 << SOURCE_BITS:
                raise ValueError(f'more than {1 << SOURCE_BITS} sources')
            self._source_names.append(name)
        return code

    def _grow(self, extra):
        need = self._count + extra
        if need <= len(self.ids):
            return
        size = max(need, 2 * len(self.ids), 64)
        for name in self._ROW_ARRAYS:
            old = getattr(self, name)
            new = np.zeros((size,) + old.shape[1:], old.dtype)
            if name == 'first_stamp_ns':
                new[:] = _NO_STAMP
            new[:len(old)] = old
            setattr(self, name, new)
        for source, seen in self._seen_by.items():
            self._seen_by[source] = np.concatenate([seen, np.zeros(size - len(seen), bool)])

    def _rows_of(self, ids):
        """Return the rows of ``ids``, adding unconfirmed entries for new IDs."""
        rows = self._lookup(ids)
        if (rows >= 0).all():
            return rows
        new = unique_ints(ids[rows < 0])
        if len(new):
            self._grow(len(new))
            rows = np.arange(self._count, self._count + len(new))
            self.ids[rows] = new
            self._count += len(new)
            order = np.argsort(self.ids[:self._count], kind='stable')
            self._sorted_ids = self.ids[:self._count][order]
            self._sorted_rows = order
        return self._lookup(ids)

    def _lookup(self, ids):
        """Return the rows of ``ids``, -1 for unknown IDs."""
        if not len(self._sorted_ids):
            return np.full(len(ids), -1, np.int64)
        # One search per distinct ID, in order: 3x cheaper for 16,000 rows.
        ids, inverse = unique_inverse(ids) if len(ids) > 256 else (ids, slice(None))
        position = np.minimum(np.searchsorted(self._sorted_ids, ids), len(self._sorted_ids) - 1)
        rows = np.where(self._sorted_ids[position] == ids, self._sorted_rows[position], -1)
        return rows[inverse]

    def _known_rows(self, ids, confirmed=True):
        """Return the rows of the distinct ``ids`` that are known and (not) confirmed."""
        rows = self._lookup(unique_ints(np.asarray(ids, dtype=np.int64)))
        rows = rows[rows >= 0]
        return rows[self.confirmed[rows] == confirmed]

    def _seen(self, source):
        seen = self._seen_by.get(source)
        if seen is None:
            seen = self._seen_by[source] = np.zeros(len(self.ids), bool)
        return seen

    def update(self, ids: ArrayLike, z: ArrayLike, R: ArrayLike, R_dep: Optional[ArrayLike] = None,
               source: Union[str, Sequence[str], NDArray[np.str_]] = '',
               stamp_ns: ArrayLike = 0, settle: bool = True,
               source_index: Optional[ArrayLike] = None) -> UpdateResult:
        """
        Fuse a batch of observations, row by row in order; all or nothing.

        ``ids`` (N,) landmark IDs; ``z`` (N, 2) observed positions [m]; ``R`` (N, 2, 2)
        their covariances, positive definite, and ``R_dep`` their dependent parts (zero
        when absent) [m^2]; ``source`` who made each (str or N names; with
        ``source_index`` (N,), the names it indexes); ``stamp_ns`` times [ns], int or
        (N,). ``settle=False``: the split-CI folds may wait for the next ``settle()``
        (which ``snapshot``, ``estimate`` and ``to_records`` call): a caller that
        updates many times between two reads folds once per read; same results.
        Returns an ``UpdateResult``; raises ValueError if ``stamp_ns`` is not integer
        or ``source_index`` out of range.
        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        checkpoint = self._checkpoint(ids)
        try:
            result = self._update(ids, z, R, R_dep, source, stamp_ns, source_index)
            if settle:
                self.settle()
            return result
        except BaseException:
            # All or nothing: whatever failed half way, the map is as it was.
            self._restore(checkpoint)
            raise

    _ROW_ARRAYS = ('ids', 'mean', 'cov_ind', 'cov_dep', 'gate', 'confirmed', 'observations',
                   'rejections', 'consecutive', 'first_stamp_ns', 'last_stamp_ns')

    def _checkpoint(self, ids):
        """Save what an update of ``ids`` can change (their rows, the registries)."""
        if 8 * len(ids) < self._count:
            rows = self._lookup(unique_ints(ids))
            rows = rows[rows >= 0]
        else:   # a mask over the rows: cheaper than sorting the IDs
            rows = self._lookup(ids)
            taken = np.zeros(self._count, bool)
            taken[rows[rows >= 0]] = True
            rows = np.flatnonzero(taken)
        return Checkpoint(self._count, rows, {
            name: getattr(self, name).take(rows, axis=0) for name in self._ROW_ARRAYS},
            {source: seen[rows].copy() for source, seen in self._seen_by.items()},
            {row: copy.copy(self._buffers[row]) for row in rows.tolist() if row in self._buffers},
            list(self._source_names), self._method.checkpoint(rows))

    def _restore(self, checkpoint):
        """Put the map back to a ``_checkpoint``."""
        count, rows = checkpoint.count, checkpoint.rows
        for name, values in checkpoint.arrays.items():
            getattr(self, name)[rows] = values
        added = slice(count, self._count)
        for name in self._ROW_ARRAYS:      # rows added by the failed update, as new
            getattr(self, name)[added] = _NO_STAMP if name == 'first_stamp_ns' else 0
        for source in list(self._seen_by):
            if source in checkpoint.seen:
                self._seen_by[source][rows] = checkpoint.seen[source]
                self._seen_by[source][added] = False
            else:
                del self._seen_by[source]
        for row in rows.tolist():
            self._buffers.pop(row, None)
        for row in [row for row in self._buffers if row >= count]:
            del self._buffers[row]
        self._buffers.update(checkpoint.buffers)
        for name in self._source_names[len(checkpoint.sources):]:
            del self._source_codes[name]
        self._source_names[:] = checkpoint.sources
        self._method.restore(checkpoint.method)
        if self._count != count:
            self._count = count
            order = np.argsort(self.ids[:count], kind='stable')
            self._sorted_ids, self._sorted_rows = self.ids[:count][order], order

    def _update(self, ids, z, R, R_dep, source, stamp_ns, source_index):
        batch = Batch.of(len(ids), (z, R, R_dep, stamp_ns), (source, source_index),
                         self._source_names, self.source_code)
        result = UpdateResult()
        if not len(ids):
            return result
        rows = self._rows_of(ids)
        changed: List[NDArray[np.int64]] = []
        known = self.confirmed[rows]
        # Confirmed landmarks' rows in passes; the others one by one until confirmed.
        self._update_confirmed(rows[known], batch, np.flatnonzero(known), result, changed)
        later = []      # rows of landmarks confirmed earlier in this batch
        for i in np.flatnonzero(~known).tolist():
            if self.confirmed[rows[i]]:
                later.append(i)
            else:
                self._add_tentative(rows[i], batch.observation(i), result, changed)
        at = np.array(later, np.int64)
        self._update_confirmed(rows[at], batch, at, result, changed)
        # By source once per update, not once per pass (60 sources: a loop over them).
        self._count_by_source(batch.codes[batch.taken], rows[batch.taken], result.accepted, True)
        if changed:
            result.changed_ids = unique_ints(self.ids[np.concatenate(changed)])
        return result

    def _update_confirmed(self, rows, batch, positions, result, changed):
        """Gate and fuse rows of confirmed landmarks, each landmark's in order."""
        while len(rows):
            rows, positions = self._pass(rows, batch, positions, result, changed)

    def _pass(self, rows, batch, positions, result, changed):
        """
        Take every landmark's rows up to its next gate refresh or rebuild; return the rest.

        Until then a landmark's gate reference does not change, so its rows are gated
        together (``rows`` in arrival order, grouped here by landmark, stable).
        """
        order = np.argsort(rows, kind='stable')
        rows, positions = rows[order], positions[order]
        index = np.arange(len(rows))
        first = np.ones(len(rows), bool)
        first[1:] = rows[1:] != rows[:-1]
        starts = np.flatnonzero(first)
        group = np.cumsum(first) - 1
        start = starts[group]
        # take(): numpy's fancy indexing of (N, 2, 2) rows is several times slower.
        gate = self.gate.take(rows, axis=0)
        R_ind, R_dep = batch.R_ind.take(positions, axis=0), batch.R_dep.take(positions, axis=0)
        d = batch.z.take(positions, axis=0) - gate[:, :2]
        d2 = mahalanobis_sq_2x2(d[:, 0], d[:, 1], *(
            gate[:, 2 + k] + _entries(R_ind)[k] + _entries(R_dep)[k] for k in range(3)))
        ok = d2 <= self.threshold   # NaN (degenerate input) is rejected
        taken = np.cumsum(ok)
        count = self.observations[rows] + taken - (taken[start] - ok[start])
        last_ok = np.maximum.accumulate(np.where(ok, index, -1))
        leading = last_ok < start
        streak = np.where(ok, 0, np.where(leading, self.consecutive[rows] + index - start + 1,
                                          index - last_ok))
        refresh = ok & gate_due(count)
        rebuild = ~ok & (streak >= self.max_consecutive_rejections)
        stop = np.minimum.reduceat(np.where(refresh | rebuild, index, len(rows)), starts)
        stop = np.minimum(stop, np.append(starts[1:], len(rows)) - 1)
        now = index <= stop[group]
        self._take(rows[now], batch, positions[now], ok[now], result, changed)
        ends = rows[stop]
        self.consecutive[ends] = streak[stop]
        self._settle_rows(ends[refresh[stop]])
        self._refresh_gate(ends[refresh[stop]])
        for row in ends[rebuild[stop]].tolist():
            self._reinitialise(row, result, changed)
        return rows[~now], positions[~now]

    def _take(self, rows, batch, positions, ok, result, changed):
        """Book rows of confirmed landmarks (grouped by landmark, in order) gated ``ok``."""
        codes = batch.codes[positions]
        if ok.any():
            good, at = rows[ok], positions[ok]
            first = np.ones(len(good), bool)
            first[1:] = good[1:] != good[:-1]
            landmarks, index = good[first], np.cumsum(first) - 1
            current = Estimates(*(x.take(landmarks, axis=0)
                                  for x in (self.mean, self.cov_ind, self.cov_dep)))
            fused = self._method.absorb(landmarks, current, index, batch.rows(good, at))
            if fused is not None:
                self.mean[landmarks], self.cov_ind[landmarks], self.cov_dep[landmarks] = fused
            self.observations[landmarks] += np.bincount(index)
            self.last_stamp_ns[landmarks] = batch.stamps_ns[at[np.append(first[1:], True)]]
            changed.append(landmarks)
            batch.taken[at] = True
            if self._buffers:
                for row in self._buffers.keys() & set(landmarks.tolist()):
                    del self._buffers[row]
        if not ok.all():
            np.add.at(self.rejections, rows[~ok], 1)
            self._count_by_source(codes[~ok], rows[~ok], result.rejected, False)
            # Recent rejections: those after a landmark's last accepted row.
            index = np.arange(len(rows))
            last_ok = np.maximum.accumulate(np.where(ok, index, -1))
            later = np.append(rows[1:] != rows[:-1], True)
            recent = ~ok & (index > np.minimum.accumulate(
                np.where(later, last_ok, len(rows))[::-1])[::-1])
            for i in np.flatnonzero(recent).tolist():
                self._buffers.setdefault(int(rows[i]), deque(
                    maxlen=self.max_consecutive_rejections)).append(
                        batch.observation(positions[i]))

    def _count_by_source(self, codes, rows, counter, seen):
        """Add rows to ``counter`` by source name; with ``seen``, mark the sources seen."""
        order = np.argsort(codes, kind='stable')
        bounds = np.searchsorted(codes[order], np.arange(len(self._source_names) + 1))
        for code in np.flatnonzero(np.diff(bounds)).tolist():
            name = self._source_names[code]
            counter[name] += int(bounds[code + 1] - bounds[code])
            if seen:
                self._seen(name)[rows[order[bounds[code]:bounds[code + 1]]]] = True

    def _set(self, row, estimate):
        """Make ``row`` a confirmed landmark of ``estimate`` (one row), its gate reference."""
        self.mean[row], self.cov_ind[row], self.cov_dep[row] = (x[0] for x in estimate)
        self._refresh_gate(row)
        self.confirmed[row] = True
        self.consecutive[row] = 0

    def _refresh_gate(self, rows):
        """Make the estimates of ``rows`` (an index or indices) their gate references."""
        xx, xy, yy = _entries(self.cov_ind.take(rows, axis=0) + self.cov_dep.take(rows, axis=0))
        self.gate[rows, 0], self.gate[rows, 1] = self.mean[rows, 0], self.mean[rows, 1]
        self.gate[rows, 2], self.gate[rows, 3], self.gate[rows, 4] = xx, xy, yy

    def _add_tentative(self, row, observation, result, changed):
        buffer = self._buffers.setdefault(
            row, deque(maxlen=max(4 * self.min_observations, self.max_consecutive_rejections)))
        if len(buffer) == buffer.maxlen:
            result.rejected[buffer[0].source] += 1
            self.rejections[row] += 1
        buffer.append(observation)
        if self.first_stamp_ns[row] == _NO_STAMP:
            self.first_stamp_ns[row] = observation.stamp_ns
        buffered = list(buffer)
        cluster = self._rebuild(row, buffered)
        if cluster:
            for obs in buffered:
                if any(obs is member for member in cluster):
                    result.accepted[obs.source] += 1
                else:
                    result.rejected[obs.source] += 1
                    self.rejections[row] += 1
            result.confirmed.append(int(self.ids[row]))
            changed.append(np.array([row]))

    def _reinitialise(self, row, result, changed):
        # The recent rejections stay counted as rejections: they were, when they came.
        if self._rebuild(row, list(self._buffers.get(row, ()))):
            result.reinitialised.append(int(self.ids[row]))
            changed.append(np.array([row]))

    def _rebuild(self, row, observations):
        """Set ``row`` from the largest agreeing subset; return it (empty if too small)."""
        cluster = agreeing(observations, self.threshold, self._method.fuse, self._method.name)
        if len(cluster) < self.min_observations:
            return []
        z, R_ind, R_dep = stack(cluster)
        codes = np.array([self.source_code(obs.source) for obs in cluster], np.int64)
        self._set(row, self._method.start(row, Rows(np.full(len(cluster), row, np.int64),
                                                    codes, z, R_ind, R_dep)))
        self.observations[row] = len(cluster)
        self.last_stamp_ns[row] = max(obs.stamp_ns for obs in cluster)
        for obs in cluster:
            self._seen(obs.source)[row] = True
        self._buffers.pop(row, None)
        return cluster

    def settle(self, ids: Optional[ArrayLike] = None) -> None:
        """Fold what ``update(..., settle=False)`` left (of ``ids``, unknown ignored; all)."""
        rows = np.arange(self._count) if ids is None else self._lookup(
            np.asarray(ids, dtype=np.int64).reshape(-1))
        self._settle_rows(rows[rows >= 0])

    def _settle_rows(self, rows):
        rows, fused = self._method.settle(rows)
        if fused is not None:
            self.mean[rows], self.cov_ind[rows], self.cov_dep[rows] = fused

    def known(self, ids: ArrayLike) -> NDArray[np.bool_]:
        """Return whether the map has had rows of each ID (bool, shape (N,))."""
        return self._lookup(np.asarray(ids, dtype=np.int64).reshape(-1)) >= 0

    def forget(self, ids: ArrayLike) -> int:
        """
        Drop the buffered observations of unconfirmed IDs; return how many IDs that was.

        The IDs stay ``known``, with no observation; unknown and confirmed ones are
        ignored.
        """
        rows = self._known_rows(ids, confirmed=False)
        for row in rows.tolist():
            self._buffers.pop(row, None)
        self.first_stamp_ns[rows] = _NO_STAMP
        return len(rows)

    def retire(self, ids: ArrayLike) -> int:
        """
        Take confirmed landmarks out of the map (a merged duplicate); return how many.

        Their IDs stay ``known``: a later observation starts one again as a new ID.
        """
        rows = self._known_rows(ids)
        self.confirmed[rows] = False
        self.observations[rows] = 0
        self.consecutive[rows] = 0
        self.first_stamp_ns[rows] = _NO_STAMP
        for row in rows.tolist():
            self._buffers.pop(row, None)
        self._method.retire(rows)
        return len(rows)

    def merge(self, keep_id: int, drop_id: int) -> bool:
        """
        Fuse confirmed landmark ``drop_id`` into ``keep_id`` and retire it; False if not both.

        By the method's rule (``methods``: split CI adds the per-source sums, as if the
        observations had gone to ``keep_id``); counts add up, stamps span both.
        """
        rows = self._lookup(np.array([keep_id, drop_id], np.int64))
        if keep_id == drop_id or (rows < 0).any() or not self.confirmed[rows].all():
            return False
        keep, drop = (int(r) for r in rows)
        self._settle_rows(rows)
        one, other = slice(keep, keep + 1), slice(drop, drop + 1)
        self._set(keep, self._method.merge(
            keep, drop, Estimates(self.mean[one], self.cov_ind[one], self.cov_dep[one]),
            Estimates(self.mean[other], self.cov_ind[other], self.cov_dep[other])))
        self.observations[keep] += self.observations[drop]
        self.first_stamp_ns[keep] = min(self.first_stamp_ns[keep], self.first_stamp_ns[drop])
        self.last_stamp_ns[keep] = max(self.last_stamp_ns[keep], self.last_stamp_ns[drop])
        self.retire(np.array([drop_id], np.int64))
        return True

    def estimate(
            self, landmark_id: int
    ) -> Optional[Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]:
        """Return ``m`` (2,), ``P`` and ``P_dep`` (2, 2) of a confirmed landmark, or None."""
        row = int(self._lookup(np.array([landmark_id], np.int64))[0])
        if row < 0 or not self.confirmed[row]:
            return None
        self._settle_rows(np.array([row], np.int64))
        return (self.mean[row].copy(), self.cov_ind[row] + self.cov_dep[row],
                self.cov_dep[row].copy())

    def set_estimate(self, landmark_id: int, m: ArrayLike, P: ArrayLike, P_dep: ArrayLike,
                     source: str, stamp_ns: int = 0, observations: int = 1) -> None:
        """
        Insert or replace a confirmed landmark's estimate computed outside the map.

        For partial observations (``core.partial``): ``m`` (2,) [m], total covariance
        ``P`` and its dependent part ``P_dep`` (2, 2) [m^2], booked under ``source``
        with ``stamp_ns`` [ns], adding ``observations`` to the landmark's count; held
        as the method holds an estimate (split CI: the per-source sums collapse into
        one source). Waiting observations of the landmark are dropped.
        """
        m = np.asarray(m, dtype=np.float64).reshape(2)
        P = np.asarray(P, dtype=np.float64).reshape(2, 2)
        P_dep = np.asarray(P_dep, dtype=np.float64).reshape(2, 2)
        code = self.source_code(source)
        row = int(self._rows_of(np.array([landmark_id], np.int64))[0])
        held = self._method.held(Estimates(m[None], (P - P_dep)[None], P_dep[None]))
        self._method.replace(row, code, held)
        self._set(row, held)
        self.observations[row] += int(observations)
        if self.first_stamp_ns[row] == _NO_STAMP:
            self.first_stamp_ns[row] = int(stamp_ns)
        self.last_stamp_ns[row] = max(int(self.last_stamp_ns[row]), int(stamp_ns))
        self._seen(source)[row] = True
        self._buffers.pop(row, None)

    def snapshot(self, ids: Optional[ArrayLike] = None) -> MapSnapshot:
        """
        Return the confirmed landmarks (only those of ``ids`` if given), sorted by ID.

        Returns
        -------
        MapSnapshot
            IDs (K,), means (K, 2) [m], total covariances and their dependent parts
            (K, 2, 2) [m^2], observations fused into each (K,); unpacks like a tuple.

        """
        if ids is None:
            rows = np.flatnonzero(self.confirmed[:self._count])
        else:
            rows = self._known_rows(ids)
        rows = rows[np.argsort(self.ids[rows], kind='stable')]
        self._settle_rows(rows)
        mean, cov_ind, cov_dep = (x.take(rows, axis=0)  # take(): see _pass
                                  for x in (self.mean, self.cov_ind, self.cov_dep))
        return MapSnapshot(self.ids.take(rows), mean, cov_ind + cov_dep, cov_dep,
                           self.observations.take(rows))

    def sources_of(self, landmark_id: int) -> List[str]:
        """Return the sorted sources whose observations a landmark fused."""
        row = int(self._lookup(np.array([landmark_id], np.int64))[0])
        if row < 0:
            raise KeyError(landmark_id)
        return sorted(source for source, seen in self._seen_by.items() if seen[row])

    def to_records(self) -> List[Dict[str, Any]]:
        """
        Return the confirmed landmarks as plain dicts (for saving); stamps in ns.

        Each covariance is ``records.floored``: a record always passes the live row checks.
        """
        records = []
        snapshot = self.snapshot()
        rows = self._lookup(snapshot.ids)
        covariances = floored(self.cov_ind.take(rows, axis=0) + self.cov_dep.take(rows, axis=0))
        for k, (landmark_id, row) in enumerate(zip(snapshot.ids.tolist(), rows.tolist())):
            records.append({
                'id': landmark_id,
                'mean': self.mean[row].tolist(),
                'covariance': covariances[k].tolist(),
                'covariance_dependent': self.cov_dep[row].tolist(),
                'observations': int(self.observations[row]),
                'rejections': int(self.rejections[row]),
                'sources': self.sources_of(landmark_id),
                'first_stamp_ns': int(self.first_stamp_ns[row]),
                'last_stamp_ns': int(self.last_stamp_ns[row]),
                **self._method.records(row, self._source_names),
            })
        return records

    def load_records(self, records: Sequence[Mapping[str, Any]]) -> None:
        """
        Replace the map with confirmed landmarks from ``to_records`` output.

        Raises
        ------
        ValueError
            If a record is malformed; the map is left empty then.

        """
        self.reset()
        try:
            ids = np.array([int(r['id']) for r in records], dtype=np.int64)
            if len(set(ids.tolist())) != len(ids):
                raise ValueError('duplicate landmark IDs')
            rows = self._rows_of(ids)
            for row, record in zip(rows.tolist(), records):
                estimate, counts, stamps = parse_record(record)
                self._set(row, Estimates(*(x[None] for x in estimate)))
                self.observations[row], self.rejections[row] = counts
                self.first_stamp_ns[row], self.last_stamp_ns[row] = stamps
                for source in record['sources']:
                    self._seen(str(source))[row] = True
                self._method.load(row, record, estimate, self.source_code)
        except (KeyError, TypeError, ValueError) as error:
            self.reset()
            raise ValueError(f'malformed landmark record: {error}') from error
