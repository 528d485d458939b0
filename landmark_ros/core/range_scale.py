"""
Range scale error of a sensor that infers range from apparent size, with Jacobians.

A camera that reads the range of a target from its apparent size in the image (the
MRCLAM robots read barcodes on cylinders) misreads it by a factor that depends on where
the target is in the image (lens distortion changes the apparent size off the optical
axis) and on the range itself (a constant error of the measured size in pixels is a
relative range error that grows with the range). The model of a reading
``z = (r, b)`` (range [m], bearing [rad]):

    r = r_true * g(r, b),   g(r, b) = 1 + c0 + c1 b + c2 b^2 + k r

with ``coeffs = (c0, c1, c2)`` (relative error at the optical axis, per radian, per
radian squared) and ``per_m = k`` (relative error per metre of the reading [1/m]). The
correction is then a function of the reading alone:

    r_true = r / g(r, b)

(the bearing is unchanged). ``coeffs = (0, 0, 0)`` and ``per_m = 0`` is the identity,
the default of every sensor. ``mrclam.calibrate.fit_range_scale`` estimates the
coefficients from ground truth.

Symbols
-------
z : reading ``(range, bearing)``, shape (2,) or (N, 2).
z_c : corrected reading, same shape.
J_zc_z : Jacobian of ``z_c`` with respect to ``z``, shape (2, 2) or (N, 2, 2).
"""

from typing import Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

IDENTITY = (0.0, 0.0, 0.0)
"""Coefficients of no correction."""

MIN_SCALE = 0.5
"""Smallest ``g`` accepted: a correction that more than doubles a range is refused."""


def scale(z: ArrayLike, coeffs: Sequence[float] = IDENTITY,
          per_m: float = 0.0) -> NDArray[np.float64]:
    """
    Return the scale ``g(r, b)`` of readings (module docstring).

    Parameters
    ----------
    z : ndarray, shape (2,) or (N, 2)
        Readings (range [m], bearing [rad]).
    coeffs : sequence of 3 float
        ``(c0, c1, c2)``: relative range error at bearing 0, per rad, per rad^2.
    per_m : float
        Relative range error per metre of range [1/m].

    Returns
    -------
    ndarray, shape () or (N,)

    """
    z = np.asarray(z, dtype=np.float64)
    r, b = z[..., 0], z[..., 1]
    c0, c1, c2 = (float(c) for c in coeffs)
    return 1.0 + c0 + b * (c1 + c2 * b) + per_m * r


def is_identity(coeffs: Sequence[float], per_m: float) -> bool:
    """Return whether the coefficients correct nothing."""
    return not any(coeffs) and not per_m


def correct(z: ArrayLike, coeffs: Sequence[float] = IDENTITY,
            per_m: float = 0.0) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return corrected readings and the Jacobian of the correction.

    ``r_c = r / g(r, b)``, ``b_c = b``;
    ``d r_c / d r = (g - k r) / g^2``, ``d r_c / d b = -r (c1 + 2 c2 b) / g^2``.
    A noise ``R`` of the reading becomes ``J_zc_z R J_zc_z^T``.

    Parameters
    ----------
    z : ndarray, shape (2,) or (N, 2)
        Readings (range [m], bearing [rad]); a NaN bearing (range-only row) gives NaN.
    coeffs : sequence of 3 float
        ``(c0, c1, c2)`` (module docstring).
    per_m : float
        ``k`` [1/m].

    Returns
    -------
    z_c : ndarray, shape (2,) or (N, 2)
    J_zc_z : ndarray, shape (2, 2) or (N, 2, 2)

    Raises
    ------
    ValueError
        If ``coeffs`` does not hold 3 values, or a finite reading gives a scale below
        ``MIN_SCALE`` (the model does not hold there).

    """
    if len(coeffs) != 3:
        raise ValueError(f'coeffs must hold 3 values (c0, c1, c2), got {len(coeffs)}')
    z = np.asarray(z, dtype=np.float64)
    g = scale(z, coeffs, per_m)
    low = np.isfinite(g) & (g < MIN_SCALE)
    if np.any(low):
        raise ValueError(f'range scale {np.min(g[low]):.3g} below {MIN_SCALE}: the range '
                         'scale model does not hold for these readings')
    r, b = z[..., 0], z[..., 1]
    z_c = z.copy()
    z_c[..., 0] = r / g
    J = np.zeros(z.shape + (2,))
    J[..., 0, 0] = (g - per_m * r) / g ** 2
    J[..., 0, 1] = -r * (float(coeffs[1]) + 2.0 * float(coeffs[2]) * b) / g ** 2
    J[..., 1, 1] = 1.0
    return z_c, J


def correct_with_noise(z: ArrayLike, R: ArrayLike, coeffs: Sequence[float] = IDENTITY,
                       per_m: float = 0.0) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return corrected readings and their noise ``J R J^T`` (``correct``).

    Parameters
    ----------
    z : ndarray, shape (N, 2)
        Readings.
    R : ndarray, shape (2, 2) or (N, 2, 2)
        Their noise [m^2, m rad, rad^2].
    coeffs, per_m
        As in ``correct``.

    Returns
    -------
    z_c : ndarray, shape (N, 2)
    R_c : ndarray, shape (N, 2, 2)

    """
    z_c, J = correct(z, coeffs, per_m)
    R = np.broadcast_to(np.asarray(R, dtype=np.float64), J.shape)
    return z_c, J @ R @ np.swapaxes(J, -1, -2)
