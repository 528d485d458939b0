"""
The split-CI fold of ``landmark_map`` compiled with numba, when numba is installed.

``fold(Y, y, Q, valid)`` does what ``_source_sums._fold`` does, one landmark at a time
in a compiled loop instead of one numpy operation per step over all landmarks: the
same IEEE operations in the same order (no fast-math, no fused multiply-add), so the
results are the numpy fold's bit for bit (``test/core/test_fold_kernel.py`` checks
it). ``run`` gates a batch's rows one after the other against the landmarks' gate
references and folds each landmark once after its last row and at its refreshes
(``gate_due``), keeping each landmark's fold between batches (``LandmarkMap``'s
split-CI batch). A (landmark, source) step costs about a tenth of the numpy fold's.

``load()`` imports numba and compiles the kernel on first use (a process that never
folds does not load numba: about 80 MB and a second; compiling without numba's disk
cache takes about 10 s). It returns None when numba cannot be imported or fails to
compile the kernel for this numpy, and ``landmark_map`` then uses the numpy fold. The
environment variable ``LANDMARK_ROS_NUMBA=0`` turns the kernel off (for comparisons).

Sources: split covariance intersection, Julier and Uhlmann, "General decentralized
data fusion with covariance intersection", Handbook of Multisensor Data Fusion, 2001;
the weight search and the closed forms are ``core.gaussian``'s
(``sci_omega_2x2``, ``split_ci_2x2_entries``), the per-source estimate and the order
``_source_sums``' (``_estimate``, ``_log2_det``).
"""

import math
import os
import sys
from typing import Any, Callable, Optional, Tuple

from landmark_ros.core.gaussian import (_OMEGA_BRACKET, _OMEGA_QUADRATIC, OMEGA_EDGE,
                                        OMEGA_TOLERANCE)
import numpy as np
from numpy.typing import NDArray

FoldResult = Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]

fold: Optional[Callable[..., FoldResult]] = None
"""The compiled fold (``Y, y, Q, valid -> m, P_ind, P_dep``), or None."""

AVAILABLE = False
"""Whether ``fold`` is the compiled kernel."""


def _limits():
    """
    Return the weight search's bracket, edge value, tolerance and quadratic regime as one array.

    Passed at each call rather than read as globals: numba freezes globals into its
    on-disk cache, which would not see a change of ``core.gaussian``'s constants.
    """
    return np.array([_OMEGA_BRACKET, 1.0 - _OMEGA_BRACKET, OMEGA_EDGE, OMEGA_TOLERANCE,
                     _OMEGA_QUADRATIC])


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
    radius = math.hypot(0.5 * (a - c), b)
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


def _omega_of(p1i0, p1i1, p1i2, p1d0, p1d1, p1d2, p2i0, p2i1, p2i2, p2d0, p2d1, p2d2,
              limits):
    s = _scale4(p1i0 + p1d0, p1i2 + p1d2, p2i0 + p2d0, p2i2 + p2d2)
    a0, a1, a2 = p1i0 / s, p1i1 / s, p1i2 / s
    b0, b1, b2 = p1d0 / s, p1d1 / s, p1d2 / s
    c0, c1, c2 = p2i0 / s, p2i1 / s, p2i2 / s
    e0, e1, e2 = p2d0 / s, p2d1 / s, p2d2 / s
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


def _split_ci(first, second, omega, out):
    # split_ci_2x2_entries on packed (x, y, ind xx, xy, yy, dep xx, xy, yy).
    s = _scale4(first[2] + first[5], first[4] + first[7],
                second[2] + second[5], second[4] + second[7])
    p1i0, p1i1, p1i2 = first[2] / s, first[3] / s, first[4] / s
    p1d0, p1d1, p1d2 = first[5] / s, first[6] / s, first[7] / s
    p2i0, p2i1, p2i2 = second[2] / s, second[3] / s, second[4] / s
    p2d0, p2d1, p2d2 = second[5] / s, second[6] / s, second[7] / s
    u, v = omega, 1.0 - omega
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


def _source_part(Y, y, Q, valid, part):
    # One source's estimate (``_source_sums._estimate``) packed into ``part``; its size.
    a, b, c = _inverse(Y[0], Y[1], Y[2])
    part[0] = a * y[0] + b * y[1]
    part[1] = b * y[0] + c * y[1]
    da, db, dc = _psd(a * Q[0] + b * Q[2], 0.5 * (a * Q[1] + b * Q[3] + b * Q[0] + c * Q[2]),
                      b * Q[1] + c * Q[3])
    part[2], part[3], part[4] = a, b, c
    part[5], part[6], part[7] = da, db, dc
    return _log2_det(a + da, b + db, c + dc) if valid else math.inf


