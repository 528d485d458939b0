"""
The package's loops compiled with numba: optional, stateless, loaded in the background.

``fold(table, slots, lo, hi)`` returns what ``source_sums.fold_numpy`` returns, one
landmark at a time in a compiled loop (a (landmark, source) step costs about a tenth
of numpy's): the same IEEE operations in the same order (no fast-math, no fused
multiply-add), so the same bits; ``accumulate`` adds rows to the sums as
``np.add.at`` does (same bits). ``agree`` is the split-CI loop of
``records.agreeing`` (the rebuild of a landmark; same bits). Change detection's two
row-by-row loops (``fuser.change_detection``): ``cusum``, the capped CUSUM (the same
bits as ``MoveDetector._loop``), and ``reference``, the white reference filters
(covariance form; the numpy path's information form agrees to rounding, so an alarm
could only differ for a statistic within rounding of the threshold).

The first call starts a daemon thread that imports numba and compiles the functions
below (or reads numba's disk cache); until it is done, and for good when numba is
missing, broken or off (``LANDMARK_ROS_NUMBA=0``), each public function returns None
and callers use numpy. ``ready()`` tells, ``load()`` waits. The only module of the
package that imports numba.

The scalar closed forms below are those of ``core.gaussian`` (``sci_omega_2x2``,
``split_ci_2x2_entries``), ``core.arrays`` (``power_of_4_scale``, ``inverse_2x2``,
``psd_projection_2x2``, ``mahalanobis_sq_2x2``) and ``source_sums`` (a source's
estimate, its size), for one landmark at a time: numba compiles loops over scalars,
not numpy's whole-array expressions. ``test/fusion/test_compiled.py`` and
``test/fuser/test_change_compiled.py`` run them plain and compiled against numpy.
"""

import math
import os
import threading
from typing import Any, Callable, Dict, Optional, Tuple

from landmark_ros.core.gaussian import (OMEGA_BRACKET, OMEGA_EDGE, OMEGA_QUADRATIC,
                                        OMEGA_TOLERANCE)
import numpy as np
from numpy.typing import NDArray


def _limits(independent=False):
    """
    Return the weight search's constants (an argument: numba would freeze globals).

    The last entry is 1.0 when the sources are independent of each other (no weight).
    """
    return np.array([OMEGA_BRACKET, 1.0 - OMEGA_BRACKET, OMEGA_EDGE, OMEGA_TOLERANCE,
                     OMEGA_QUADRATIC, 1.0 if independent else 0.0])


def _scale4(d0, d1, d2, d3):
    # power_of_4_scale: NaN anywhere gives 1, as np.maximum then isfinite do.
    largest = abs(d0)
    for d in (d1, d2, d3):
        a = abs(d)
        if a != a or largest != largest:
            largest = math.nan
        elif a > largest:
            largest = a
    if not (largest > 0.0 and math.isfinite(largest)):
        largest = 1.0
    # frexp's exponent and ldexp from the bits where the numbers are normal (the
    # library calls cost more than the rest of a 2x2 inverse), the calls otherwise.
    field = (np.float64(largest).view(np.int64) >> 52) & 0x7ff
    exponent = field - 1022 if field > 0 else math.frexp(largest)[1]
    power = exponent - (exponent & 1)
    if -1022 <= power <= 1023:
        return np.int64((power + 1023) << 52).view(np.float64)
    return math.ldexp(1.0, power)


def _inverse(a, b, c):
    s = _scale4(a, c, 0.0, 0.0)
    a, b, c = a / s, b / s, c / s
    inv_det = 1.0 / ((a * c - b * b) * s)
    return c * inv_det, -b * inv_det, a * inv_det


def _psd(a, b, c):
    if a >= 0.0 and c >= 0.0 and a * c >= b * b:
        return a, b, c
    half_sum = 0.5 * (a + c)
    radius = np.hypot(0.5 * (a - c), b)     # libm, as numpy (not math.hypot)
    top = half_sum + radius
    low = half_sum - radius
    scale = top / (top - low) if top > 0.0 else 0.0
    return scale * (a - low), scale * b, scale * (c - low)


