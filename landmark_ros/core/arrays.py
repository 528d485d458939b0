"""Input checks and small array helpers shared by the core modules."""

from typing import Iterable, Optional, Sequence, Tuple, TypeVar, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray


Entries2x2 = Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
"""``(xx, xy, yy)`` of symmetric 2x2 matrices, each entry shape () or (N,)."""

_Int = TypeVar('_Int', bound=np.integer)


def as_vectors(value: ArrayLike, size: int, name: str) -> NDArray[np.float64]:
    """
    Return ``value`` as a float64 array whose last axis has ``size`` entries.

    Parameters
    ----------
    value : array_like, shape (size,) or (N, size)
        The input to convert.
    size : int
        Entries of the last axis (vectors) or of each matrix side.
    name : str
        Used in the error message.

    Raises
    ------
    ValueError
        If the last axis does not have ``size`` entries or there are more than
        two axes.

    """
    array = np.asarray(value, dtype=np.float64)
    if array.ndim not in (1, 2) or array.shape[-1] != size:
        raise ValueError(
            f'{name} must have shape ({size},) or (N, {size}), got {array.shape}')
    return array


def as_matrices(value: ArrayLike, size: int, name: str) -> NDArray[np.float64]:
    """
    Return ``value`` as a float64 array of ``(size, size)`` matrices.

    Parameters
    ----------
    value : array_like, shape (size, size) or (N, size, size)
        The input to convert.
    size : int
        Entries of the last axis (vectors) or of each matrix side.
    name : str
        Used in the error message.

    Raises
    ------
    ValueError
        If the shape is not ``(size, size)`` or ``(N, size, size)``.

    """
    array = np.asarray(value, dtype=np.float64)
    if array.ndim not in (2, 3) or array.shape[-2:] != (size, size):
        raise ValueError(
            f'{name} must have shape ({size}, {size}) or (N, {size}, {size}), '
            f'got {array.shape}')
    return array


def transpose(J: NDArray[np.float64]) -> NDArray[np.float64]:
    """Swap the last two axes of a matrix or a batch of matrices."""
    return np.swapaxes(J, -1, -2)


