"""
Row bookkeeping of change detection: recent rows for the rebuild, rows grouped (ROS-free).

``RowLog`` keeps the last ``capacity`` rows the tests took, each with a sequence number,
so that an alarm can rebuild its landmark from the rows since its test last left zero
(``fuser.change_detection``) without the tests copying rows into per-landmark lists.
``Groups`` groups a batch's rows by landmark and runs Page's recursion on each group in
closed form.
"""

from collections import deque
from typing import Deque, List, Sequence, Tuple

from landmark_ros.fusion.records import Observation
import numpy as np
from numpy.typing import NDArray

LOG_ROWS = 1 << 16
"""Rows the log keeps (the most recent); a rebuild takes its rows from them."""


class RowLog:
    """
    The most recent rows the tests took, in arrival order, by reference to their batches.

    A batch's arrays are kept as given (no copy: the caller must not change them), until
    every one of its rows is older than the last ``capacity`` rows.

    Parameters
    ----------
    capacity : int
        Rows kept (> 0).

    """

    def __init__(self, capacity: int = LOG_ROWS) -> None:
        self.capacity = int(capacity)
        self.next = 0
        """Sequence number of the next row."""
        self._batches: Deque[Tuple[int, NDArray[np.int64], NDArray[np.int64],
                                   NDArray[np.intp], Sequence[NDArray]]] = deque()

    def append(self, landmarks: NDArray[np.int64], sources: NDArray[np.int64],
               positions: NDArray[np.intp], rows: Sequence[NDArray]) -> NDArray[np.int64]:
        """
        Add rows (arrival order); return their sequence numbers.

        Parameters
        ----------
        landmarks, sources : ndarray of int, shape (N,)
            Landmark IDs and source codes of the rows.
        positions : ndarray of int, shape (N,)
            Where the rows are in ``rows``.
        rows : tuple
            ``z`` (M, 2), ``R_ind``, ``R_dep`` (M, 2, 2), source names (M,), stamps (M,).

        """
        sequence = self.next + np.arange(len(landmarks), dtype=np.int64)
        self._batches.append((self.next, landmarks, sources, positions, rows))
        self.next += len(landmarks)
        while self._batches and (self._batches[0][0] + len(self._batches[0][1])
                                 <= self.next - self.capacity):
            self._batches.popleft()
        return sequence

    def rows_of(self, landmark_id: int, first: int, names: List[str],
                most: int) -> List[Observation]:
        """
        Return a landmark's rows from sequence number ``first`` on, at most the last ``most``.

        ``names`` turns source codes into source names. Rows older than the last
        ``capacity`` are missing.
        """
        first = max(first, self.next - self.capacity)
        found: List[Observation] = []
        for start, landmarks, sources, positions, rows in reversed(self._batches):
            if start + len(landmarks) <= first or len(found) >= most:
                break
            at = np.flatnonzero(landmarks == landmark_id)
            at = at[at >= first - start][::-1][:most - len(found)]
            z, R_ind, R_dep, _, stamps = rows
            found += [Observation(z[k], R_ind[k], R_dep[k], names[sources[i]], int(stamps[k]))
                      for i, k in zip(at.tolist(), positions[at].tolist())]
        return found[::-1]


def subset(groups: Tuple[NDArray[np.int64], NDArray[np.intp]],
           mask: NDArray[np.bool_]) -> Tuple[NDArray[np.int64], NDArray[np.intp]]:
    """
    Return ``core.arrays.unique_inverse`` of the rows ``mask`` keeps, from that of all rows.

    Parameters
    ----------
    groups : tuple
        ``(unique (K,), inverse (N,))`` of the rows' IDs.
    mask : ndarray of bool, shape (N,)
        The rows kept.

    """
    unique, inverse = groups
    inverse = inverse[mask]
    present = np.bincount(inverse, minlength=len(unique)) > 0
    return unique[present], (np.cumsum(present) - 1)[inverse]


class Groups:
    """A batch's rows grouped by a key, arrival order kept within each group."""

    def __init__(self, keys: NDArray[np.int64]) -> None:
        self.order = np.argsort(keys, kind='stable')
        first = np.ones(len(keys), bool)
        first[1:] = keys[self.order][1:] != keys[self.order][:-1]
        self.starts = np.flatnonzero(first)
        self.ends = np.append(self.starts[1:], len(keys)) - 1
        self.group = np.cumsum(first) - 1
        self.unique = keys[self.order][self.starts]
        self.count = len(self.starts)

    def lindley(self, g: NDArray[np.float64], start: NDArray[np.float64]) -> NDArray[np.float64]:
        """Return Page's statistic after each row (grouped order), from ``start`` per group."""
        total = np.cumsum(g)
        C = start[self.group] + total - (total[self.starts] - g[self.starts])[self.group]
        # C_k - min(0, min_{j<=k} C_j) per group; the offset keeps a group's running
        # minimum from reaching the next, and costs the last bits (below: 0).
        span = 2.0 * (np.abs(C).max() + 1.0)
        offset = self.group * span
        low = np.minimum(np.minimum.accumulate(np.minimum(C, 0.0) - offset) + offset, 0.0)
        statistic = C - low
        statistic[statistic <= 8.0 * np.finfo(float).eps * (offset + span)] = 0.0
        return statistic