def _log2_det(a, b, c):
    s = _scale4(a, c, 0.0, 0.0)
    mantissa, exponent = math.frexp((a / s) * (c / s) - (b / s) * (b / s))
    if not mantissa > 0.0:
        return -math.inf
    return exponent + 2 * (math.frexp(s)[1] - 1) + 2.0 * (mantissa - 0.5)


def _omega_of(first, second, limits):
    # sci_omega_2x2 of two packed estimates (from 0.5); limits: _limits().
    s = _scale4(first[2] + first[5], first[4] + first[7], second[2] + second[5],
                second[4] + second[7])
    a0, a1, a2 = first[2] / s, first[3] / s, first[4] / s
    b0, b1, b2 = first[5] / s, first[6] / s, first[7] / s
    c0, c1, c2 = second[2] / s, second[3] / s, second[4] / s
    e0, e1, e2 = second[5] / s, second[6] / s, second[7] / s
    si0, si1, si2 = a0 + c0, a1 + c1, a2 + c2
    dd0, dd1, dd2 = e0 - b0, e1 - b1, e2 - b2
    two_det_1i = 2.0 * (a0 * a2 - a1 * a1)
    two_det_2i = 2.0 * (c0 * c2 - c1 * c1)
    edge_lo, edge_hi, edge, tolerance = limits[0], limits[1], limits[2], limits[3]
    quadratic = limits[4]
    u, lo, hi = 0.5, edge_lo, edge_hi
    lo_seen, hi_seen = False, False
    last = math.nan     # the previous Newton step's size (NaN: none, no early stop)
    for _ in range(200):
        v = 1.0 - u
        uv = u * v
        w = v - u
        ma, mb, mc = v * b0 + u * e0 + uv * si0, v * b1 + u * e1 + uv * si1, \
            v * b2 + u * e2 + uv * si2
        pa, pb, pc = dd0 + w * si0, dd1 + w * si1, dd2 + w * si2
        ea, eb, ec = b0 + u * a0, b1 + u * a1, b2 + u * a2
        fa, fb, fc = e0 + v * c0, e1 + v * c1, e2 + v * c2
        det_m = ma * mc - mb * mb
        det_e = ea * ec - eb * eb
        det_f = fa * fc - fb * fb
        i_m, i_e, i_f = 1.0 / det_m, 1.0 / det_e, 1.0 / det_f
        r_m = (ma * pc + pa * mc - 2.0 * mb * pb) * i_m
        r_e = (ea * a2 + a0 * ec - 2.0 * eb * a1) * i_e
        r_f = -(fa * c2 + c0 * fc - 2.0 * fb * c1) * i_f
        dm2 = 2.0 * (pa * pc - pb * pb) - 2.0 * (ma * si2 + si0 * mc - 2.0 * mb * si1)
        slope = r_m - r_e - r_f
        curvature = (dm2 * i_m - r_m * r_m - two_det_1i * i_e + r_e * r_e
                     - two_det_2i * i_f + r_f * r_f)
        positive = slope > 0.0
        if positive:
            lo_seen = True
            lo = u
        else:
            hi_seen = True
            hi = u
        step = slope / curvature
        new = u - step
        if not math.isfinite(slope):
            return 0.5
        if u <= edge_lo and not positive:
            return edge
        if u >= edge_hi and positive:
            return 1.0 - edge
        if abs(step) <= tolerance or hi - lo <= tolerance:
            if hi - lo <= tolerance and not (new >= lo and new <= hi):
                return 0.5 * (lo + hi)
            return new
        size = abs(step)
        if (size <= quadratic and size <= last * last
                and size * size * size <= tolerance * last * last and new > lo and new < hi):
            return new
        below, above = not (new > lo), not (new < hi)
        last = math.nan if below or above else size
        if below and not lo_seen:
            new = edge_lo
        elif above and not hi_seen:
            new = edge_hi
        if (below and lo_seen) or (above and hi_seen):
            new = 0.5 * (lo + hi)
        u = new
    return u


