"""
Gaussians: product fusion, covariance intersection, Mahalanobis gate, checks.

Symbols
-------
m1, m2 : means, shape (n,) or (N, n).
P1, P2 : their covariances, shape (n, n) or (N, n, n).
x : a point, shape (n,) or (N, n).
d2 : squared Mahalanobis distance, shape () or (N,).

"""

import math

from landmark_ros.core._arrays import (as_matrices, as_vectors, common_batch_shape, det,
                                       entries_2x2, solve, symmetric_2x2, symmetrise,
                                       to_batch, transpose)
import numpy as np


COVARIANCE_OK = 0
COVARIANCE_NONFINITE = 1
COVARIANCE_ASYMMETRIC = 2
COVARIANCE_NOT_PSD = 3
COVARIANCE_PROBLEMS = {
    COVARIANCE_NONFINITE: 'covariance_nonfinite',
    COVARIANCE_ASYMMETRIC: 'covariance_asymmetric',
    COVARIANCE_NOT_PSD: 'covariance_not_psd',
}
"""Names of the codes ``covariance_status`` returns, as counters and logs use them."""


def _pair(m1, P1, m2, P2):
    n = np.shape(m1)[-1] if np.ndim(m1) else 0
    m1 = as_vectors(m1, n, 'm1')
    m2 = as_vectors(m2, n, 'm2')
    return m1, as_matrices(P1, n, 'P1'), m2, as_matrices(P2, n, 'P2')


def _solve_vec(A, b):
    """Solve ``A x = b`` for vectors ``b`` of shape (n,) or (N, n)."""
    A, b = np.broadcast_arrays(A, b[..., None])
    return solve(A, b)[..., 0]


def fuse(m1, P1, m2, P2):
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
        m, P = _fuse_2x2(m1, entries_2x2(P1), m2, entries_2x2(P2))
        return to_batch(shape, m, 1), to_batch(shape, P, 2)
    S = P1 + P2
    # P1 S^-1 P2 equals P1 - P1 S^-1 P1 and treats both inputs alike.
    P = symmetrise(P1 @ solve(S, np.broadcast_to(P2, S.shape)))
    m = (P2 @ _solve_vec(S, m1)[..., None] + P1 @ _solve_vec(S, m2)[..., None])[..., 0]
    return to_batch(shape, m, 1), to_batch(shape, P, 2)


def information(P):
    """
    Return the information matrix ``P^-1`` (solved, not inverted).

    Parameters
    ----------
    P : ndarray, shape (n, n) or (N, n, n), positive definite
        Covariance matrices.

    Returns
    -------
    ndarray, shape (n, n) or (N, n, n)

    """
    eye = np.broadcast_to(np.eye(P.shape[-1]), P.shape)
    return symmetrise(solve(P, eye))


def fuse_many(ms, Ps):
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


def covariance_intersection_omega(P1, P2):
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


def _omega_2x2(P1, P2):
    # With A = P1^-1 and B = P2^-1 (closed-form inverses), D = A - B:
    # det(B + w D) = det B + w t + w^2 det D, maximised over [0, 1].
    (a1, b1, c1), (a2, b2, c2) = P1, P2
    det1, det2 = a1 * c1 - b1 * b1, a2 * c2 - b2 * b2
    dxx, dxy, dyy = c1 / det1 - c2 / det2, b2 / det2 - b1 / det1, a1 / det1 - a2 / det2
    bxx, bxy, byy = c2 / det2, -b2 / det2, a2 / det2
    t = bxx * dyy + byy * dxx - 2.0 * bxy * dxy
    det_D = dxx * dyy - dxy * dxy
    with np.errstate(divide='ignore', invalid='ignore'):
        stationary = np.clip(np.where(det_D < 0.0, -t / (2.0 * det_D), 0.0), 0.0, 1.0)
    candidates = np.stack([np.zeros_like(t), np.ones_like(t), stationary], axis=-1)
    value = candidates * t[..., None] + candidates ** 2 * det_D[..., None]
    best = np.take_along_axis(candidates, np.argmax(value, axis=-1)[..., None], axis=-1)
    return best[..., 0][()]


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


def covariance_intersection(m1, P1, m2, P2, omega=None):
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


