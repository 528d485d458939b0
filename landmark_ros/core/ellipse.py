"""
Geometry of the k-sigma contour of a 2D Gaussian, for plots and RViz markers.

Symbols
-------
mean : shape (2,) or (N, 2) [m].
P : covariance, shape (2, 2) or (N, 2, 2) [m^2], positive semi-definite.
k : number of standard deviations (Mahalanobis radius) of the contour.

"""

from typing import Tuple, Union

from landmark_ros.core.arrays import as_matrices, as_vectors
import numpy as np
from numpy.typing import ArrayLike, NDArray


def ellipse_axes(P: ArrayLike, k: float = 1.0) -> Tuple[
        Union[float, NDArray[np.float64]], Union[float, NDArray[np.float64]],
        Union[float, NDArray[np.float64]]]:
    """
    Return the semi-axes and orientation of the k-sigma ellipse of ``P``.

    Parameters
    ----------
    P : array_like, shape (2, 2) or (N, 2, 2)
        Covariance matrices.
    k : float
        Size of the contour in standard deviations (Mahalanobis radius).

    Returns
    -------
    semi_major : float or ndarray, shape () or (N,) [m]
    semi_minor : float or ndarray, shape () or (N,) [m]
    angle : float or ndarray, shape () or (N,) [rad]
        Direction of the major axis, counter-clockwise from the x axis.

    """
    P = as_matrices(P, 2, 'P')
    a, b, c = P[..., 0, 0], 0.5 * (P[..., 0, 1] + P[..., 1, 0]), P[..., 1, 1]
    centre = 0.5 * (a + c)
    radius = np.hypot(0.5 * (a - c), b)
    # Clip tiny negative eigenvalues from rounding on singular matrices.
    major = k * np.sqrt(np.maximum(centre + radius, 0.0))
    minor = k * np.sqrt(np.maximum(centre - radius, 0.0))
    angle = 0.5 * np.arctan2(2.0 * b, a - c)
    return major[()], minor[()], angle[()]


def ellipse_points(mean: ArrayLike, P: ArrayLike, k: float = 1.0,
                   num_points: int = 36) -> NDArray[np.float64]:
    """
    Return points on the k-sigma contour ``(x - mean)^T P^-1 (x - mean) = k^2``.

    Parameters
    ----------
    mean : array_like, shape (2,) or (N, 2)
        Centre of the ellipse.
    P : array_like, shape (2, 2) or (N, 2, 2)
        Covariance matrices.
    k : float
        Size of the contour in standard deviations (Mahalanobis radius).
    num_points : int
        Points per ellipse; the first is not repeated at the end.

    Returns
    -------
    ndarray, shape (num_points, 2) or (N, num_points, 2) [m]

    """
    mean = as_vectors(mean, 2, 'mean')
    major, minor, angle = (np.asarray(v)[..., None] for v in ellipse_axes(P, k))
    t = np.linspace(0.0, 2.0 * np.pi, num_points, endpoint=False)
    u, v = major * np.cos(t), minor * np.sin(t)
    cos, sin = np.cos(angle), np.sin(angle)
    return np.stack([
        mean[..., 0:1] + cos * u - sin * v,
        mean[..., 1:2] + sin * u + cos * v,
    ], axis=-1)
