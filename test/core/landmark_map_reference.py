"""
Reference copy of core/landmark_map.py before issue 12 (test_landmark_map_plan only).

Frozen at commit 4885365: split CI folded round by round with warm-started weights.
Not part of the package; do not edit, except for one change the package made on
purpose since: rows are gated against a reference estimate refreshed on the schedule
of ``_fold_kernel.gate_due`` instead of against the current estimate (the lines
marked ``# gate``).

A map of landmark estimates fused by ID, with gating and confirmation.

Symbols
-------
ids : landmark IDs, shape (N,), integers.
z : observed landmark positions in the world, shape (N, 2) [m].
R : their covariances, shape (N, 2, 2) [m^2]; ``R_dep`` the dependent part (pose
    uncertainty, sensor bias: correlated across observations), ``R_ind = R - R_dep``
    the independent part (sensor noise). ``update`` takes ``R`` and ``R_dep`` (the
    wire format) and works with ``R_ind`` and ``R_dep`` from then on.
m, P : a landmark estimate and its covariance; inside the map ``P`` is held as its
    independent and dependent parts, ``P = P_ind + P_dep`` only at output.
stamp_ns : observation times, integer nanoseconds.

Fusion methods
--------------
independent
    Product of Gaussians: exact when every error is independent. Everything counts
    as independent (``P_dep = 0``).
covariance_intersection
    Consistent whatever the correlations; the whole covariance counts as dependent
    (``P_ind = 0``).
split_covariance_intersection
    Within a source (one robot), the dependent parts (its pose error, its sensor
    bias) are one shared error: the source's estimate is the information-weighted
    mean of its observations, whose independent parts (noise) average down while
    the dependent part, their weighted mean, does not. The map keeps per (landmark,
    source) sums, updated incrementally. Across sources the correlation is unknown:
    the source estimates are fused by split covariance intersection (independent
    parts as information, dependent parts bounded as CI does, the weight omega
    the exact optimum), folded from the tightest source up so that the result does
    not depend on the order the sources arrived in.

Each method is a small strategy object (``fuse``, ``update``, ``initialise``,
``records``, ``load``) chosen once by ``LandmarkMap(fusion)``.

An observation of a known landmark is gated by its squared Mahalanobis distance
to the estimate (innovation covariance ``P + R``). A new ID becomes a landmark
once ``min_observations`` of its observations agree with each other; a
landmark rejected ``max_consecutive_rejections`` times in a row is rebuilt from
those recent observations when they agree (it moved). Rows of one batch are
applied in order, so a batch gives the same map as its rows one by one (bit for
bit): rows of confirmed landmarks go in rounds in which each landmark appears
once, and every computation is element-wise.
"""

from collections import Counter, deque
import copy
from dataclasses import dataclass, field
from typing import NamedTuple

from landmark_ros.core import _fold_kernel  # gate
from landmark_ros.core._arrays import (inverse_2x2, mahalanobis_sq_2x2, power_of_4_scale,
                                       symmetric_2x2)
from landmark_ros.core.gating import chi2_threshold
from landmark_ros.core.gaussian import (ci_2x2, covariance_intersection, fuse_2x2, information,
                                        sci_omega_2x2, split_ci_2x2_entries,
                                        split_covariance_intersection)
import numpy as np

_TABLE_LIMIT = 1 << 20
"""IDs below this are looked up in a dense table, others by binary search."""

_NO_STAMP = np.iinfo(np.int64).min
"""``first_stamp_ns`` of a landmark that has not had an observation yet."""

_SOURCE_BITS = 24
"""A (landmark row, source) pair is the key ``row << 24 | source code``."""

FUSION_METHODS = ('independent', 'covariance_intersection', 'split_covariance_intersection')


class MapSnapshot(NamedTuple):
    """The confirmed landmarks, sorted by ID (``LandmarkMap.snapshot``)."""

    ids: np.ndarray
    """Landmark IDs, int64, shape (K,)."""
    m: np.ndarray
    """Means, shape (K, 2) [m]."""
    P: np.ndarray
    """Total covariances, shape (K, 2, 2) [m^2]."""
    P_dep: np.ndarray
    """Their dependent parts, shape (K, 2, 2) [m^2]."""
    observations: np.ndarray
    """Observations fused into each, int64, shape (K,)."""


def _no_ids():
    return np.empty(0, np.int64)


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
    changed_ids: np.ndarray = field(default_factory=_no_ids, compare=False)
    """IDs (int64, sorted, unique) whose published estimate changed in this update;
    not part of ``==`` (an array)."""

    @property
    def changed(self):
        """Whether the confirmed map changed."""
        return bool(self.accepted or self.confirmed or self.reinitialised)


@dataclass(frozen=True)
class _Observation:
    z: np.ndarray
    R_ind: np.ndarray
    R_dep: np.ndarray
    source: str
    stamp_ns: int


@dataclass(frozen=True)
class _Batch:
    """One ``update`` call's rows: independent and dependent parts, global source codes."""

    z: np.ndarray
    R_ind: np.ndarray
    R_dep: np.ndarray
    names: list
    codes: np.ndarray
    stamps_ns: np.ndarray

    def observation(self, i):
        return _Observation(self.z[i], self.R_ind[i], self.R_dep[i], self.names[self.codes[i]],
                            int(self.stamps_ns[i]))