def _congruence(k00, k01, k10, k11, a, b, c):
    r00, r01 = k00 * a + k01 * b, k00 * b + k01 * c
    r10, r11 = k10 * a + k11 * b, k10 * b + k11 * c
    return r00 * k00 + r01 * k01, r00 * k10 + r01 * k11, r10 * k10 + r11 * k11


def _split_ci(first, second, u, v, out):
    # split_ci_2x2_entries on packed (x, y, ind xx, xy, yy, dep xx, xy, yy); the
    # dependent parts divided by u and v (omega, 1 - omega; 1, 1: independent).
    s = _scale4(first[2] + first[5], first[4] + first[7],
                second[2] + second[5], second[4] + second[7])
    p1i0, p1i1, p1i2 = first[2] / s, first[3] / s, first[4] / s
    p1d0, p1d1, p1d2 = first[5] / s, first[6] / s, first[7] / s
    p2i0, p2i1, p2i2 = second[2] / s, second[3] / s, second[4] / s
    p2d0, p2d1, p2d2 = second[5] / s, second[6] / s, second[7] / s
    d10, d11, d12 = p1d0 / u, p1d1 / u, p1d2 / u
    d20, d21, d22 = p2d0 / v, p2d1 / v, p2d2 / v
    a0, a1, a2 = d10 + p1i0, d11 + p1i1, d12 + p1i2
    b0, b1, b2 = d20 + p2i0, d21 + p2i1, d22 + p2i2
    q0, q1, q2 = _inverse(a0 + b0, a1 + b1, a2 + b2)
    # W1 = B (A + B)^-1, W2 = A (A + B)^-1.
    w10, w11, w12, w13 = (b0 * q0 + b1 * q1, b0 * q1 + b1 * q2,
                          b1 * q0 + b2 * q1, b1 * q1 + b2 * q2)
    w20, w21, w22, w23 = (a0 * q0 + a1 * q1, a0 * q1 + a1 * q2,
                          a1 * q0 + a2 * q1, a1 * q1 + a2 * q2)
    m0 = w10 * first[0] + w11 * first[1] + w20 * second[0] + w21 * second[1]
    m1 = w12 * first[0] + w13 * first[1] + w22 * second[0] + w23 * second[1]
    i1 = _congruence(w10, w11, w12, w13, p1i0, p1i1, p1i2)
    i2 = _congruence(w20, w21, w22, w23, p2i0, p2i1, p2i2)
    c1 = _congruence(w10, w11, w12, w13, d10, d11, d12)
    c2 = _congruence(w20, w21, w22, w23, d20, d21, d22)
    out[0], out[1] = m0, m1
    out[2], out[3], out[4] = (i1[0] + i2[0]) * s, (i1[1] + i2[1]) * s, (i1[2] + i2[2]) * s
    out[5], out[6], out[7] = (c1[0] + c2[0]) * s, (c1[1] + c2[1]) * s, (c1[2] + c2[2]) * s


def _source_part(Y, y, Q, part):
    # One source's estimate (``source_sums._estimate``) packed into ``part``; its size.
    a, b, c = _inverse(Y[0], Y[1], Y[2])
    part[0] = a * y[0] + b * y[1]
    part[1] = b * y[0] + c * y[1]
    d0, d1, d2 = _congruence(a, b, b, c, Q[0], Q[1], Q[2])
    da, db, dc = _psd(Q[3] * d0, Q[3] * d1, Q[3] * d2)
    part[2], part[3], part[4] = a, b, c
    part[5], part[6], part[7] = da, db, dc
    return _log2_det(a + da, b + db, c + dc)


