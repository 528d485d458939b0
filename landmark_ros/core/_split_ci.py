"""
Split covariance intersection and its weight (the implementation behind ``gaussian``).

Import these names from ``landmark_ros.core.gaussian``; the symbols and the scaling of
the 2x2 closed forms are described there.

Sources
-------
S. J. Julier and J. K. Uhlmann, "General decentralized data fusion with covariance
intersection", *Handbook of Multisensor Data Fusion*, CRC Press, 2001, ch. 12; H. Li,
F. Nashashibi and M. Yang, "Split covariance intersection filter: theory and its
application to vehicle localization", IEEE T-ITS 14(4), 2013.

"""

import math
from typing import Optional, Tuple, Union

from landmark_ros.core.arrays import (as_matrices, as_vectors, common_batch_shape,
                                      Entries2x2, entries_2x2, inverse_2x2, power_of_4_scale,
                                      solve, symmetric_2x2, symmetrise, to_batch, transpose)
import numpy as np
from numpy.typing import ArrayLike, NDArray


OMEGA_EDGE = 1e-9
"""Split-CI weights are searched in ``[OMEGA_EDGE, 1 - OMEGA_EDGE]`` (open interval)."""

OMEGA_TOLERANCE = 1e-12
"""Newton steps on the split-CI weight stop below this change in omega."""

OMEGA_BRACKET = 1e-6
"""The split-CI Newton search brackets ``[1e-6, 1 - 1e-6]``: closer to an end, the
slope of a singular dependent part's determinant (zero at the end, rounded to about
1e-16 in the inputs) is noise. An optimum outside returns ``OMEGA_EDGE`` (or its
mirror), within 1e-6 of the true one."""

OMEGA_QUADRATIC = 1e-6
"""A split-CI Newton step at most this large, and at most the square of the Newton step
before it, is taken as quadratic convergence: the next step would be about
``step^3 / previous^2``; when that is below ``OMEGA_TOLERANCE`` (and the Newton point is
inside the bracket) the search ends there, one evaluation early (0.25 to 0.8 of 4.5
evaluations on average, depending on the problems). Never right after a jump to an end
or a bisection: there tiny steps can be a slow crawl. Over a million random problems
(scales 1e-4 to 1e4, singular dependent parts) the weight stayed within 1.2e-8 of the
full search's, the larger differences where log det is flat to rounding; any weight in
(0, 1) keeps split CI consistent."""


def _broadcast_entries(P: Entries2x2, shape: Tuple[int, ...]) -> Entries2x2:
    """Return the entries of ``P`` broadcast to ``shape`` (read-only views)."""
    a, b, c = (np.broadcast_to(x, shape) for x in P)
    return a, b, c


def split_covariance_intersection_omega(
        P1_ind: ArrayLike, P1_dep: ArrayLike, P2_ind: ArrayLike,
        P2_dep: ArrayLike) -> Union[float, NDArray[np.float64]]:
    """
    Return the split-CI weight ``omega`` that minimises ``det(P)``.

    ``P^-1 = A^-1 + B^-1`` with ``A = P1_dep / omega + P1_ind`` and
    ``B = P2_dep / (1 - omega) + P2_ind``. For positive semi-definite dependent parts
    each term is a parallel sum, operator concave in omega, so ``log det P^-1`` is
    concave and the optimum unique (an indefinite dependent part breaks this: callers
    project it first, as ``LandmarkMap`` does). Multiplied out,
    ``det(P^-1) = det M / (det E det F)`` with ``M = (1 - w) P1_dep + w P2_dep
    + w (1 - w) (P1_ind + P2_ind)``, ``E = P1_dep + w P1_ind``,
    ``F = P2_dep + (1 - w) P2_ind``: finite for singular dependent parts. For 2x2
    matrices the derivative of its logarithm and the second derivative are closed
    forms (the three determinants are polynomials of degree 4, 2 and 2 in omega), and
    a safeguarded Newton iteration (bisection when a step leaves the bracket) finds
    the root to ``OMEGA_TOLERANCE``, vectorised over all matrices at once, each
    element stopping on its own (so an element's result does not depend on the
    others in the batch); other sizes use a golden-section search on ``log det``.
    When the optimum lies within 1e-6 of an end (one side is far tighter, or has no
    dependent part), ``OMEGA_EDGE`` or ``1 - OMEGA_EDGE`` is returned. Any omega in
    (0, 1) gives a consistent estimate; this one is the tightest. (``LandmarkMap``
    used to search a coarse grid, omega within 1e-3 of the optimum and ``det P``
    within about 1e-6 of its minimum, so its maps differ from today's by that much.)

    Parameters
    ----------
    P1_ind, P1_dep : array_like, shape (n, n) or (N, n, n)
        Independent and dependent parts of the first covariance.
    P2_ind, P2_dep : array_like, shape (n, n) or (N, n, n)
        Independent and dependent parts of the second covariance.

    Returns
    -------
    omega : float or ndarray, shape () or (N,)

    """
    parts = [np.asarray(P, dtype=np.float64) for P in (P1_ind, P1_dep, P2_ind, P2_dep)]
    shape = np.broadcast_shapes(*(P.shape[:-2] for P in parts))
    if parts[0].shape[-1] == 2:
        e1i, e1d, e2i, e2d = (_broadcast_entries(entries_2x2(P), shape) for P in parts)
        return sci_omega_2x2(e1i, e1d, e2i, e2d)[()]
    P1i, P1d, P2i, P2d = (np.broadcast_to(P, shape + P.shape[-2:]) for P in parts)

    def log_f(u):
        w, v = u[..., None, None], 1.0 - u[..., None, None]
        return (np.linalg.slogdet(v * P1d + w * P2d + w * v * (P1i + P2i))[1]
                - np.linalg.slogdet(P1d + w * P1i)[1] - np.linalg.slogdet(P2d + v * P2i)[1])

    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    lo = np.full(shape, OMEGA_EDGE)
    hi = np.full(shape, 1.0 - OMEGA_EDGE)
    for _ in range(64):
        w1 = hi - ratio * (hi - lo)
        w2 = lo + ratio * (hi - lo)
        left = log_f(w1) >= log_f(w2)
        hi = np.where(left, w2, hi)
        lo = np.where(left, lo, w1)
    return (0.5 * (lo + hi))[()]