def _fold_all(parts, order, n, prefix, limits):
    # prefix[j] = the fold of the sources order[0..j].
    for i in range(8):
        prefix[0, i] = parts[order[0], i]
    for j in range(1, n):
        _fold_step(prefix[j - 1], parts[order[j]], prefix[j], limits)


def _fold_one(Y, y, Q, valid, parts, size, order, prefix, out, limits):
    # One landmark: Y (W, 3), y (W, 2), Q (W, 4), valid (W,) -> out (8,) packed.
    width = len(valid)
    n = 0
    for j in range(width):
        size[j] = _source_part(Y[j], y[j], Q[j], valid[j], parts[j])
        if valid[j]:
            n += 1
    # Stable insertion sort of the columns by size (few sources per landmark).
    for j in range(width):
        key = size[j]
        i = j
        while i > 0 and size[order[i - 1]] > key:
            order[i] = order[i - 1]
            i -= 1
        order[i] = j
    _fold_all(parts, order, n, prefix, limits)
    for i in range(8):
        out[i] = prefix[n - 1, i]


def _kernel(Y, y, Q, valid, out, limits):
    count, width = valid.shape
    parts = np.empty((width, 8))
    size = np.empty(width)
    order = np.empty(width, np.int64)
    prefix = np.empty((width, 8))
    for k in range(count):
        _fold_one(Y[k], y[k], Q[k], valid[k], parts, size, order, prefix, out[k], limits)


def _mahalanobis_sq(dx, dy, a, b, c):
    # mahalanobis_sq_2x2, the same operations.
    s = _scale4(a, c, 0.0, 0.0)
    root = math.sqrt(s)
    a, b, c, dx, dy = a / s, b / s, c / s, dx / root, dy / root
    return (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * c - b * b)


# Columns of the per-slot table of ``run``: the sums (Y, y, Q), the slot's rank in
# its landmark's fold order, 1.0 when it holds observations, the source's packed
# estimate (``_source_part``), the prefix fold at its rank and its size. One row per
# slot: a landmark's sources are read together. What every accepted row reads and
# writes (the sums, rank, flag) comes first: 88 bytes, two cache lines, not three.
RANK, VALID, PART, PREFIX, SIZE, COLUMNS = 9, 10, 11, 19, 27, 28

GATE_BITS = 2
"""A landmark's gate reference is refreshed 2 ** GATE_BITS times per doubling of its
observations (every observation up to 2 ** (GATE_BITS + 1) - 1): it then holds at
least 2 ** GATE_BITS / (2 ** GATE_BITS + 1) (4/5) of the information of the current
estimate. 3 (8/9) cost about a third more in the fold for landmarks with tens of
sources, and gave the same MRCLAM and Monte Carlo figures."""


def _refold(lo, width, key_slots, table, order, limits, partial):
    # The fold of one landmark (pairs key_slots[lo:lo + width]), as _fold_one, kept per
    # slot. ``partial``: the kept fold holds for the pairs not marked changed (size NaN,
    # or rank -1: new to the fold); their estimates are kept and the fold is redone
    # from the first place where the order differs. Otherwise all of it.
    n = 0
    for j in range(width):
        t = table[key_slots[lo + j]]
        if t[VALID] != 0.0:
            if not partial or t[RANK] < 0.0 or t[SIZE] != t[SIZE]:
                t[SIZE] = _source_part(t[0:3], t[3:5], t[5:9], True, t[PART:PART + 8])
                t[RANK] = -1.0
            n += 1
        else:
            t[SIZE] = math.inf
            t[RANK] = -1.0
    # Stable insertion sort of the pairs by size (key order breaks ties).
    for j in range(width):
        key = table[key_slots[lo + j], SIZE]
        i = j
        while i > 0 and table[key_slots[lo + order[i - 1]], SIZE] > key:
            order[i] = order[i - 1]
            i -= 1
        order[i] = j
    # The first places hold the same unchanged pairs as before: their prefixes hold.
    start = 0
    while start < n and table[key_slots[lo + order[start]], RANK] == start:
        start += 1
    return _fold_from(start, n, lo, key_slots, table, order, limits)


