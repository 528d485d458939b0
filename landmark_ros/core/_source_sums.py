"""
Per (landmark, source) sums for split covariance intersection, and their fold.

``LandmarkMap``'s split-CI strategy keeps, per (landmark, source) pair, the
information sums of the source's observations (``_SourceParts``); a landmark's
estimate is the split-CI fold of its sources' estimates, from the tightest source
up (``_fold``: the compiled kernel of ``_fold_kernel`` when numba is there, else
``_fold_numpy``). ``_SourceParts.run`` gates and folds a batch's rows as the map would
take them one by one. Private to ``core``: ``landmark_map`` is the interface.

Sources: split covariance intersection, Julier and Uhlmann, "General decentralized
data fusion with covariance intersection", Handbook of Multisensor Data Fusion, 2001.
"""

from landmark_ros.core import _fold_kernel, _pair_index
from landmark_ros.core._arrays import (inverse_2x2, power_of_4_scale, psd_projection_2x2,
                                       symmetric_2x2, unique_ints)
from landmark_ros.core.gaussian import information, sci_omega_2x2, split_ci_2x2_entries
import numpy as np

_SOURCE_BITS = 24
"""A (landmark row, source) pair is the key ``row << 24 | source code``."""

_COMPACT_SLACK = 4096
"""Slots no pair holds that ``finish`` tolerates beyond half as many as the pairs."""


def _entries(P):
    """Return ``(xx, xy, yy)`` of symmetric 2x2 matrices (views, no averaging)."""
    return P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]


# --- Per-source sums for split CI ------------------------------------------------------------

