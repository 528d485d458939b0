"""Tests of ros.cloud: PointCloud2 columns read and written with numpy."""


from landmark_ros.ros import cloud
from landmark_ros.ros.cloud import CloudError, CloudWriter, FieldSpec, read_columns
import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header


# --- cloud ---------------------------------------------------------------------------------------

ALL_TYPES = [('i8', np.int8, PointField.INT8), ('u8', np.uint8, PointField.UINT8),
             ('i16', np.int16, PointField.INT16), ('u16', np.uint16, PointField.UINT16),
             ('i32', np.int32, PointField.INT32), ('u32', np.uint32, PointField.UINT32),
             ('f32', np.float32, PointField.FLOAT32), ('f64', np.float64, PointField.FLOAT64)]


def _fill(rows, rng):
    values = {}
    for name, dtype, _ in ALL_TYPES:
        if np.dtype(dtype).kind == 'f':
            column = rng.standard_normal(len(rows)).astype(dtype) * 1e3
            column[:2] = [np.finfo(dtype).max, np.nan]
        else:
            info = np.iinfo(dtype)
            column = rng.integers(info.min, info.max, len(rows), dtype=dtype, endpoint=True)
            column[:2] = [info.min, info.max]
        rows[name] = column
        values[name] = column
    return values


def test_cloud_writer_reader_round_trip_all_datatypes(rng):
    writer = CloudWriter([(name, dtype) for name, dtype, _ in ALL_TYPES])
    rows = writer.rows(25)
    values = _fill(rows, rng)
    header = Header(frame_id='map')
    msg = writer.message(header, rows)
    assert msg.header.frame_id == 'map' and msg.height == 1 and msg.width == 25
    assert not msg.is_bigendian and msg.point_step % 8 == 0
    assert msg.row_step == msg.point_step * 25 == len(msg.data)
    assert [f.datatype for f in msg.fields] == [code for _, _, code in ALL_TYPES]
    for f, (_, dtype, _) in zip(msg.fields, ALL_TYPES):
        assert f.offset % np.dtype(dtype).itemsize == 0 and f.count == 1
    columns = read_columns(msg, tuple(FieldSpec(name, (code,)) for name, _, code in ALL_TYPES))
    for name, dtype, _ in ALL_TYPES:
        expected = values[name]
        got = columns[name]
        if np.dtype(dtype).kind == 'f':
            assert got.dtype == np.float64
            np.testing.assert_array_equal(got, expected.astype(np.float64))
        else:
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, expected.astype(np.int64))


def test_cloud_writer_layout_aligns_fields():
    writer = CloudWriter([('a', np.uint8), ('b', np.float64), ('c', np.uint16),
                          ('d', np.float32)])
    assert [f.offset for f in writer.fields] == [0, 8, 16, 20]
    assert writer.dtype.itemsize == 24
    writer = CloudWriter([('a', np.uint8)])
    assert writer.dtype.itemsize == 8


def _manual_cloud(values, dtype, height, width, row_step=None, bigendian=False, pad=b'\xab'):
    """Build a PointCloud2 from a structured array of height * width rows by hand."""
    msg = PointCloud2()
    msg.height, msg.width = height, width
    msg.is_bigendian = bigendian
    msg.point_step = dtype.itemsize
    msg.row_step = row_step or width * dtype.itemsize
    codes = {np.dtype(t).newbyteorder('='): c for _, t, c in ALL_TYPES}
    msg.fields = [PointField(name=name, offset=dtype.fields[name][1],
                             datatype=codes[dtype.fields[name][0].newbyteorder('=')], count=1)
                  for name in dtype.names]
    data = b''
    raw = values.tobytes()
    for r in range(height):
        row = raw[r * width * dtype.itemsize:(r + 1) * width * dtype.itemsize]
        data += row + pad * (msg.row_step - len(row))
    msg.data = data
    return msg


def test_cloud_reader_big_endian(rng):
    dtype = np.dtype({'names': ['x', 'id', 'v'], 'formats': ['>f8', '>u4', '>i2'],
                      'offsets': [0, 8, 12], 'itemsize': 16})
    values = np.zeros(7, dtype)
    values['x'] = rng.standard_normal(7)
    values['id'] = rng.integers(0, 2 ** 32, 7)
    values['v'] = rng.integers(-2 ** 15, 2 ** 15, 7)
    msg = _manual_cloud(values, dtype, 1, 7, bigendian=True)
    columns = read_columns(msg, (FieldSpec('x', (PointField.FLOAT64,)),
                                 FieldSpec('id', (PointField.UINT32,)),
                                 FieldSpec('v', (PointField.INT16,))))
    np.testing.assert_array_equal(columns['x'], values['x'])
    np.testing.assert_array_equal(columns['id'], values['id'].astype(np.int64))
    np.testing.assert_array_equal(columns['v'], values['v'].astype(np.int64))


