"""
Gaussians: product fusion, covariance intersection and split CI, with their weights.

Symbols
-------
m1, m2 : means, shape (n,) or (N, n).
P1, P2 : their covariances, shape (n, n) or (N, n, n).
x : a point, shape (n,) or (N, n).
d2 : squared Mahalanobis distance, shape () or (N,).
omega : a covariance-intersection weight in [0, 1], shape () or (N,).

Scale
-----
Every closed form for 2x2 matrices (determinant, inverse, solve, Mahalanobis
distance, ``fuse``, covariance intersection and split CI with their weights) first
divides the matrices by a power of 4 near their largest variance (exact in floating
point), so nothing over- or underflows for covariances in the accepted range
(``MIN_VARIANCE`` to ``MAX_VARIANCE``, condition number up to ``MAX_CONDITION``,
checked by ``covariance_range_status``) and results keep about
``-log10(MAX_CONDITION * 2.2e-16)`` = 6.7 significant digits in the worst case there.
Outside the range results stay finite as long as they are representable.

Split CI (``split_covariance_intersection``, its weight, the 2x2 entry forms) is
implemented in ``core._split_ci`` and imported here: use it from this module.

"""

import math
from typing import Optional, Tuple, Union

# OMEGA_BRACKET and OMEGA_QUADRATIC are imported by fusion.compiled from here.
from landmark_ros.core._split_ci import (_divide, OMEGA_BRACKET, OMEGA_EDGE,  # noqa: F401
                                         OMEGA_QUADRATIC, OMEGA_TOLERANCE, sci_omega_2x2,
                                         split_ci_2x2_entries, split_covariance_intersection,
                                         split_covariance_intersection_omega)
from landmark_ros.core.arrays import (as_matrices, as_vectors, common_batch_shape,
                                      Entries2x2, entries_2x2, inverse_2x2, power_of_4_scale,
                                      solve, solve_vectors, symmetric_2x2, symmetrise, to_batch)
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['OMEGA_EDGE', 'OMEGA_TOLERANCE', 'ci_2x2', 'covariance_intersection',
           'covariance_intersection_omega', 'fuse', 'fuse_2x2', 'fuse_many', 'information',
           'sci_omega_2x2', 'split_ci_2x2_entries', 'split_covariance_intersection',
           'split_covariance_intersection_omega']


def _pair(m1, P1, m2, P2):
    n = np.shape(m1)[-1] if np.ndim(m1) else 0
    m1 = as_vectors(m1, n, 'm1')
    m2 = as_vectors(m2, n, 'm2')
    return m1, as_matrices(P1, n, 'P1'), m2, as_matrices(P2, n, 'P2')


