"""
The PointCloud2 schemas of the package's topics, with writers and readers.

``observations`` (into ``landmark_observer``): ``id`` (any integer type; absent or
``UNKNOWN_ID`` = 4294967295: a row without an ID; IDs from the fuser's
``first_new_id`` (1000000000) up are reserved for landmarks it finds without an ID and
are rejected at the fuser as ``id_reserved``, the range kept in its map file),
``range`` [m], ``bearing`` [rad]
(FLOAT32 or FLOAT64), optional ``class`` (any integer type), ``range_variance``,
``bearing_variance``, ``range_bearing_covariance``.

``landmarks`` (observer out, fuser in), ``fused_landmarks``, ``fused_landmark_updates``
(fuser out) and ``ground_truth_landmarks`` (sim out) start alike, little-endian:

========== ======= ====== ==============================================================
field      type    offset meaning
========== ======= ====== ==============================================================
x, y, z    FLOAT32 0 4 8  position [m] for display: RViz's PointCloud2 display and PCL
                          (``fromROSMsg``) read only FLOAT32 ``x y z``; z is 0
id         UINT32  12     landmark ID (``UNKNOWN_ID`` 4294967295: none)
mean_x,    FLOAT64 16 24  the position estimate [m] at full precision: what the package's
mean_y                    readers use (``x``, ``y`` are it rounded to float32: 0.5 mm
                          off 10 km from the origin, 2 cm at 300 km)
cov_xx,    FLOAT64 32...  total covariance [m^2]
cov_xy,
cov_yy
cov_dep_*  FLOAT64        its dependent part (pose and bias: correlated between
                          observations); readers accept clouds without it (zero)
========== ======= ====== ==============================================================

Readers take ``mean_x``, ``mean_y`` when the cloud has them and ``x``, ``y`` (FLOAT32 or
FLOAT64) otherwise, so clouds of other tools and bags recorded with the earlier layout
(``id`` first, FLOAT64 ``x y z``, no ``mean_*``) read as before.

``partial_observations`` (observer out, fuser in; see ``fuser.partial``;
no position, so nothing for RViz to draw): ``id`` UINT32, ``kind`` UINT8 (0 range,
1 bearing), ``value`` [m or rad], ``variance``, ``variance_dep`` (independent noise and
bias variances), ``sensor_x``, ``sensor_y``, ``sensor_theta`` (sensor pose in the world),
``sensor_cov_xx``, ``_xy``, ``_xt``, ``_yy``, ``_yt``, ``_tt`` (its covariance) FLOAT64,
``view_group`` UINT32, then ``range_scale_q0``, ``_q1``, ``_q2``,
``range_scale_bearing_limit`` FLOAT64 (a camera's range scale over its image,
``core.partial.Views``; optional for readers, absent: none), little-endian, in this order.
``landmarks`` gains ``class`` UINT32 when the message had a ``class`` or a row without
an ID, and the ``SCAN_FIELDS`` (per row, the same for all rows of the message: robot
position and pose covariance) when it had a row without an ID, then ``sensor_theta``
(the sensor heading in the world; optional for readers, NaN: unknown), plus
``BIAS_FIELDS`` when the observer models a sensor bias, then ``bias_cov_ss`` (the
variance of a range scale error; optional for readers, absent or NaN: 0). Readers take
each group all or none.

``fused_landmarks`` (fuser out): the landmark fields then ``observations`` UINT32 and
``class`` UINT32.
``fused_landmark_updates`` (fuser out): as ``fused_landmarks``; a message that
announces landmarks taken out of the map (a duplicate track merged into another) also
has ``merged_into`` UINT32 after ``class``: a removed landmark's row has
``observations`` 0, ``merged_into`` the landmark it went into and that landmark's
estimate; every other row has ``merged_into`` ``UNKNOWN_ID`` (``read_removed``).
"""

from typing import NamedTuple


from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.pipeline.partial_rows import (PARTIAL_COLUMNS, RANGE_SCALE_COLUMNS,
                                                with_range_scale)