def split_covariance_intersection_omega(P1_ind, P1_dep, P2_ind, P2_dep, grid=16, levels=4):
    """
    Return the split-CI weight ``omega`` in (0, 1) that (nearly) minimises ``det(P)``.

    ``det(P^-1) = det(A + B) / (det A det B)`` with ``A = P1_dep / omega + P1_ind`` and
    ``B = P2_dep / (1 - omega) + P2_ind``; multiplied out it stays finite for singular
    dependent parts. It is maximised on a grid of ``grid - 1`` interior points and
    both ends, then ``levels`` times on a grid of the same size over the two cells
    around the best point: omega within ``(2 / grid)^levels / grid`` of the optimum
    (1.5e-5 by default). Any omega in (0, 1) gives a consistent estimate; this one is
    tight.

    Parameters
    ----------
    P1_ind, P1_dep : array_like, shape (n, n) or (N, n, n)
        Independent and dependent parts of the first covariance.
    P2_ind, P2_dep : array_like, shape (n, n) or (N, n, n)
        Independent and dependent parts of the second covariance.
    grid : int
        Points per grid level.
    levels : int
        Refinements after the first grid.

    Returns
    -------
    omega : float or ndarray, shape () or (N,)

    """
    parts = [np.asarray(P, dtype=np.float64) for P in (P1_ind, P1_dep, P2_ind, P2_dep)]
    shape = np.broadcast_shapes(*(P.shape[:-2] for P in parts))
    if parts[0].shape[-1] == 2:
        (a1i, b1i, c1i), (a1d, b1d, c1d), (a2i, b2i, c2i), (a2d, b2d, c2d) = (
            (e[..., None] for e in entries_2x2(P)) for P in parts)

        def objective(u):
            v = 1.0 - u
            uv = u * v
            with np.errstate(divide='ignore', invalid='ignore'):
                value = _det_2x2(v * a1d + u * a2d + uv * (a1i + a2i),
                                 v * b1d + u * b2d + uv * (b1i + b2i),
                                 v * c1d + u * c2d + uv * (c1i + c2i)) / (
                    _det_2x2(a1d + u * a1i, b1d + u * b1i, c1d + u * c1i)
                    * _det_2x2(a2d + v * a2i, b2d + v * b2i, c2d + v * c2i))
            return np.where(np.isfinite(value), value, -np.inf)
    else:
        P1i, P1d, P2i, P2d = (P[..., None, :, :] for P in parts)

        def objective(u):
            u4, v4 = u[..., None, None], 1.0 - u[..., None, None]
            with np.errstate(divide='ignore', invalid='ignore'):
                value = det(v4 * P1d + u4 * P2d + u4 * v4 * (P1i + P2i)) / (
                    det(P1d + u4 * P1i) * det(P2d + v4 * P2i))
            return np.where(np.isfinite(value), value, -np.inf)

    def best_of(candidates):
        values = objective(candidates)
        index = np.argmax(values, axis=-1)[..., None]
        return (np.take_along_axis(candidates, index, -1),
                np.take_along_axis(values, index, -1))

    edge = 1e-9
    steps = np.arange(1, grid) / grid
    best, _ = best_of(np.broadcast_to(np.concatenate([[edge], steps, [1.0 - edge]]),
                                      shape + (grid + 1,)))
    # Zoom in: each level a grid of the same size over the two cells around the best.
    half_width = 1.0 / grid
    offsets = np.linspace(-1.0, 1.0, grid + 1)
    for _ in range(levels):
        best, _ = best_of(np.clip(best + half_width * offsets, edge, 1.0 - edge))
        half_width *= 2.0 / grid
    return best[..., 0][()]


def split_covariance_intersection(m1, P1_ind, P1_dep, m2, P2_ind, P2_dep, omega=None):
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


def _det_2x2(xx, xy, yy):
    return xx * yy - xy * xy


def _fuse_2x2(m1, P1, m2, P2):
    """Return ``fuse`` for 2x2 covariances given as ``(xx, xy, yy)`` entries."""
    (a1, b1, c1), (a2, b2, c2) = P1, P2
    sa, sb, sc = a1 + a2, b1 + b2, c1 + c2
    det_S = sa * sc - sb * sb
    if not np.all(det_S != 0.0):
        raise np.linalg.LinAlgError('P1 + P2 is singular')
    inv_det = 1.0 / det_S
    # K = P1 S^-1; the fused mean is m1 + K (m2 - m1), the covariance K P2.
    k00, k01 = (a1 * sc - b1 * sb) * inv_det, (b1 * sa - a1 * sb) * inv_det
    k10, k11 = (b1 * sc - c1 * sb) * inv_det, (c1 * sa - b1 * sb) * inv_det
    d0, d1 = m2[..., 0] - m1[..., 0], m2[..., 1] - m1[..., 1]
    m = np.stack([m1[..., 0] + k00 * d0 + k01 * d1, m1[..., 1] + k10 * d0 + k11 * d1], axis=-1)
    xy = 0.5 * (k00 * b2 + k01 * c2 + k10 * a2 + k11 * b2)
    return m, symmetric_2x2(k00 * a2 + k01 * b2, xy, k10 * b2 + k11 * c2)