# Columns of the sums table (``source_sums.SourceSums``): a pair's sums, then the fold
# kept for it: 1.0 while its sums changed since (DIRTY), its source's estimate (PART),
# that estimate's size, its place in its landmark's fold order and the fold up to
# that place (PREFIX), for the compiled fold to start from the first place that
# changed. The fold is a pure function of the sums: the kept prefixes give its bits.
DIRTY, PART, SIZE, RANK, PREFIX, COLUMNS = 9, 10, 18, 19, 20, 28


def _fold_one(table, slots, order, out, limits):
    # One landmark, pairs table[slots] (n >= 1) -> out (8,); updates the kept fold.
    n = len(slots)
    for j in range(n):
        t = table[slots[j]]
        if t[DIRTY] != 0.0:
            t[SIZE] = _source_part(t[0:3], t[3:5], t[5:9], t[PART:PART + 8])
    # Stable insertion sort of the sources by size (key order breaks ties).
    for j in range(n):
        key = table[slots[j], SIZE]
        i = j
        while i > 0 and table[slots[order[i - 1]], SIZE] > key:
            order[i] = order[i - 1]
            i -= 1
        order[i] = j
    # The first places hold the sources of the last fold, unchanged: their prefixes hold.
    start = 0
    while start < n and table[slots[order[start]], DIRTY] == 0.0 and (
            table[slots[order[start]], RANK] == start):
        start += 1
    for j in range(n):
        table[slots[j], DIRTY] = 0.0
    if start == 0:
        t = table[slots[order[0]]]
        for i in range(8):
            t[PREFIX + i] = t[PART + i]
        t[RANK] = 0.0
        start = 1
    for j in range(start, n):
        first = table[slots[order[j - 1]], PREFIX:PREFIX + 8]
        t = table[slots[order[j]]]
        u, v = 1.0, 1.0
        if limits[5] == 0.0:
            u = _omega_of(first, t[PART:PART + 8], limits)
            v = 1.0 - u
        _split_ci(first, t[PART:PART + 8], u, v, t[PREFIX:PREFIX + 8])
        t[RANK] = j
    for i in range(8):
        out[i] = table[slots[order[n - 1]], PREFIX + i]


def _fold_all(table, slots, lo, hi, out, limits):
    # Landmark k's pairs are table[slots[lo[k]:hi[k]]] (at least one) -> out[k] (8,).
    width = 1
    for k in range(len(lo)):
        width = max(width, hi[k] - lo[k])
    order = np.empty(width, np.int64)
    for k in range(len(lo)):
        _fold_one(table, slots[lo[k]:hi[k]], order, out[k], limits)


def _accumulate(table, slots, added):
    # np.add.at(table[:, j], slots, added[:, j]) for each column j: row by row, in order.
    for n in range(len(slots)):
        for j in range(added.shape[1]):
            table[slots[n], j] += added[n, j]


def _mahalanobis(dx, dy, a, b, c):
    # core.arrays.mahalanobis_sq_2x2 (its scale, its operations).
    s = _scale4(a, c, 0.0, 0.0)
    root = math.sqrt(s)
    a, b, c, dx, dy = a / s, b / s, c / s, dx / root, dy / root
    return (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * c - b * b)


def _agree(z, R, members, seed, threshold, limits, keep):
    # records.agreeing's loop for split CI: R (N, 6) the rows' independent and dependent
    # entries; keep[j] whether members[j] joins the estimate fused so far.
    first = members[0]
    estimate, row, out = np.empty(8), np.empty(8), np.empty(8)
    estimate[0], estimate[1] = z[first, 0], z[first, 1]
    for i in range(6):
        estimate[2 + i] = R[first, i]
    keep[0] = True
    for j in range(1, len(members)):
        i = members[j]
        d2 = _mahalanobis(z[i, 0] - estimate[0], z[i, 1] - estimate[1],
                          (estimate[2] + estimate[5]) + (R[i, 0] + R[i, 3]),
                          (estimate[3] + estimate[6]) + (R[i, 1] + R[i, 4]),
                          (estimate[4] + estimate[7]) + (R[i, 2] + R[i, 5]))
        keep[j] = i == seed or d2 <= threshold
        if keep[j]:
            row[0], row[1] = z[i, 0], z[i, 1]
            for k in range(6):
                row[2 + k] = R[i, k]
            u = _omega_of(estimate, row, limits)
            _split_ci(estimate, row, u, 1.0 - u, out)
            estimate[:] = out


