"""
Per (landmark, source) information sums for split covariance intersection, and their fold.

A source's estimate of a landmark is ``m_s = Y^-1 y`` with ``Y = sum W_i``,
``W_i = R_ind_i^-1`` and ``y = sum W_i z_i`` (independent parts as information),
covariance ``Y^-1 + D``. ``D`` bounds the error the dependent parts leave in ``m_s``,
``sum_i B_i d_i`` with ``B_i = Y^-1 W_i`` and ``d_i`` of covariance ``R_dep_i``,
correlated in any way (a shared error that averaging need not reduce): for any scalar
weights ``w_i > 0`` summing to one, ``Cov(sum_i B_i d_i) <= sum_i B_i R_dep_i B_i^T / w_i``
(the covariance intersection inequality), and with ``w_i = c_i / C``,
``c_i = sqrt(trace(W_i R_dep_i W_i))``, ``C = sum c_i``, that is

    D = C Y^-1 S Y^-1,   S = sum_i W_i R_dep_i W_i / c_i,

a congruence of running sums, positive semi-definite by construction. With equal rows
``D`` is their dependent part; with rows of one shape it is ``(mean sqrt(R_dep))^2``,
at most their mean. (The matrix-weighted mean ``sym(Y^-1 sum W_i R_dep_i)`` is no
bound: with rows whose independent parts point in different directions it can be
indefinite, and projected onto the covariances it loses a direction.) A landmark's
estimate is the split-CI fold
of its sources' estimates from the tightest source up (``fold``), a pure function of
its sums: folding once per batch or once per row gives the same bits.

Sources: split covariance intersection, Julier and Uhlmann, "General decentralized
data fusion with covariance intersection", Handbook of Multisensor Data Fusion, 2001.
"""

from typing import Any, Callable, Dict, List, NamedTuple, Sequence, Tuple

from landmark_ros.core.arrays import (inverse_2x2, power_of_4_scale, psd_projection_2x2,
                                      symmetric_2x2, unique_ints)
from landmark_ros.core.gaussian import information, sci_omega_2x2, split_ci_2x2_entries
from landmark_ros.fusion import compiled
import numpy as np
from numpy.typing import NDArray

SOURCE_BITS = 24
"""A (landmark row, source code) pair is the key ``row << 24 | code``."""


class Estimates(NamedTuple):
    """Landmark estimates held as independent and dependent parts."""

    m: NDArray[np.float64]
    """Means, shape (K, 2) [m]."""
    P_ind: NDArray[np.float64]
    """Independent parts, shape (K, 2, 2) [m^2]."""
    P_dep: NDArray[np.float64]
    """Dependent parts, shape (K, 2, 2) [m^2]."""


class SumsCheckpoint(NamedTuple):
    """What ``SourceSums.restore`` needs to undo the changes since ``checkpoint``."""

    keys: NDArray[np.int64]
    slots: NDArray[np.int64]
    slot_count: int
    journal: List[Tuple[NDArray[np.int64], NDArray[np.float64]]]


def entries(P: NDArray[np.float64]) -> Tuple[Any, Any, Any]:
    """Return ``(xx, xy, yy)`` of symmetric 2x2 matrices (views, no averaging)."""
    return P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]