def _fold_from(start, n, lo, key_slots, table, order, limits):
    # Redo a landmark's kept fold from place ``start`` of its ``n`` ordered pairs
    # (``order``: local indices into key_slots[lo:]); return the last pair's slot.
    if start == 0:
        t = table[key_slots[lo + order[0]]]
        for i in range(8):
            t[PREFIX + i] = t[PART + i]
        t[RANK] = 0.0
        start = 1
    for j in range(start, n):
        t = table[key_slots[lo + order[j]]]
        _fold_step(table[key_slots[lo + order[j - 1]], PREFIX:PREFIX + 8], t[PART:PART + 8],
                   t[PREFIX:PREFIX + 8], limits)
        t[RANK] = j
    return key_slots[lo + order[n - 1]]


def _fold_step(first, second, out, limits):
    # out = split CI of the packed estimates first and second (weight searched from 0.5).
    omega = _omega_of(first[2], first[3], first[4], first[5], first[6], first[7],
                      second[2], second[3], second[4], second[5], second[6], second[7],
                      limits)
    _split_ci(first, second, omega, out)


def _move(lo, width, q, key_slots, table, order, limits):
    # Pair q (local index) of a landmark whose fold is kept changed (or is new to the
    # fold: rank -1): move it to its place in the order by size and fold again from
    # the first place that changed.
    p = key_slots[lo + q]
    tp = table[p]
    n = 0
    for j in range(width):
        s = key_slots[lo + j]
        if s != p and table[s, VALID] != 0.0:
            n += 1
    old = int(tp[RANK]) if tp[VALID] != 0.0 and tp[RANK] >= 0.0 else n
    tp[VALID] = 1.0
    for j in range(width):
        s = key_slots[lo + j]
        if s != p and table[s, VALID] != 0.0:
            r = int(table[s, RANK])
            order[r if r < old else r - 1] = j
    key = _source_part(tp[0:3], tp[3:5], tp[5:9], True, tp[PART:PART + 8])
    tp[SIZE] = key
    new = n
    for j in range(n):
        other = order[j]
        value = table[key_slots[lo + other], SIZE]
        if value > key or (value == key and other > q):
            new = j
            break
    for j in range(n, new, -1):
        order[j] = order[j - 1]
    order[new] = q
    n += 1
    return _fold_from(min(old, new), n, lo, key_slots, table, order, limits)


def _add_terms(t, z0, z1, R_ind, R_dep):
    # t[0:9] += _source_sums._terms of one observation (the same operations).
    a, b, c = R_ind[0, 0], R_ind[0, 1], R_ind[1, 1]
    trace = a + c
    floor = 1e-12 * (trace if trace > 0.0 else R_dep[0, 0] + R_dep[1, 1])
    ya, yb, yc = _inverse(a + floor, b, c + floor)
    t[0] += ya
    t[1] += yb
    t[2] += yc
    t[3] += ya * z0 + yb * z1
    t[4] += yb * z0 + yc * z1
    t[5] += ya * R_dep[0, 0] + yb * R_dep[1, 0]
    t[6] += ya * R_dep[0, 1] + yb * R_dep[1, 1]
    t[7] += yb * R_dep[0, 0] + yc * R_dep[1, 0]
    t[8] += yb * R_dep[0, 1] + yc * R_dep[1, 1]


def _gate_due(n):
    # Whether the gate reference is refreshed after a landmark's n-th observation:
    # every one up to 2 ** (GATE_BITS + 1) - 1, then 2 ** GATE_BITS per doubling.
    step = 1
    top = n >> (GATE_BITS + 1)
    while top > 0:
        top >>= 1
        step <<= 1
    return n % step == 0


def _settle(k, single, lo, hi, key_slots, table, kept, order, state, limits):
    # Fold landmark k again after its sums changed: only pair ``single`` (when >= 0
    # and the fold is kept) or several (those with a NaN size) -> state[k].
    width = hi[k] - lo[k]
    if kept[k] and single >= 0:
        last = _move(lo[k], width, single - lo[k], key_slots, table, order, limits)
    else:
        last = _refold(lo[k], width, key_slots, table, order, limits, kept[k])
        kept[k] = True
    for j in range(8):
        state[k, j] = table[last, PREFIX + j]


def _pending_position(slot, lo, hi, key_slots):
    # A landmark's pending change as ``single``: -1 none, -2 several, else the
    # position in key_slots of the one changed slot.
    if slot < 0:
        return slot
    for p in range(lo, hi):
        if key_slots[p] == slot:
            return p
    return -2


