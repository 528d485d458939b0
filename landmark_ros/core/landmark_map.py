"""
A map of landmark estimates fused by ID, with gating and confirmation.

Symbols
-------
ids : landmark IDs, shape (N,), integers.
z : observed landmark positions in the world, shape (N, 2) [m].
R : their covariances, shape (N, 2, 2); ``R_dep`` the dependent part (pose
    uncertainty, sensor bias: correlated across observations), ``R - R_dep`` the
    independent part (sensor noise).
m, P : a landmark estimate and its covariance; ``P_dep`` its dependent part.

Fusion methods
--------------
independent
    Product of Gaussians: exact when every error is independent.
covariance_intersection
    Consistent whatever the correlations; the whole covariance counts as dependent.
split_covariance_intersection
    Within a source (one robot), the dependent parts (its pose error, its sensor
    bias) are one shared error: the source's estimate is the information-weighted
    mean of its observations, whose independent parts (noise) average down while
    the dependent part, their weighted mean, does not. Across sources the
    correlation is unknown: the source estimates are fused by split covariance
    intersection (independent parts as information, dependent parts bounded as
    CI does), the tightest first.

An observation of a known landmark is gated by its squared Mahalanobis distance
to the estimate (innovation covariance ``P + R``). A new ID becomes a landmark
once ``min_observations`` of its observations agree with each other; a
landmark rejected ``max_consecutive_rejections`` times in a row is rebuilt from
those recent observations when they agree (it moved). Rows of one batch are
applied in order, so a batch gives the same map as its rows one by one.
"""

from collections import Counter, deque
from dataclasses import dataclass, field

from landmark_ros.core.gaussian import (chi2_threshold, covariance_intersection, fuse,
                                        information, split_covariance_intersection,
                                        split_covariance_intersection_omega)
import numpy as np

_TABLE_LIMIT = 1 << 20
"""IDs below this are looked up in a dense table, others by binary search."""


FUSION_METHODS = ('independent', 'covariance_intersection', 'split_covariance_intersection')


@dataclass
class UpdateResult:
    """What one ``LandmarkMap.update`` did, for counters and logs."""

    accepted: Counter = field(default_factory=Counter)
    """Observations fused into confirmed landmarks, by source."""
    rejected: Counter = field(default_factory=Counter)
    """Observations gated out or left out of a confirmation, by source."""
    confirmed: list = field(default_factory=list)
    """IDs that became landmarks."""
    reinitialised: list = field(default_factory=list)
    """IDs rebuilt from their recent observations."""

    @property
    def changed(self):
        """Whether the confirmed map changed."""
        return bool(self.accepted or self.confirmed or self.reinitialised)


@dataclass(frozen=True)
class _Observation:
    z: np.ndarray
    R: np.ndarray
    R_dep: np.ndarray
    source: str
    stamp: float