def fuse(m1: ArrayLike, P1: ArrayLike, m2: ArrayLike,
         P2: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Fuse two independent Gaussian estimates of the same quantity (their product).

    Computed in covariance form, so one of ``P1``, ``P2`` may be singular (an exactly
    known quantity) as long as ``P1 + P2`` is invertible. The result is symmetric in
    its two arguments.

    Parameters
    ----------
    m1 : array_like, shape (n,) or (N, n)
        Mean of the first estimate.
    P1 : array_like, shape (n, n) or (N, n, n)
        Covariance of the first estimate.
    m2 : array_like, shape (n,) or (N, n)
        Mean of the second estimate.
    P2 : array_like, shape (n, n) or (N, n, n)
        Covariance of the second estimate.

    Returns
    -------
    m : ndarray, shape (n,) or (N, n)
    P : ndarray, shape (n, n) or (N, n, n)

    Raises
    ------
    numpy.linalg.LinAlgError
        If ``P1 + P2`` is singular.

    """
    m1, P1, m2, P2 = _pair(m1, P1, m2, P2)
    shape = common_batch_shape([m1, m2], [P1, P2])
    if m1.shape[-1] == 2:
        m, P = fuse_2x2(m1, entries_2x2(P1), m2, entries_2x2(P2))
        return to_batch(shape, m, 1), to_batch(shape, P, 2)
    S = P1 + P2
    # P1 S^-1 P2 equals P1 - P1 S^-1 P1 and treats both inputs alike.
    P = symmetrise(P1 @ solve(S, np.broadcast_to(P2, S.shape)))
    m = (P2 @ solve_vectors(S, m1)[..., None] + P1 @ solve_vectors(S, m2)[..., None])[..., 0]
    return to_batch(shape, m, 1), to_batch(shape, P, 2)


def information(P: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return the information matrix ``P^-1`` (closed form for 2x2, else solved), scaled.

    Parameters
    ----------
    P : ndarray, shape (n, n) or (N, n, n), positive definite
        Covariance matrices.

    Returns
    -------
    ndarray, shape (n, n) or (N, n, n)
        Exactly symmetric.

    """
    if P.shape[-1] == 2:
        return symmetric_2x2(*inverse_2x2(*entries_2x2(P)))
    eye = np.broadcast_to(np.eye(P.shape[-1]), P.shape)
    return symmetrise(solve(P, eye))


def fuse_many(ms: ArrayLike,
              Ps: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Fuse ``N`` independent estimates of one quantity by summing their information.

    Parameters
    ----------
    ms : array_like, shape (N, n)
        Means of the estimates.
    Ps : array_like, shape (N, n, n), each positive definite
        Their covariances.

    Returns
    -------
    m : ndarray, shape (n,)
    P : ndarray, shape (n, n)

    Raises
    ------
    ValueError
        If there is no estimate or the shapes do not match.

    """
    ms = np.asarray(ms, dtype=np.float64)
    if ms.ndim != 2 or ms.shape[0] == 0:
        raise ValueError(f'ms must have shape (N, n) with N >= 1, got {ms.shape}')
    Ps = as_matrices(Ps, ms.shape[1], 'Ps')
    if Ps.shape[0:1] != ms.shape[0:1]:
        raise ValueError(f'ms and Ps disagree on N: {ms.shape} and {Ps.shape}')
    Y = information(Ps)
    P = information(Y.sum(axis=0))
    m = P @ (Y @ ms[..., None]).sum(axis=0)[..., 0]
    return m, P


def covariance_intersection_omega(P1: ArrayLike,
                                  P2: ArrayLike) -> Union[float, NDArray[np.float64]]:
    """
    Return the weight ``omega`` in [0, 1] that minimises ``det(P)`` in CI.

    ``P^-1 = omega P1^-1 + (1 - omega) P2^-1``. ``log det P^-1`` is concave in omega,
    so the optimum is unique: in closed form for 2x2 matrices, by golden-section search
    otherwise.

    Parameters
    ----------
    P1 : array_like, shape (n, n) or (N, n, n), positive definite
        Covariance of the first estimate.
    P2 : array_like, shape (n, n) or (N, n, n), positive definite
        Covariance of the second estimate.

    Returns
    -------
    omega : float or ndarray, shape () or (N,)

    """
    P1 = np.asarray(P1, dtype=np.float64)
    P2 = np.asarray(P2, dtype=np.float64)
    if P1.shape[-1] == 2:
        return _omega_2x2(entries_2x2(P1), entries_2x2(P2))
    A, B = np.broadcast_arrays(information(P1), information(P2))
    return _omega_golden(A, B)


def ci_2x2(
        m1: NDArray[np.float64], P1: Entries2x2, m2: NDArray[np.float64], P2: Entries2x2,
        omega: Optional[NDArray[np.float64]] = None
) -> Optional[Tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """
    Return covariance intersection of 2x2 entries in information form, or None.

    ``P^-1 = omega A + (1 - omega) B`` with ``A = P1^-1``, ``B = P2^-1`` (scaled closed
    forms, see ``fuse_2x2``); omega 0 and 1 return the inputs exactly.

    Parameters
    ----------
    m1, m2 : ndarray, shape (2,) or (N, 2)
        Means [m].
    P1, P2 : tuple of ndarray
        ``(xx, xy, yy)`` of the covariances [m^2].
    omega : ndarray, shape () or (N,), optional
        Weight of the first estimate in [0, 1]; by default the one minimising
        ``det P``, from the same inverses (``covariance_intersection_omega``).

    Returns
    -------
    tuple or None
        ``(m, P)``; None when an input is singular (relative determinant below
        1e-13), for which ``covariance_intersection`` takes its general path.

    """
    s = power_of_4_scale(P1[0], P1[2], P2[0], P2[2])
    p1, p2 = _divide(P1, s), _divide(P2, s)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        if not np.all((p1[0] * p1[2] - p1[1] * p1[1] > 1e-13 * p1[0] * p1[2])
                      & (p2[0] * p2[2] - p2[1] * p2[1] > 1e-13 * p2[0] * p2[2])):
            return None
        one = np.ones_like(s)
        A, B = inverse_2x2(*p1, one), inverse_2x2(*p2, one)
        if omega is None:
            omega = np.asarray(_omega_of_information(A, B))
        u, v = omega, 1.0 - omega
        Y = tuple(u * a + v * b for a, b in zip(A, B))
        P = inverse_2x2(*Y)
        x1, z1, x2, z2 = m1[..., 0], m1[..., 1], m2[..., 0], m2[..., 1]
        y0 = u * (A[0] * x1 + A[1] * z1) + v * (B[0] * x2 + B[1] * z2)
        y1 = u * (A[1] * x1 + A[2] * z1) + v * (B[1] * x2 + B[2] * z2)
        m = np.stack([P[0] * y0 + P[1] * y1, P[1] * y0 + P[2] * y1], axis=-1)
    P = symmetric_2x2(*(x * s for x in P))
    first = (omega >= 1.0)[..., None]
    second = (omega <= 0.0)[..., None]
    P1_full, P2_full = symmetric_2x2(*P1), symmetric_2x2(*P2)
    m = np.where(first, m1, np.where(second, m2, m))
    P = np.where(first[..., None], P1_full, np.where(second[..., None], P2_full, P))
    return m, P


def _omega_2x2(P1, P2):
    # Both scaled by one power of 4 (omega does not depend on a common scale).
    s = power_of_4_scale(P1[0], P1[2], P2[0], P2[2])
    (a1, b1, c1), (a2, b2, c2) = ((x / s for x in P) for P in (P1, P2))
    one = np.ones_like(s)
    return _omega_of_information(inverse_2x2(a1, b1, c1, one), inverse_2x2(a2, b2, c2, one))


def _omega_of_information(A, B):
    # With A = P1^-1 and B = P2^-1 as entries, D = A - B:
    # det(B + w D) = det B + w t + w^2 det D, maximised over [0, 1].
    (axx, axy, ayy), (bxx, bxy, byy) = A, B
    dxx, dxy, dyy = axx - bxx, axy - bxy, ayy - byy
    t = bxx * dyy + byy * dxx - 2.0 * bxy * dxy
    det_D = dxx * dyy - dxy * dxy
    with np.errstate(divide='ignore', invalid='ignore'):
        stationary = np.clip(np.where(det_D < 0.0, -t / (2.0 * det_D), 0.0), 0.0, 1.0)
        # w t + w^2 det D at the candidates 0, 1 and the stationary point, NaN as -inf;
        # the first of the largest wins.
        at_0 = 0.0 * t + 0.0 * det_D
        at_1 = t + det_D
        at_s = stationary * t + (stationary * stationary) * det_D
    at_0, at_1, at_s = (np.where(x == x, x, -np.inf) for x in (at_0, at_1, at_s))
    best = np.where(at_1 > at_0, 1.0, 0.0)
    return np.where(at_s > np.maximum(at_0, at_1), stationary, best)[()]


def _omega_golden(A, B, iterations=80):
    def log_det(w):
        return np.linalg.slogdet(w[..., None, None] * A + (1.0 - w[..., None, None]) * B)[1]

    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    lo = np.zeros(A.shape[:-2])
    hi = np.ones(A.shape[:-2])
    for _ in range(iterations):
        w1 = hi - ratio * (hi - lo)
        w2 = lo + ratio * (hi - lo)
        left = log_det(w1) >= log_det(w2)
        hi = np.where(left, w2, hi)
        lo = np.where(left, lo, w1)
    return (0.5 * (lo + hi))[()]


def covariance_intersection(
        m1: ArrayLike, P1: ArrayLike, m2: ArrayLike, P2: ArrayLike,
        omega: Optional[ArrayLike] = None) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Fuse two estimates whose cross-correlation is unknown (covariance intersection).

    ``P^-1 = omega P1^-1 + (1 - omega) P2^-1`` and
    ``P^-1 m = omega P1^-1 m1 + (1 - omega) P2^-1 m2``: consistent whatever the
    correlation between the two errors.

    Parameters
    ----------
    m1 : array_like, shape (n,) or (N, n)
        Mean of the first estimate.
    P1 : array_like, shape (n, n) or (N, n, n), positive definite
        Covariance of the first estimate.
    m2 : array_like, shape (n,) or (N, n)
        Mean of the second estimate.
    P2 : array_like, shape (n, n) or (N, n, n), positive definite
        Covariance of the second estimate.
    omega : float or array_like, shape () or (N,), optional
        Weight of the first estimate in [0, 1]; by default the one that minimises
        ``det(P)`` (``covariance_intersection_omega``).

    Returns
    -------
    m : ndarray, shape (n,) or (N, n)
    P : ndarray, shape (n, n) or (N, n, n)

    Raises
    ------
    ValueError
        If ``omega`` is outside [0, 1].

    """
    m1, P1, m2, P2 = _pair(m1, P1, m2, P2)
    if omega is None:
        omega = covariance_intersection_omega(P1, P2)
    omega = np.asarray(omega, dtype=np.float64)
    if np.any((omega < 0.0) | (omega > 1.0)) or not np.all(np.isfinite(omega)):
        raise ValueError(f'omega must lie in [0, 1], got {omega}')
    if m1.shape[-1] == 2:
        fast = ci_2x2(m1, entries_2x2(P1), m2, entries_2x2(P2), omega)
        if fast is not None:
            shape = np.broadcast_shapes(common_batch_shape([m1, m2], [P1, P2]), omega.shape)
            return to_batch(shape, fast[0], 1), to_batch(shape, fast[1], 2)
    # CI is the product of the two Gaussians with covariances inflated by 1/omega.
    w = omega[..., None, None]
    with np.errstate(divide='ignore', invalid='ignore'):
        inner = (omega > 0.0) & (omega < 1.0)
        w_safe = np.where(inner[..., None, None], w, 0.5)
        m, P = fuse(m1, P1 / w_safe, m2, P2 / (1.0 - w_safe))
    first = (omega >= 1.0)[..., None]
    second = (omega <= 0.0)[..., None]
    m = np.where(first, m1, np.where(second, m2, m))
    P = np.where(first[..., None], P1, np.where(second[..., None], P2, P))
    shape = np.broadcast_shapes(common_batch_shape([m1, m2], [P1, P2]), omega.shape)
    return to_batch(shape, m, 1), to_batch(shape, P, 2)


def fuse_2x2(m1: NDArray[np.float64], P1: Entries2x2, m2: NDArray[np.float64],
             P2: Entries2x2) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return ``fuse`` for 2x2 covariances given as ``(xx, xy, yy)`` entries.

    ``m1``, ``m2`` have shape (2,) or (N, 2); returns ``m`` (N, 2) and ``P`` (N, 2, 2)
    (or single items). Raises ``numpy.linalg.LinAlgError`` if ``P1 + P2`` is singular.

    Information form: a closed-form 2x2 inverse is its adjugate over its determinant,
    so its error is a common factor ``1 + delta`` (``|delta|`` about the condition
    number times 2.2e-16), which keeps the thin direction of an ill-conditioned input
    exact where the covariance form ``P1 (P1 + P2)^-1 P2`` would lose it. Rows with a
    singular input (an exactly known direction) use the covariance form.
    """
    s = power_of_4_scale(P1[0] + P2[0], P1[2] + P2[2])
    p1 = tuple(x / s for x in P1)
    p2 = tuple(x / s for x in P2)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        Y1, Y2 = inverse_2x2(*p1), inverse_2x2(*p2)
        Y = tuple(x + y for x, y in zip(Y1, Y2))
        P = inverse_2x2(*Y)
        y0 = Y1[0] * m1[..., 0] + Y1[1] * m1[..., 1] + Y2[0] * m2[..., 0] + Y2[1] * m2[..., 1]
        y1 = Y1[1] * m1[..., 0] + Y1[2] * m1[..., 1] + Y2[1] * m2[..., 0] + Y2[2] * m2[..., 1]
        m = np.stack([P[0] * y0 + P[1] * y1, P[1] * y0 + P[2] * y1], axis=-1)
        # Relative determinants det / (xx yy), 1 / condition number and more: below
        # 1e-13 (far outside the accepted range) the input counts as singular.
        singular = ~((p1[0] * p1[2] - p1[1] * p1[1] > 1e-13 * p1[0] * p1[2])
                     & (p2[0] * p2[2] - p2[1] * p2[1] > 1e-13 * p2[0] * p2[2]))
    P = symmetric_2x2(*(x * s for x in P))
    if not singular.any():
        return m, P
    shape = np.broadcast_shapes(m.shape[:-1], singular.shape)
    m = np.array(np.broadcast_to(m, shape + (2,))).reshape(-1, 2)
    P = np.array(np.broadcast_to(P, shape + (2, 2))).reshape(-1, 2, 2)
    index = np.flatnonzero(np.broadcast_to(singular, shape))

    def pick(x, tail=()):
        return np.broadcast_to(x, shape + tail).reshape((-1,) + tail)[index]

    m_cov, P_cov = _fuse_2x2_covariance_form(
        pick(m1, (2,)), tuple(pick(x) for x in p1), pick(m2, (2,)), tuple(pick(x) for x in p2))
    m[index] = m_cov
    P[index] = P_cov * pick(s)[:, None, None]
    return m.reshape(shape + (2,)), P.reshape(shape + (2, 2))


def _fuse_2x2_covariance_form(m1, P1, m2, P2):
    """Return ``fuse`` in covariance form for scaled 2x2 entries (one input may be singular)."""
    (a1, b1, c1), (a2, b2, c2) = P1, P2
    sa, sb, sc = a1 + a2, b1 + b2, c1 + c2
    det_S = sa * sc - sb * sb
    if not np.all(det_S != 0.0):
        raise np.linalg.LinAlgError('P1 + P2 is singular')
    inv_det = 1.0 / det_S
    # K = P1 S^-1 (dimensionless); the fused mean is m1 + K (m2 - m1), the covariance K P2.
    k00, k01 = (a1 * sc - b1 * sb) * inv_det, (b1 * sa - a1 * sb) * inv_det
    k10, k11 = (b1 * sc - c1 * sb) * inv_det, (c1 * sa - b1 * sb) * inv_det
    d0, d1 = m2[..., 0] - m1[..., 0], m2[..., 1] - m1[..., 1]
    m = np.stack([m1[..., 0] + k00 * d0 + k01 * d1, m1[..., 1] + k10 * d0 + k11 * d1], axis=-1)
    xy = 0.5 * (k00 * b2 + k01 * c2 + k10 * a2 + k11 * b2)
    return m, symmetric_2x2(k00 * a2 + k01 * b2, xy, k10 * b2 + k11 * c2)