def _sci_slope(u, table):
    """
    Return d/dw and d2/dw2 of ``log det(P^-1)`` of split CI at ``w = u`` (scaled entries).

    ``table`` holds the scaled entries of ``sci_omega_2x2``, shape (20, N): rows 0-11
    ``P1i``, ``P1d``, ``P2i``, ``P2d``; 12-14 ``Si = P1i + P2i``; 15-17
    ``Dd = P2d - P1d``; 18-19 twice ``det P1i`` and ``det P2i``.
    """
    P1i, P1d, P2i, P2d = table[0:3], table[3:6], table[6:9], table[9:12]
    Si, Dd, two_det_1i, two_det_2i = table[12:15], table[15:18], table[18], table[19]
    v = 1.0 - u
    uv = u * v
    w = v - u
    ma, mb, mc = (v * x + u * y + uv * z for x, y, z in zip(P1d, P2d, Si))   # M
    pa, pb, pc = (x + w * z for x, z in zip(Dd, Si))                          # M'
    ea, eb, ec = (x + u * y for x, y in zip(P1d, P1i))                        # E
    fa, fb, fc = (x + v * y for x, y in zip(P2d, P2i))                        # F
    det_m = ma * mc - mb * mb
    det_e = ea * ec - eb * eb
    det_f = fa * fc - fb * fb
    i_m, i_e, i_f = 1.0 / det_m, 1.0 / det_e, 1.0 / det_f   # three divisions, not six
    r_m = (ma * pc + pa * mc - 2.0 * mb * pb) * i_m
    r_e = (ea * P1i[2] + P1i[0] * ec - 2.0 * eb * P1i[1]) * i_e
    r_f = -(fa * P2i[2] + P2i[0] * fc - 2.0 * fb * P2i[1]) * i_f
    # M'' = -2 (P1i + P2i), E'' = F'' = 0.
    dm2 = 2.0 * (pa * pc - pb * pb) - 2.0 * (ma * Si[2] + Si[0] * mc - 2.0 * mb * Si[1])
    slope = r_m - r_e - r_f
    curvature = (dm2 * i_m - r_m * r_m - two_det_1i * i_e + r_e * r_e
                 - two_det_2i * i_f + r_f * r_f)
    return slope, curvature


