"""
The index of split CI's (landmark, source) pairs, compiled with numba when it is installed.

``_source_sums`` keeps the pairs as sorted int64 keys (landmark row, then source
code) with a slot each. A batch groups its rows by landmark (``group``), finds where
each landmark's pairs lie (``bounds``) and each row's pair among them (``locate``),
and merges the new pairs into the keys (``merge``): linear or logarithmic loops,
compiled as ``_fold_kernel``'s are (``_fold_kernel.compiled``: no fast-math), plain
Python without numba.
"""

from typing import Any, Callable, Dict, Tuple

from landmark_ros.core import _fold_kernel
import numpy as np
from numpy.typing import NDArray


def _group_kernel(rows, top, order, landmarks, landmark):
    # Counting sort of rows (values below top): stable order, distinct rows, index.
    index = np.full(top, -1, np.int64)
    count = np.zeros(top, np.int64)
    for r in rows:
        count[r] += 1
    distinct = 0
    start = 0
    for r in range(top):
        if count[r]:
            index[r] = distinct
            landmarks[distinct] = r
            count[r], start = start, start + count[r]
            distinct += 1
    for i in range(len(rows)):
        r = rows[i]
        landmark[i] = index[r]
        order[count[r]] = i
        count[r] += 1
    return distinct


def _bounds_kernel(keys, landmarks, shift, lo, hi):
    # keys[lo[k]:hi[k]] = those of landmark landmarks[k] (increasing): a galloping
    # search forward from the previous landmark's end, then a scan of its few pairs.
    n = len(keys)
    a = 0
    for k in range(len(landmarks)):
        first, end = landmarks[k] << shift, (landmarks[k] + 1) << shift
        b, step = a, 1
        while b < n and keys[b] < first:
            a = b + 1
            b += step
            step <<= 1
        b = min(b, n)
        while a < b:
            middle = (a + b) >> 1
            if keys[middle] < first:
                a = middle + 1
            else:
                b = middle
        lo[k] = a
        while a < n and keys[a] < end:
            a += 1
        hi[k] = a


def _locate_kernel(keys, lo, hi, landmark, wanted, position):
    # position[i] = where keys[lo:hi] of row i's landmark holds wanted[i], else -1.
    for i in range(len(wanted)):
        k = landmark[i]
        a, b, key = lo[k], hi[k], wanted[i]
        while a < b:                # binary search of the landmark's pairs
            middle = (a + b) >> 1
            if keys[middle] < key:
                a = middle + 1
            else:
                b = middle
        position[i] = a if a < hi[k] and keys[a] == key else -1


def _merge_kernel(keys, slots, new, new_slots, out_keys, out_slots):
    # Merge sorted keys and sorted new keys (none in keys), slots alongside.
    i = j = 0
    for k in range(len(out_keys)):
        if j == len(new) or (i < len(keys) and keys[i] < new[j]):
            out_keys[k], out_slots[k] = keys[i], slots[i]
            i += 1
        else:
            out_keys[k], out_slots[k] = new[j], new_slots[j]
            j += 1


def group(rows: NDArray[np.intp]) -> Tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """
    Group rows by value: what a stable argsort and ``np.unique`` give, in one pass.

    Parameters
    ----------
    rows : ndarray of int, shape (N,)
        Non-negative values (landmark rows).

    Returns
    -------
    order : ndarray of int, shape (N,)
        ``np.argsort(rows, kind='stable')``.
    distinct : ndarray of int, shape (K,)
        The distinct values, increasing.
    index : ndarray of int, shape (N,)
        Each row's index in ``distinct``.

    """
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    order = np.empty(len(rows), np.int64)
    distinct = np.empty(len(rows), np.int64)
    index = np.empty(len(rows), np.int64)
    top = int(rows.max()) + 1 if len(rows) else 0
    count = _compiled('_group_kernel')(rows, top, order, distinct, index)
    return order, distinct[:count], index


def bounds(keys: NDArray[np.int64], landmarks: NDArray[np.int64],
           shift: int) -> Tuple[NDArray[np.intp], NDArray[np.intp]]:
    """
    Return where the keys of each landmark start and end in sorted ``keys``.

    A landmark's keys are ``landmark << shift`` up to ``(landmark + 1) << shift``;
    ``landmarks`` increasing. What ``np.searchsorted`` of both ends gives, in one
    forward pass (a batch's landmarks are close together in the keys).
    """
    landmarks = np.ascontiguousarray(landmarks, dtype=np.int64)
    lo = np.empty(len(landmarks), np.int64)
    hi = np.empty(len(landmarks), np.int64)
    _compiled('_bounds_kernel')(keys, landmarks, int(shift), lo, hi)
    return lo, hi


def locate(keys: NDArray[np.int64], lo: NDArray[np.intp], hi: NDArray[np.intp],
           landmark: NDArray[np.intp], wanted: NDArray[np.int64]) -> NDArray[np.intp]:
    """
    Return where sorted ``keys`` hold ``wanted[i]`` within ``lo[k]:hi[k]``, ``k = landmark[i]``.

    A binary search of each landmark's few pairs instead of all keys; -1 where the
    key is not there.
    """
    position = np.empty(len(wanted), np.int64)
    _compiled('_locate_kernel')(keys, lo, hi, landmark, wanted, position)
    return position


def merge(keys: NDArray[np.int64], slots: NDArray[np.int64], new: NDArray[np.int64],
          new_slots: NDArray[np.int64]) -> Tuple[NDArray[np.int64], NDArray[np.int64]]:
    """
    Return sorted ``keys`` with the sorted ``new`` keys (none already there) merged in.

    What ``np.insert`` at ``np.searchsorted(keys, new)`` gives, in one linear pass;
    ``slots`` and ``new_slots`` are carried alongside.
    """
    out_keys = np.empty(len(keys) + len(new), np.int64)
    out_slots = np.empty(len(keys) + len(new), np.int64)
    _compiled('_merge_kernel')(keys, slots, new, new_slots, out_keys, out_slots)
    return out_keys, out_slots


_kernels: Dict[str, Callable[..., Any]] = {}


def _compiled(name: str) -> Callable[..., Any]:
    """Return the kernel ``name`` compiled on first use (the Python function without numba)."""
    kernel = _kernels.get(name)
    if kernel is None:
        function = globals()[name]
        kernel = _kernels[name] = _fold_kernel.compiled(function) or function
    return kernel