@dataclass(frozen=True)
class _Batch:
    z: np.ndarray
    R: np.ndarray
    R_dep: np.ndarray
    names: list
    codes: np.ndarray
    stamps: np.ndarray

    def observation(self, i):
        return _Observation(self.z[i], self.R[i], self.R_dep[i], self.names[self.codes[i]],
                            float(self.stamps[i]))


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

    """

    def __init__(self, fusion='split_covariance_intersection', gate_probability=0.999,
                 min_observations=2, max_consecutive_rejections=5):
        if fusion not in FUSION_METHODS:
            raise ValueError(f'fusion must be one of {FUSION_METHODS}, got {fusion!r}')
        if min_observations < 1 or max_consecutive_rejections < 1:
            raise ValueError('min_observations and max_consecutive_rejections must be >= 1')
        self.fusion = fusion
        self.threshold = chi2_threshold(2, gate_probability)
        self.min_observations = int(min_observations)
        self.max_consecutive_rejections = int(max_consecutive_rejections)
        self.reset()

    # State ---------------------------------------------------------------------

    def reset(self):
        """Forget every landmark."""
        self._count = 0
        self._row = {}
        self._sorted_ids = np.empty(0, np.int64)
        self._sorted_rows = np.empty(0, np.int64)
        self._table = np.empty(0, np.int64)
        self.ids = np.empty(0, np.int64)
        self.mean = np.empty((0, 2))
        self.cov_ind = np.empty((0, 2, 2))
        self.cov_dep = np.empty((0, 2, 2))
        self.confirmed = np.empty(0, bool)
        self.observations = np.empty(0, np.int64)
        self.rejections = np.empty(0, np.int64)
        self.consecutive = np.empty(0, np.int64)
        self.first_stamp = np.empty(0)
        self.last_stamp = np.empty(0)
        self._seen_by = {}
        self._buffers = {}
        self._parts = _SourceParts() if self.fusion == 'split_covariance_intersection' else None

    def __len__(self):
        """Return the number of confirmed landmarks."""
        return int(self.confirmed[:self._count].sum())

    def _grow(self, extra):
        need = self._count + extra
        if need <= len(self.ids):
            return
        size = max(need, 2 * len(self.ids), 64)
        for name in ('ids', 'mean', 'cov_ind', 'cov_dep', 'confirmed', 'observations',
                     'rejections', 'consecutive', 'first_stamp', 'last_stamp'):
            old = getattr(self, name)
            new = np.zeros((size,) + old.shape[1:], old.dtype)
            if name == 'first_stamp':
                new[:] = np.nan
            new[:len(old)] = old
            setattr(self, name, new)
        for source, seen in self._seen_by.items():
            self._seen_by[source] = np.concatenate([seen, np.zeros(size - len(seen), bool)])

    def _rows_of(self, ids):
        """Return the rows of ``ids``, adding unconfirmed entries for new IDs."""
        unique = np.unique(ids)
        new = unique[self._lookup(unique) < 0]
        if len(new):
            self._grow(len(new))
            rows = np.arange(self._count, self._count + len(new))
            self.ids[rows] = new
            self._row.update(zip(new.tolist(), rows.tolist()))
            self._count += len(new)
            order = np.argsort(self.ids[:self._count], kind='stable')
            self._sorted_ids = self.ids[:self._count][order]
            self._sorted_rows = order
            small = (new >= 0) & (new < _TABLE_LIMIT)
            if small.any():
                size = max(len(self._table), int(new[small].max()) + 1)
                table = np.full(size, -1, np.int64)
                table[:len(self._table)] = self._table
                table[new[small]] = rows[small]
                self._table = table
        return self._lookup(ids)

    def _lookup(self, ids):
        """Return the rows of ``ids``, -1 for unknown IDs."""
        if len(ids) and 0 <= ids.min() and ids.max() < len(self._table):
            return self._table[ids]
        position = np.minimum(np.searchsorted(self._sorted_ids, ids), len(self._sorted_ids) - 1)
        if not len(self._sorted_ids):
            return np.full(len(ids), -1, np.int64)
        found = self._sorted_ids[position] == ids
        return np.where(found, self._sorted_rows[position], -1)

    def _seen(self, source):
        seen = self._seen_by.get(source)
        if seen is None:
            seen = self._seen_by[source] = np.zeros(len(self.ids), bool)
        return seen

    # Update --------------------------------------------------------------------

    def update(self, ids, z, R, R_dep=None, source='', stamp=0.0):
        """
        Fuse a batch of observations, row by row in order.

        Parameters
        ----------
        ids : array_like of int, shape (N,)
            Landmark IDs.
        z : array_like, shape (N, 2)
            Observed positions in the world [m].
        R : array_like, shape (N, 2, 2)
            Their covariances, positive definite.
        R_dep : array_like, shape (N, 2, 2), optional
            Dependent part of ``R`` (zero when absent).
        source : str or sequence of str, length N
            Who made each observation (for counters and the saved map).
        stamp : float or array_like, shape (N,)
            Time of each observation [s].

        Returns
        -------
        UpdateResult

        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
        R = np.asarray(R, dtype=np.float64).reshape(-1, 2, 2)
        R_dep = np.zeros_like(R) if R_dep is None else np.asarray(
            R_dep, dtype=np.float64).reshape(-1, 2, 2)
        count = len(ids)
        if isinstance(source, str):
            names, codes = [source], np.zeros(count, np.int64)
        else:
            names, codes = np.unique(np.asarray(source, dtype=str), return_inverse=True)
            names = names.tolist()
        stamps = np.broadcast_to(np.asarray(stamp, dtype=np.float64), (count,))
        result = UpdateResult()
        if not count:
            return result
        rows = self._rows_of(ids)
        batch = _Batch(z, R, R_dep, names, codes.reshape(-1), stamps)
        known = self.confirmed[rows]
        # Rows of already confirmed landmarks: in rounds of distinct landmarks, which
        # keeps each landmark's own order while fusing the rows of a round together.
        if known.any():
            index = np.flatnonzero(known)
            for positions in _rounds(rows[index]):
                self._update_confirmed(rows[index[positions]], batch, index[positions],
                                       result)
        for i in np.flatnonzero(~known).tolist():
            if self.confirmed[rows[i]]:  # confirmed earlier in this batch
                self._update_confirmed(rows[i:i + 1], batch, np.array([i]), result)
            else:
                self._add_tentative(rows[i], batch.observation(i), result)
        return result

    def _update_confirmed(self, rows, batch, positions, result):
        z, R, R_dep = batch.z[positions], batch.R[positions], batch.R_dep[positions]
        m, P_ind, P_dep = self.mean[rows], self.cov_ind[rows], self.cov_dep[rows]
        d = z - m
        S = P_ind + P_dep + R
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        d2 = (d[:, 0] * (S[:, 1, 1] * d[:, 0] - S[:, 0, 1] * d[:, 1])
              + d[:, 1] * (S[:, 0, 0] * d[:, 1] - S[:, 1, 0] * d[:, 0])) / det
        ok = d2 <= self.threshold
        if ok.any():
            good = rows[ok]
            if self._parts is None:
                self.mean[good], self.cov_ind[good], self.cov_dep[good] = self._fuse(
                    m[ok], P_ind[ok], P_dep[ok], z[ok], R[ok] - R_dep[ok], R_dep[ok])
            else:
                names = [batch.names[c] for c in batch.codes[positions[ok]].tolist()]
                self._parts.add(good, names, z[ok], R[ok] - R_dep[ok], R_dep[ok])
                self.mean[good], self.cov_ind[good], self.cov_dep[good] = (
                    self._parts.combine(good))
            self.observations[good] += 1
            self.consecutive[good] = 0
            self.last_stamp[good] = batch.stamps[positions[ok]]
            codes = batch.codes[positions[ok]]
            for code, count in enumerate(np.bincount(codes, minlength=len(batch.names))):
                if count:
                    self._seen(batch.names[code])[good[codes == code]] = True
                    result.accepted[batch.names[code]] += int(count)
            if self._buffers:
                for row in self._buffers.keys() & set(good.tolist()):
                    del self._buffers[row]
        for i in np.flatnonzero(~ok).tolist():
            row = rows[i]
            observation = batch.observation(positions[i])
            self.rejections[row] += 1
            self.consecutive[row] += 1
            result.rejected[observation.source] += 1
            recent = self._buffers.setdefault(
                row, deque(maxlen=self.max_consecutive_rejections))
            recent.append(observation)
            if self.consecutive[row] >= self.max_consecutive_rejections:
                self._reinitialise(row, result)

    def _fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations; return the new mean and covariance parts."""
        if self.fusion == 'independent':
            m, P = fuse(m, P_ind + P_dep, z, R_ind + R_dep)
            return m, P, np.zeros_like(P)
        if self.fusion == 'covariance_intersection':
            m, P = covariance_intersection(m, P_ind + P_dep, z, R_ind + R_dep)
            return m, np.zeros_like(P), P
        return split_covariance_intersection(m, P_ind, P_dep, z, R_ind, R_dep)

    def _add_tentative(self, row, observation, result):
        buffer = self._buffers.setdefault(
            row, deque(maxlen=max(4 * self.min_observations, self.max_consecutive_rejections)))
        if len(buffer) == buffer.maxlen:
            result.rejected[buffer[0].source] += 1
            self.rejections[row] += 1
        buffer.append(observation)
        if np.isnan(self.first_stamp[row]):
            self.first_stamp[row] = observation.stamp
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

    def _reinitialise(self, row, result):
        # The recent rejections stay counted as rejections: they were, when they came.
        if self._rebuild(row, list(self._buffers.get(row, ()))):
            result.reinitialised.append(int(self.ids[row]))

    def _rebuild(self, row, observations):
        """Set ``row`` from the largest agreeing subset; return it (empty if too small)."""
        cluster = _agreeing(observations, self.threshold, self._fuse)
        if len(cluster) < self.min_observations:
            return []
        first = cluster[0]
        m, P_ind, P_dep = first.z[None], (first.R - first.R_dep)[None], first.R_dep[None]
        for obs in cluster[1:]:
            m, P_ind, P_dep = self._fuse(m, P_ind, P_dep, obs.z[None],
                                         (obs.R - obs.R_dep)[None], obs.R_dep[None])
        if self.fusion == 'independent':
            P_ind, P_dep = P_ind + P_dep, np.zeros_like(P_dep)
        elif self.fusion == 'covariance_intersection':
            P_ind, P_dep = np.zeros_like(P_ind), P_ind + P_dep
        else:
            self._parts.clear(row)
            self._parts.add(np.full(len(cluster), row), [obs.source for obs in cluster],
                            np.array([obs.z for obs in cluster]),
                            np.array([obs.R - obs.R_dep for obs in cluster]),
                            np.array([obs.R_dep for obs in cluster]))
            m, P_ind, P_dep = self._parts.combine(np.array([row]))
        self.mean[row], self.cov_ind[row], self.cov_dep[row] = m[0], P_ind[0], P_dep[0]
        self.confirmed[row] = True
        self.observations[row] = len(cluster)
        self.consecutive[row] = 0
        self.last_stamp[row] = max(obs.stamp for obs in cluster)
        for obs in cluster:
            self._seen(obs.source)[row] = True
        self._buffers.pop(row, None)
        return cluster

    # Output --------------------------------------------------------------------

    def snapshot(self):
        """
        Return the confirmed landmarks, sorted by ID.

        Returns
        -------
        ids : ndarray of int64, shape (K,)
        m : ndarray, shape (K, 2)
        P : ndarray, shape (K, 2, 2)
            Total covariance.
        P_dep : ndarray, shape (K, 2, 2)
            Its dependent part.
        observations : ndarray of int64, shape (K,)
            Observations fused into each.

        """
        rows = np.flatnonzero(self.confirmed[:self._count])
        rows = rows[np.argsort(self.ids[rows], kind='stable')]
        return (self.ids[rows].copy(), self.mean[rows].copy(),
                self.cov_ind[rows] + self.cov_dep[rows], self.cov_dep[rows].copy(),
                self.observations[rows].copy())

    def sources_of(self, landmark_id):
        """Return the sorted sources whose observations a landmark fused."""
        row = self._row[landmark_id]
        return sorted(source for source, seen in self._seen_by.items() if seen[row])

    def to_records(self):
        """Return the confirmed landmarks as plain dicts (for saving)."""
        records = []
        for landmark_id in self.snapshot()[0].tolist():
            row = self._row[landmark_id]
            records.append({
                'id': landmark_id,
                'mean': self.mean[row].tolist(),
                'covariance': (self.cov_ind[row] + self.cov_dep[row]).tolist(),
                'covariance_dependent': self.cov_dep[row].tolist(),
                'observations': int(self.observations[row]),
                'rejections': int(self.rejections[row]),
                'sources': self.sources_of(landmark_id),
                'first_stamp': float(self.first_stamp[row]),
                'last_stamp': float(self.last_stamp[row]),
            })
            if self._parts is not None:
                records[-1]['per_source'] = self._parts.records(row)
        return records

    def load_records(self, records):
        """
        Replace the map with confirmed landmarks from ``to_records`` output.

        Parameters
        ----------
        records : list of dict
            As ``to_records`` returns them.

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
                P = np.array(record['covariance'], dtype=np.float64).reshape(2, 2)
                P_dep = np.array(record['covariance_dependent'], dtype=np.float64).reshape(2, 2)
                mean = np.array(record['mean'], dtype=np.float64).reshape(2)
                if not (np.all(np.isfinite(P)) and np.all(np.isfinite(P_dep))
                        and np.all(np.isfinite(mean))):
                    raise ValueError(f"landmark {record['id']}: non-finite values")
                self.mean[row], self.cov_ind[row], self.cov_dep[row] = mean, P - P_dep, P_dep
                self.confirmed[row] = True
                self.observations[row] = int(record['observations'])
                self.rejections[row] = int(record.get('rejections', 0))
                self.first_stamp[row] = float(record['first_stamp'])
                self.last_stamp[row] = float(record['last_stamp'])
                for source in record['sources']:
                    self._seen(str(source))[row] = True
                if self._parts is not None:
                    self._parts.load(row, record.get('per_source')
                                     or _one_source(mean, P - P_dep, P_dep))
        except (KeyError, TypeError, ValueError) as error:
            self.reset()
            raise ValueError(f'malformed landmark record: {error}') from error