def _reference(x, X, live, slots, z, W, clip, d2):
    # change_reference's white filters, row by row (covariance form): a slot not live
    # starts from its row; a row whose d2 is above the clip does not update.
    for n in range(len(slots)):
        s = slots[n]
        if not live[s]:
            x[s, 0], x[s, 1] = z[n, 0], z[n, 1]
            X[s, 0, 0], X[s, 0, 1], X[s, 1, 0], X[s, 1, 1] = W[n, 0], W[n, 1], W[n, 1], W[n, 2]
            live[s] = True
            d2[n] = math.nan
            continue
        a, b, c = X[s, 0, 0], X[s, 0, 1], X[s, 1, 1]
        nx, ny = z[n, 0] - x[s, 0], z[n, 1] - x[s, 1]
        d2[n] = _mahalanobis(nx, ny, a + W[n, 0], b + W[n, 1], c + W[n, 2])
        if d2[n] <= clip:
            i0, i1, i2 = _inverse(a + W[n, 0], b + W[n, 1], c + W[n, 2])
            k00, k01, k10, k11 = a * i0 + b * i1, a * i1 + b * i2, b * i0 + c * i1, b * i1 + c * i2
            x[s, 0] += k00 * nx + k01 * ny
            x[s, 1] += k10 * nx + k11 * ny
            b_new = b - (k00 * b + k01 * c)
            X[s, 0, 0] = a - (k00 * a + k01 * b)
            X[s, 0, 1], X[s, 1, 0] = b_new, b_new
            X[s, 1, 1] = c - (k10 * b + k11 * c)


def _cusum(keys, g, E, C, first, limits, alarm):
    # change_detection's capped statistic row by row (MoveDetector._loop); keys: rows'
    # slots, source codes and sequence numbers; limits: (threshold, cap). A landmark's
    # rows after its alarm in the batch are not taken.
    slots, codes, sequence = keys[0], keys[1], keys[2]
    alarmed = np.zeros(len(C), np.bool_)
    for n in range(len(slots)):
        s = slots[n]
        if alarmed[s]:
            continue
        if C[s] <= 0.0:
            first[s] = sequence[n]
        counted = min(E[s, codes[n]], limits[1])
        E[s, codes[n]] += g[n]
        statistic = C[s] + (min(E[s, codes[n]], limits[1]) - counted)
        C[s] = max(statistic, 0.0)
        if statistic <= 0.0:
            E[s, :] = 0.0
        elif statistic >= limits[0]:
            alarmed[s] = True
            alarm[n] = True


_COMPILED = ('_scale4', '_inverse', '_psd', '_log2_det', '_omega_of', '_congruence',
             '_split_ci', '_source_part', '_fold_one', '_fold_all', '_accumulate',
             '_mahalanobis', '_agree', '_reference', '_cusum')
"""The functions compiled, callees before callers."""

_state: Dict[str, Any] = {'thread': None, 'kernels': None}
_lock = threading.Lock()


def _kernel(name: str, python: bool) -> Optional[Callable[..., Any]]:
    """Return a compiled function (the plain one when ``python``); None while not ready."""
    if python:
        return globals()[name]
    kernels = _state['kernels']
    if kernels is None:
        start()
        return None
    return kernels[name]


def fold_python(table: NDArray[np.float64], slots: NDArray[np.int64], lo: NDArray[np.int64],
                hi: NDArray[np.int64], independent: bool = False) -> NDArray[np.float64]:
    """Return ``fold`` by the plain Python functions (slow; for tests); keeps the fold too."""
    return _call(_fold_all, table, slots, lo, hi, independent)