def _split_ci_2x2(m1, P1i, P1d, m2, P2i, P2d, omega):
    """Return ``split_covariance_intersection`` for 2x2 parts given as entries."""
    u, v = omega, 1.0 - omega
    A = tuple(d / u + i for d, i in zip(P1d, P1i))
    B = tuple(d / v + i for d, i in zip(P2d, P2i))
    sa, sb, sc = A[0] + B[0], A[1] + B[1], A[2] + B[2]
    inv_det = 1.0 / (sa * sc - sb * sb)
    # W1 = B S^-1 (gain on m1), W2 = A S^-1 = I - W1 (gain on m2).
    w00, w01 = (B[0] * sc - B[1] * sb) * inv_det, (B[1] * sa - B[0] * sb) * inv_det
    w10, w11 = (B[1] * sc - B[2] * sb) * inv_det, (B[2] * sa - B[1] * sb) * inv_det
    m = np.stack([w00 * m1[..., 0] + w01 * m1[..., 1] + (1.0 - w00) * m2[..., 0]
                  - w01 * m2[..., 1],
                  w10 * m1[..., 0] + w11 * m1[..., 1] - w10 * m2[..., 0]
                  + (1.0 - w11) * m2[..., 1]], axis=-1)
    # P = W1 A; P_ind = W1 P1i W1^T + W2 P2i W2^T.
    P = (w00 * A[0] + w01 * A[1], 0.5 * (w00 * A[1] + w01 * A[2] + w10 * A[0] + w11 * A[1]),
         w10 * A[1] + w11 * A[2])
    P_ind = tuple(x + y for x, y in zip(_congruence(w00, w01, w10, w11, P1i),
                                        _congruence(1.0 - w00, -w01, -w10, 1.0 - w11, P2i)))
    return (m, symmetric_2x2(*P_ind),
            symmetric_2x2(*(total - ind for total, ind in zip(P, P_ind))))


def _congruence(k00, k01, k10, k11, P):
    """Return the entries of ``K P K^T`` for ``K = [[k00, k01], [k10, k11]]``."""
    a, b, c = P
    r00, r01 = k00 * a + k01 * b, k00 * b + k01 * c
    r10, r11 = k10 * a + k11 * b, k10 * b + k11 * c
    return r00 * k00 + r01 * k01, r00 * k10 + r01 * k11, r10 * k10 + r11 * k11


def mahalanobis_sq(x, mean, P):
    """
    Return the squared Mahalanobis distance ``(x - mean)^T P^-1 (x - mean)``.

    Compare it with ``chi2_threshold`` directly: both are squared quantities.
    Angular components are not wrapped here; pass wrapped differences if needed.

    Parameters
    ----------
    x : array_like, shape (n,) or (N, n)
        The point (or chi-square value) to evaluate.
    mean : array_like, shape (n,) or (N, n)
        Centre of the ellipse.
    P : array_like, shape (n, n) or (N, n, n), positive definite
        Covariance matrices.

    Returns
    -------
    d2 : float or ndarray, shape () or (N,)

    """
    x = np.asarray(x, dtype=np.float64)
    d = x - np.asarray(mean, dtype=np.float64)
    P = as_matrices(P, d.shape[-1], 'P')
    return np.sum(d * _solve_vec(P, d), axis=-1)[()]


def gate(d2, chi2_threshold):
    """
    Return True where a squared Mahalanobis distance passes the gate.

    Parameters
    ----------
    d2 : float or ndarray, shape () or (N,)
        Squared Mahalanobis distances.
    chi2_threshold : float
        From ``chi2_threshold(dof, probability)``.

    Returns
    -------
    bool or ndarray of bool, same shape as ``d2``

    """
    return (np.asarray(d2) <= chi2_threshold)[()]