def sci_omega_2x2(P1i: Entries2x2, P1d: Entries2x2, P2i: Entries2x2, P2d: Entries2x2,
                  start: Optional[NDArray[np.float64]] = None) -> NDArray[np.float64]:
    """
    Return ``split_covariance_intersection_omega`` for 2x2 parts given as entries.

    Safeguarded Newton on the slope of ``log det P^-1`` (decreasing: the function is
    concave), from ``start``. The bracket starts as ``[1e-6, 1 - 1e-6]``; a step out
    of it first goes to that end, where a slope pointing outwards means the optimum is
    at the end (``OMEGA_EDGE`` or ``1 - OMEGA_EDGE`` is returned); a step out of an
    evaluated bracket bisects. Each element stops on its own once a Newton step is
    below ``OMEGA_TOLERANCE``, once quadratic convergence puts the next one below it
    (``OMEGA_QUADRATIC``) or once the bracket is narrower than ``OMEGA_TOLERANCE`` (at
    its middle if the Newton point is outside: where the slope is rounding noise), so
    its result depends on its inputs and ``start`` only.

    Parameters
    ----------
    P1i, P1d, P2i, P2d : tuple of ndarray, each entry shape (N,) or ()
        ``(xx, xy, yy)`` of the four parts, broadcast to one shape.
    start : ndarray, shape (N,) or (), optional
        First iterate (a previous optimum of a similar problem saves iterations);
        0.5 by default.

    Returns
    -------
    ndarray, shape (N,) or ()

    """
    s = power_of_4_scale(P1i[0] + P1d[0], P1i[2] + P1d[2], P2i[0] + P2d[0], P2i[2] + P2d[2])
    shape = s.shape
    size = s.size
    # Every per-element input in one table, so that dropping the finished elements
    # is one indexing operation: rows 0-11 the four parts, 12-17 Si and Dd, 18-19
    # twice the independent determinants.
    table = np.empty((20, size))
    for k, x in enumerate((*P1i, *P1d, *P2i, *P2d)):
        table[k] = np.broadcast_to(x / s, shape).reshape(-1)
    table[12:15] = table[0:3] + table[6:9]
    table[15:18] = table[9:12] - table[3:6]
    table[18] = 2.0 * (table[0] * table[2] - table[1] * table[1])
    table[19] = 2.0 * (table[6] * table[8] - table[7] * table[7])
    edge_lo, edge_hi = OMEGA_BRACKET, 1.0 - OMEGA_BRACKET
    omega = np.full(size, 0.5)
    u = np.full(size, 0.5) if start is None else np.clip(
        np.broadcast_to(start, shape).reshape(-1), edge_lo, edge_hi)
    lo, hi = np.full(size, edge_lo), np.full(size, edge_hi)
    lo_seen, hi_seen = np.zeros(size, bool), np.zeros(size, bool)
    last = np.full(size, np.nan)      # the previous Newton step's size (NaN: none)
    active = np.arange(size)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        for _ in range(200):
            slope, curvature = _sci_slope(u, table)
            positive = slope > 0.0
            lo_seen |= positive
            hi_seen |= ~positive
            lo = np.where(positive, u, lo)
            hi = np.where(positive, hi, u)
            step = slope / curvature
            new = u - step
            # The optimum at an end: the slope there points outwards.
            at_lo = (u <= edge_lo) & ~positive
            at_hi = (u >= edge_hi) & positive
            # A step below the tolerance ends the search at the Newton point (which
            # may round onto the bracket's end).
            collapsed = hi - lo <= OMEGA_TOLERANCE
            done = (np.abs(step) <= OMEGA_TOLERANCE) | collapsed
            # Or when quadratic convergence puts the next step below it.
            size_ = np.abs(step)
            done |= ((size_ <= OMEGA_QUADRATIC) & (size_ <= last * last)
                     & (size_ * size_ * size_ <= OMEGA_TOLERANCE * last * last)
                     & (new > lo) & (new < hi))
            # A collapsed bracket ends at the Newton point only if that lies in it: where
            # the slope is rounding noise the point can be anywhere, even past 1.
            stray = collapsed & ~((new >= lo) & (new <= hi))
            result = np.where(at_lo, OMEGA_EDGE, np.where(at_hi, 1.0 - OMEGA_EDGE, np.where(
                stray, 0.5 * (lo + hi), new)))
            failed = ~np.isfinite(slope)
            done |= at_lo | at_hi | failed
            result = np.where(failed, 0.5, result)
            # Out of the bracket: to an end not evaluated yet, else bisect.
            below, above = ~(new > lo), ~(new < hi)
            new = np.where(below & ~lo_seen, edge_lo, np.where(above & ~hi_seen, edge_hi, new))
            new = np.where((below & lo_seen) | (above & hi_seen), 0.5 * (lo + hi), new)
            # The step's size for the next test; NaN (no test) after a jump or a bisection.
            last = np.where(below | above, np.nan, size_)
            omega[active[done]] = result[done]
            keep = ~done
            if not keep.any():
                break
            if keep.all():
                u = new
                continue
            active, u, lo, hi = active[keep], new[keep], lo[keep], hi[keep]
            lo_seen, hi_seen, last = lo_seen[keep], hi_seen[keep], last[keep]
            table = table[:, keep]
        else:
            omega[active] = u
    return omega.reshape(shape)