class SourceSums:
    """
    The sums of every (landmark row, source code) pair.

    ``keys`` are sorted (a landmark's pairs lie together, in source-code order), each
    with its ``slots`` row in ``table`` (per pair: ``(xx, xy, yy)`` of ``Y``, ``y``,
    ``(00, 01, 10, 11)`` of ``Q``). ``keys`` and ``slots`` are replaced when pairs come
    or go, never changed in place; ``table`` only grows, and ``add`` journals the sums
    it changes, so a checkpoint is cheap.
    """

    def __init__(self, independent: bool = False) -> None:
        self.independent = bool(independent)
        """Whether the sources' dependent parts are independent of each other (``fold``)."""
        self.keys = np.empty(0, np.int64)
        self.slots = np.empty(0, np.int64)
        self.table = np.zeros((64, compiled.COLUMNS))   # sums, then the kept fold
        self.count = 0
        self.journal: List[Tuple[NDArray[np.int64], NDArray[np.float64]]] = []
        self.journal_count = 0

    def _bounds(self, rows):
        rows = np.asarray(rows, np.int64)
        return (np.searchsorted(self.keys, rows << SOURCE_BITS),
                np.searchsorted(self.keys, (rows + 1) << SOURCE_BITS))

    def _slots(self, rows, codes):
        """Return the slots of (row, code) pairs, adding the new pairs (zero sums)."""
        keys = (np.asarray(rows, np.int64) << SOURCE_BITS) | np.asarray(codes, np.int64)
        at = np.searchsorted(self.keys, keys)
        found = at < len(self.keys)
        found[found] = self.keys[at[found]] == keys[found]
        if found.all():
            return self.slots[at]
        new, first = unique_ints(keys[~found]), self.count
        self.count += len(new)      # the table's rows from count on hold zeros
        if self.count > len(self.table):    # 4x: fewer copies; untouched zeros cost no RAM
            grown = np.zeros((4 * self.count, compiled.COLUMNS))
            grown[:first] = self.table[:first]
            self.table = grown
        slots = np.empty(len(keys), np.int64)
        slots[found] = self.slots[at[found]]
        slots[~found] = first + np.searchsorted(new, keys[~found])
        where = np.searchsorted(self.keys, new)
        self.keys = np.insert(self.keys, where, new)
        self.slots = np.insert(self.slots, where, np.arange(first, self.count))
        return slots

    def add(self, rows: NDArray[np.int64], codes: NDArray[np.int64], z: NDArray[np.float64],
            R_ind: NDArray[np.float64], R_dep: NDArray[np.float64]) -> None:
        """Add observations (in order) to the sums of their (row, code) pairs."""
        slots = self._slots(rows, codes)
        old = slots[slots < self.journal_count]
        self.journal.append((old, self.table.take(old, axis=0)[:, :9]))
        added = terms(z, R_ind, R_dep)
        if not compiled.accumulate(self.table, slots, added):
            for j in range(9):  # np.add.at column by column: 20 times faster than on rows
                np.add.at(self.table[:, j], slots, added[:, j])
        self.table[slots, compiled.DIRTY] = 1.0

    def fold(self, rows: NDArray[np.int64]) -> Estimates:
        """Return the split-CI fold of the sources of each of ``rows`` (each has one)."""
        return self.fold_held(rows)[1]

    def fold_held(self, rows: NDArray[np.int64]) -> Tuple[NDArray[np.int64], Any]:
        """Return those of ``rows`` that have sources and their fold (None if none have)."""
        lo, hi = self._bounds(rows)
        held = hi > lo
        rows, lo, hi = rows[held], lo[held], hi[held]
        return rows, (fold(self.table, self.slots, lo, hi, self.independent) if len(rows)
                      else None)

    def clear(self, rows: NDArray[np.int64]) -> None:
        """Forget the sources of landmarks (their slots stay unused until ``checkpoint``)."""
        gone = spans(*self._bounds(unique_ints(np.asarray(rows, np.int64))))
        if len(gone):
            self.keys = np.delete(self.keys, gone)
            self.slots = np.delete(self.slots, gone)

    def merge_into(self, keep: int, drop: int) -> None:
        """Add the sums of row ``drop`` to those of row ``keep``, source by source."""
        lo, hi = self._bounds([drop])
        codes = self.keys[lo[0]:hi[0]] & ((1 << SOURCE_BITS) - 1)
        sums = self.table[self.slots[lo[0]:hi[0]], :9]
        slots = self._slots(np.full(len(codes), keep, np.int64), codes)
        self.table[slots, :9] += sums
        self.table[slots, compiled.DIRTY] = 1.0

    def checkpoint(self) -> SumsCheckpoint:
        """Start a journal of the changes to the sums; return what ``restore`` needs."""
        if self.count > 2 * len(self.slots) + 4096:     # give back the unused slots
            live = self.table[self.slots]
            self.table = np.zeros((max(64, 2 * len(live)), compiled.COLUMNS))
            self.table[:len(live)] = live
            self.slots = np.arange(len(self.slots))
            self.count = len(self.slots)
        self.journal, self.journal_count = [], self.count
        return SumsCheckpoint(self.keys, self.slots, self.count, self.journal)

    def restore(self, state: SumsCheckpoint) -> None:
        """Undo every change since ``checkpoint``."""
        for slots, sums in reversed(state.journal):
            self.table[slots, :9] = sums
            self.table[slots, compiled.DIRTY] = 1.0
        self.table[state.slot_count:self.count] = 0.0
        self.keys, self.slots, self.count = state.keys, state.slots, state.slot_count

    def records(self, row: int, names: Sequence[str]) -> List[Dict[str, Any]]:
        """Return the sums of one landmark as plain data, sorted by source name."""
        lo, hi = self._bounds([row])
        out = []
        sums = self.table[self.slots[lo[0]:hi[0]], :9].tolist()
        for key, s in zip(self.keys[lo[0]:hi[0]].tolist(), sums):
            out.append({'source': names[key & ((1 << SOURCE_BITS) - 1)],
                        'information': [[s[0], s[1]], [s[1], s[2]]],
                        'information_mean': s[3:5],
                        'dependent_sum': [[s[5], s[6]], [s[6], s[7]]],
                        'dependent_weight': s[8]})
        return sorted(out, key=lambda record: record['source'])

    def load(self, row: int, records: Sequence[Dict[str, Any]],
             source_code: Callable[[str], int]) -> None:
        """Set the sums of one landmark from ``records`` (``source_code``: name to code)."""
        codes = np.array([source_code(str(r['source'])) for r in records], np.int64)
        slots = self._slots(np.full(len(records), row, np.int64), codes)
        for slot, record in zip(slots.tolist(), records):
            Y = np.array(record['information'], dtype=np.float64).reshape(2, 2)
            S = np.array(record['dependent_sum'], dtype=np.float64).reshape(2, 2)
            y = np.array(record['information_mean'], dtype=np.float64).reshape(2)
            Q = _dependent_sums(Y, S, record.get('dependent_weight'))
            self.table[slot, :9] = [Y[0, 0], 0.5 * (Y[0, 1] + Y[1, 0]), Y[1, 1], *y, *Q]
            self.table[slot, compiled.DIRTY] = 1.0