def _run_kernel(landmark, rows_in_order, position, at, z, R_ind, R_dep, lo, hi, key_slots,
                table, kept, state, gate, observations, pending, lazy, threshold, accepted,
                seen, saved_slots, saved_sums, saved_owner, limits):
    width = 1
    for k in range(len(lo)):
        width = max(width, hi[k] - lo[k])
    order = np.empty(width, np.int64)
    count = len(rows_in_order)
    saved_count = 0
    # Landmark by landmark (each in arrival order): the landmarks do not interact,
    # and a landmark's pairs stay in the cache for all its rows. ``single``: the one
    # pair whose sums changed since the landmark was last folded (-1 none, -2 more).
    single = -1
    for index in range(count):
        i = rows_in_order[index]
        k = landmark[i]
        if index == 0 or landmark[rows_in_order[index - 1]] != k:
            single = _pending_position(pending[k], lo[k], hi[k], key_slots)
        x = at[i]
        g = gate[k]
        a = g[2] + R_ind[x, 0, 0] + R_dep[x, 0, 0]
        b = g[3] + R_ind[x, 0, 1] + R_dep[x, 0, 1]
        c = g[4] + R_ind[x, 1, 1] + R_dep[x, 1, 1]
        d2 = _mahalanobis_sq(z[x, 0] - g[0], z[x, 1] - g[1], a, b, c)
        accepted[i] = d2 <= threshold
        if accepted[i]:
            p = position[i]
            t = table[key_slots[p]]
            if not seen[p]:         # the pair's sums before the batch, once
                seen[p] = True
                c = saved_count
                saved_slots[c], saved_owner[c] = key_slots[p], k
                for j in range(9):
                    saved_sums[c, j] = t[j]
                saved_count += 1
            _add_terms(t, z[x, 0], z[x, 1], R_ind[x], R_dep[x])
            t[SIZE] = math.nan          # its estimate in the kept fold is stale
            if t[VALID] == 0.0:        # a pair new to the fold (no rank yet): observed now
                t[VALID] = 1.0
                t[RANK] = -1.0
            if single == -1:
                single = p
            elif single != p:
                single = -2
            observations[k] += 1
            if _gate_due(observations[k]):
                _settle(k, single, lo, hi, key_slots, table, kept, order, state, limits)
                single = -1
                m = state[k]
                g[0], g[1] = m[0], m[1]
                g[2], g[3], g[4] = m[2] + m[5], m[3] + m[6], m[4] + m[7]
        if index + 1 == count or landmark[rows_in_order[index + 1]] != k:
            if single != -1 and not lazy:
                _settle(k, single, lo, hi, key_slots, table, kept, order, state, limits)
                single = -1
            pending[k] = key_slots[single] if single >= 0 else single
    return saved_count


def _settle_kernel(lo, hi, pending, key_slots, table, kept, state, limits):
    width = 1
    for k in range(len(lo)):
        width = max(width, hi[k] - lo[k])
    order = np.empty(width, np.int64)
    for k in range(len(lo)):
        single = _pending_position(pending[k], lo[k], hi[k], key_slots)
        if single != -1 and hi[k] > lo[k]:
            _settle(k, single, lo, hi, key_slots, table, kept, order, state, limits)
        pending[k] = -1


def _compiled_fold(Y, y, Q, valid):
    """Run the kernel on contiguous copies; return ``m, P_ind, P_dep`` as ``_fold``."""
    Y, y, Q = (np.ascontiguousarray(x, dtype=np.float64) for x in (Y, y, Q))
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    out = np.empty((len(valid), 8))
    with np.errstate(all='ignore'):
        _kernel(Y, y, Q, valid, out, _limits())
    P_ind = np.empty((len(valid), 2, 2))
    P_dep = np.empty((len(valid), 2, 2))
    P_ind[:, 0, 0], P_ind[:, 0, 1], P_ind[:, 1, 0], P_ind[:, 1, 1] = \
        out[:, 2], out[:, 3], out[:, 3], out[:, 4]
    P_dep[:, 0, 0], P_dep[:, 0, 1], P_dep[:, 1, 0], P_dep[:, 1, 1] = \
        out[:, 5], out[:, 6], out[:, 6], out[:, 7]
    return out[:, :2].copy(), P_ind, P_dep