from landmark_ros.pipeline.scan import Scan
from landmark_ros.ros.cloud import CloudError, CloudWriter, FieldSpec, INTEGER_TYPES
from landmark_ros.ros.cloud import columns_of, read_columns, read_records
from landmark_ros.ros.cloud import REAL_TYPES
from landmark_ros.ros.conversions import planar_pose_covariance, set_planar_pose, set_stamp
import numpy as np
from std_msgs.msg import Header

OBSERVATION_FIELDS = (
    FieldSpec('id', INTEGER_TYPES, required=False),
    FieldSpec('range', REAL_TYPES, required=False),
    FieldSpec('bearing', REAL_TYPES, required=False),
    FieldSpec('class', INTEGER_TYPES, required=False),
    FieldSpec('range_variance', REAL_TYPES, required=False),
    FieldSpec('bearing_variance', REAL_TYPES, required=False),
    FieldSpec('range_bearing_covariance', REAL_TYPES, required=False),
)
DISPLAY_FIELDS = ('x', 'y', 'z')
"""FLOAT32 position fields at offsets 0, 4, 8 of every landmark cloud (RViz, PCL)."""
MEAN_FIELDS = ('mean_x', 'mean_y')
"""FLOAT64 position estimate of every landmark cloud, read before ``x``, ``y``."""
LANDMARK_SCHEMA = tuple((name, np.float32) for name in DISPLAY_FIELDS) + (
    ('id', np.uint32), ('mean_x', np.float64), ('mean_y', np.float64),
    ('cov_xx', np.float64), ('cov_xy', np.float64), ('cov_yy', np.float64),
    ('cov_dep_xx', np.float64), ('cov_dep_xy', np.float64), ('cov_dep_yy', np.float64),
)
FUSED_SCHEMA = LANDMARK_SCHEMA + (('observations', np.uint32), ('class', np.uint32))
DEPENDENT_FIELDS = ('cov_dep_xx', 'cov_dep_xy', 'cov_dep_yy')
SCAN_FIELDS = ('robot_x', 'robot_y', 'pose_cov_xx', 'pose_cov_xy', 'pose_cov_xt',
               'pose_cov_yy', 'pose_cov_yt', 'pose_cov_tt')
"""Robot position [m] and (x, y, theta) pose covariance of a message with unlabelled rows."""
BIAS_FIELDS = ('bias_cov_rr', 'bias_cov_rb', 'bias_cov_bb', 'sensor_x', 'sensor_y')
"""Sensor bias covariance (range [m^2], bearing [rad^2]) and sensor position [m]."""
SCALE_FIELD = 'bias_cov_ss'
"""Variance of a range scale error shared by the message (with ``BIAS_FIELDS``; optional:
a cloud without it, or NaN, has none)."""
HEADING_FIELD = 'sensor_theta'
"""Sensor heading in the world [rad] of a message with unlabelled rows (with
``SCAN_FIELDS``; optional: a cloud without it, or NaN, has no heading)."""
LANDMARK_FIELDS = tuple(
    FieldSpec(name, INTEGER_TYPES if name in ('id', 'observations', 'class') else REAL_TYPES,
              required=name not in MEAN_FIELDS + DEPENDENT_FIELDS + ('observations', 'class'))
    for name, _ in FUSED_SCHEMA if name != 'z') + tuple(
    FieldSpec(name, REAL_TYPES, required=False)
    for name in SCAN_FIELDS + BIAS_FIELDS + (HEADING_FIELD, SCALE_FIELD))
"""What the readers take: ``z`` is not read, ``mean_*`` replace ``x``, ``y`` when there."""

_OBSERVATION_WRITER = CloudWriter((('id', np.uint32), ('range', np.float64),
                                   ('bearing', np.float64)))
_OBSERVATION_NOISE_WRITER = CloudWriter((
    ('id', np.uint32), ('range', np.float64), ('bearing', np.float64),
    ('range_variance', np.float64), ('bearing_variance', np.float64),
    ('range_bearing_covariance', np.float64)))
PARTIAL_SCHEMA = tuple(
    (name, np.uint32 if name in ('id', 'view_group') else np.uint8 if name == 'kind'
     else np.float64) for name in PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS)
PARTIAL_FIELDS = tuple(
    FieldSpec(name, INTEGER_TYPES if dtype is not np.float64 else REAL_TYPES,
              required=name not in RANGE_SCALE_COLUMNS)
    for name, dtype in PARTIAL_SCHEMA)