class _SourceParts:
    """
    Per (landmark, source) information sums for split covariance intersection.

    A source's estimate of a landmark is ``m_s = Y^-1 y`` with ``Y = sum R_ind_i^-1``
    and ``y = sum R_ind_i^-1 z_i`` (independent parts as information), covariance
    ``Y^-1 + D`` where ``D`` is ``sym(Y^-1 Q)`` projected onto the positive
    semi-definite matrices (``psd_projection_2x2``), ``Q = sum R_ind_i^-1 R_dep_i``: the
    information-weighted mean of the dependent parts, a shared error that averaging
    does not reduce. Pairs are found by binary search in a sorted array of keys
    ``row << 24 | source code``, so a landmark's pairs are contiguous, in source-code
    order; their sums live in flat arrays indexed by a slot. ``keys`` and ``slots`` are
    replaced, never changed in place (a checkpoint holds the old arrays).

    A landmark's estimate is a pure function of its sums (``_fold``, no state carried
    from one fold to the next), so folding once per batch or once per row gives the
    same estimate, bit for bit. The compiled batch (``run``) also keeps each
    landmark's fold per slot (``size``, ``rank``, ``prefix``; ``_fold_kernel.run``)
    while ``kept[row]`` says it matches the sums: every other change of a landmark's
    sums clears that flag.
    """

    def __init__(self):
        self.keys = np.empty(0, np.int64)     # sorted
        self.slots = np.empty(0, np.int64)    # slot of each key
        self.count = 0
        self.table = np.zeros((64, _fold_kernel.COLUMNS))    # per slot: sums, kept fold
        self.kept = np.zeros(64, bool)        # per landmark row
        self.pending = np.full(64, -1, np.int64)   # per landmark row: see settle
        self.journal = None                   # [(slots, their sums)] while a checkpoint holds
        self.journal_count = 0                # slots from here on are new since it

    # The sums of each slot: ``(xx, xy, yy)`` of the information sum, the information
    # mean, ``(00, 01, 10, 11)`` of sum R_ind^-1 R_dep; views into ``table``.
    sums = property(lambda self: self.table[:, 0:9])
    Y = property(lambda self: self.table[:, 0:3])
    y = property(lambda self: self.table[:, 3:5])
    Q = property(lambda self: self.table[:, 5:9])

    def _new_slots(self, count):
        """Return ``count`` new slots (zero sums, not valid), growing the arrays."""
        slots = np.arange(self.count, self.count + count)
        self.count += count
        if self.count > len(self.table):
            # In place (realloc: a large block is remapped, not copied; numpy zeroes the
            # new rows, which touches them: hence a quarter more, not twice). No view of
            # the table outlives a call, so none can dangle.
            self.table.resize((max(self.count, len(self.table) * 5 // 4), self.table.shape[1]),
                              refcheck=False)
        return slots

    def _insert(self, new, valid):
        """Insert the sorted new keys ``new`` with new slots; return the slots."""
        slots = self._new_slots(len(new))
        self.table[slots, _fold_kernel.VALID] = 1.0 if valid else 0.0
        if _fold_kernel.AVAILABLE:
            self.keys, self.slots = _pair_index.merge(self.keys, self.slots, new, slots)
        else:
            at = np.searchsorted(self.keys, new)
            self.keys = np.insert(self.keys, at, new)
            self.slots = np.insert(self.slots, at, slots)
        return slots

    def _grow_kept(self, rows):
        """Make ``kept`` cover landmark rows below ``rows``."""
        if rows > len(self.kept):
            size = max(rows, 2 * len(self.kept))
            grown = np.zeros(size, bool)
            grown[:len(self.kept)] = self.kept
            self.kept = grown
            pending = np.full(size, -1, np.int64)
            pending[:len(self.pending)] = self.pending
            self.pending = pending

    def _changed(self, rows):
        """Note that the sums of ``rows`` change outside ``run`` (their kept folds go)."""
        rows = np.asarray(rows, np.int64)
        if len(rows):
            self._grow_kept(int(rows.max()) + 1)
            self.kept[rows] = False

    def _touch(self, slots):
        """Journal the sums of ``slots`` before they change (while a checkpoint holds)."""
        if self.journal is not None:
            slots = slots[slots < self.journal_count]
            self.journal.append((slots, self.sums[slots].copy()))

    def _pairs(self, rows, codes):
        """Return the slots of (row, code) pairs, creating the new ones."""
        keys = (rows << _SOURCE_BITS) | codes
        position = np.searchsorted(self.keys, keys)
        found = position < len(self.keys)
        found[found] = self.keys[position[found]] == keys[found]
        if not found.all():
            self._insert(unique_ints(keys[~found]), True)
            position = np.searchsorted(self.keys, keys)
        return self.slots[position]

    def _ranges(self, rows):
        """Return the positions in ``keys`` of the pairs of ``rows``, concatenated."""
        return _spans(*self._bounds(rows))

    def add(self, rows, codes, z, R_ind, R_dep, unique=False):
        """
        Add observations to the sums of their (landmark row, source code) pairs.

        Rows of one call that share a pair are added in order (``np.add.at``); with
        ``unique`` (every pair once, as in a round) by plain indexing.
        """
        slots = self._pairs(rows, codes)
        self._touch(slots)
        self._changed(rows)
        Y, y, Q = _terms(z, R_ind, R_dep)
        if unique:
            self.Y[slots] += Y
            self.y[slots] += y
            self.Q[slots] += Q
        else:
            np.add.at(self.Y, slots, Y)
            np.add.at(self.y, slots, y)
            np.add.at(self.Q, slots, Q)

    def checkpoint(self, rows):
        """
        Start journaling changes to the sums; return what ``restore`` needs.

        ``rows``: the landmarks the update may change (the journal covers any).
        """
        self.journal, self.journal_count = [], self.count
        return self.keys, self.slots, self.count, self.journal, np.asarray(rows, np.int64)

    def finish(self):
        """Stop journaling (the update the checkpoint was for is over); compact if due."""
        self.journal = None
        if self.count - len(self.keys) > len(self.keys) // 2 + _COMPACT_SLACK:
            self._compact()

    def _compact(self):
        """
        Give back the slots no pair holds (those of forgotten, rebuilt or merged landmarks).

        The live slots move to the front in key order (a landmark's pairs then lie
        together); ``slots`` and the pending slots follow. Only while no checkpoint
        holds (the journal and a restore name slots).
        """
        live = self.slots
        self.table[:len(live)] = self.table[live]
        self.table[len(live):self.count] = 0.0
        renumber = np.full(self.count, -2, np.int64)    # a slot no pair holds: fold all
        renumber[live] = np.arange(len(live))
        single = self.pending >= 0
        self.pending[single] = renumber[self.pending[single]]
        self.slots = np.arange(len(live), dtype=np.int64)
        self.count = len(live)

    def restore(self, state):
        """
        Undo every change since ``checkpoint``; every kept fold is dropped.

        The landmarks of the checkpoint are left pending (their estimates in the map
        are put back, possibly from before a fold that ``settle`` has still to do).
        """
        keys, slots_of_keys, count, journal, rows = state
        for slots, sums in reversed(journal):
            self.sums[slots] = sums
        self.table[count:self.count] = 0.0     # slots made since: unused again
        self.keys, self.slots, self.count = keys, slots_of_keys, count
        self.kept[:] = False
        self._grow_kept(int(rows.max()) + 1 if len(rows) else 0)
        self.pending[rows] = -2
        self.journal = None

    def merge_into(self, keep: int, drop: int) -> None:
        """
        Add the sums of landmark row ``drop`` to those of row ``keep``, source by source.

        The sums are linear in the observations: ``keep`` then holds what it would
        hold had the observations of ``drop`` been added to it.
        """
        lo, hi = np.searchsorted(self.keys, [drop << _SOURCE_BITS, (drop + 1) << _SOURCE_BITS])
        if lo == hi:
            return
        codes = self.keys[lo:hi] & ((1 << _SOURCE_BITS) - 1)
        sources = self.slots[lo:hi].copy()
        targets = self._pairs(np.full(len(codes), keep, np.int64), codes)
        self._touch(targets)
        self._changed([keep, drop])
        self.sums[targets] += self.sums[sources]

    def clear(self, row):
        """Forget the sources of one landmark."""
        self._changed([row])
        self.pending[row] = -1
        lo, hi = np.searchsorted(self.keys, [row << _SOURCE_BITS, (row + 1) << _SOURCE_BITS])
        self.keys = np.delete(self.keys, np.s_[lo:hi])
        self.slots = np.delete(self.slots, np.s_[lo:hi])

    def combine(self, rows):
        """
        Fuse the source estimates of each landmark of ``rows`` by split CI (``_fold``).

        Returns
        -------
        m : ndarray, shape (K, 2)
        P_ind, P_dep : ndarray, shape (K, 2, 2)

        """
        lo = np.searchsorted(self.keys, rows << _SOURCE_BITS)
        hi = np.searchsorted(self.keys, (rows + 1) << _SOURCE_BITS)
        columns = np.arange(int((hi - lo).max()))
        valid = columns < (hi - lo)[:, None]
        slots = self.slots[np.minimum(lo[:, None] + columns, len(self.keys) - 1)]
        return _fold(self.Y[slots], self.y[slots], self.Q[slots], valid)

    def run(self, landmark_map, rows, batch, positions, lazy=False):
        """
        Gate the rows of confirmed landmarks one by one and fold them (``_fold_kernel.run``).

        The sums and the kept folds change in place; ``commit`` then keeps the outcome
        or ``rollback`` undoes it (the sums as they were, the folds of these landmarks
        dropped). Pairs new in the batch get slots that hold no observation until a
        row of theirs is accepted. Rows are gated against ``landmark_map.gate``. With
        ``lazy`` the landmarks' folds after their last rows are left pending
        (``settle``).

        Returns
        -------
        dict
            ``accepted`` (N,) the gate's decisions, ``landmarks`` the distinct rows and
            ``landmark`` each row's index in them, ``order`` the rows sorted by landmark
            (stable), ``state`` (K, 8) their estimates (those left pending: as they
            were) and ``gate`` (K, 5) their gate references after the batch, and what
            ``commit`` and ``rollback`` need.

        """
        codes = batch.codes[positions]
        keys = (rows << _SOURCE_BITS) | codes
        # The distinct landmarks, each row's index in them and the rows grouped by
        # landmark in arrival order (``_apply_run`` reuses it).
        order, landmarks, landmark = _pair_index.group(rows)
        self._grow_kept(int(landmarks[-1]) + 1)
        before = (self.keys, self.slots, self.count)
        lo, hi = _pair_index.bounds(self.keys, landmarks, _SOURCE_BITS)
        position = _pair_index.locate(self.keys, lo, hi, landmark, keys)
        found = position >= 0
        new, new_slots = keys[:0], keys[:0]
        if not found.all():
            new = unique_ints(keys[~found])
            new_slots = self._insert(new, False)
            lo, hi = _pair_index.bounds(self.keys, landmarks, _SOURCE_BITS)
            position = _pair_index.locate(self.keys, lo, hi, landmark, keys)
        state = np.concatenate([landmark_map.mean[landmarks],
                                np.stack(_entries(landmark_map.cov_ind[landmarks]), axis=1),
                                np.stack(_entries(landmark_map.cov_dep[landmarks]), axis=1)],
                               axis=1)
        kept = self.kept[landmarks]
        gate = landmark_map.gate[landmarks]
        pending = self.pending[landmarks]
        accepted, (touched, saved, owner) = _fold_kernel.run(
            landmark, order, position, positions, batch.z, batch.R_ind, batch.R_dep, lo, hi,
            self.slots, self.table, kept, state, gate, landmark_map.observations[landmarks],
            pending, lazy, landmark_map.threshold)
        if self.journal is not None:
            old = touched < self.journal_count
            self.journal.append((touched[old], saved[old]))
        self.kept[landmarks] = kept
        return {'accepted': accepted, 'landmarks': landmarks, 'landmark': landmark,
                'order': order, 'state': state, 'gate': gate, 'pending': pending,
                'before': before, 'new': new,
                'new_slots': new_slots, 'touched': touched, 'owner': owner,
                'saved': saved}

    def _bounds(self, rows):
        """Return where the pairs of each of the sorted ``rows`` start and end in ``keys``."""
        return (np.searchsorted(self.keys, rows << _SOURCE_BITS),
                np.searchsorted(self.keys, (rows + 1) << _SOURCE_BITS))

    def commit(self, run):
        """
        Keep a ``run``: note the folds it left pending; drop the pairs no row observed.

        Their slots are given back when the run's new slots are still the newest (the
        used ones past the new end move into them): rows gated out on new pairs,
        batch after batch, would otherwise grow the table without end.
        """
        pending, new, new_slots = run['pending'], run['new'], run['new_slots']
        unused = self.table[new_slots, _fold_kernel.VALID] == 0.0
        if unused.any():
            at = np.searchsorted(self.keys, new[unused])
            self.keys = np.delete(self.keys, at)      # new arrays: the slots change below
            self.slots = np.delete(self.slots, at)
            first = int(new_slots[0])
            if first + len(new_slots) == self.count:
                # The used slots past the new end fill the unused ones below it.
                end = first + int(np.count_nonzero(~unused))
                below = new_slots < end
                holes = np.flatnonzero(unused & below)
                movers = np.flatnonzero(~unused & ~below)
                self.table[new_slots[holes]] = self.table[new_slots[movers]]
                self.table[end:self.count] = 0.0
                self.slots[np.searchsorted(self.keys, new[movers])] = new_slots[holes]
                renumber = new_slots.copy()
                renumber[unused] = -2
                renumber[movers] = new_slots[holes]
                pending = pending.copy()
                newer = pending >= first            # a single changed slot among the new
                pending[newer] = renumber[pending[newer] - first]
                self.count = end
        self.pending[run['landmarks']] = pending

    def rollback(self, run, landmarks=None):
        """
        Undo a ``run``: its sums and pairs as they were, the folds it kept dropped.

        ``landmarks`` (bool, one per landmark of the run): undo only those; their new
        pairs are emptied, and ``commit`` (of the rest, ``without``) drops them.
        """
        if landmarks is not None and not landmarks.all():
            undo = landmarks[run['owner']]
            self.sums[run['touched'][undo]] = run['saved'][undo]
            rows = run['landmarks'][landmarks]
            emptied = np.isin(run['new'] >> _SOURCE_BITS, rows)
            self.table[run['new_slots'][emptied]] = 0.0
            self.kept[rows] = False
            return
        keys, slots, count = run['before']
        self.sums[run['touched']] = run['saved']
        self.table[count:self.count] = 0.0
        self.keys, self.slots, self.count = keys, slots, count
        self.kept[run['landmarks']] = False

    @staticmethod
    def without(run, landmarks):
        """
        Return a ``run`` without the rows of ``landmarks`` (bool per landmark), and the rows kept.

        For ``LandmarkMap._apply_run`` and ``commit`` after ``rollback(run, landmarks)``.
        """
        keep = ~landmarks
        kept = np.flatnonzero(keep[run['landmark']])
        renumber = np.cumsum(keep) - 1
        at = np.full(len(run['landmark']), -1)
        at[kept] = np.arange(len(kept))
        order = at[run['order']]
        return dict(run, accepted=run['accepted'][kept],
                    landmark=renumber[run['landmark'][kept]], order=order[order >= 0],
                    landmarks=run['landmarks'][keep], state=run['state'][keep],
                    gate=run['gate'][keep], pending=run['pending'][keep]), kept

    def settle(self, rows):
        """
        Fold the landmarks of ``rows`` whose fold a lazy ``run`` left pending.

        Returns
        -------
        rows : ndarray of int, shape (K,)
            Those landmarks (the others' estimates in the map are current).
        state : ndarray, shape (K, 8)
            Their packed estimates (``_fold_kernel.run``).

        """
        rows = np.asarray(rows, np.int64)
        rows = rows[rows < len(self.pending)]
        rows = rows[self.pending[rows] != -1]
        state = np.empty((len(rows), 8))
        if len(rows):
            lo, hi = self._bounds(rows)
            kept, pending = self.kept[rows], self.pending[rows]
            _fold_kernel.settle(lo, hi, pending, self.slots, self.table, kept, state)
            self.kept[rows], self.pending[rows] = kept, pending
            rows = rows[hi > lo]
            state = state[hi > lo]
        return rows, state

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
        self._touch(slots)
        self._changed([row])
        for slot, record in zip(slots.tolist(), records):
            Y = np.array(record['information'], dtype=np.float64).reshape(2, 2)
            Q = np.array(record['dependent_sum'], dtype=np.float64).reshape(2, 2)
            self.Y[slot] = Y[0, 0], 0.5 * (Y[0, 1] + Y[1, 0]), Y[1, 1]
            self.y[slot] = np.array(record['information_mean'], dtype=np.float64).reshape(2)
            self.Q[slot] = Q.reshape(4)


def _spans(lo, hi):
    """Return the indices ``lo[k]:hi[k]`` for every ``k``, concatenated."""
    counts = hi - lo
    starts = np.repeat(lo - np.cumsum(counts) + counts, counts)
    return starts + np.arange(int(counts.sum()))


def _terms(z, R_ind, R_dep):
    """
    Return what observations add to their pair's sums: ``Y``, ``y`` and ``Q`` terms.

    Returns
    -------
    Y : ndarray, shape (N, 3)
        ``(xx, xy, yy)`` of ``R_ind^-1``.
    y : ndarray, shape (N, 2)
        ``R_ind^-1 z``.
    Q : ndarray, shape (N, 4)
        ``(00, 01, 10, 11)`` of ``R_ind^-1 R_dep``.

    """
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
    return Y, y, Q


def _estimate(Y, y, Q):
    """Return the source estimates ``m, P_ind, P_dep`` of sums, as entries (``_SourceParts``)."""
    P_ind = inverse_2x2(Y[..., 0], Y[..., 1], Y[..., 2])
    a, b, c = P_ind
    m = (a * y[..., 0] + b * y[..., 1], b * y[..., 0] + c * y[..., 1])
    P_dep = (a * Q[..., 0] + b * Q[..., 2],
             0.5 * (a * Q[..., 1] + b * Q[..., 3] + b * Q[..., 0] + c * Q[..., 2]),
             b * Q[..., 1] + c * Q[..., 3])
    # sym(Y^-1 Q) is indefinite when a source's rows have differently shaped
    # dependent fractions; split CI needs a covariance there (its weight objective is
    # concave only for positive semi-definite parts), so it is projected onto them.
    return m, P_ind, psd_projection_2x2(*P_dep)


def _fold(Y, y, Q, valid):
    """
    Fuse the source estimates of each landmark by split CI, the tightest first.

    Split CI is not associative: folding the sources from the smallest covariance
    (determinant) up makes the result independent of the order they arrived in.
    Vectorised over the landmarks: step ``j`` folds the ``j``-th tightest source of
    every landmark that has one. Every operation is element-wise and the weight search
    starts from the same point every time, so a landmark's result depends on its own
    sums only (not on the other rows, nor on earlier folds).

    Parameters
    ----------
    Y, y, Q : ndarray, shape (K, W, 3), (K, W, 2), (K, W, 4)
        Sums of up to ``W`` sources of ``K`` landmarks (``_SourceParts``).
    valid : ndarray of bool, shape (K, W)
        Which of them hold a source (at least one per landmark).

    Returns
    -------
    m : ndarray, shape (K, 2)
    P_ind, P_dep : ndarray, shape (K, 2, 2)

    Notes
    -----
    The same fold compiled (``core._fold_kernel``, bit for bit the same results) runs
    instead when numba is installed: a step costs about a tenth.

    """
    compiled = _fold_kernel.load()
    if compiled is not None:
        return compiled(Y, y, Q, valid)
    return _fold_numpy(Y, y, Q, valid)


def _fold_numpy(Y, y, Q, valid):
    """Return ``_fold`` computed with numpy operations vectorised over the landmarks."""
    m, P_ind, P_dep = _estimate(Y, y, Q)
    size = np.where(valid, _log2_det(*(i + d for i, d in zip(P_ind, P_dep))), np.inf)
    counts = valid.sum(axis=1)
    # Landmarks with the most sources first: those still folding form a prefix.
    by_count = np.argsort(-counts, kind='stable')
    counts = counts[by_count]
    order = np.argsort(size[by_count], axis=1, kind='stable')
    parts = np.take_along_axis(np.stack([*m, *P_ind, *P_dep], axis=-1)[by_count],
                               order[:, :, None], axis=1)         # (K, W, 8), tightest first
    fused = parts[:, 0].copy()
    steps = (counts[:, None] > np.arange(1, int(counts[0]))).sum(axis=0)
    for j, k in enumerate(steps.tolist(), start=1):
        first, second = fused[:k], parts[:k, j]
        first_m, first_i, first_d = _split_entries(first)
        second_m, second_i, second_d = _split_entries(second)
        # From 0.5 every time, as ``split_covariance_intersection_omega``.
        omega = sci_omega_2x2(first_i, first_d, second_i, second_d)
        new_m, new_i, new_d = split_ci_2x2_entries(first_m, first_i, first_d, second_m,
                                                   second_i, second_d, omega)
        fused[:k] = np.stack([*new_m, *new_i, *new_d], axis=1)
    fused[by_count] = fused.copy()
    return (fused[:, :2].copy(), symmetric_2x2(fused[:, 2], fused[:, 3], fused[:, 4]),
            symmetric_2x2(fused[:, 5], fused[:, 6], fused[:, 7]))


def _split_entries(parts):
    """Return ``(m, P_ind, P_dep)`` entry tuples of packed ``(K, 8)`` estimates."""
    return ((parts[:, 0], parts[:, 1]), (parts[:, 2], parts[:, 3], parts[:, 4]),
            (parts[:, 5], parts[:, 6], parts[:, 7]))


def _rank(groups):
    """Return how many earlier entries share each entry's group (its rank in it)."""
    order = np.argsort(groups, kind='stable')
    sorted_groups = groups[order]
    starts = np.ones(len(groups), bool)
    starts[1:] = sorted_groups[1:] != sorted_groups[:-1]
    first = np.maximum.accumulate(np.where(starts, np.arange(len(groups)), 0))
    rank = np.empty(len(groups), np.int64)
    rank[order] = np.arange(len(groups)) - first
    return rank


def _levels(groups):
    """Split entry positions into levels by rank: each group at most once per level."""
    if not len(groups):
        return []
    rank = _rank(groups)
    if rank.max() == 0:
        return [np.arange(len(groups))]
    by_rank = np.argsort(rank, kind='stable')
    bounds = np.searchsorted(rank[by_rank], np.arange(rank.max() + 2))
    return [by_rank[bounds[k]:bounds[k + 1]] for k in range(rank.max() + 1)]


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