def split_covariance_intersection(
        m1: ArrayLike, P1_ind: ArrayLike, P1_dep: ArrayLike, m2: ArrayLike, P2_ind: ArrayLike,
        P2_dep: ArrayLike, omega: Optional[ArrayLike] = None
) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """
    Fuse two estimates whose errors have independent and correlated parts (split CI).

    Each covariance is the sum of an independent part (uncorrelated with anything
    else) and a dependent part (correlated in an unknown way). The dependent parts
    are bounded as covariance intersection does (``P1_dep / omega``,
    ``P2_dep / (1 - omega)``), the independent parts are fused as information.

    Parameters
    ----------
    m1 : array_like, shape (n,) or (N, n)
        Mean of the first estimate.
    P1_ind, P1_dep : array_like, shape (n, n) or (N, n, n)
        Independent and dependent parts of its covariance.
    m2 : array_like, shape (n,) or (N, n)
        Mean of the second estimate.
    P2_ind, P2_dep : array_like, shape (n, n) or (N, n, n)
        Independent and dependent parts of its covariance.
    omega : float or array_like, shape () or (N,), optional
        Weight in (0, 1); by default ``split_covariance_intersection_omega``.

    Returns
    -------
    m : ndarray, shape (n,) or (N, n)
    P_ind : ndarray, shape (n, n) or (N, n, n)
        Independent part of the fused covariance.
    P_dep : ndarray, shape (n, n) or (N, n, n)
        Dependent part; the fused covariance is ``P_ind + P_dep``.

    Raises
    ------
    ValueError
        If ``omega`` is not strictly between 0 and 1.

    """
    n = np.shape(m1)[-1]
    m1, m2 = as_vectors(m1, n, 'm1'), as_vectors(m2, n, 'm2')
    P1i, P1d = as_matrices(P1_ind, n, 'P1_ind'), as_matrices(P1_dep, n, 'P1_dep')
    P2i, P2d = as_matrices(P2_ind, n, 'P2_ind'), as_matrices(P2_dep, n, 'P2_dep')
    if omega is None:
        omega = split_covariance_intersection_omega(P1i, P1d, P2i, P2d)
    omega = np.asarray(omega, dtype=np.float64)
    if not np.all((omega > 0.0) & (omega < 1.0)):
        raise ValueError(f'omega must lie strictly between 0 and 1, got {omega}')
    shape = np.broadcast_shapes(common_batch_shape([m1, m2], [P1i, P1d, P2i, P2d]),
                                omega.shape)
    if n == 2:
        m, P_ind, P_dep = _split_ci_2x2(m1, entries_2x2(P1i), entries_2x2(P1d), m2,
                                        entries_2x2(P2i), entries_2x2(P2d), omega)
        return to_batch(shape, m, 1), to_batch(shape, P_ind, 2), to_batch(shape, P_dep, 2)
    w = omega[..., None, None]
    A = P1d / w + P1i
    B = P2d / (1.0 - w) + P2i
    S = A + B
    # Covariance form: P = A S^-1 B, gains W1 = B S^-1 on m1 and W2 = A S^-1 on m2.
    W1 = transpose(solve(S, transpose(np.broadcast_to(B, S.shape))))
    W2 = transpose(solve(S, transpose(np.broadcast_to(A, S.shape))))
    m = (W1 @ m1[..., None] + W2 @ m2[..., None])[..., 0]
    P = symmetrise(W2 @ B)
    P_ind = symmetrise(W1 @ P1i @ transpose(W1) + W2 @ P2i @ transpose(W2))
    return to_batch(shape, m, 1), to_batch(shape, P_ind, 2), to_batch(shape, P - P_ind, 2)


def _split_ci_2x2(m1, P1i, P1d, m2, P2i, P2d, omega):
    """Return ``split_covariance_intersection`` for 2x2 parts given as entries."""
    m, P_ind, P_dep = split_ci_2x2_entries((m1[..., 0], m1[..., 1]), P1i, P1d,
                                           (m2[..., 0], m2[..., 1]), P2i, P2d, omega)
    return np.stack(m, axis=-1), symmetric_2x2(*P_ind), symmetric_2x2(*P_dep)