class _SourceParts:
    """
    Per (landmark, source) information sums for split covariance intersection.

    A source's estimate of a landmark is ``m_s = Y^-1 y`` with ``Y = sum R_ind_i^-1``
    and ``y = sum R_ind_i^-1 z_i`` (independent parts as information), covariance
    ``Y^-1 + D`` where ``D = sym(Y^-1 sum R_ind_i^-1 R_dep_i)``: the information-weighted
    mean of the dependent parts, a shared error that averaging does not reduce.
    """

    def __init__(self):
        self.index = {}
        self.sources = []
        self.table = np.full((64, 4), -1, np.int64)
        self.Y = np.zeros((64, 2, 2))
        self.y = np.zeros((64, 2))
        self.Q = np.zeros((64, 2, 2))

    def _pair(self, row, source):
        pair = self.index.get((row, source))
        if pair is not None:
            return pair
        pair = self.index[(row, source)] = len(self.sources)
        self.sources.append(source)
        if pair >= len(self.Y):
            grow = len(self.Y)
            self.Y = np.concatenate([self.Y, np.zeros((grow, 2, 2))])
            self.y = np.concatenate([self.y, np.zeros((grow, 2))])
            self.Q = np.concatenate([self.Q, np.zeros((grow, 2, 2))])
        if row >= len(self.table):
            self.table = np.concatenate(
                [self.table, np.full((max(row + 1, 2 * len(self.table)) - len(self.table),
                                      self.table.shape[1]), -1, np.int64)])
        free = np.flatnonzero(self.table[row] < 0)
        if not len(free):
            self.table = np.concatenate(
                [self.table, np.full((len(self.table), self.table.shape[1]), -1, np.int64)],
                axis=1)
            free = np.flatnonzero(self.table[row] < 0)
        self.table[row, free[0]] = pair
        return pair

    def add(self, rows, sources, z, R_ind, R_dep):
        """Add observations (rows of the map, source names) to their sums."""
        pairs = np.array([self._pair(row, source)
                          for row, source in zip(rows.tolist(), sources)], dtype=np.int64)
        # A positive definite independent part is needed for weights; a tiny floor
        # keeps an all-dependent observation from dividing by zero.
        scale = 1e-12 * np.maximum(R_ind[:, 0, 0] + R_ind[:, 1, 1], 1e-300)
        a, b, c = R_ind[:, 0, 0] + scale, R_ind[:, 0, 1], R_ind[:, 1, 1] + scale
        det = a * c - b * b
        Y = np.empty_like(R_ind)
        Y[:, 0, 0], Y[:, 1, 1] = c / det, a / det
        Y[:, 0, 1] = Y[:, 1, 0] = -b / det
        np.add.at(self.Y, pairs, Y)
        np.add.at(self.y, pairs, (Y @ z[:, :, None])[:, :, 0])
        np.add.at(self.Q, pairs, Y @ R_dep)

    def clear(self, row):
        """Forget the sources of one landmark."""
        if row < len(self.table):
            for pair in self.table[row][self.table[row] >= 0].tolist():
                del self.index[(row, self.sources[pair])]
            self.table[row] = -1

    def estimate(self, pairs):
        """Return the source estimates ``(m, P_ind, P_dep)`` of some pairs."""
        P_ind = information(self.Y[pairs])
        m = (P_ind @ self.y[pairs][:, :, None])[:, :, 0]
        P_dep = P_ind @ self.Q[pairs]
        return m, P_ind, 0.5 * (P_dep + np.swapaxes(P_dep, 1, 2))

    def combine(self, rows):
        """
        Fuse the source estimates of each landmark by split CI, the tightest first.

        Split CI is not associative: folding the sources from the smallest covariance
        (determinant) up makes the result independent of the order they arrived in.
        """
        table = self.table[rows]
        table = table[:, :int((table >= 0).sum(axis=1).max())]
        count, width = table.shape
        m, P_ind, P_dep = self.estimate(np.maximum(table, 0).reshape(-1))
        m, P_ind, P_dep = (a.reshape((count, width) + a.shape[1:]) for a in (m, P_ind, P_dep))
        P = P_ind + P_dep
        size = np.where(table >= 0, P[..., 0, 0] * P[..., 1, 1] - P[..., 0, 1] ** 2, np.inf)
        order = np.argsort(size, axis=1, kind='stable')
        valid = np.take_along_axis(table >= 0, order, 1)
        m = np.take_along_axis(m, order[..., None], 1)
        P_ind = np.take_along_axis(P_ind, order[..., None, None], 1)
        P_dep = np.take_along_axis(P_dep, order[..., None, None], 1)
        fused = m[:, 0], P_ind[:, 0], P_dep[:, 0]
        for j in range(1, width):
            has = valid[:, j]
            first = tuple(f[has] for f in fused)
            second = m[has, j], P_ind[has, j], P_dep[has, j]
            omega = split_covariance_intersection_omega(first[1], first[2], second[1],
                                                        second[2])
            parts = split_covariance_intersection(*first, *second, omega=omega)
            for f, part in zip(fused, parts):
                f[has] = part
        return fused

    def records(self, row):
        """Return the sums of one landmark as plain data."""
        pairs = self.table[row][self.table[row] >= 0].tolist() if row < len(self.table) else []
        return [{'source': self.sources[p], 'information': self.Y[p].tolist(),
                 'information_mean': self.y[p].tolist(), 'dependent_sum': self.Q[p].tolist()}
                for p in pairs]

    def load(self, row, records):
        """Restore the sums of one landmark from ``records``."""
        for record in records:
            pair = self._pair(row, str(record['source']))
            self.Y[pair] = np.array(record['information'], dtype=np.float64).reshape(2, 2)
            self.y[pair] = np.array(record['information_mean'], dtype=np.float64).reshape(2)
            self.Q[pair] = np.array(record['dependent_sum'], dtype=np.float64).reshape(2, 2)