def run(landmark: NDArray[np.intp], order: NDArray[np.intp], position: NDArray[np.intp],
        at: NDArray[np.intp],
        z: NDArray[np.float64], R_ind: NDArray[np.float64], R_dep: NDArray[np.float64],
        lo: NDArray[np.intp], hi: NDArray[np.intp], key_slots: NDArray[np.intp],
        table: NDArray[np.float64], kept: NDArray[np.bool_], state: NDArray[np.float64],
        gate: NDArray[np.float64], observations: NDArray[np.int64],
        pending: NDArray[np.int64], lazy: bool, threshold: float
        ) -> Tuple[NDArray[np.bool_], Tuple[NDArray[np.int64], NDArray[np.float64],
                                            NDArray[np.int64]]]:
    """
    Gate the rows of a batch one after the other and fold their landmarks, as the map would.

    Row ``i`` (arrival order) observes landmark ``landmark[i]``, whose (landmark,
    source) pairs are the slots ``key_slots[lo[k]:hi[k]]`` (in key order, that is by
    source code), whose estimate is ``state[k]`` and whose gate reference is
    ``gate[k]``. A row passes when its squared Mahalanobis distance to the reference
    (innovation covariance ``P + R_ind + R_dep``) is at most ``threshold``; then what
    it adds to the sums (``_source_sums._terms``, the same operations) is added to
    those of the slot ``key_slots[position[i]]`` and the landmark's count
    ``observations[k]`` goes up. When the count reaches a refresh point
    (``GATE_BITS``) the landmark is folded and its reference becomes the new
    estimate; after its last row in the batch it is folded if its sums changed, or,
    with ``lazy``, left pending: ``pending[k]`` then says what changed since the
    last fold (-1 nothing, -2 several pairs, else the one changed slot), for a later
    ``run`` or ``settle`` to take up.

    A slot's row of ``table`` holds its sums and, for a landmark with ``kept[k]`` (its
    fold up to date with its sums), its source's estimate, its size (``_log2_det`` of
    the covariance), its rank in the fold order and the prefix fold up to that rank
    (the columns ``RANK`` to ``PREFIX``). When one source changed, it moves to its new
    place and the fold is redone from the first place that changed. When several did
    (a row marks its pair's size NaN), they get new estimates, the others keep theirs
    and the fold is redone from the first place that changed. Without a kept fold the
    whole fold is done and kept (``kept[k]`` is set). The estimates are those of
    ``_fold`` on the sums, bit for bit. ``table``, ``kept``, ``state``, ``gate``,
    ``observations`` and ``pending`` are updated in place. Call only after ``load()``
    returned the kernel.

    Parameters
    ----------
    landmark : ndarray of int, shape (N,)
        Each row's landmark, an index into ``state``, ``gate``, ``lo``, ``hi``, ``kept``.
    order : ndarray of int, shape (N,)
        The rows grouped by landmark, each landmark's in arrival order
        (``_pair_index.group``): the order they are taken in (landmarks do not interact).
    position : ndarray of int, shape (N,)
        Each row's (landmark, source) pair, an index into ``key_slots``.
    at : ndarray of int, shape (N,)
        Each row's index in ``z``, ``R_ind``, ``R_dep``.
    z : ndarray, shape (M, 2)
        Observed positions [m].
    R_ind, R_dep : ndarray, shape (M, 2, 2)
        Independent and dependent parts of their covariances [m^2].
    lo, hi : ndarray of int, shape (K,)
        Landmark ``k``'s pairs are ``key_slots[lo[k]:hi[k]]``.
    key_slots : ndarray of int, shape (P,)
        The slot of each pair.
    table : ndarray, shape (S, COLUMNS)
        Per slot: its sums (``Y``, ``y``, ``Q``: 9 columns), then the kept fold (see
        above); column ``VALID`` is 1.0 for the slots that hold observations.
    kept : ndarray of bool, shape (K,)
        Whether a landmark's kept fold is up to date.
    state : ndarray, shape (K, 8)
        Packed estimates: mean, ``(xx, xy, yy)`` of ``P_ind``, of ``P_dep``.
    gate : ndarray, shape (K, 5)
        Gate references: mean, ``(xx, xy, yy)`` of ``P_ind + P_dep``.
    observations : ndarray of int64, shape (K,)
        Observations fused into each landmark so far.
    pending : ndarray of int64, shape (K,)
        What changed since each landmark's last fold (see above).
    lazy : bool
        Leave the fold after a landmark's last row to later (``pending``).
    threshold : float
        Gate on the squared Mahalanobis distance.

    Returns
    -------
    accepted : ndarray of bool, shape (N,)
    saved : tuple of (ndarray of int (C,), ndarray (C, 9), ndarray of int (C,))
        Each slot whose sums the batch changed, once: the slot, its sums as they were
        before the batch and its landmark (an index into ``state``), in the order the
        kernel first added to them. What a rollback restores.

    """
    count = len(landmark)
    accepted = np.empty(count, np.bool_)
    seen = np.zeros(len(key_slots), np.bool_)
    slots, owner = np.empty(count, np.int64), np.empty(count, np.int64)
    sums = np.empty((count, 9))
    with np.errstate(all='ignore'):
        changed = _run_kernel(landmark, order, position, at, z, R_ind, R_dep, lo, hi,
                              key_slots, table, kept, state, gate, observations, pending,
                              bool(lazy), float(threshold), accepted, seen, slots, sums, owner,
                              _limits())
    return accepted, (slots[:changed], sums[:changed], owner[:changed])


