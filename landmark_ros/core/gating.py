"""
Mahalanobis distance and the chi-square gate.

The textbook chapter names the chi-square test for data association and then leaves
it out; here it is: ``mahalanobis_sq`` of an innovation against its covariance,
compared by ``gate`` with ``chi2_threshold(dof, probability)``. 2x2 covariances take
the scaled closed form (see ``core.gaussian``, Scale); larger ones a solve.
"""

from typing import Union

from landmark_ros.core.arrays import (as_matrices, entries_2x2, mahalanobis_sq_2x2,
                                      matrix_scale, solve_vectors)
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special


def mahalanobis_sq(x: ArrayLike, mean: ArrayLike,
                   P: ArrayLike) -> Union[float, NDArray[np.float64]]:
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
    if d.shape[-1] == 2:
        a, b, c = entries_2x2(P)
        return mahalanobis_sq_2x2(d[..., 0], d[..., 1], a, b, c)[()]
    s = matrix_scale(P)
    d = d / np.sqrt(s)[..., None]
    return np.sum(d * solve_vectors(P / s[..., None, None], d), axis=-1)[()]


def gate(d2: ArrayLike, chi2_threshold: float) -> Union[np.bool_, NDArray[np.bool_]]:
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


def chi2_survival(x: float, dof: int) -> float:
    """
    Return ``P(X > x)`` for a chi-square variable ``X`` with integer ``dof``.

    ``scipy.special.chdtrc`` (the regularised upper incomplete gamma function).

    Parameters
    ----------
    x : float
        The point (or chi-square value) to evaluate.
    dof : int, >= 1
        Degrees of freedom.

    Returns
    -------
    float
        1.0 for ``x <= 0``.

    """
    if x <= 0.0:
        return 1.0
    return float(special.chdtrc(dof, x))


def chi2_threshold(dof: int, probability: float) -> float:
    """
    Return the chi-square quantile: ``P(X <= threshold) = probability``.

    ``scipy.special.chdtri`` on the upper tail ``1 - probability``, the inverse of
    ``chi2_survival``.

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
    return float(special.chdtri(int(dof), 1.0 - probability))


_OMEGAS = np.linspace(0.0, 1.0, 101)[1:-1]
"""Weights over which ``difference_mahalanobis_sq`` maximises (0.01 to 0.99)."""


def difference_mahalanobis_sq(d: NDArray[np.float64], P_ind_a: NDArray[np.float64],
                              P_dep_a: NDArray[np.float64], P_ind_b: NDArray[np.float64],
                              P_dep_b: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return a lower bound of the squared Mahalanobis distance of ``a - b``, any correlation.

    ``max over omega of d^T S(omega)^-1 d`` with ``S(omega) = P_ind_a + P_ind_b +
    P_dep_a / omega + P_dep_b / (1 - omega)``: each ``S(omega)`` bounds the covariance
    of the difference when the independent parts are uncorrelated and the dependent
    parts correlated in any way (covariance intersection, Julier and Uhlmann 1997),
    so each gives a lower bound of the true distance and the largest is the tightest
    (the merge test of ``fuser.tracks``). Maximised over ``omega`` in 0.01 .. 0.99;
    where one of the two has no dependent part they cannot correlate and the distance
    on ``P_a + P_b`` is exact.

    Parameters
    ----------
    d : ndarray, shape (N, 2) [m]
        Differences of the means.
    P_ind_a, P_dep_a, P_ind_b, P_dep_b : ndarray, shape (N, 2, 2) [m^2]
        Independent and dependent parts of the two covariances.

    Returns
    -------
    ndarray, shape (N,)

    """
    total = P_ind_a + P_ind_b + P_dep_a + P_dep_b
    plain = np.einsum('ni,ni->n', d, np.linalg.solve(total, d[..., None])[..., 0])
    # Without a dependent part on one side the two cannot correlate: the sum is exact.
    exact = ~np.any(P_dep_a, axis=(1, 2)) | ~np.any(P_dep_b, axis=(1, 2))
    if exact.all():
        return plain
    w = _OMEGAS[:, None, None, None]
    S = P_ind_a + P_ind_b + P_dep_a / w + P_dep_b / (1.0 - w)        # (W, N, 2, 2)
    d_w = np.broadcast_to(d, S.shape[:-1])
    bound = np.einsum('wni,wni->wn', d_w, np.linalg.solve(S, d_w[..., None])[..., 0])
    return np.where(exact, plain, bound.max(axis=0))