def _call(kernel, table, slots, lo, hi, independent):
    out = np.empty((len(lo), 8))
    with np.errstate(all='ignore'):
        kernel(np.ascontiguousarray(table, dtype=np.float64), *(
            np.ascontiguousarray(x, dtype=np.int64) for x in (slots, lo, hi)), out,
            _limits(independent))
    return out


def fold(table: NDArray[np.float64], slots: NDArray[np.int64], lo: NDArray[np.int64],
         hi: NDArray[np.int64], independent: bool = False) -> Optional[NDArray[np.float64]]:
    """
    Return the fold of landmarks, compiled; None while that is not ready.

    Landmark ``k``'s sources are ``table[slots[lo[k]:hi[k]]]`` (``source_sums.fold``:
    at least one); returns shape (K, 8): mean, ``(xx, xy, yy)`` of ``P_ind`` and of
    ``P_dep``. ``independent``: the sources' dependent parts are independent of each
    other (no weight). Updates the kept folds in ``table`` (columns ``DIRTY`` on); a
    table is folded one way only. Starts loading the compiled functions on first call
    (``start``), without waiting.
    """
    kernel = _kernel('_fold_all', False)
    return None if kernel is None else _call(kernel, table, slots, lo, hi, independent)


def accumulate(table: NDArray[np.float64], slots: NDArray[np.int64],
               added: NDArray[np.float64]) -> bool:
    """
    Add ``added`` (N, C) to the first C columns of ``table``'s rows ``slots`` (N,), in order.

    ``np.add.at`` column by column, the same bits (a slot's rows added one after the
    other); ``table`` C-contiguous float64, changed in place. Return False (nothing
    done) while not compiled.
    """
    kernel = _kernel('_accumulate', False)
    if kernel is None:
        return False
    kernel(table, np.ascontiguousarray(slots, np.int64), np.ascontiguousarray(added, np.float64))
    return True


def agree(z: NDArray[np.float64], R: NDArray[np.float64], members: NDArray[np.int64],
          seed: int, threshold: float, python: bool = False) -> Optional[NDArray[np.bool_]]:
    """
    Return which ``members`` join the split-CI estimate (None while not compiled).

    ``records.agreeing``'s loop. ``z`` (N, 2) [m] and ``R`` (N, 6) [m^2] (entries of
    ``R_ind``, then of ``R_dep``) the rows; ``members`` (M,) the rows that pass the
    pairwise gate with ``seed``, in order. The same bits as ``agreeing`` with
    ``SplitCovarianceIntersection.fuse``. ``python``: the plain functions (tests).
    """
    kernel = _kernel('_agree', python)
    if kernel is None:
        return None
    keep = np.zeros(len(members), np.bool_)
    with np.errstate(all='ignore'):
        kernel(np.ascontiguousarray(z, np.float64), np.ascontiguousarray(R, np.float64),
               np.ascontiguousarray(members, np.int64), int(seed), float(threshold),
               _limits(), keep)
    return keep


def reference(state: Tuple[NDArray[Any], ...], slots: NDArray[np.int64],
              z: NDArray[np.float64], W: NDArray[np.float64], clip: float,
              python: bool = False) -> Optional[NDArray[np.float64]]:
    """
    Run white reference filters over rows in order; return ``d2`` (None: not compiled).

    ``state`` ``(x (L, 2), X (L, 2, 2), live (L,))`` of ``fuser.change_reference``,
    updated in place (C-contiguous float64 and bool); ``slots`` (N,) each row's filter,
    ``z`` (N, 2) [m], ``W`` (N, 3) [m^2] its covariance's entries. A filter not live
    starts from its row (``d2`` NaN). Agrees with the numpy information form to rounding.
    """
    kernel = _kernel('_reference', python)
    if kernel is None:
        return None
    d2 = np.empty(len(slots))
    with np.errstate(all='ignore'):
        kernel(*state, np.ascontiguousarray(slots, np.int64), np.ascontiguousarray(
            z, np.float64), np.ascontiguousarray(W, np.float64), float(clip), d2)
    return d2