PARTIAL_WRITER = CloudWriter(PARTIAL_SCHEMA)
PARTIAL_WRITER_NAMES = frozenset(PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS)
LANDMARK_WRITER = CloudWriter(LANDMARK_SCHEMA)
FUSED_WRITER = CloudWriter(FUSED_SCHEMA)
_REMOVED_WRITER = CloudWriter(FUSED_SCHEMA + (('merged_into', np.uint32),))
REMOVED_FIELDS = (FieldSpec('id', INTEGER_TYPES), FieldSpec('observations', INTEGER_TYPES),
                  FieldSpec('merged_into', INTEGER_TYPES, required=False))
NOT_MERGED = 4294967295
"""``merged_into`` of a row that announces no removal (``UNKNOWN_ID``)."""
_CLASS_WRITER = CloudWriter(LANDMARK_SCHEMA + (('class', np.uint32),))
_SCAN_WRITER = CloudWriter(LANDMARK_SCHEMA + (('class', np.uint32),) + tuple(
    (name, np.float64) for name in SCAN_FIELDS + (HEADING_FIELD,)))
_BIAS_WRITER = CloudWriter(LANDMARK_SCHEMA + (('class', np.uint32),) + tuple(
    (name, np.float64) for name in SCAN_FIELDS + (HEADING_FIELD,) + BIAS_FIELDS
    + (SCALE_FIELD,)))


class Landmarks(NamedTuple):
    """The rows of a ``landmarks`` or ``fused_landmarks`` cloud."""

    ids: np.ndarray
    """Landmark IDs, int64, shape (N,)."""
    m: np.ndarray
    """Positions [m], shape (N, 2)."""
    P: np.ndarray
    """Total covariances [m^2], shape (N, 2, 2)."""
    P_dep: np.ndarray
    """Dependent parts, shape (N, 2, 2); zero when the cloud has none."""
    observations: np.ndarray
    """Observations fused per landmark, int64, shape (N,); one when absent."""


class LandmarkExtras(NamedTuple):
    """The optional groups of a ``landmarks`` cloud beyond ``Landmarks``."""

    classes: np.ndarray
    """Landmark classes, int64, shape (N,); zero when absent."""
    scan: object
    """``fuser.tracks.Scan`` of the message (from its first row); None when absent."""


def make_header(stamp_s, frame_id):
    """Return a ``std_msgs/Header`` at ``stamp_s`` seconds in ``frame_id``."""
    result = Header(frame_id=frame_id)
    set_stamp(result.stamp, stamp_s)
    return result


def pose_message(stamp_s, pose, P_pose, frame_id='map'):
    """
    Return the ``pose`` input of the observer: a PoseWithCovarianceStamped.

    Parameters
    ----------
    stamp_s : float
        Stamp [s].
    pose : array_like, shape (3,)
        Planar pose (x [m], y [m], yaw [rad]).
    P_pose : array_like, shape (3, 3)
        Its covariance; the other entries of the 6x6 covariance are zero.
    frame_id : str
        World frame.

    Returns
    -------
    geometry_msgs.msg.PoseWithCovarianceStamped

    """
    msg = PoseWithCovarianceStamped(header=make_header(stamp_s, frame_id))
    set_planar_pose(msg.pose.pose, pose)
    msg.pose.covariance = planar_pose_covariance(P_pose)
    return msg


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


