"""
Landmark clouds are drawable by RViz and readable by PCL, and keep the estimate's precision.

RViz's PointCloud2 display (``XYZPCTransformer``) takes a cloud only when it has fields
``x``, ``y``, ``z`` of datatype FLOAT32; PCL's ``fromROSMsg`` into ``pcl::PointXYZ`` maps
the fields of the same name and datatype (FLOAT32, count 1) and copies them from their
offsets. ``rviz_xyz`` and ``pcl_xyz`` below do what those do; the package's own readers
(``schemas.read_landmark_clouds`` on ``cloud_bytes``, ``read_landmarks``) must still get
the float64 estimate back, from these clouds and from the earlier FLOAT64 layout.
"""

from pathlib import Path

from hypothesis import given, settings, strategies as st
from landmark_ros.pipeline.scan import Scan
from landmark_ros.ros.cloud import CloudError, CloudWriter
from landmark_ros.ros.cloud_bytes import read_cloud_bytes
from landmark_ros.ros.schemas import fused_landmark_message, landmark_message, make_header
from landmark_ros.ros.schemas import read_landmark_cloud, read_landmark_clouds
from landmark_ros.ros.schemas import read_landmarks, read_removed
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointField
import yaml

ROOT = Path(__file__).resolve().parents[2]
C = np.array([[0.04, 0.01], [0.01, 0.09]])


def rviz_xyz(msg):
    """Return the points RViz's XYZ position transformer draws; raise if it refuses."""
    fields = {f.name: f for f in msg.fields}
    if not all(name in fields and fields[name].datatype == PointField.FLOAT32
               for name in 'xyz'):
        raise AssertionError('No position transformer available for cloud')
    return pcl_xyz(msg)


def pcl_xyz(msg):
    """Return ``pcl::fromROSMsg`` into ``pcl::PointXYZ``: FLOAT32 x y z by name, shape (N, 3)."""
    fields = {f.name: f for f in msg.fields}
    for name in 'xyz':
        field = fields.get(name)
        assert field is not None and field.datatype == PointField.FLOAT32 and \
            field.count == 1, f'pcl::PointXYZ has no match for {name}'
    dtype = np.dtype({'names': list('xyz'), 'formats': ['<f4'] * 3,
                      'offsets': [fields[n].offset for n in 'xyz'],
                      'itemsize': msg.point_step})
    rows = np.frombuffer(bytes(msg.data), dtype, count=msg.width * msg.height)
    return np.stack([rows['x'], rows['y'], rows['z']], axis=1)


def clouds(m, ids=None):
    """Return every kind of landmark cloud the package publishes, by topic."""
    n = len(m)
    ids = np.arange(n) if ids is None else ids
    P = np.broadcast_to(C, (n, 2, 2))
    header = make_header(12.5, 'map')
    scan = Scan(np.array([1.0, 2.0]), np.diag([0.01, 0.01, 0.001]), np.diag([0.01, 1e-4]),
                np.array([1.5, 2.0]))
    return {
        'landmarks': landmark_message(header, ids, m, P, 0.5 * P),
        'landmarks (class)': landmark_message(header, ids, m, P, classes=np.ones(n, int)),
        'landmarks (unlabelled rows)': landmark_message(header, ids, m, P, scan=scan),
        'fused_landmarks': fused_landmark_message(header, ids, m, P, 0.5 * P, np.full(n, 3)),
        'fused_landmark_updates': fused_landmark_message(
            header, ids, m, P, 0.5 * P, np.full(n, 3), merged_into=np.full(n, 4294967295)),
    }


M = np.array([[2.449431021, 5.728156342], [-17.25, 0.1], [512345.678901, 4321987.654321]])


@pytest.mark.parametrize('topic', list(clouds(M)))
def test_every_landmark_cloud_is_drawn_by_rviz_and_read_by_pcl(topic):
    msg = clouds(M)[topic]
    fields = {f.name: f for f in msg.fields}
    assert [(fields[n].offset, fields[n].datatype, fields[n].count) for n in 'xyz'] == \
        [(0, PointField.FLOAT32, 1), (4, PointField.FLOAT32, 1), (8, PointField.FLOAT32, 1)]
    assert msg.is_bigendian is False
    expected = np.column_stack([M, np.zeros(len(M))]).astype(np.float32)
    np.testing.assert_array_equal(rviz_xyz(msg), expected)
    np.testing.assert_array_equal(pcl_xyz(msg), expected)


@pytest.mark.parametrize('topic', list(clouds(M)))
def test_the_package_reads_the_float64_estimate_back(topic):
    msg = clouds(M)[topic]
    fields = {f.name: f for f in msg.fields}
    assert [fields[n].datatype for n in ('mean_x', 'mean_y')] == [PointField.FLOAT64] * 2
    np.testing.assert_array_equal(read_landmarks(msg).m, M)   # exactly, not to float32
    (fast, _), = read_landmark_clouds([read_cloud_bytes(serialize_message(msg))])
    np.testing.assert_array_equal(fast.m, M)
    assert not np.array_equal(M.astype(np.float32).astype(np.float64), M)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e7, 1e7), st.floats(-1e7, 1e7)), min_size=1,
                max_size=20))