def _entries(P):
    """Return ``(xx, xy, yy)`` of symmetric 2x2 matrices (views, no averaging)."""
    return P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]


def _stack(observations):
    """Return ``z, R_ind, R_dep`` of a list of observations as arrays."""
    return (np.array([obs.z for obs in observations]),
            np.array([obs.R_ind for obs in observations]),
            np.array([obs.R_dep for obs in observations]))


# --- Fusion methods --------------------------------------------------------------------------

class _Independent:
    """Product of Gaussians; the estimate is held as independent (``P_dep = 0``)."""

    name = 'independent'

    def reset(self):
        """Forget every landmark (nothing to forget)."""

    def fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations row by row; return ``(m, P_ind, P_dep)``."""
        # The closed form behind gaussian.fuse, on entries (batches of (N, 2) here).
        m, P = fuse_2x2(m, _entries(P_ind + P_dep), z, _entries(R_ind + R_dep))
        return m, P, np.zeros_like(P)

    def update(self, landmark_map, rows, codes, z, R_ind, R_dep):
        """Return the new estimates of ``rows`` (one accepted observation each)."""
        return self.fuse(landmark_map.mean[rows], landmark_map.cov_ind[rows],
                         landmark_map.cov_dep[rows], z, R_ind, R_dep)

    def initialise(self, landmark_map, row, cluster):
        """Return the estimate of a landmark from agreeing observations, in order."""
        z, R_ind, R_dep = _stack(cluster)
        m, P_ind, P_dep = z[:1], R_ind[:1], R_dep[:1]
        for k in range(1, len(cluster)):
            m, P_ind, P_dep = self.fuse(m, P_ind, P_dep, z[k:k + 1], R_ind[k:k + 1],
                                        R_dep[k:k + 1])
        return self.held(m[0], P_ind[0], P_dep[0])

    @staticmethod
    def held(m, P_ind, P_dep):
        """Return an estimate the way this method holds it."""
        return m, P_ind + P_dep, np.zeros_like(P_dep)

    def records(self, landmark_map, row):
        """Return method state of one landmark for ``to_records`` (none)."""
        return {}

    def checkpoint(self, rows):
        """Return what ``restore`` needs to undo an update of ``rows`` (nothing here)."""
        return None

    def restore(self, state, first_new_row):
        """Undo an update from a ``checkpoint`` (nothing here)."""

    def load(self, landmark_map, row, record, m, P_ind, P_dep):
        """Restore method state of one landmark (none)."""

    def retire(self, rows):
        """Forget the method state of landmarks taken out of the map (none)."""


class _CovarianceIntersection(_Independent):
    """Covariance intersection; the estimate is held as dependent (``P_ind = 0``)."""

    name = 'covariance_intersection'

    def fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations row by row; return ``(m, P_ind, P_dep)``."""
        P, R = P_ind + P_dep, R_ind + R_dep
        fused = ci_2x2(m, _entries(P), z, _entries(R))   # the closed form, omega optimal
        m, P = covariance_intersection(m, P, z, R) if fused is None else fused
        return m, np.zeros_like(P), P

    @staticmethod
    def held(m, P_ind, P_dep):
        """Return an estimate the way this method holds it."""
        return m, np.zeros_like(P_ind), P_ind + P_dep


class _SplitCovarianceIntersection(_Independent):
    """Split CI across sources over per-(landmark, source) information sums."""

    name = 'split_covariance_intersection'

    def reset(self):
        """Forget every landmark."""
        self.parts = _SourceParts()

    def fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations row by row (split CI, exact omega)."""
        return split_covariance_intersection(m, P_ind, P_dep, z, R_ind, R_dep)

    def update(self, landmark_map, rows, codes, z, R_ind, R_dep):
        """Add accepted observations (one per landmark) to their sums; refold those rows."""
        self.parts.add(rows, codes, z, R_ind, R_dep, unique=True)
        return self.parts.combine(rows)

    def initialise(self, landmark_map, row, cluster):
        """Replace a landmark's sums by those of agreeing observations; fold them."""
        z, R_ind, R_dep = _stack(cluster)
        codes = np.array([landmark_map.source_code(obs.source) for obs in cluster], np.int64)
        self.parts.clear(row)
        self.parts.add(np.full(len(cluster), row, np.int64), codes, z, R_ind, R_dep)
        m, P_ind, P_dep = self.parts.combine(np.array([row], np.int64))
        return m[0], P_ind[0], P_dep[0]

    @staticmethod
    def held(m, P_ind, P_dep):
        """Return an estimate the way this method holds it."""
        return m, P_ind, P_dep

    def records(self, landmark_map, row):
        """Return the per-source sums of one landmark, sorted by source name."""
        return {'per_source': self.parts.records(row, landmark_map.source_names)}

    def load(self, landmark_map, row, record, m, P_ind, P_dep):
        """Restore the per-source sums of one landmark (one source if absent)."""
        self.parts.load(row, record.get('per_source') or _one_source(m, P_ind, P_dep),
                        landmark_map.source_code)

    def checkpoint(self, rows):
        """Return the pair index and the sums of the pairs of ``rows``."""
        return self.parts.checkpoint(rows)

    def restore(self, state, first_new_row):
        """Put the pair index and the saved sums back."""
        self.parts.restore(state, first_new_row)

    def retire(self, rows):
        """Forget the per-source sums of landmarks taken out of the map."""
        for row in np.asarray(rows).tolist():
            self.parts.clear(row)