def _one_source(mean, P_ind, P_dep):
    """Return the per-source record of an estimate held as a single source."""
    Y = np.linalg.inv(P_ind)
    return [{'source': 'loaded', 'information': Y.tolist(),
             'information_mean': (Y @ mean).tolist(),
             'dependent_sum': (Y @ P_dep).tolist()}]


def _rounds(rows):
    """Split row positions into rounds in which every landmark appears at most once."""
    order = np.argsort(rows, kind='stable')
    sorted_rows = rows[order]
    starts = np.ones(len(rows), bool)
    starts[1:] = sorted_rows[1:] != sorted_rows[:-1]
    first = np.maximum.accumulate(np.where(starts, np.arange(len(rows)), 0))
    rank = np.empty(len(rows), np.int64)
    rank[order] = np.arange(len(rows)) - first
    if rank.max() == 0:
        return [np.arange(len(rows))]
    by_rank = np.argsort(rank, kind='stable')
    bounds = np.searchsorted(rank[by_rank], np.arange(rank.max() + 2))
    return [by_rank[bounds[k]:bounds[k + 1]] for k in range(rank.max() + 1)]


def _agreeing(observations, threshold, fuse_rows):
    """
    Return the largest subset of observations that agree with one another.

    The seed is the observation that passes the pairwise gate with the most others
    (latest on ties); its partners join in arrival order while each passes the gate
    against the estimate fused so far.
    """
    if not observations:
        return []
    z = np.array([obs.z for obs in observations])
    R = np.array([obs.R for obs in observations])
    d = z[:, None, :] - z[None, :, :]
    S = R[:, None] + R[None, :]
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    d2 = (d[..., 0] * (S[..., 1, 1] * d[..., 0] - S[..., 0, 1] * d[..., 1])
          + d[..., 1] * (S[..., 0, 0] * d[..., 1] - S[..., 1, 0] * d[..., 0])) / det
    agree = d2 <= threshold
    votes = agree.sum(axis=1)
    seed = len(observations) - 1 - int(np.argmax(votes[::-1]))
    members = [i for i in range(len(observations)) if agree[seed, i]]
    cluster = [observations[members[0]]]
    m = cluster[0].z[None]
    P_ind, P_dep = (cluster[0].R - cluster[0].R_dep)[None], cluster[0].R_dep[None]
    for i in members[1:]:
        obs = observations[i]
        S = P_ind[0] + P_dep[0] + obs.R
        diff = obs.z - m[0]
        if diff @ np.linalg.solve(S, diff) > threshold:
            continue
        m, P_ind, P_dep = fuse_rows(m, P_ind, P_dep, obs.z[None], (obs.R - obs.R_dep)[None],
                                    obs.R_dep[None])
        cluster.append(obs)
    return cluster