def split_ci_2x2_entries(
        m1: Tuple[NDArray[np.float64], NDArray[np.float64]], P1i: Entries2x2, P1d: Entries2x2,
        m2: Tuple[NDArray[np.float64], NDArray[np.float64]], P2i: Entries2x2, P2d: Entries2x2,
        omega: Optional[NDArray[np.float64]]
) -> Tuple[Tuple[NDArray[np.float64], NDArray[np.float64]], Entries2x2, Entries2x2]:
    """
    Return split CI of 2x2 parts given as entries, as entries.

    Parameters
    ----------
    m1, m2 : tuple of ndarray
        ``(x, y)`` of the means, each shape () or (N,) [m].
    P1i, P1d, P2i, P2d : tuple of ndarray
        ``(xx, xy, yy)`` of the independent and dependent parts [m^2].
    omega : ndarray, shape () or (N,), or None
        Weight in (0, 1). None: the two dependent parts are independent of each other
        (no weight: the product of Gaussians, the parts kept apart).

    Returns
    -------
    m : tuple of ndarray
        ``(x, y)`` of the fused mean.
    P_ind, P_dep : tuple of ndarray
        ``(xx, xy, yy)`` of the fused parts.

    Notes
    -----
    With ``A = P1d / omega + P1i`` and ``B = P2d / (1 - omega) + P2i``, the gains
    ``W1 = P A^-1 = B (A + B)^-1`` and ``W2 = P B^-1 = A (A + B)^-1``: one inverse, of
    ``A + B`` (which stays regular when ``A`` or ``B`` is singular). Both parts are
    congruences, ``P_ind = W1 P1i W1^T + W2 P2i W2^T`` and
    ``P_dep = W1 (P1d / omega) W1^T + W2 (P2d / (1 - omega)) W2^T``: positive
    semi-definite by construction, each accurate on its own scale.

    """
    s = power_of_4_scale(P1i[0] + P1d[0], P1i[2] + P1d[2], P2i[0] + P2d[0], P2i[2] + P2d[2])
    P1i, P1d, P2i, P2d = (_divide(P, s) for P in (P1i, P1d, P2i, P2d))
    u, v = (1.0, 1.0) if omega is None else (omega, 1.0 - omega)
    D1 = _divide(P1d, u)
    D2 = _divide(P2d, v)
    A = (D1[0] + P1i[0], D1[1] + P1i[1], D1[2] + P1i[2])
    B = (D2[0] + P2i[0], D2[1] + P2i[1], D2[2] + P2i[2])
    Si = inverse_2x2(*(x + y for x, y in zip(A, B)))
    # W1 = B (A + B)^-1, W2 = A (A + B)^-1 (W1 + W2 = I).
    w1 = _product(B, Si)
    w2 = _product(A, Si)
    m = (w1[0] * m1[0] + w1[1] * m1[1] + w2[0] * m2[0] + w2[1] * m2[1],
         w1[2] * m1[0] + w1[3] * m1[1] + w2[2] * m2[0] + w2[3] * m2[1])
    P_ind = _sum_times(_congruence(*w1, P1i), _congruence(*w2, P2i), s)
    P_dep = _sum_times(_congruence(*w1, D1), _congruence(*w2, D2), s)
    return m, P_ind, P_dep


def _divide(P: Entries2x2, s: Union[float, NDArray[np.float64]]) -> Entries2x2:
    """Return the entries of ``P / s``."""
    return P[0] / s, P[1] / s, P[2] / s


def _sum_times(P: Entries2x2, Q: Entries2x2, s: NDArray[np.float64]) -> Entries2x2:
    """Return the entries of ``(P + Q) s``."""
    return (P[0] + Q[0]) * s, (P[1] + Q[1]) * s, (P[2] + Q[2]) * s


def _product(
        P: Entries2x2, Q: Entries2x2
) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Return the entries ``(k00, k01, k10, k11)`` of ``P Q`` for symmetric 2x2 entries."""
    return (P[0] * Q[0] + P[1] * Q[1], P[0] * Q[1] + P[1] * Q[2],
            P[1] * Q[0] + P[2] * Q[1], P[1] * Q[1] + P[2] * Q[2])


def _congruence(k00: NDArray[np.float64], k01: NDArray[np.float64], k10: NDArray[np.float64],
                k11: NDArray[np.float64], P: Entries2x2) -> Entries2x2:
    """Return the entries of ``K P K^T`` for ``K = [[k00, k01], [k10, k11]]``."""
    a, b, c = P
    r00, r01 = k00 * a + k01 * b, k00 * b + k01 * c
    r10, r11 = k10 * a + k11 * b, k10 * b + k11 * c
    return r00 * k00 + r01 * k01, r00 * k10 + r01 * k11, r10 * k10 + r11 * k11