def chi2_survival(x, dof):
    """
    Return ``P(X > x)`` for a chi-square variable ``X`` with integer ``dof``.

    Uses the closed forms for integer degrees of freedom (no scipy).

    Parameters
    ----------
    x : float
        The point (or chi-square value) to evaluate.
    dof : int, >= 1
        Degrees of freedom.

    Returns
    -------
    float

    """
    if x <= 0.0:
        return 1.0
    half = 0.5 * x
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= half / i
            total += term
        return math.exp(-half) * total
    term, total = 1.0, 1.0
    for i in range(1, (dof - 1) // 2):
        term *= x / (2 * i + 1)
        total += term
    tail = math.sqrt(2.0 * x / math.pi) * math.exp(-half) * total if dof > 1 else 0.0
    return math.erfc(math.sqrt(half)) + tail


def chi2_threshold(dof, probability):
    """
    Return the chi-square quantile: ``P(X <= threshold) = probability``.

    Parameters
    ----------
    dof : int
        Degrees of freedom, 1 to 100 (1 to 3 cover points, observations and poses).
    probability : float
        In (0, 1), e.g. 0.999 to keep 99.9 % of consistent observations.

    Returns
    -------
    float
        The threshold for ``mahalanobis_sq``.

    Raises
    ------
    ValueError
        If ``dof`` or ``probability`` is out of range.

    """
    if isinstance(dof, bool) or dof not in range(1, 101):
        raise ValueError(f'dof must be an integer from 1 to 100, got {dof!r}')
    if not 0.0 < probability < 1.0:
        raise ValueError(f'probability must lie in (0, 1), got {probability!r}')
    dof = int(dof)
    tail = 1.0 - probability
    lo, hi = 0.0, float(dof)
    while chi2_survival(hi, dof) > tail:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if chi2_survival(mid, dof) > tail:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def covariance_status(P, rtol=1e-9):
    """
    Check covariances: finite, symmetric and positive semi-definite.

    Parameters
    ----------
    P : array_like, shape (n, n) or (N, n, n)
        Covariance matrices.
    rtol : float
        Tolerance relative to the largest absolute entry of each matrix, for the
        asymmetry and for the most negative eigenvalue.

    Returns
    -------
    int or ndarray of int, shape () or (N,)
        ``COVARIANCE_OK`` or the first problem found: ``COVARIANCE_NONFINITE``,
        ``COVARIANCE_ASYMMETRIC``, ``COVARIANCE_NOT_PSD``.

    """
    P = np.asarray(P, dtype=np.float64)
    if P.ndim not in (2, 3) or P.shape[-1] != P.shape[-2]:
        raise ValueError(f'P must have shape (n, n) or (N, n, n), got {P.shape}')
    finite = np.all(np.isfinite(P), axis=(-2, -1))
    safe = np.where(finite[..., None, None], P, 0.0)
    scale = np.max(np.abs(safe), axis=(-2, -1))
    tol = rtol * scale
    symmetric = np.max(np.abs(safe - transpose(safe)), axis=(-2, -1)) <= tol
    psd = _smallest_eigenvalue(symmetrise(safe)) >= -tol
    status = np.where(~finite, COVARIANCE_NONFINITE,
                      np.where(~symmetric, COVARIANCE_ASYMMETRIC,
                               np.where(~psd, COVARIANCE_NOT_PSD, COVARIANCE_OK)))
    return status[()]


def _smallest_eigenvalue(P):
    if P.shape[-1] != 2:
        return np.linalg.eigvalsh(P)[..., 0]
    # Closed form for 2x2: several times faster than eigvalsh on small batches.
    a, b, c = P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]
    return 0.5 * (a + c) - np.hypot(0.5 * (a - c), b)


def validate_covariance(P, name='covariance', rtol=1e-9):
    """
    Raise unless every covariance is finite, symmetric and positive semi-definite.

    Parameters
    ----------
    P : array_like, shape (n, n) or (N, n, n)
        Covariance matrices.
    name : str
        Name used in error messages.
    rtol : float
        See ``covariance_status``.

    Returns
    -------
    ndarray
        ``P`` as float64.

    Raises
    ------
    ValueError
        Naming the first bad matrix and its problem.

    """
    status = np.atleast_1d(covariance_status(P, rtol))
    bad = np.flatnonzero(status)
    if bad.size:
        raise ValueError(
            f'{name}: {bad.size} matrix(es) rejected, first at index {bad[0]}: '
            f'{COVARIANCE_PROBLEMS[int(status[bad[0]])]}')
    return np.asarray(P, dtype=np.float64)