def _dependent_sums(Y, S, weight):
    """
    Return the four dependent sums ``(xx, xy, yy)`` of ``S`` and ``C`` of a saved source.

    A record without ``dependent_weight`` is of the earlier form, ``S = sum W_i R_dep_i``:
    it becomes one row holding its dependent part ``psd(sym(Y^-1 S))``.
    """
    if weight is not None:
        return [S[0, 0], 0.5 * (S[0, 1] + S[1, 0]), S[1, 1], float(weight)]
    D = np.linalg.solve(Y, S)
    D = psd_projection_2x2(D[0, 0], 0.5 * (D[0, 1] + D[1, 0]), D[1, 1])
    one = terms(np.zeros((1, 2)), np.linalg.inv(Y)[None], symmetric_2x2(*D)[None])[0]
    return one[5:9].tolist()


def spans(lo: NDArray[np.int64], hi: NDArray[np.int64]) -> NDArray[np.int64]:
    """Return the indices ``lo[k]:hi[k]`` for every ``k``, concatenated."""
    counts = hi - lo
    starts = np.repeat(lo - np.cumsum(counts) + counts, counts)
    return starts + np.arange(int(counts.sum()))


def terms(z: NDArray[np.float64], R_ind: NDArray[np.float64],
          R_dep: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return what observations add to their pair's sums.

    Returns
    -------
    ndarray, shape (N, 9)
        ``(xx, xy, yy)`` of ``W = R_ind^-1``, ``W z``, ``(xx, xy, yy)`` of
        ``W R_dep W / c`` and ``c = sqrt(trace(W R_dep W))`` (module docstring; zero
        for a row without dependent part).

    """
    a, b, c = entries(R_ind)
    # A positive definite independent part is needed for weights; a tiny floor
    # keeps an all-dependent observation from dividing by zero.
    trace = a + c
    floor = 1e-12 * np.where(trace > 0.0, trace, R_dep[:, 0, 0] + R_dep[:, 1, 1])
    ya, yb, yc = inverse_2x2(a + floor, b, c + floor)
    out = np.empty((len(z), 9))
    out[:, 0], out[:, 1], out[:, 2] = ya, yb, yc
    out[:, 3], out[:, 4] = ya * z[:, 0] + yb * z[:, 1], yb * z[:, 0] + yc * z[:, 1]
    t0, t1, t2 = congruence_2x2((ya, yb, yc), (R_dep[:, 0, 0],
                                               0.5 * (R_dep[:, 0, 1] + R_dep[:, 1, 0]),
                                               R_dep[:, 1, 1]))
    c = np.sqrt(np.maximum(t0 + t2, 0.0))
    inv_c = np.divide(1.0, c, out=np.zeros_like(c), where=c > 0.0)
    out[:, 5], out[:, 6], out[:, 7], out[:, 8] = t0 * inv_c, t1 * inv_c, t2 * inv_c, c
    return out


def congruence_2x2(K: Tuple[Any, Any, Any],
                   A: Tuple[Any, Any, Any]) -> Tuple[Any, Any, Any]:
    """
    Return the entries of ``K A K`` for symmetric 2x2 ``K`` and ``A`` (entry tuples).

    ``K``, ``A``: ``(xx, xy, yy)`` of arrays of one shape; the same operations, in the
    same order, as ``compiled._congruence``.
    """
    k0, k1, k2 = K
    a, b, c = A
    r00, r01 = k0 * a + k1 * b, k0 * b + k1 * c
    r10, r11 = k1 * a + k2 * b, k1 * b + k2 * c
    return r00 * k0 + r01 * k1, r00 * k1 + r01 * k2, r10 * k1 + r11 * k2


def one_source(mean: NDArray[np.float64], P_ind: NDArray[np.float64],
               P_dep: NDArray[np.float64]) -> List[Dict[str, Any]]:
    """Return the per-source record of an estimate held as a single source."""
    Y = information(P_ind)
    sums = terms(np.asarray(mean, np.float64).reshape(1, 2),
                 np.asarray(P_ind, np.float64).reshape(1, 2, 2),
                 np.asarray(P_dep, np.float64).reshape(1, 2, 2))[0]
    return [{'source': 'loaded', 'information': Y.tolist(),
             'information_mean': (Y @ mean).tolist(),
             'dependent_sum': [[sums[5], sums[6]], [sums[6], sums[7]]],
             'dependent_weight': sums[8]}]


def fold(table: NDArray[np.float64], slots: NDArray[np.int64], lo: NDArray[np.int64],
         hi: NDArray[np.int64], independent: bool = False) -> Estimates:
    """
    Fuse the source estimates of each landmark by split CI, the tightest first.

    With ``independent`` the dependent parts of different sources are independent of
    each other (each source's own pose error and sensor bias: robots posed by motion
    capture): no weight, the product of the sources' Gaussians, each source's own
    parts still bounded by CI (``_estimate``); the fused dependent part is the sources'
    dependent parts through the gains. Else their correlation is unknown (robots posed
    against a shared map): split CI.

    Split CI is not associative: folding the sources from the smallest covariance
    (determinant) up makes the result independent of the order they arrived in. The
    weight search starts from 0.5 every time, so a landmark's result depends on its
    own sums only. ``compiled.fold`` gives the same bits, about ten times faster, once
    it is loaded; ``fold_numpy`` serves until then.

    Parameters
    ----------
    table : ndarray, shape (S, 9)
        Sums of sources (``SourceSums``).
    slots : ndarray of int, shape (P,)
        Rows of ``table``.
    lo, hi : ndarray of int, shape (K,)
        Landmark ``k``'s sources are ``table[slots[lo[k]:hi[k]]]``, at least one.
    independent : bool
        Whether the sources' dependent parts are independent of each other.

    Returns
    -------
    Estimates

    """
    packed = compiled.fold(table, slots, lo, hi, independent)
    if packed is None:
        packed = fold_numpy(table, slots, lo, hi, independent)
    return Estimates(packed[:, :2].copy(), symmetric_2x2(packed[:, 2], packed[:, 3], packed[:, 4]),
                     symmetric_2x2(packed[:, 5], packed[:, 6], packed[:, 7]))


def _estimate(Y, y, Q):
    """Return the source estimates ``m, P_ind, P_dep`` of sums, as entries."""
    P_ind = inverse_2x2(Y[..., 0], Y[..., 1], Y[..., 2])
    a, b, c = P_ind
    m = (a * y[..., 0] + b * y[..., 1], b * y[..., 0] + c * y[..., 1])
    # D = C Y^-1 S Y^-1 (module docstring): positive semi-definite up to rounding,
    # which the projection removes (split CI's weight objective needs covariances).
    d0, d1, d2 = congruence_2x2(P_ind, (Q[..., 0], Q[..., 1], Q[..., 2]))
    C = Q[..., 3]
    return m, P_ind, psd_projection_2x2(C * d0, C * d1, C * d2)


def fold_numpy(table: NDArray[np.float64], slots: NDArray[np.int64], lo: NDArray[np.int64],
               hi: NDArray[np.int64], independent: bool = False) -> NDArray[np.float64]:
    """
    Return ``fold`` packed, shape (K, 8): mean, ``P_ind`` and ``P_dep`` entries (numpy).

    Vectorised over the landmarks: step ``j`` folds the ``j``-th tightest source of
    every landmark that has one; every operation is element-wise.
    """
    columns = np.arange(int((hi - lo).max()))
    valid = columns < (hi - lo)[:, None]
    sums = table[slots[np.minimum(lo[:, None] + columns, len(slots) - 1)], :9]
    m, P_ind, P_dep = _estimate(sums[..., 0:3], sums[..., 3:5], sums[..., 5:9])
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
        first, second = _split_entries(fused[:k]), _split_entries(parts[:k, j])
        omega = None if independent else sci_omega_2x2(first[1], first[2], second[1],
                                                       second[2])
        new_m, new_i, new_d = split_ci_2x2_entries(first[0], first[1], first[2], second[0],
                                                   second[1], second[2], omega)
        fused[:k] = np.stack([*new_m, *new_i, *new_d], axis=1)
    fused[by_count] = fused.copy()
    return fused


def _split_entries(parts):
    """Return ``(m, P_ind, P_dep)`` entry tuples of packed ``(K, 8)`` estimates."""
    return ((parts[:, 0], parts[:, 1]), (parts[:, 2], parts[:, 3], parts[:, 4]),
            (parts[:, 5], parts[:, 6], parts[:, 7]))


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