def test_cloud_reader_height_and_row_padding(rng):
    dtype = np.dtype({'names': ['x', 'id'], 'formats': ['<f4', '<u4'], 'offsets': [0, 4],
                      'itemsize': 12})
    height, width = 3, 4
    values = np.zeros(height * width, dtype)
    values['x'] = np.arange(12) * 1.5
    values['id'] = np.arange(12) + 100
    msg = _manual_cloud(values, dtype, height, width, row_step=width * 12 + 7)
    assert len(msg.data) == height * (width * 12 + 7)
    columns = read_columns(msg, (FieldSpec('x', (PointField.FLOAT32,)),
                                 FieldSpec('id', (PointField.UINT32,))))
    np.testing.assert_array_equal(columns['x'], values['x'])
    np.testing.assert_array_equal(columns['id'], np.arange(12) + 100)


def test_cloud_reader_optional_fields_and_empty_clouds(rng):
    writer = CloudWriter([('x', np.float32), ('id', np.uint32)])
    specs = (FieldSpec('x', (PointField.FLOAT32,)), FieldSpec('id', (PointField.UINT32,)),
             FieldSpec('range_variance', (PointField.FLOAT32,), required=False))
    rows = writer.rows(3)
    rows['x'] = [1.0, 2.0, 3.0]
    columns = read_columns(writer.message(Header(), rows), specs)
    assert set(columns) == {'x', 'id'}
    columns = read_columns(writer.message(Header(), writer.rows(0)), specs)
    assert columns['x'].shape == (0,) and columns['x'].dtype == np.float64
    assert columns['id'].shape == (0,) and columns['id'].dtype == np.int64


def _valid_message():
    writer = CloudWriter([('x', np.float32), ('id', np.uint32)])
    rows = writer.rows(4)
    rows['x'] = [1.0, 2.0, 3.0, 4.0]
    return writer.message(Header(), rows)


SPECS = (FieldSpec('x', (PointField.FLOAT32, PointField.FLOAT64)),
         FieldSpec('id', (PointField.UINT32,)))


def _break(change):
    msg = _valid_message()
    change(msg)
    return msg


@pytest.mark.parametrize('change, reason', [
    (lambda msg: setattr(msg, 'fields', msg.fields[:1]), 'missing_field'),
    (lambda msg: setattr(msg.fields[0], 'name', 'y'), 'missing_field'),
    (lambda msg: setattr(msg.fields[1], 'datatype', PointField.INT32), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[0], 'datatype', PointField.INT32), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[0], 'count', 2), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[0], 'count', 0), 'unsupported_field_type'),
    (lambda msg: setattr(msg.fields[1], 'offset', msg.point_step - 2), 'data_length_mismatch'),
    (lambda msg: setattr(msg.fields[0], 'datatype', PointField.FLOAT64) or setattr(
        msg.fields[0], 'offset', msg.point_step - 4), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'row_step', msg.row_step - 1), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'data', bytes(msg.data)[:-1]), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'data', bytes(msg.data) + b'\x00'), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'height', 2), 'data_length_mismatch'),
    (lambda msg: setattr(msg, 'width', 5), 'data_length_mismatch'),
])
def test_cloud_errors(change, reason):
    msg = _break(change)
    with pytest.raises(CloudError) as info:
        read_columns(msg, SPECS)
    assert info.value.reason == reason
    assert str(info.value).startswith(reason + ': ')
    assert isinstance(info.value, ValueError)


def test_cloud_valid_message_reads():
    columns = read_columns(_valid_message(), SPECS)
    np.testing.assert_array_equal(columns['x'], [1.0, 2.0, 3.0, 4.0])
    assert cloud.DATATYPES[np.dtype(np.float32)] == PointField.FLOAT32


def test_cloud_reader_accepts_a_list_of_specs():
    columns = read_columns(_valid_message(), list(SPECS))
    np.testing.assert_array_equal(columns['x'], [1.0, 2.0, 3.0, 4.0])


def test_cloud_layout_cache_does_not_mix_layouts(rng):
    # The same specs on clouds of different layouts (offsets, endianness) read correctly.
    specs = (FieldSpec('x', (PointField.FLOAT64,)), FieldSpec('id', (PointField.UINT32,)))
    for order in ('<', '>'):
        for offsets in ([0, 8], [4, 0], [8, 0]):
            dtype = np.dtype({'names': ['x', 'id'], 'formats': [order + 'f8', order + 'u4'],
                              'offsets': offsets, 'itemsize': 16})
            values = np.zeros(5, dtype)
            values['x'] = rng.standard_normal(5)
            values['id'] = rng.integers(0, 1000, 5)
            msg = _manual_cloud(values, dtype, 1, 5, bigendian=order == '>')
            columns = read_columns(msg, specs)
            np.testing.assert_array_equal(columns['x'], values['x'])
            np.testing.assert_array_equal(columns['id'], values['id'])
    # And a bad layout raises every time, not only the first.
    for _ in range(2):
        with pytest.raises(CloudError):
            read_columns(_break(lambda msg: setattr(msg.fields[0], 'count', 2)), SPECS)
