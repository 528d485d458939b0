"""
The PointCloud2 schemas of the package's topics, with writers and readers.

``observations`` (into ``landmark_observer``): ``id`` (any integer type), ``range``
[m], ``bearing`` [rad] (FLOAT32 or FLOAT64), optional ``range_variance``,
``bearing_variance``, ``range_bearing_covariance``.

``landmarks`` (observer out, fuser in): ``id`` UINT32, ``x``, ``y``, ``z``,
``cov_xx``, ``cov_xy``, ``cov_yy`` FLOAT64, little-endian, in this order.
"""

from landmark_ros.cloud import CloudWriter, FieldSpec, INTEGER_TYPES, read_columns
from landmark_ros.cloud import REAL_TYPES
import numpy as np

OBSERVATION_FIELDS = (
    FieldSpec('id', INTEGER_TYPES),
    FieldSpec('range', REAL_TYPES),
    FieldSpec('bearing', REAL_TYPES),
    FieldSpec('range_variance', REAL_TYPES, required=False),
    FieldSpec('bearing_variance', REAL_TYPES, required=False),
    FieldSpec('range_bearing_covariance', REAL_TYPES, required=False),
)
LANDMARK_SCHEMA = (
    ('id', np.uint32), ('x', np.float64), ('y', np.float64), ('z', np.float64),
    ('cov_xx', np.float64), ('cov_xy', np.float64), ('cov_yy', np.float64),
)
LANDMARK_FIELDS = tuple(
    FieldSpec(name, INTEGER_TYPES if name == 'id' else REAL_TYPES)
    for name, _ in LANDMARK_SCHEMA)

_OBSERVATION_WRITER = CloudWriter((('id', np.uint32), ('range', np.float64),
                                   ('bearing', np.float64)))
_OBSERVATION_NOISE_WRITER = CloudWriter((
    ('id', np.uint32), ('range', np.float64), ('bearing', np.float64),
    ('range_variance', np.float64), ('bearing_variance', np.float64),
    ('range_bearing_covariance', np.float64)))
LANDMARK_WRITER = CloudWriter(LANDMARK_SCHEMA)


def observation_message(header, ids, z, R=None):
    """
    Return an ``observations`` cloud.

    Parameters
    ----------
    header : std_msgs.msg.Header
        Acquisition stamp and sensor frame.
    ids : array_like of int, shape (N,)
        Landmark IDs.
    z : array_like, shape (N, 2)
        Range [m] and bearing [rad] per row.
    R : array_like, shape (N, 2, 2), optional
        Per-row noise covariance; without it the observer's parameters apply.

    Returns
    -------
    sensor_msgs.msg.PointCloud2

    """
    z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    writer = _OBSERVATION_WRITER if R is None else _OBSERVATION_NOISE_WRITER
    rows = writer.rows(len(z))
    rows['id'] = np.asarray(ids).reshape(-1)
    rows['range'], rows['bearing'] = z[:, 0], z[:, 1]
    if R is not None:
        R = np.asarray(R, dtype=np.float64).reshape(-1, 2, 2)
        rows['range_variance'], rows['bearing_variance'] = R[:, 0, 0], R[:, 1, 1]
        rows['range_bearing_covariance'] = R[:, 0, 1]
    return writer.message(header, rows)


def landmark_message(header, ids, m, P_m):
    """
    Return a ``landmarks`` cloud.

    Parameters
    ----------
    header : std_msgs.msg.Header
        Stamp and world frame.
    ids : array_like of int, shape (N,)
        Landmark IDs.
    m : array_like, shape (N, 2)
        Positions [m].
    P_m : array_like, shape (N, 2, 2)
        Covariances [m^2].

    Returns
    -------
    sensor_msgs.msg.PointCloud2

    """
    m = np.asarray(m, dtype=np.float64).reshape(-1, 2)
    P_m = np.asarray(P_m, dtype=np.float64).reshape(-1, 2, 2)
    rows = LANDMARK_WRITER.rows(len(m))
    rows['id'] = np.asarray(ids).reshape(-1)
    rows['x'], rows['y'] = m[:, 0], m[:, 1]
    rows['cov_xx'], rows['cov_xy'], rows['cov_yy'] = P_m[:, 0, 0], P_m[:, 0, 1], P_m[:, 1, 1]
    return LANDMARK_WRITER.message(header, rows)


def read_landmarks(msg):
    """
    Return the rows of a ``landmarks`` cloud.

    Parameters
    ----------
    msg : sensor_msgs.msg.PointCloud2
        The message to read.

    Returns
    -------
    ids : ndarray of int64, shape (N,)
    m : ndarray, shape (N, 2)
    P_m : ndarray, shape (N, 2, 2)

    Raises
    ------
    landmark_ros.cloud.CloudError
        If a field is missing, of the wrong type, or the data length is wrong.

    """
    columns = read_columns(msg, LANDMARK_FIELDS)
    P_m = np.empty((len(columns['x']), 2, 2))
    P_m[:, 0, 0], P_m[:, 1, 1] = columns['cov_xx'], columns['cov_yy']
    P_m[:, 0, 1] = P_m[:, 1, 0] = columns['cov_xy']
    return columns['id'], np.stack([columns['x'], columns['y']], axis=1), P_m