_STRATEGIES = {cls.name: cls for cls in (
    _Independent, _CovarianceIntersection, _SplitCovarianceIntersection)}


# --- The map ---------------------------------------------------------------------------------

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

    Raises
    ------
    ValueError
        If ``fusion`` is unknown or a count is below 1.

    """

    def __init__(self, fusion='split_covariance_intersection', gate_probability=0.999,
                 min_observations=2, max_consecutive_rejections=5):
        if fusion not in FUSION_METHODS:
            raise ValueError(f'fusion must be one of {FUSION_METHODS}, got {fusion!r}')
        if min_observations < 1 or max_consecutive_rejections < 1:
            raise ValueError('min_observations and max_consecutive_rejections must be >= 1')
        self.fusion = fusion
        self._method = _STRATEGIES[fusion]()
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
        self.gate_mean, self.gate_cov = np.empty((0, 2)), np.empty((0, 2, 2))  # gate
        self.confirmed = np.empty(0, bool)
        self.observations = np.empty(0, np.int64)
        self.rejections = np.empty(0, np.int64)
        self.consecutive = np.empty(0, np.int64)
        self.first_stamp_ns = np.empty(0, np.int64)
        self.last_stamp_ns = np.empty(0, np.int64)
        self._seen_by = {}
        self._buffers = {}
        self._source_names = []
        self._source_codes = {}
        self._method.reset()

    def __len__(self):
        """Return the number of confirmed landmarks."""
        return int(self.confirmed[:self._count].sum())

    @property
    def source_names(self):
        """Return the source names, indexed by their codes."""
        return self._source_names

    def source_code(self, name):
        """Return the map's integer code of a source name, registering a new one."""
        code = self._source_codes.get(name)
        if code is None:
            code = self._source_codes[name] = len(self._source_names)
            if code >= 1 << _SOURCE_BITS:
                raise ValueError(f'more than {1 << _SOURCE_BITS} sources')
            self._source_names.append(name)
        return code

    def _grow(self, extra):
        need = self._count + extra
        if need <= len(self.ids):
            return
        size = max(need, 2 * len(self.ids), 64)
        for name in ('ids', 'mean', 'cov_ind', 'cov_dep', 'confirmed', 'observations',
                     'rejections', 'consecutive', 'first_stamp_ns', 'last_stamp_ns',
                     'gate_mean', 'gate_cov'):  # gate
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

    def update(self, ids, z, R, R_dep=None, source='', stamp_ns=0):
        """
        Fuse a batch of observations, row by row in order.

        Parameters
        ----------
        ids : array_like of int, shape (N,)
            Landmark IDs.
        z : array_like, shape (N, 2)
            Observed positions in the world [m].
        R : array_like, shape (N, 2, 2)
            Their total covariances, positive definite [m^2].
        R_dep : array_like, shape (N, 2, 2), optional
            Dependent part of ``R`` (zero when absent) [m^2].
        source : str or sequence of str, length N
            Who made each observation (for counters and the saved map).
        stamp_ns : int or array_like of int, shape (N,)
            Time of each observation [ns].

        Returns
        -------
        UpdateResult

        Raises
        ------
        ValueError
            If ``stamp_ns`` is not integer.

        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        checkpoint = self._checkpoint(ids)
        try:
            return self._update(ids, z, R, R_dep, source, stamp_ns)
        except BaseException:
            # All or nothing: whatever failed half way, the map is as it was.
            self._restore(checkpoint)
            raise

    _ROW_ARRAYS = ('ids', 'mean', 'cov_ind', 'cov_dep', 'confirmed', 'observations',
                   'rejections', 'consecutive', 'first_stamp_ns', 'last_stamp_ns',
                   'gate_mean', 'gate_cov')  # gate

    def _checkpoint(self, ids):
        """Save what an update of ``ids`` can change (their rows, the registries)."""
        rows = self._lookup(np.unique(ids))
        rows = rows[rows >= 0]
        return {
            'count': self._count, 'rows': rows,
            'arrays': {name: getattr(self, name)[rows].copy() for name in self._ROW_ARRAYS},
            'seen': {source: seen[rows].copy() for source, seen in self._seen_by.items()},
            'buffers': {row: copy.copy(self._buffers[row]) for row in rows.tolist()
                        if row in self._buffers},
            'sources': list(self._source_names),
            'method': self._method.checkpoint(rows),
        }

    def _restore(self, checkpoint):
        """Put the map back to a ``_checkpoint``."""
        count, rows = checkpoint['count'], checkpoint['rows']
        for name, values in checkpoint['arrays'].items():
            getattr(self, name)[rows] = values
        added = np.arange(count, self._count)
        added_ids = self.ids[added].tolist()
        for name in self._ROW_ARRAYS:      # rows added by the failed update, as new
            getattr(self, name)[added] = _NO_STAMP if name == 'first_stamp_ns' else 0
        for source in list(self._seen_by):
            if source in checkpoint['seen']:
                self._seen_by[source][rows] = checkpoint['seen'][source]
                self._seen_by[source][added] = False
            else:
                del self._seen_by[source]
        for row in rows.tolist():
            self._buffers.pop(row, None)
        for row in [row for row in self._buffers if row >= count]:
            del self._buffers[row]
        self._buffers.update(checkpoint['buffers'])
        for name in self._source_names[len(checkpoint['sources']):]:
            del self._source_codes[name]
        self._source_names[:] = checkpoint['sources']
        self._method.restore(checkpoint['method'], count)
        if self._count != count:
            self._count = count
            for landmark_id in added_ids:
                self._row.pop(landmark_id, None)
            order = np.argsort(self.ids[:count], kind='stable')
            self._sorted_ids, self._sorted_rows = self.ids[:count][order], order
            self._table[self._table >= count] = -1

    def _update(self, ids, z, R, R_dep, source, stamp_ns):
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
        R = np.asarray(R, dtype=np.float64).reshape(-1, 2, 2)
        R_dep = np.zeros_like(R) if R_dep is None else np.asarray(
            R_dep, dtype=np.float64).reshape(-1, 2, 2)
        stamps_ns = np.asarray(stamp_ns)
        if not (np.issubdtype(stamps_ns.dtype, np.integer) or stamps_ns.size == 0):
            raise ValueError(f'stamp_ns must be integer nanoseconds, got {stamps_ns.dtype}')
        count = len(ids)
        stamps_ns = np.broadcast_to(stamps_ns.astype(np.int64), (count,))
        if isinstance(source, str):
            codes = np.full(count, self.source_code(source), np.int64)
        else:
            names, first, inverse = np.unique(np.asarray(source, dtype=str),
                                              return_index=True, return_inverse=True)
            # Register new names in the order they first appear (as row by row would).
            by_name = np.empty(len(names), np.int64)
            for k in np.argsort(first, kind='stable').tolist():
                by_name[k] = self.source_code(str(names[k]))
            codes = by_name[inverse.reshape(-1)]
        result = UpdateResult()
        if not count:
            return result
        rows = self._rows_of(ids)
        # The one conversion to the independent part.
        batch = _Batch(z, R - R_dep, R_dep, self._source_names, codes, stamps_ns)
        changed = []
        known = self.confirmed[rows]
        # Rows of already confirmed landmarks: in rounds of distinct landmarks, which
        # keeps each landmark's own order while fusing the rows of a round together.
        if known.any():
            index = np.flatnonzero(known)
            for positions in _rounds(rows[index]):
                self._update_confirmed(rows[index[positions]], batch, index[positions],
                                       result, changed)
        for i in np.flatnonzero(~known).tolist():
            if self.confirmed[rows[i]]:  # confirmed earlier in this batch
                self._update_confirmed(rows[i:i + 1], batch, np.array([i]), result, changed)
            else:
                self._add_tentative(rows[i], batch.observation(i), result, changed)
        if changed:
            result.changed_ids = np.unique(self.ids[np.concatenate(changed)])
        return result

    def _refresh_gate(self, rows):  # gate
        self.gate_mean[rows] = self.mean[rows]  # gate
        self.gate_cov[rows] = self.cov_ind[rows] + self.cov_dep[rows]  # gate

    def _update_confirmed(self, rows, batch, positions, result, changed):
        """Gate and fuse rows of confirmed landmarks, each landmark at most once."""
        z, R_ind, R_dep = batch.z[positions], batch.R_ind[positions], batch.R_dep[positions]
        S = self.gate_cov[rows] + R_ind + R_dep  # gate
        d = z - self.gate_mean[rows]  # gate
        d2 = mahalanobis_sq_2x2(d[:, 0], d[:, 1], *_entries(S))
        ok = d2 <= self.threshold   # NaN (degenerate input) is rejected
        if ok.any():
            good = rows[ok]
            codes = batch.codes[positions[ok]]
            self.mean[good], self.cov_ind[good], self.cov_dep[good] = self._method.update(
                self, good, codes, z[ok], R_ind[ok], R_dep[ok])
            self.observations[good] += 1
            self._refresh_gate(good[_fold_kernel.gate_due(self.observations[good])])  # gate
            self.consecutive[good] = 0
            self.last_stamp_ns[good] = batch.stamps_ns[positions[ok]]
            changed.append(good)
            for code, count in enumerate(np.bincount(codes).tolist()):
                if count:
                    name = batch.names[code]
                    self._seen(name)[good[codes == code]] = True
                    result.accepted[name] += count
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
                self._reinitialise(row, result, changed)

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
        cluster = _agreeing(observations, self.threshold, self._method.fuse)
        if len(cluster) < self.min_observations:
            return []
        self.mean[row], self.cov_ind[row], self.cov_dep[row] = self._method.initialise(
            self, row, cluster)
        self.confirmed[row] = True
        self.observations[row] = len(cluster)
        self._refresh_gate(row)  # gate
        self.consecutive[row] = 0
        self.last_stamp_ns[row] = max(obs.stamp_ns for obs in cluster)
        for obs in cluster:
            self._seen(obs.source)[row] = True
        self._buffers.pop(row, None)
        return cluster

    def known(self, ids):
        """
        Return whether the map has had rows of each ID (confirmed, tentative or forgotten).

        Parameters
        ----------
        ids : array_like of int, shape (N,)
            Landmark IDs.

        Returns
        -------
        ndarray of bool, shape (N,)

        """
        return self._lookup(np.asarray(ids, dtype=np.int64).reshape(-1)) >= 0

    def forget(self, ids):
        """
        Drop the buffered observations of unconfirmed IDs (confirmed ones are kept).

        The IDs stay known (``known``), with no observation: a later row of one of them
        starts it again from scratch.

        Parameters
        ----------
        ids : array_like of int, shape (N,)
            Landmark IDs; unknown ones are ignored.

        Returns
        -------
        int
            The unconfirmed IDs whose observations were dropped.

        """
        rows = self._lookup(np.unique(np.asarray(ids, dtype=np.int64)))
        rows = rows[rows >= 0]
        rows = rows[~self.confirmed[rows]]
        for row in rows.tolist():
            self._buffers.pop(row, None)
        self.first_stamp_ns[rows] = _NO_STAMP
        return len(rows)

    def retire(self, ids):
        """
        Take confirmed landmarks out of the map (a duplicate merged into another one).

        They leave the snapshot and the records; their IDs stay known (``known``). An
        observation of one of them later starts it again as a new ID would.

        Parameters
        ----------
        ids : array_like of int, shape (N,)
            Landmark IDs; unknown and unconfirmed ones are ignored.

        Returns
        -------
        int
            The landmarks taken out.

        """
        rows = self._lookup(np.unique(np.asarray(ids, dtype=np.int64)))
        rows = rows[rows >= 0]
        rows = rows[self.confirmed[rows]]
        self.confirmed[rows] = False
        self.observations[rows] = 0
        self.consecutive[rows] = 0
        self.first_stamp_ns[rows] = _NO_STAMP
        for row in rows.tolist():
            self._buffers.pop(row, None)
        self._method.retire(rows)
        return len(rows)
    # Estimates from elsewhere -------------------------------------------------------

    def estimate(self, landmark_id):
        """
        Return the estimate of a confirmed landmark, or None.

        Returns
        -------
        m : ndarray, shape (2,) [m]
        P : ndarray, shape (2, 2) [m^2]
            Total covariance.
        P_dep : ndarray, shape (2, 2) [m^2]
            Its dependent part.

        """
        row = self._row.get(int(landmark_id))
        if row is None or not self.confirmed[row]:
            return None
        return (self.mean[row].copy(), self.cov_ind[row] + self.cov_dep[row],
                self.cov_dep[row].copy())

    def set_estimate(self, landmark_id, m, P, P_dep, source, stamp_ns=0, observations=1):
        """
        Insert or replace a confirmed landmark's estimate computed outside the map.

        For partial views (``core.partial``): the estimate is held the way the fusion
        method holds one (``independent``: all independent; covariance intersection:
        all dependent). With split CI the landmark's per-source sums are collapsed
        into one synthetic source ``source`` holding the estimate: later range-bearing
        rows of other sources fold with it by split CI, but what each earlier source
        contributed is no longer told apart. Any waiting observations of the landmark
        are dropped.

        Parameters
        ----------
        landmark_id : int
            The landmark's ID.
        m : array_like, shape (2,) [m]
            Its position.
        P : array_like, shape (2, 2) [m^2]
            Total covariance, positive definite.
        P_dep : array_like, shape (2, 2) [m^2]
            Its dependent part.
        source : str
            Source name the estimate is booked under.
        stamp_ns : int
            Stamp of the newest view in it [ns].
        observations : int
            Views the estimate adds to the landmark's count.

        """
        m = np.asarray(m, dtype=np.float64).reshape(2)
        P = np.asarray(P, dtype=np.float64).reshape(2, 2)
        P_dep = np.asarray(P_dep, dtype=np.float64).reshape(2, 2)
        code = self.source_code(source)
        row = int(self._rows_of(np.array([landmark_id], np.int64))[0])
        mean, P_ind, P_dep = self._method.held(m, P - P_dep, P_dep)
        if isinstance(self._method, _SplitCovarianceIntersection):
            self._method.parts.clear(row)
            self._method.parts.add(np.array([row], np.int64), np.array([code], np.int64),
                                   mean[None], P_ind[None], P_dep[None])
        self.mean[row], self.cov_ind[row], self.cov_dep[row] = mean, P_ind, P_dep
        self._refresh_gate(row)  # gate
        self.confirmed[row] = True
        self.observations[row] += int(observations)
        self.consecutive[row] = 0
        if self.first_stamp_ns[row] == _NO_STAMP:
            self.first_stamp_ns[row] = int(stamp_ns)
        self.last_stamp_ns[row] = max(int(self.last_stamp_ns[row]), int(stamp_ns))
        self._seen(source)[row] = True
        self._buffers.pop(row, None)

    # Output --------------------------------------------------------------------

    def snapshot(self, ids=None):
        """
        Return the confirmed landmarks, sorted by ID.

        Parameters
        ----------
        ids : array_like of int, optional
            Only these landmarks (those of them that are confirmed); all by default.

        Returns
        -------
        MapSnapshot
            ``(ids, m, P, P_dep, observations)``: IDs int64 (K,), means (K, 2) [m],
            total covariances and their dependent parts (K, 2, 2) [m^2], observations
            fused into each int64 (K,). Unpacks like a tuple.

        """
        if ids is None:
            rows = np.flatnonzero(self.confirmed[:self._count])
        else:
            rows = self._lookup(np.unique(np.asarray(ids, dtype=np.int64)))
            rows = rows[rows >= 0]
            rows = rows[self.confirmed[rows]]
        rows = rows[np.argsort(self.ids[rows], kind='stable')]
        return MapSnapshot(self.ids[rows].copy(), self.mean[rows].copy(),
                           self.cov_ind[rows] + self.cov_dep[rows], self.cov_dep[rows].copy(),
                           self.observations[rows].copy())

    def sources_of(self, landmark_id):
        """Return the sorted sources whose observations a landmark fused."""
        row = self._row[landmark_id]
        return sorted(source for source, seen in self._seen_by.items() if seen[row])

    def to_records(self):
        """Return the confirmed landmarks as plain dicts (for saving); stamps in ns."""
        records = []
        for landmark_id in self.snapshot().ids.tolist():
            row = self._row[landmark_id]
            records.append({
                'id': landmark_id,
                'mean': self.mean[row].tolist(),
                'covariance': (self.cov_ind[row] + self.cov_dep[row]).tolist(),
                'covariance_dependent': self.cov_dep[row].tolist(),
                'observations': int(self.observations[row]),
                'rejections': int(self.rejections[row]),
                'sources': self.sources_of(landmark_id),
                'first_stamp_ns': int(self.first_stamp_ns[row]),
                'last_stamp_ns': int(self.last_stamp_ns[row]),
                **self._method.records(self, row),
            })
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
                self._refresh_gate(row)  # gate
                self.confirmed[row] = True
                self.observations[row] = int(record['observations'])
                self.rejections[row] = int(record.get('rejections', 0))
                self.first_stamp_ns[row] = _integer(record['first_stamp_ns'])
                self.last_stamp_ns[row] = _integer(record['last_stamp_ns'])
                for source in record['sources']:
                    self._seen(str(source))[row] = True
                self._method.load(self, row, record, mean, P - P_dep, P_dep)
        except (KeyError, TypeError, ValueError) as error:
            self.reset()
            raise ValueError(f'malformed landmark record: {error}') from error


def _integer(value):
    """Return ``value`` as an int; raise ValueError unless it is an integer (not bool)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f'expected an integer, got {value!r}')
    return int(value)