def landmark_message(header, ids, m, P_m, P_dep=None, out=None, classes=None, scan=None):
    """
    Return a ``landmarks`` cloud (the fused schema is ``fused_landmark_message``).

    Parameters
    ----------
    header : std_msgs.msg.Header
        Stamp and world frame.
    ids : array_like of int, shape (N,)
        Landmark IDs.
    m : array_like, shape (N, 2)
        Positions [m].
    P_m : array_like, shape (N, 2, 2)
        Total covariances [m^2].
    P_dep : array_like, shape (N, 2, 2), optional
        Their dependent parts; zero when not given.
    out : sensor_msgs.msg.PointCloud2, optional
        A message to fill instead of a new one.
    classes : array_like of int, shape (N,), optional
        Landmark classes; given, the cloud has ``class``.
    scan : landmark_ros.pipeline.scan.Scan, optional
        Robot pose terms of the message, written to every row (``SCAN_FIELDS``, and
        ``BIAS_FIELDS`` when it has a bias).

    Returns
    -------
    sensor_msgs.msg.PointCloud2

    """
    if scan is not None:
        writer = _SCAN_WRITER if scan.R_bias is None else _BIAS_WRITER
    else:
        writer = LANDMARK_WRITER if classes is None else _CLASS_WRITER
    rows = _landmark_rows(writer, ids, m, P_m, P_dep)
    if classes is not None:
        rows['class'] = np.asarray(classes).reshape(-1)
    if scan is not None:
        rows['robot_x'], rows['robot_y'] = scan.robot_xy
        P = scan.P_pose
        rows['pose_cov_xx'], rows['pose_cov_xy'], rows['pose_cov_xt'] = P[0]
        rows['pose_cov_yy'], rows['pose_cov_yt'], rows['pose_cov_tt'] = P[1, 1], P[1, 2], P[2, 2]
        rows[HEADING_FIELD] = np.nan if scan.heading is None else scan.heading
        if scan.R_bias is not None:
            rows['bias_cov_rr'], rows['bias_cov_rb'] = scan.R_bias[0]
            rows['bias_cov_bb'] = scan.R_bias[1, 1]
            rows['sensor_x'], rows['sensor_y'] = scan.sensor_xy
            rows[SCALE_FIELD] = scan.range_scale_variance
    return writer.message(header, rows, out)


def fused_landmark_message(header, ids, m, P_m, P_dep, observations, classes=None,
                           merged_into=None):
    """
    Return a ``fused_landmarks`` cloud, or a ``fused_landmark_updates`` one.

    Parameters
    ----------
    header : std_msgs.msg.Header
        Stamp and world frame.
    ids : array_like of int, shape (N,)
        Landmark IDs.
    m : array_like, shape (N, 2)
        Positions [m].
    P_m : array_like, shape (N, 2, 2)
        Total covariances [m^2].
    P_dep : array_like, shape (N, 2, 2), or None
        Their dependent parts; None writes zeros.
    observations : array_like of int, shape (N,)
        Observations fused per landmark.
    classes : array_like of int, shape (N,), optional
        Landmark classes (0 when not given).
    merged_into : array_like of int, shape (N,), optional
        Per row the landmark a removed landmark went into, ``NOT_MERGED`` for the
        others; given, the cloud has ``merged_into`` (``fused_landmark_updates``).

    Returns
    -------
    sensor_msgs.msg.PointCloud2

    """
    writer = FUSED_WRITER if merged_into is None else _REMOVED_WRITER
    rows = _landmark_rows(writer, ids, m, P_m, P_dep)
    rows['observations'] = np.asarray(observations).reshape(-1)
    if classes is not None:
        rows['class'] = np.asarray(classes).reshape(-1)
    if merged_into is not None:
        rows['merged_into'] = np.asarray(merged_into).reshape(-1)
    return writer.message(header, rows)


def _landmark_rows(writer, ids, m, P_m, P_dep):
    """Return the rows of ``writer`` with the IDs, positions and covariances filled."""
    m = np.asarray(m, dtype=np.float64).reshape(-1, 2)
    P_m = np.asarray(P_m, dtype=np.float64).reshape(-1, 2, 2)
    rows = writer.rows(len(m))
    rows['id'] = np.asarray(ids).reshape(-1)
    rows['x'], rows['y'] = m[:, 0], m[:, 1]           # rounded to float32
    rows['mean_x'], rows['mean_y'] = m[:, 0], m[:, 1]
    rows['cov_xx'], rows['cov_xy'], rows['cov_yy'] = P_m[:, 0, 0], P_m[:, 0, 1], P_m[:, 1, 1]
    if P_dep is not None:
        P_dep = np.asarray(P_dep, dtype=np.float64).reshape(-1, 2, 2)
        rows['cov_dep_xx'], rows['cov_dep_xy'] = P_dep[:, 0, 0], P_dep[:, 0, 1]
        rows['cov_dep_yy'] = P_dep[:, 1, 1]
    return rows


