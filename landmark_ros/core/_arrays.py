"""Input checks and small array helpers shared by the core modules."""

import numpy as np


def as_vectors(value, size, name):
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


def as_matrices(value, size, name):
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


def transpose(J):
    """Swap the last two axes of a matrix or a batch of matrices."""
    return np.swapaxes(J, -1, -2)


def sandwich(J, P):
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


def symmetrise(P):
    """Return ``(P + P.T) / 2`` for a matrix or a batch of matrices."""
    return 0.5 * (P + transpose(P))


def matrix(rows, batch_shape):
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


def batch_shape(*arrays):
    """Return the broadcast leading shape of vectors: ``()`` or ``(N,)``."""
    return np.broadcast_shapes(*(a.shape[:-1] for a in arrays))


def det(P):
    """Return determinants of square matrices, in closed form for 2x2."""
    if P.shape[-1] == 2:
        return P[..., 0, 0] * P[..., 1, 1] - P[..., 0, 1] * P[..., 1, 0]
    return np.linalg.det(P)


def solve(A, B):
    """
    Solve ``A X = B`` for matrices, in closed form (Cramer's rule) for 2x2.

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
    if A.shape[-1] != 2:
        return np.linalg.solve(A, B)
    d = det(A)[..., None]
    a, b, c, e = A[..., 0, 0, None], A[..., 0, 1, None], A[..., 1, 0, None], A[..., 1, 1, None]
    x0 = (e * B[..., 0, :] - b * B[..., 1, :]) / d
    x1 = (a * B[..., 1, :] - c * B[..., 0, :]) / d
    return np.stack([x0, x1], axis=-2)


def symmetric_2x2(xx, xy, yy):
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


def entries_2x2(P):
    """Return ``(xx, xy, yy)`` of 2x2 matrices, the off-diagonal averaged."""
    return P[..., 0, 0], 0.5 * (P[..., 0, 1] + P[..., 1, 0]), P[..., 1, 1]


def common_batch_shape(vectors=(), matrices=()):
    """Return the broadcast batch shape, ``()`` or ``(N,)``, of vectors and matrices."""
    shapes = {v.shape[:-1] for v in vectors if v is not None}
    shapes.update(M.shape[:-2] for M in matrices if M is not None)
    shapes.discard(())
    if len(shapes) <= 1:
        return shapes.pop() if shapes else ()
    return np.broadcast_shapes(*shapes)


def to_batch(shape, array, item_ndim):
    """Broadcast an output to the batch shape ``shape`` (a copy only when it grows)."""
    target = tuple(shape) + array.shape[array.ndim - item_ndim:]
    return array if array.shape == target else np.broadcast_to(array, target).copy()