def test_positions_survive_exactly_and_display_rounded(points):
    m = np.array(points, dtype=np.float64)
    for msg in clouds(m).values():
        np.testing.assert_array_equal(read_landmarks(msg).m, m)
        np.testing.assert_array_equal(pcl_xyz(msg)[:, :2], m.astype(np.float32))


OLD_SCHEMA = (('id', np.uint32), ('x', np.float64), ('y', np.float64), ('z', np.float64),
              ('cov_xx', np.float64), ('cov_xy', np.float64), ('cov_yy', np.float64),
              ('cov_dep_xx', np.float64), ('cov_dep_xy', np.float64), ('cov_dep_yy', np.float64),
              ('observations', np.uint32))


def old_cloud(m, ids):
    """Return a fused cloud in the earlier layout: id first, FLOAT64 x y z, no mean_*."""
    writer = CloudWriter(OLD_SCHEMA)
    rows = writer.rows(len(m))
    rows['id'], rows['x'], rows['y'] = ids, m[:, 0], m[:, 1]
    rows['cov_xx'], rows['cov_xy'], rows['cov_yy'] = C[0, 0], C[0, 1], C[1, 1]
    rows['observations'] = 2
    return writer.message(make_header(1.0, 'map'), rows)


def test_clouds_of_the_earlier_layout_still_read():
    ids = np.array([4, 9, 11])
    old = old_cloud(M, ids)
    rows = read_landmarks(old)
    assert rows.ids.tolist() == ids.tolist() and rows.observations.tolist() == [2] * 3
    np.testing.assert_array_equal(rows.m, M)
    np.testing.assert_array_equal(rows.P, np.broadcast_to(C, (3, 2, 2)))
    # Both layouts in one batch of the fuser's reader (runs of one layout each).
    new = clouds(M[:2], ids[:2])['fused_landmarks']
    batch = [read_cloud_bytes(serialize_message(msg)) for msg in (old, new, old)]
    got = read_landmark_clouds(batch)
    for (rows, _), expected in zip(got, (M, M[:2], M)):
        np.testing.assert_array_equal(rows.m, expected)


def test_a_pcl_style_float32_cloud_reads():
    writer = CloudWriter((('x', np.float32), ('y', np.float32), ('z', np.float32),
                          ('id', np.uint32), ('cov_xx', np.float32), ('cov_xy', np.float32),
                          ('cov_yy', np.float32)))
    rows = writer.rows(2)
    rows['x'], rows['y'], rows['id'] = [1.5, -2.25], [3.0, 4.5], [1, 2]
    rows['cov_xx'], rows['cov_yy'] = 0.25, 0.5
    got = read_landmarks(writer.message(make_header(1.0, 'map'), rows))
    np.testing.assert_array_equal(got.m, [[1.5, 3.0], [-2.25, 4.5]])
    np.testing.assert_array_equal(got.P[:, 1, 1], [0.5, 0.5])


def test_half_a_position_estimate_is_refused():
    writer = CloudWriter((('x', np.float32), ('y', np.float32), ('z', np.float32),
                          ('id', np.uint32), ('mean_x', np.float64), ('cov_xx', np.float64),
                          ('cov_xy', np.float64), ('cov_yy', np.float64)))
    msg = writer.message(make_header(1.0, 'map'), writer.rows(1))
    with pytest.raises(CloudError, match='mean_y') as error:
        read_landmarks(msg)
    assert error.value.reason == 'partial_field_group'


def test_removed_landmarks_still_announced():
    msg = fused_landmark_message(make_header(1.0, 'map'), [5, 6], M[:2], [C, C], None, [0, 3],
                                 merged_into=[6, 4294967295])
    removed, into = read_removed(msg)
    assert removed.tolist() == [5] and into.tolist() == [6]


def test_every_cloud_rviz_is_configured_to_show_is_a_drawable_one():
    document = yaml.safe_load((ROOT / 'rviz' / 'landmarks.rviz').read_text())
    shown = {d['Topic']['Value'] for d in document['Visualization Manager']['Displays']
             if d['Class'] == 'rviz_default_plugins/PointCloud2'}
    assert shown == {'/fused_landmarks'}     # add a check below for any new cloud display
    rviz_xyz(clouds(M)['fused_landmarks'])


def test_the_range_scale_variance_of_a_scan_survives_the_cloud():
    m = M[:2]
    P = np.broadcast_to(C, (2, 2, 2))
    header = make_header(12.5, 'map')
    for scale in (0.0, 1e-4):
        scan = Scan(np.array([1.0, 2.0]), np.diag([0.01, 0.01, 0.001]),
                    np.diag([0.01, 1e-4]), np.array([1.5, 2.0]), 0.3, scale)
        msg = landmark_message(header, np.arange(2), m, P, 0.5 * P, scan=scan)
        for read in (read_landmark_cloud(msg),
                     read_landmark_clouds([read_cloud_bytes(serialize_message(msg))])[0]):
            assert read[1].scan.range_scale_variance == scale
            np.testing.assert_array_equal(read[1].scan.R_bias, scan.R_bias)
    # A cloud of the earlier layout (no bias_cov_ss) reads as no scale error.
    plain = Scan(np.array([1.0, 2.0]), np.diag([0.01, 0.01, 0.001]))
    msg = landmark_message(header, np.arange(2), m, P, 0.5 * P, scan=plain)
    assert read_landmark_cloud(msg)[1].scan.range_scale_variance == 0.0