def read_removed(msg):
    """
    Return the landmarks a ``fused_landmark_updates`` message announces as removed.

    Parameters
    ----------
    msg : sensor_msgs.msg.PointCloud2
        The message to read.

    Returns
    -------
    removed : ndarray of int64, shape (K,)
        Landmark IDs taken out of the map.
    merged_into : ndarray of int64, shape (K,)
        The landmark each went into.

    Raises
    ------
    landmark_ros.ros.cloud.CloudError
        As ``read_columns``.

    """
    columns = read_columns(msg, REMOVED_FIELDS)
    if 'merged_into' not in columns:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    removed = (columns['observations'] == 0) & (columns['merged_into'] != NOT_MERGED)
    return columns['id'][removed], columns['merged_into'][removed]


def read_landmarks(msg):
    """
    Return the rows of a ``landmarks`` or ``fused_landmarks`` cloud.

    Parameters
    ----------
    msg : sensor_msgs.msg.PointCloud2
        The message to read.

    Returns
    -------
    Landmarks

    Raises
    ------
    landmark_ros.ros.cloud.CloudError
        As ``read_landmark_cloud``.

    """
    return read_landmark_cloud(msg)[0]


def read_landmark_cloud(msg):
    """
    Return the rows of a ``landmarks`` or ``fused_landmarks`` cloud and its optional groups.

    Parameters
    ----------
    msg : sensor_msgs.msg.PointCloud2
        The message to read.

    Returns
    -------
    Landmarks
    LandmarkExtras

    Raises
    ------
    landmark_ros.ros.cloud.CloudError
        If a field is missing, of the wrong type, or the data length is wrong
        (``missing_field``, ``unsupported_field_type``, ``data_length_mismatch``), or
        only part of the ``cov_dep_*`` group, of ``SCAN_FIELDS`` or of ``BIAS_FIELDS``
        is present, or ``BIAS_FIELDS`` without ``SCAN_FIELDS`` (``partial_field_group``).

    """
    return _landmarks_of(read_columns(msg, LANDMARK_FIELDS))


def read_landmark_clouds(msgs):
    """
    Return what ``read_landmark_cloud`` returns for each message, or its CloudError.

    The records of consecutive clouds with one layout are converted together: a
    callback that takes many small clouds pays the conversion's fixed cost once.

    Parameters
    ----------
    msgs : sequence of sensor_msgs.msg.PointCloud2 (or ``cloud_bytes.Cloud``)
        The clouds, in any order (runs of one layout are read together).

    Returns
    -------
    list
        Per message, ``(Landmarks, LandmarkExtras)`` or the ``CloudError`` it raised.

    """
    out = [None] * len(msgs)
    records = []
    for k, msg in enumerate(msgs):
        try:
            records.append((k, read_records(msg, LANDMARK_FIELDS)))
        except CloudError as error:
            out[k] = error
    start = 0
    while start < len(records):
        stop = start + 1
        dtype = records[start][1].dtype
        while stop < len(records) and records[stop][1].dtype is dtype:
            stop += 1
        group = records[start:stop]
        start = stop
        try:
            # The bytes joined (np.concatenate of structured arrays costs ~1 us each).
            joined = np.frombuffer(b''.join([r.data for _, r in group]), dtype)
            rows, extras = _landmarks_of(columns_of(joined), scans=True)
        except CloudError as error:
            for k, _ in group:
                out[k] = error
            continue
        first = 0
        for k, part in group:
            at = slice(first, first + len(part))
            first = at.stop
            out[k] = (Landmarks(*(column[at] for column in rows)),
                      LandmarkExtras(extras.classes[at], extras.scan[at.start]
                                     if extras.scan is not None and len(part) else None))
    return out


class _Scans:
    """The ``Scan`` of the row at an index of columns (a message's first row), on demand."""

    def __init__(self, columns):
        self.columns = columns

    def __getitem__(self, index):
        return _scan(self.columns, index)


