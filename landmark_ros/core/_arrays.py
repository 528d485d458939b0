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