def settle(lo: NDArray[np.intp], hi: NDArray[np.intp], pending: NDArray[np.int64],
           key_slots: NDArray[np.intp], table: NDArray[np.float64], kept: NDArray[np.bool_],
           state: NDArray[np.float64]) -> None:
    """
    Fold the landmarks that ``run`` left ``pending`` (``lazy``); the same bits as ``_fold``.

    Landmark ``k`` (pairs ``key_slots[lo[k]:hi[k]]``) gets its estimate in ``state[k]``
    (packed as in ``run``) when ``pending[k]`` is not -1, its kept fold updated
    (``kept[k]`` set); ``pending`` is all -1 after. A landmark without pairs is
    skipped. Call only after ``load()`` returned the kernel.
    """
    with np.errstate(all='ignore'):
        _settle_kernel(lo, hi, pending, key_slots, table, kept, state, _limits())


def gate_due(observations: NDArray[np.int64]) -> NDArray[np.bool_]:
    """
    Return whether a landmark's gate reference is refreshed once it has ``observations``.

    Every observation up to ``2 ** (GATE_BITS + 1) - 1``, then ``2 ** GATE_BITS`` times
    per doubling: the reference holds at least 4/5 of the current information, and
    refreshing it (a fold) costs next to nothing per observation for a landmark seen
    thousands of times. What ``_gate_due`` computes in the kernel.
    """
    n = np.asarray(observations, dtype=np.int64)
    length = np.frexp(np.maximum(n, 1).astype(np.float64))[1].astype(np.int64)  # bit length
    step = np.left_shift(1, np.maximum(length - (GATE_BITS + 1), 0))
    return n % step == 0


def load() -> Optional[Callable[..., FoldResult]]:
    """
    Return the compiled fold, compiling (or loading from numba's disk cache) on first use.

    None when numba is missing, broken for this numpy, or turned off by
    ``LANDMARK_ROS_NUMBA=0``; then callers use the numpy fold. The first call in a
    process costs about 1 s with a warm disk cache and about 10 s without.
    """
    global fold, AVAILABLE, _tried
    if _tried:
        return fold
    _tried = True
    if os.environ.get('LANDMARK_ROS_NUMBA', '1') == '0':
        return None
    try:
        import numba
        jit = numba.njit(cache=True, error_model='numpy', fastmath=False, nogil=True)
        module = sys.modules[__name__]
        # Callees first: a compiled function calls the compiled versions of its
        # callees, which it finds among the module's globals.
        for name in _COMPILED:
            setattr(module, name, jit(getattr(module, name)))
        eye = np.array([[[1.0, 0.0, 1.0]]])
        _compiled_fold(eye, np.zeros((1, 1, 2)), np.zeros((1, 1, 4)), np.ones((1, 1), bool))
    except Exception:   # noqa: BLE001 - any failure: the numpy fold serves
        return None
    fold, AVAILABLE = _compiled_fold, True
    return fold


def compiled(function: Callable[..., Any]) -> Optional[Callable[..., Any]]:
    """
    Return ``function`` compiled as the kernel is (numba, no fast-math), or None.

    None when ``load()`` found no usable numba. For small loops elsewhere in the
    package that must give numpy's bits (``pipeline.rows``' sufficient row check).
    """
    if load() is None:
        return None
    import numba
    return numba.njit(cache=True, error_model='numpy', fastmath=False, nogil=True)(function)


_tried = False

_COMPILED = ('_scale4', '_inverse', '_psd', '_log2_det', '_omega_of', '_congruence', '_split_ci',
             '_source_part', '_fold_step', '_fold_from', '_fold_all', '_fold_one', '_kernel',
             '_mahalanobis_sq', '_refold', '_move', '_add_terms', '_gate_due', '_settle',
             '_pending_position', '_run_kernel', '_settle_kernel')
"""The functions ``load`` compiles, callees before callers."""
