"""
Covariance checks: finite, symmetric, positive semi-definite, and in the accepted range.

``covariance_status`` finds non-finite, asymmetric and indefinite matrices and
``covariance_range_status`` the ones outside the range the core computes reliably
(``MIN_VARIANCE`` to ``MAX_VARIANCE``, condition number up to ``MAX_CONDITION``); the
codes have the names counters and logs use (``COVARIANCE_PROBLEMS``,
``COVARIANCE_RANGE_PROBLEMS``). Every input message's covariances pass both.
"""

from typing import Union

from landmark_ros.core.arrays import matrix_scale, symmetrise, transpose
import numpy as np
from numpy.typing import ArrayLike, NDArray


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

MIN_VARIANCE = 1e-12
"""Smallest accepted variance (diagonal entry) of a covariance [m^2]: (1 um)^2."""

MAX_VARIANCE = 1e12
"""Largest accepted variance (diagonal entry) of a covariance [m^2]: (1000 km)^2."""

MAX_CONDITION = 1e9
"""
Largest accepted condition number (largest / smallest eigenvalue) of a covariance.

A 2x2 inverse or solve loses about ``log10(condition)`` of float64's 15.7 digits, so
at 1e9 gates and fused estimates keep about 6.7 significant digits (relative error
``1e9 * 2.2e-16 = 2.2e-7``); beyond, the thin direction of the ellipse is noise. It is
a ratio of standard deviations of about 3e4, more than a real range-bearing sensor
(for example 1 cm of range against 1 mrad of bearing at 300 m) produces. Together
with the variance bounds it keeps every scaled determinant above 1e-9 and every
fused product inside the float range.
"""

COVARIANCE_TOO_SMALL = 4
COVARIANCE_TOO_LARGE = 5
COVARIANCE_ILL_CONDITIONED = 6
COVARIANCE_RANGE_PROBLEMS = {
    COVARIANCE_NONFINITE: 'covariance_nonfinite',
    COVARIANCE_TOO_SMALL: 'covariance_too_small',
    COVARIANCE_TOO_LARGE: 'covariance_too_large',
    COVARIANCE_ILL_CONDITIONED: 'covariance_ill_conditioned',
}
"""Names of the codes ``covariance_range_status`` returns, as counters and logs use them."""


def covariance_status(P: ArrayLike,
                      rtol: float = 1e-9) -> Union[np.int_, NDArray[np.int_]]:
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


def validate_covariance(P: ArrayLike, name: str = 'covariance',
                        rtol: float = 1e-9) -> NDArray[np.float64]:
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


def covariance_range_status(P: ArrayLike) -> Union[np.int_, NDArray[np.int_]]:
    """
    Check that covariances lie in the range the core computes reliably.

    Call it on covariances ``covariance_status`` accepted: every diagonal entry in
    ``[MIN_VARIANCE, MAX_VARIANCE]`` and a condition number (largest over smallest
    eigenvalue) of at most ``MAX_CONDITION``. Inside that range every closed form of
    the core is free of overflow and underflow (see the module docstring).

    Parameters
    ----------
    P : array_like, shape (n, n) or (N, n, n)
        Symmetric positive semi-definite covariances [m^2].

    Returns
    -------
    int or ndarray of int, shape () or (N,)
        ``COVARIANCE_OK`` or the first problem found: ``COVARIANCE_NONFINITE``,
        ``COVARIANCE_TOO_SMALL``, ``COVARIANCE_TOO_LARGE``,
        ``COVARIANCE_ILL_CONDITIONED`` (names in ``COVARIANCE_RANGE_PROBLEMS``).

    Raises
    ------
    ValueError
        If ``P`` is not ``(n, n)`` or ``(N, n, n)``.

    """
    P = np.asarray(P, dtype=np.float64)
    if P.ndim not in (2, 3) or P.shape[-1] != P.shape[-2]:
        raise ValueError(f'P must have shape (n, n) or (N, n, n), got {P.shape}')
    finite = np.all(np.isfinite(P), axis=(-2, -1))
    safe = np.where(finite[..., None, None], P, 1.0)
    diagonal = np.diagonal(safe, axis1=-2, axis2=-1)
    small = np.min(diagonal, axis=-1) < MIN_VARIANCE
    large = np.max(diagonal, axis=-1) > MAX_VARIANCE
    s = matrix_scale(safe)
    scaled = symmetrise(safe) / s[..., None, None]
    if P.shape[-1] == 2:
        a, b, c = scaled[..., 0, 0], scaled[..., 0, 1], scaled[..., 1, 1]
        largest = 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)
        # smallest = det / largest; compared without dividing.
        ill = (a * c - b * b) * MAX_CONDITION < largest * largest
    else:
        eigenvalues = np.linalg.eigvalsh(scaled)
        ill = eigenvalues[..., 0] * MAX_CONDITION < eigenvalues[..., -1]
    status = np.where(~finite, COVARIANCE_NONFINITE,
                      np.where(small, COVARIANCE_TOO_SMALL,
                               np.where(large, COVARIANCE_TOO_LARGE,
                                        np.where(ill, COVARIANCE_ILL_CONDITIONED,
                                                 COVARIANCE_OK))))
    return status[()]