def cusum(state: Tuple[NDArray[Any], ...], rows: Tuple[NDArray[Any], ...],
          threshold: float, cap: float, python: bool = False) -> Optional[NDArray[np.bool_]]:
    """
    Run the capped CUSUM over rows in order; return the alarms' rows (None: not compiled).

    ``state`` ``(E (L, K), C (L,), first (L,))`` of ``fuser.change_detection``, updated
    in place; ``rows`` ``(slots, codes, g, sequence)``, each (N,). A landmark takes no
    row after its alarm in the call. The same bits as ``MoveDetector._loop``.
    """
    kernel = _kernel('_cusum', python)
    if kernel is None:
        return None
    slots, codes, g, sequence = rows
    alarm = np.zeros(len(slots), np.bool_)
    kernel(np.array([slots, codes, sequence], np.int64), np.ascontiguousarray(g, np.float64),
           *state, np.array([threshold, cap]), alarm)
    return alarm


def enabled() -> bool:
    """Return whether the environment allows numba (``LANDMARK_ROS_NUMBA`` is not ``0``)."""
    return os.environ.get('LANDMARK_ROS_NUMBA', '1') != '0'


def start() -> None:
    """Start loading the compiled functions in a daemon thread, once; return at once."""
    with _lock:
        if _state['thread'] is None:
            thread = threading.Thread(target=_load, name='landmark_ros.compiled', daemon=True)
            _state['thread'] = thread
            thread.start()


def load(timeout: Optional[float] = None) -> bool:
    """Start loading if needed, wait for it (up to ``timeout`` s); return ``ready()``."""
    start()
    _state['thread'].join(timeout)
    return ready()


def ready() -> bool:
    """Return whether the compiled functions serve."""
    return _state['kernels'] is not None


def _load() -> None:
    """Import numba and compile the functions (numba's disk cache when it can)."""
    if not enabled():
        return
    try:
        import numba
    except ImportError:
        return
    jit = numba.njit(cache=True, error_model='numpy', fastmath=False, nogil=True)
    kernels: Dict[str, Callable[..., Any]] = {}
    try:
        for name in _COMPILED:
            # A compiled function calls the compiled callees it finds among its globals:
            # a private copy of this module's namespace holds them, the module keeps the
            # plain functions.
            function = globals()[name]
            scope = dict(function.__globals__, **kernels)
            kernels[name] = jit(type(function)(function.__code__, scope, name))
        table = np.zeros((1, COLUMNS))
        table[0, 0], table[0, 2], table[0, DIRTY] = 1.0, 1.0, 1.0
        for independent in (False, True):
            _call(kernels['_fold_all'], table, [0], [0], [1], independent)
        _warm(kernels)
    except Exception:   # noqa: BLE001 - any failure: the numpy code serves
        return
    _state['kernels'] = kernels


def _warm(kernels):
    """Call each detection kernel once with the argument types callers pass."""
    z, one = np.zeros((1, 2)), np.zeros(1, np.int64)
    kernels['_accumulate'](np.zeros((1, COLUMNS)), one, np.zeros((1, 9)))
    kernels['_agree'](z, np.ones((1, 6)), one, 0, 1.0, _limits(), np.zeros(1, np.bool_))
    kernels['_reference'](z, np.zeros((1, 2, 2)), np.zeros(1, np.bool_), one, z,
                          np.ones((1, 3)), 1.0, np.zeros(1))
    kernels['_cusum'](np.zeros((3, 1), np.int64), np.zeros(1), np.zeros((1, 1)), np.zeros(1),
                      one.copy(), np.ones(2), np.zeros(1, np.bool_))