def sandwich(J: NDArray[np.float64], P: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return ``J @ P @ J.T`` for single matrices or batches, symmetrised.

    Parameters
    ----------
    J : ndarray, shape (m, n) or (N, m, n)
        Jacobian of the map the covariance goes through.
    P : ndarray, shape (n, n) or (N, n, n)
        Covariance matrices.

    Returns
    -------
    ndarray, shape (m, m) or (N, m, m)

    """
    return symmetrise(J @ P @ transpose(J))


def symmetrise(P: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return ``(P + P.T) / 2`` for a matrix or a batch of matrices."""
    return 0.5 * (P + transpose(P))


def matrix(rows: Sequence[Sequence[Union[float, NDArray[np.float64]]]],
           batch_shape: Tuple[int, ...]) -> NDArray[np.float64]:
    """
    Build matrices from nested lists of entries.

    Parameters
    ----------
    rows : list of list of array_like
        ``rows[i][j]`` is entry ``(i, j)``: a scalar or an array that broadcasts
        to ``batch_shape``.
    batch_shape : tuple
        ``()`` for a single matrix, ``(N,)`` for a batch.

    Returns
    -------
    ndarray, shape batch_shape + (r, c)

    """
    out = np.empty(tuple(batch_shape) + (len(rows), len(rows[0])))
    for i, row in enumerate(rows):
        for j, entry in enumerate(row):
            out[..., i, j] = entry
    return out


def batch_shape(*arrays: NDArray[np.float64]) -> Tuple[int, ...]:
    """Return the broadcast leading shape of vectors: ``()`` or ``(N,)``."""
    return np.broadcast_shapes(*(a.shape[:-1] for a in arrays))


def power_of_4_scale(*diagonals: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return per-matrix scales ``s = 4^k`` near the largest of some diagonal entries.

    Dividing a matrix by ``s`` is exact in floating point (a power of two) and brings
    its entries near 1, so closed-form 2x2 determinants and inverses neither overflow
    nor underflow; ``sqrt(s) = 2^k`` is exact too (for scaling vectors).

    Parameters
    ----------
    *diagonals : ndarray, shape () or (N,)
        Diagonal entries (variances) of the matrices that share a scale.

    Returns
    -------
    ndarray, shape () or (N,)
        ``4^k`` with ``max |d| / 4 < 4^k <= 4 max |d|``; 1 where every entry is zero or
        not finite.

    """
    largest = np.abs(diagonals[0])
    for d in diagonals[1:]:
        largest = np.maximum(largest, np.abs(d))
    largest = np.where((largest > 0.0) & np.isfinite(largest), largest, 1.0)
    exponent = np.frexp(largest)[1]
    return np.ldexp(1.0, exponent - (exponent & 1))


def det_2x2(a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64],
            s: Optional[NDArray[np.float64]] = None) -> NDArray[np.float64]:
    """
    Return ``a c - b^2``, the determinant of symmetric 2x2 matrices, computed scaled.

    Parameters
    ----------
    a, b, c : ndarray, shape () or (N,)
        Entries (0, 0), (0, 1) = (1, 0) and (1, 1).
    s : ndarray, shape () or (N,), optional
        Scale from ``power_of_4_scale``; by default that of ``a`` and ``c``.

    Returns
    -------
    ndarray, shape () or (N,)
        Exact to rounding when ``a c`` and ``b^2`` are representable; scaling keeps
        the products inside the float range, so only a determinant that is itself
        beyond the range (about 1e-308 to 1e308) under- or overflows.

    """
    s = power_of_4_scale(a, c) if s is None else s
    a, b, c = a / s, b / s, c / s
    return (a * c - b * b) * s * s


def inverse_2x2(a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64],
                s: Optional[NDArray[np.float64]] = None) -> Entries2x2:
    """
    Return the entries of the inverse of symmetric 2x2 matrices, computed scaled.

    Parameters
    ----------
    a, b, c : ndarray, shape () or (N,)
        Entries (0, 0), (0, 1) = (1, 0) and (1, 1) of positive definite matrices.
    s : ndarray, shape () or (N,), optional
        Scale from ``power_of_4_scale``; by default that of ``a`` and ``c``.

    Returns
    -------
    tuple of ndarray, shape () or (N,)
        ``(a, b, c)`` of the inverse; infinite or NaN where the matrix is singular.

    """
    s = power_of_4_scale(a, c) if s is None else s
    a, b, c = a / s, b / s, c / s
    with np.errstate(divide='ignore', invalid='ignore'):
        inv_det = 1.0 / ((a * c - b * b) * s)
    return c * inv_det, -b * inv_det, a * inv_det


def psd_projection_2x2(a: NDArray[np.float64], b: NDArray[np.float64],
                       c: NDArray[np.float64]) -> Entries2x2:
    """
    Return the nearest positive semi-definite matrices of symmetric 2x2 matrices.

    The projection in the Frobenius norm (Higham, Linear Algebra Appl. 103, 1988):
    negative eigenvalues set to zero. Matrices that are already positive
    semi-definite are returned unchanged, bit for bit.

    Parameters
    ----------
    a, b, c : ndarray, shape () or (N,)
        Entries (0, 0), (0, 1) = (1, 0) and (1, 1), finite.

    Returns
    -------
    tuple of ndarray, shape () or (N,)
        ``(a, b, c)`` of the projections.

    """
    a, b, c = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (a, b, c)))
    # Positive semi-definite: both diagonal entries and the determinant non-negative.
    psd = (a >= 0.0) & (c >= 0.0) & (a * c >= b * b)
    if np.all(psd):
        return a, b, c
    half_sum = 0.5 * (a + c)
    radius = np.hypot(0.5 * (a - c), b)
    top = half_sum + radius                   # the larger eigenvalue
    low = half_sum - radius
    with np.errstate(divide='ignore', invalid='ignore'):
        # Only the top eigenvalue is kept: top * (P - low I) / (top - low).
        scale = np.where(top > 0.0, top / (top - low), 0.0)
    pa, pb, pc = scale * (a - low), scale * b, scale * (c - low)
    return np.where(psd, a, pa), np.where(psd, b, pb), np.where(psd, c, pc)


def mahalanobis_sq_2x2(
        dx: NDArray[np.float64], dy: NDArray[np.float64], a: NDArray[np.float64],
        b: NDArray[np.float64], c: NDArray[np.float64],
        s: Optional[NDArray[np.float64]] = None) -> NDArray[np.float64]:
    """
    Return ``d^T P^-1 d`` for 2-vectors ``d`` and symmetric 2x2 ``P``, computed scaled.

    Parameters
    ----------
    dx, dy : ndarray, shape () or (N,)
        Components of ``d``.
    a, b, c : ndarray, shape () or (N,)
        Entries (0, 0), (0, 1) = (1, 0) and (1, 1) of positive definite ``P``.
    s : ndarray, shape () or (N,), optional
        Scale from ``power_of_4_scale``; by default that of ``a`` and ``c``.

    Returns
    -------
    ndarray, shape () or (N,)
        Non-negative; ``inf`` (or NaN for ``d = 0``) where ``P`` is singular.

    """
    s = power_of_4_scale(a, c) if s is None else s
    root = np.sqrt(s)
    a, b, c, dx, dy = a / s, b / s, c / s, dx / root, dy / root
    with np.errstate(divide='ignore', invalid='ignore'):
        return (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * c - b * b)


def matrix_scale(P: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return ``power_of_4_scale`` of the diagonals of square matrices, shape () or (N,)."""
    return power_of_4_scale(*(P[..., i, i] for i in range(P.shape[-1])))


def det(P: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return determinants of square matrices: closed form for 2x2, scaled (``det_2x2``)."""
    if P.shape[-1] != 2:
        return np.linalg.det(P)
    s = matrix_scale(P)
    return ((P[..., 0, 0] / s) * (P[..., 1, 1] / s) - (P[..., 0, 1] / s) * (P[..., 1, 0] / s)
            ) * s * s


def solve(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Solve ``A X = B`` for matrices; closed form (Cramer's rule) for 2x2, scaled.

    ``A`` is divided by a power of 4 near its largest diagonal entry first (exact), so
    the closed form neither overflows nor underflows for any representable ``A``
    whose scaled determinant is not zero.

    Parameters
    ----------
    A : ndarray, shape (n, n) or (N, n, n)
        Invertible matrices.
    B : ndarray, shape (n, k) or (N, n, k)
        Right-hand sides.

    Returns
    -------
    ndarray, shape (n, k) or (N, n, k)

    """
    s = matrix_scale(A)[..., None, None]
    A = A / s
    if A.shape[-1] != 2:
        return np.linalg.solve(A, B) / s
    d = (A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0])[..., None] * s[..., 0]
    a, b, c, e = A[..., 0, 0, None], A[..., 0, 1, None], A[..., 1, 0, None], A[..., 1, 1, None]
    x0 = (e * B[..., 0, :] - b * B[..., 1, :]) / d
    x1 = (a * B[..., 1, :] - c * B[..., 0, :]) / d
    return np.stack([x0, x1], axis=-2)


def solve_vectors(A: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Solve ``A x = b`` (``solve``) for vectors ``b`` of shape (n,) or (N, n); x likewise."""
    A, b = np.broadcast_arrays(A, b[..., None])
    return solve(A, b)[..., 0]


def symmetric_2x2(xx: Union[float, NDArray[np.float64]], xy: Union[float, NDArray[np.float64]],
                  yy: Union[float, NDArray[np.float64]]) -> NDArray[np.float64]:
    """
    Build symmetric 2x2 matrices from their three distinct entries.

    Parameters
    ----------
    xx, xy, yy : float or ndarray, shape () or (N,)
        Entries (0, 0), (0, 1) = (1, 0) and (1, 1).

    Returns
    -------
    ndarray, shape (2, 2) or (N, 2, 2)

    """
    out = np.empty(np.broadcast(xx, xy, yy).shape + (2, 2))
    out[..., 0, 0] = xx
    out[..., 0, 1] = xy
    out[..., 1, 0] = xy
    out[..., 1, 1] = yy
    return out


def entries_2x2(P: NDArray[np.float64]) -> Entries2x2:
    """Return ``(xx, xy, yy)`` of 2x2 matrices, the off-diagonal averaged."""
    return P[..., 0, 0], 0.5 * (P[..., 0, 1] + P[..., 1, 0]), P[..., 1, 1]


def common_batch_shape(
        vectors: Iterable[Optional[NDArray[np.float64]]] = (),
        matrices: Iterable[Optional[NDArray[np.float64]]] = ()) -> Tuple[int, ...]:
    """Return the broadcast batch shape, ``()`` or ``(N,)``, of vectors and matrices."""
    shapes = {v.shape[:-1] for v in vectors if v is not None}
    shapes.update(M.shape[:-2] for M in matrices if M is not None)
    shapes.discard(())
    if len(shapes) <= 1:
        return shapes.pop() if shapes else ()
    return np.broadcast_shapes(*shapes)


def to_batch(shape: Tuple[int, ...], array: NDArray[np.float64],
             item_ndim: int) -> NDArray[np.float64]:
    """Broadcast an output to the batch shape ``shape`` (a copy only when it grows)."""
    target = tuple(shape) + array.shape[array.ndim - item_ndim:]
    return array if array.shape == target else np.broadcast_to(array, target).copy()


def unique_ints(values: NDArray[_Int]) -> NDArray[_Int]:
    """
    Return the distinct values of an integer array, sorted: ``np.unique`` for integers.

    By a sort and a comparison of neighbours: numpy 2.4's ``np.unique`` hashes first
    and took 0.7 ms for 10,000 int64 keys here, against 0.04 ms for this.

    Parameters
    ----------
    values : ndarray of int, any shape
        Flattened, as ``np.unique`` does.

    Returns
    -------
    ndarray, shape (K,)
        Same dtype as ``values``.

    """
    ordered = np.sort(np.asarray(values).reshape(-1))
    keep = np.empty(len(ordered), bool)
    keep[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=keep[1:])
    return ordered[keep]


def unique_inverse(values: NDArray[_Int]) -> Tuple[NDArray[_Int], NDArray[np.intp]]:
    """
    Return the distinct values of an integer array and where each value is among them.

    ``np.unique(values, return_inverse=True)`` for a 1-D integer array, by one
    (unstable) argsort: about half of ``np.unique``'s time for 20,000 int64 keys here.

    Parameters
    ----------
    values : ndarray of int, shape (N,)
        Any integers.

    Returns
    -------
    unique : ndarray, shape (K,)
        Sorted, same dtype as ``values``.
    inverse : ndarray of int, shape (N,)
        ``unique[inverse] == values``.

    """
    values = np.asarray(values).reshape(-1)
    order = np.argsort(values)
    ordered = values[order]
    first = np.empty(len(ordered), bool)
    first[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    inverse = np.empty(len(values), np.intp)
    inverse[order] = np.cumsum(first) - 1
    return ordered[first], inverse