# --- Per-source sums for split CI ------------------------------------------------------------

class _SourceParts:
    """
    Per (landmark, source) information sums for split covariance intersection.

    A source's estimate of a landmark is ``m_s = Y^-1 y`` with ``Y = sum R_ind_i^-1``
    and ``y = sum R_ind_i^-1 z_i`` (independent parts as information), covariance
    ``Y^-1 + D`` where ``D = sym(Y^-1 Q)``, ``Q = sum R_ind_i^-1 R_dep_i``: the
    information-weighted mean of the dependent parts, a shared error that averaging
    does not reduce. Pairs are found by binary search in a sorted array of keys
    ``row << 24 | source code``, so a landmark's pairs are contiguous, in source-code
    order; their sums live in flat arrays indexed by a slot.
    """

    def __init__(self):
        self.keys = np.empty(0, np.int64)     # sorted
        self.slots = np.empty(0, np.int64)    # slot of each key
        self.count = 0
        self.Y = np.zeros((64, 3))            # (xx, xy, yy) of the information sum
        self.y = np.zeros((64, 2))
        self.Q = np.zeros((64, 4))            # (00, 01, 10, 11) of sum R_ind^-1 R_dep
        self.omega = np.full((64, 4), 0.5)    # last split-CI weight per (row, fold step)

    def _pairs(self, rows, codes):
        """Return the slots of (row, code) pairs, creating the new ones."""
        keys = (rows << _SOURCE_BITS) | codes
        position = np.searchsorted(self.keys, keys)
        found = position < len(self.keys)
        found[found] = self.keys[position[found]] == keys[found]
        if not found.all():
            new = np.unique(keys[~found])
            slots = np.arange(self.count, self.count + len(new))
            self.count += len(new)
            if self.count > len(self.Y):
                size = max(self.count, 2 * len(self.Y))
                for name in ('Y', 'y', 'Q'):
                    old = getattr(self, name)
                    grown = np.zeros((size,) + old.shape[1:])
                    grown[:len(old)] = old
                    setattr(self, name, grown)
            at = np.searchsorted(self.keys, new)
            self.keys = np.insert(self.keys, at, new)
            self.slots = np.insert(self.slots, at, slots)
            position = np.searchsorted(self.keys, keys)
        return self.slots[position]

    def add(self, rows, codes, z, R_ind, R_dep, unique=False):
        """
        Add observations to the sums of their (landmark row, source code) pairs.

        Rows of one call that share a pair are added in order (``np.add.at``); with
        ``unique`` (every pair once, as in a round) by plain indexing.
        """
        slots = self._pairs(rows, codes)
        a, b, c = _entries(R_ind)
        # A positive definite independent part is needed for weights; a tiny floor
        # keeps an all-dependent observation from dividing by zero.
        trace = a + c
        floor = 1e-12 * np.where(trace > 0.0, trace, R_dep[:, 0, 0] + R_dep[:, 1, 1])
        ya, yb, yc = inverse_2x2(a + floor, b, c + floor)
        Y = np.stack([ya, yb, yc], axis=1)
        y = np.stack([ya * z[:, 0] + yb * z[:, 1], yb * z[:, 0] + yc * z[:, 1]], axis=1)
        Q = np.stack([ya * R_dep[:, 0, 0] + yb * R_dep[:, 1, 0],
                      ya * R_dep[:, 0, 1] + yb * R_dep[:, 1, 1],
                      yb * R_dep[:, 0, 0] + yc * R_dep[:, 1, 0],
                      yb * R_dep[:, 0, 1] + yc * R_dep[:, 1, 1]], axis=1)
        if unique:
            self.Y[slots] += Y
            self.y[slots] += y
            self.Q[slots] += Q
        else:
            np.add.at(self.Y, slots, Y)
            np.add.at(self.y, slots, y)
            np.add.at(self.Q, slots, Q)

    def checkpoint(self, rows):
        """Return the index and the sums of every pair of ``rows`` (for ``restore``)."""
        lo = np.searchsorted(self.keys, rows << _SOURCE_BITS)
        hi = np.searchsorted(self.keys, (rows + 1) << _SOURCE_BITS)
        slots = self.slots[np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)])
                           .astype(np.int64)] if len(rows) else np.empty(0, np.int64)
        touched = rows[rows < len(self.omega)]
        return (self.keys.copy(), self.slots.copy(), self.count, slots,
                self.Y[slots].copy(), self.y[slots].copy(), self.Q[slots].copy(),
                touched, self.omega[touched].copy(), self.omega.shape)

    def restore(self, state, first_new_row):
        """Undo every change since ``checkpoint``; rows from ``first_new_row`` are new."""
        keys, slots_of_keys, count, slots, Y, y, Q, touched, omega, shape = state
        for sums in (self.Y, self.y, self.Q):     # new slots are taken as zero sums
            sums[count:self.count] = 0.0
        self.keys, self.slots, self.count = keys, slots_of_keys, count
        self.Y[slots], self.y[slots], self.Q[slots] = Y, y, Q
        # The warm starts of the omega search: rows and steps added since are new again.
        self.omega[touched, :shape[1]] = omega
        self.omega[min(shape[0], first_new_row):] = 0.5
        self.omega[:, shape[1]:] = 0.5

    def clear(self, row):
        """Forget the sources of one landmark."""
        lo, hi = np.searchsorted(self.keys, [row << _SOURCE_BITS, (row + 1) << _SOURCE_BITS])
        self.keys = np.delete(self.keys, np.s_[lo:hi])
        self.slots = np.delete(self.slots, np.s_[lo:hi])

    def estimate(self, slots):
        """Return the source estimates ``m, P_ind, P_dep`` of some pairs, as entries."""
        Y, y, Q = self.Y[slots], self.y[slots], self.Q[slots]
        P_ind = inverse_2x2(Y[..., 0], Y[..., 1], Y[..., 2])
        a, b, c = P_ind
        m = (a * y[..., 0] + b * y[..., 1], b * y[..., 0] + c * y[..., 1])
        P_dep = (a * Q[..., 0] + b * Q[..., 2],
                 0.5 * (a * Q[..., 1] + b * Q[..., 3] + b * Q[..., 0] + c * Q[..., 2]),
                 b * Q[..., 1] + c * Q[..., 3])
        return m, P_ind, P_dep

    def combine(self, rows):
        """
        Fuse the source estimates of each landmark by split CI, the tightest first.

        Split CI is not associative: folding the sources from the smallest covariance
        (determinant) up makes the result independent of the order they arrived in.
        Vectorised over the landmarks: step ``j`` folds the ``j``-th tightest source
        of every landmark that has one.

        Returns
        -------
        m : ndarray, shape (K, 2)
        P_ind, P_dep : ndarray, shape (K, 2, 2)

        """
        lo = np.searchsorted(self.keys, rows << _SOURCE_BITS)
        hi = np.searchsorted(self.keys, (rows + 1) << _SOURCE_BITS)
        counts = hi - lo
        # Landmarks with the most sources first: those still folding form a prefix.
        by_count = np.argsort(-counts, kind='stable')
        lo, counts = lo[by_count], counts[by_count]
        width = int(counts[0])
        columns = np.arange(width)
        valid = columns < counts[:, None]
        slots = self.slots[np.minimum(lo[:, None] + columns, len(self.keys) - 1)]
        m, P_ind, P_dep = self.estimate(slots)
        size = np.where(valid, _log2_det(*(i + d for i, d in zip(P_ind, P_dep))), np.inf)
        order = np.argsort(size, axis=1, kind='stable')

        def column(parts, j, k):
            return tuple(np.take_along_axis(x[:k], order[:k, j:j + 1], 1)[:, 0] for x in parts)

        total = len(rows)
        fused_m, fused_i, fused_d = column(m, 0, total), column(P_ind, 0, total), column(
            P_dep, 0, total)
        ordered_rows = rows[by_count]
        need_rows, need_steps = int(rows.max()) + 1, width - 1
        if need_rows > len(self.omega) or need_steps > self.omega.shape[1]:
            rows_now, steps_now = self.omega.shape
            grown = np.full((rows_now if need_rows <= rows_now else max(need_rows, 2 * rows_now),
                             steps_now if need_steps <= steps_now else max(need_steps,
                                                                           2 * steps_now)),
                            0.5)
            grown[:len(self.omega), :self.omega.shape[1]] = self.omega
            self.omega = grown
        steps = (counts[:, None] > columns[1:]).sum(axis=0)
        for j in range(1, width):
            k = int(steps[j - 1])
            first_m = tuple(x[:k] for x in fused_m)
            first_i = tuple(x[:k] for x in fused_i)
            first_d = tuple(x[:k] for x in fused_d)
            second_m, second_i, second_d = column(m, j, k), column(P_ind, j, k), column(
                P_dep, j, k)
            # The last weight of this landmark and step starts the search: the same
            # history (row by row or in rounds) gives the same start, bit for bit.
            hint = (ordered_rows[:k], j - 1)
            omega = sci_omega_2x2(first_i, first_d, second_i, second_d, self.omega[hint])
            self.omega[hint] = omega
            new_m, new_i, new_d = split_ci_2x2_entries(first_m, first_i, first_d, second_m,
                                                       second_i, second_d, omega)
            for fused, new in ((fused_m, new_m), (fused_i, new_i), (fused_d, new_d)):
                for x, value in zip(fused, new):
                    x[:k] = value
        back = np.empty_like(by_count)
        back[by_count] = np.arange(total)
        mean = np.stack(fused_m, axis=1)[back]
        return (mean, symmetric_2x2(*(x[back] for x in fused_i)),
                symmetric_2x2(*(x[back] for x in fused_d)))

    def records(self, row, names):
        """Return the sums of one landmark as plain data, sorted by source name."""
        lo, hi = np.searchsorted(self.keys, [row << _SOURCE_BITS, (row + 1) << _SOURCE_BITS])
        out = []
        for key, slot in zip(self.keys[lo:hi].tolist(), self.slots[lo:hi].tolist()):
            Y, Q = self.Y[slot].tolist(), self.Q[slot].tolist()
            out.append({'source': names[key & ((1 << _SOURCE_BITS) - 1)],
                        'information': [[Y[0], Y[1]], [Y[1], Y[2]]],
                        'information_mean': self.y[slot].tolist(),
                        'dependent_sum': [[Q[0], Q[1]], [Q[2], Q[3]]]})
        return sorted(out, key=lambda record: record['source'])

    def load(self, row, records, source_code):
        """Restore the sums of one landmark from ``records`` (``source_code``: name to code)."""
        codes = np.array([source_code(str(r['source'])) for r in records], np.int64)
        slots = self._pairs(np.full(len(records), row, np.int64), codes)
        for slot, record in zip(slots.tolist(), records):
            Y = np.array(record['information'], dtype=np.float64).reshape(2, 2)
            Q = np.array(record['dependent_sum'], dtype=np.float64).reshape(2, 2)
            self.Y[slot] = Y[0, 0], 0.5 * (Y[0, 1] + Y[1, 0]), Y[1, 1]
            self.y[slot] = np.array(record['information_mean'], dtype=np.float64).reshape(2)
            self.Q[slot] = Q.reshape(4)