def _landmarks_of(columns, scans=False):
    """
    Return ``Landmarks`` and ``LandmarkExtras`` of landmark cloud columns.

    ``LandmarkExtras.scan`` is the first row's ``Scan``, or with ``scans`` a ``_Scans``
    of every row (None without the fields either way).
    """
    count = len(columns['x'])
    for group, what in ((MEAN_FIELDS, 'the position estimate'),
                        (DEPENDENT_FIELDS, 'the dependent covariance'),
                        (SCAN_FIELDS, 'the robot pose terms'),
                        (BIAS_FIELDS, 'the sensor bias terms')):
        present = [name for name in group if name in columns]
        if present and len(present) != len(group):
            missing = [name for name in group if name not in columns]
            raise CloudError('partial_field_group',
                             f'{present} without {missing}: {what} need all '
                             f'{len(group)} fields or none')
    if BIAS_FIELDS[0] in columns and SCAN_FIELDS[0] not in columns:
        raise CloudError('partial_field_group', 'sensor bias fields without the robot pose '
                         'fields')

    def matrices(xx, xy, yy):
        P = np.zeros((count, 2, 2))
        if xx in columns:
            P[:, 0, 0], P[:, 1, 1] = columns[xx], columns[yy]
            P[:, 0, 1] = P[:, 1, 0] = columns[xy]
        return P

    if SCAN_FIELDS[0] not in columns:
        scan = None
    else:
        scan = _Scans(columns) if scans else _scan(columns, 0)
    x, y = MEAN_FIELDS if MEAN_FIELDS[0] in columns else ('x', 'y')
    return (Landmarks(columns['id'], np.stack([columns[x], columns[y]], axis=1),
                      matrices('cov_xx', 'cov_xy', 'cov_yy'),
                      matrices(*DEPENDENT_FIELDS),
                      columns.get('observations', np.ones(count, np.int64))),
            LandmarkExtras(columns.get('class', np.zeros(count, np.int64)), scan))


def _scan(columns, index):
    """Return the ``Scan`` of a landmark cloud's row ``index``, None without the fields."""
    if SCAN_FIELDS[0] not in columns or index >= len(columns[SCAN_FIELDS[0]]):
        return None
    v = {name: float(columns[name][index])
         for name in SCAN_FIELDS + BIAS_FIELDS + (HEADING_FIELD, SCALE_FIELD)
         if name in columns}
    P_pose = np.array([[v['pose_cov_xx'], v['pose_cov_xy'], v['pose_cov_xt']],
                       [v['pose_cov_xy'], v['pose_cov_yy'], v['pose_cov_yt']],
                       [v['pose_cov_xt'], v['pose_cov_yt'], v['pose_cov_tt']]])
    R_bias = sensor_xy = None
    if 'bias_cov_rr' in v:
        R_bias = np.array([[v['bias_cov_rr'], v['bias_cov_rb']],
                           [v['bias_cov_rb'], v['bias_cov_bb']]])
        sensor_xy = np.array([v['sensor_x'], v['sensor_y']])
    heading, scale = v.get(HEADING_FIELD, np.nan), v.get(SCALE_FIELD, np.nan)
    return Scan(np.array([v['robot_x'], v['robot_y']]), P_pose, R_bias, sensor_xy,
                float(heading) if np.isfinite(heading) else None,
                float(scale) if np.isfinite(scale) and R_bias is not None else 0.0)


def partial_observation_message(header, columns, out=None):
    """
    Return a ``partial_observations`` cloud.

    Parameters
    ----------
    header : std_msgs.msg.Header
        Stamp and world frame.
    columns : dict of str to ndarray, shape (N,)
        ``pipeline.partial_rows.PARTIAL_COLUMNS`` and optionally ``RANGE_SCALE_COLUMNS``
        (``PartialObservations.columns``).
    out : sensor_msgs.msg.PointCloud2, optional
        A message to fill instead of a new one.

    Returns
    -------
    sensor_msgs.msg.PointCloud2

    """
    rows = PARTIAL_WRITER.rows(len(columns['id']))
    for name, values in with_range_scale(columns).items():
        if name in PARTIAL_WRITER_NAMES:
            rows[name] = values
    return PARTIAL_WRITER.message(header, rows, out)


def read_partial_observations(msg):
    """
    Return the columns of a ``partial_observations`` cloud.

    Raises
    ------
    landmark_ros.ros.cloud.CloudError
        If a field is missing, of the wrong type, or the data length is wrong.

    """
    return read_columns(msg, PARTIAL_FIELDS)