def _log2_det(a, b, c):
    """
    Return a key increasing with ``a c - b^2`` (about its base-2 logarithm), never inf.

    From the scaled determinant's exact exponent and mantissa: it orders covariances
    by size however large or small they are; -inf for a singular one.
    """
    s = power_of_4_scale(a, c)
    mantissa, exponent = np.frexp((a / s) * (c / s) - (b / s) * (b / s))
    key = exponent + 2 * (np.frexp(s)[1] - 1) + 2.0 * (mantissa - 0.5)
    return np.where(mantissa > 0.0, key, -np.inf)


def _one_source(mean, P_ind, P_dep):
    """Return the per-source record of an estimate held as a single source."""
    Y = information(P_ind)
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
    against the estimate fused so far. The seed always belongs to its own subset
    (it is never gated out), so the subset is never empty, even when distances are
    NaN (degenerate covariances).
    """
    if not observations:
        return []
    z, R_ind, R_dep = _stack(observations)
    R = R_ind + R_dep
    d = z[:, None, :] - z[None, :, :]
    S = R[:, None] + R[None, :]
    d2 = mahalanobis_sq_2x2(d[..., 0], d[..., 1], *_entries(S))
    agree = d2 <= threshold
    np.fill_diagonal(agree, True)
    votes = agree.sum(axis=1)
    seed = len(observations) - 1 - int(np.argmax(votes[::-1]))
    members = np.flatnonzero(agree[seed]).tolist()
    first = members[0]
    cluster = [observations[first]]
    m, P_ind, P_dep = z[first:first + 1], R_ind[first:first + 1], R_dep[first:first + 1]
    for i in members[1:]:
        diff = z[i] - m[0]
        S = P_ind[0] + P_dep[0] + R[i]
        if i != seed and not mahalanobis_sq_2x2(diff[0], diff[1], *_entries(S)) <= threshold:
            continue
        m, P_ind, P_dep = fuse_rows(m, P_ind, P_dep, z[i:i + 1], R_ind[i:i + 1],
                                    R_dep[i:i + 1])
        cluster.append(observations[i])
    return cluster
