"""Tests of ros.cloud_bytes: serialized PointCloud2 read without building the message."""

from landmark_ros.pipeline.scan import Scan
from landmark_ros.ros import cloud_bytes
from landmark_ros.ros.cloud import CloudError, read_columns
from landmark_ros.ros.cloud_bytes import read_cloud_bytes
from landmark_ros.ros.schemas import LANDMARK_FIELDS, landmark_message, read_landmark_cloud
from landmark_ros.ros.schemas import read_landmark_clouds
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header


def random_cloud(rng):
    """Return a PointCloud2 with random names, layout, sizes and bytes."""
    fields = []
    for k in range(int(rng.integers(0, 7))):
        name = 'f' * int(rng.integers(0, 9)) + str(k)     # every length mod 4
        fields.append(PointField(name=name, offset=int(rng.integers(0, 64)),
                                 datatype=int(rng.integers(1, 9)),
                                 count=int(rng.integers(0, 3))))
    msg = PointCloud2(height=int(rng.integers(0, 4)), width=int(rng.integers(0, 50)),
                      fields=fields, is_bigendian=bool(rng.integers(0, 2)),
                      point_step=int(rng.integers(0, 100)), row_step=int(rng.integers(0, 999)),
                      is_dense=bool(rng.integers(0, 2)))
    msg.header = Header(frame_id='m' * int(rng.integers(0, 11)) + 'ä' * int(rng.integers(0, 2)))
    msg.header.stamp.sec = int(rng.integers(-2 ** 31, 2 ** 31))
    msg.header.stamp.nanosec = int(rng.integers(0, 10 ** 9))
    msg.data = rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
    return msg


def assert_same(got, msg):
    """Assert that a read cloud holds what the message holds."""
    assert isinstance(got, cloud_bytes.Cloud)
    assert (got.header.stamp.sec, got.header.stamp.nanosec, got.header.frame_id) == (
        msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id)
    assert [(f.name, f.offset, f.datatype, f.count) for f in got.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    assert (got.height, got.width, got.is_bigendian, got.point_step, got.row_step,
            got.is_dense) == (msg.height, msg.width, msg.is_bigendian, msg.point_step,
                              msg.row_step, msg.is_dense)
    assert bytes(got.data) == bytes(msg.data)


@pytest.mark.parametrize('seed', range(40))
def test_a_serialized_cloud_reads_back_field_for_field(seed):
    rng = np.random.default_rng(seed)
    msg = random_cloud(rng)
    assert_same(read_cloud_bytes(serialize_message(msg)), msg)
    # The same layout again (its fields from the cache), after a frame ID of every
    # length modulo 4 and with other data.
    for frame_id in ('', 'a', 'ab', 'abc', 'abcd'):
        msg.header.frame_id = frame_id
        msg.data = rng.integers(0, 256, int(rng.integers(0, 50)), dtype=np.uint8).tobytes()
        assert_same(read_cloud_bytes(serialize_message(msg)), msg)


def test_a_landmark_cloud_reads_as_the_message_does(rng):
    count = 100
    A = rng.normal(0.0, 0.3, (count, 2, 2))
    P = A @ np.swapaxes(A, 1, 2) + 0.01 * np.eye(2)
    msg = landmark_message(Header(frame_id='map'), np.arange(count), rng.normal(0, 5, (count, 2)),
                           P, 0.3 * P)
    raw = serialize_message(msg)
    got = read_cloud_bytes(raw)
    assert isinstance(got, cloud_bytes.Cloud)
    for a, b in zip(read_landmark_cloud(got), read_landmark_cloud(msg)):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    columns = read_columns(got, LANDMARK_FIELDS)
    assert not any(np.shares_memory(column, np.frombuffer(raw, np.uint8))
                   for column in columns.values())            # copies, not views of the bytes


@pytest.mark.parametrize('seed', range(20))
def test_cut_or_damaged_bytes_give_what_rclpy_gives_or_a_named_error(seed):
    # Past the fast path rclpy decides: the same message, or malformed_message.
    rng = np.random.default_rng(seed)
    raw = bytearray(serialize_message(random_cloud(rng)))
    cases = [bytes(raw[:int(rng.integers(0, len(raw)))]), b'', b'\x00\x01',
             b'\x00\x00' + bytes(raw[2:])]                       # big-endian header
    damaged = bytearray(raw)
    for at in rng.integers(0, len(raw), 3):
        damaged[at] = int(rng.integers(0, 256))
    cases.append(bytes(damaged))
    for case in cases:
        try:
            got = read_cloud_bytes(case)
        except CloudError as error:
            assert error.reason == 'malformed_message'
            continue
        assert isinstance(got, (cloud_bytes.Cloud, PointCloud2))


def test_a_layout_from_the_cache_must_match_every_byte_but_the_padding(rng):
    # The fields of a known layout are reused only when all their bytes but the
    # padding match: a changed name, offset, datatype or count is read anew.
    msg = PointCloud2(fields=[PointField(name='ab', offset=0, datatype=7, count=1),
                              PointField(name='c', offset=4, datatype=7, count=1)],
                      width=1, height=1, point_step=8, row_step=8, data=bytes(8))
    raw = bytearray(serialize_message(msg))

    def read(data):
        # Twice: the second read finds these exact bytes among those seen.
        first, second = read_cloud_bytes(bytes(data)), read_cloud_bytes(bytes(data))
        assert second.fields == first.fields
        return first

    assert_same(read(raw), msg)
    at = raw.index(b'ab\x00')
    # Padding after 'ab\0' (one byte) and after each datatype (three): other values.
    padded = bytearray(raw)
    padded[at + 3] ^= 0xFF
    assert_same(read(padded), msg)
    for change, expected in ((b'xb\x00', 'xb'), (b'ax\x00', 'ax')):
        changed = bytearray(raw)
        changed[at:at + 3] = change
        got = read(changed)
        assert [f.name for f in got.fields] == [expected, 'c']
    changed = bytearray(raw)
    changed[at + 4] = 9                         # the offset of 'ab'
    assert read(changed).fields[0].offset == 9
    assert_same(read(raw), msg)


def test_clouds_read_together_equal_each_read_alone(rng):
    # Runs of one layout are converted together, then cut back per message: the same
    # rows, classes and scans (each message's first row) as one at a time, and an
    # unreadable cloud among them is an error of its own.
    sent = {}

    def cloud(kind, count):
        A = rng.normal(0.0, 0.3, (count, 2, 2))
        P = A @ np.swapaxes(A, 1, 2) + 0.01 * np.eye(2)
        ids, m = rng.integers(0, 50, count), rng.normal(0, 5, (count, 2))
        header = Header(frame_id='map')
        if kind == 'plain':
            return landmark_message(header, ids, m, P, 0.3 * P)
        if kind == 'classes':
            return landmark_message(header, ids, m, P, classes=rng.integers(0, 4, count))
        if kind == 'scan':
            # The sensor heading, or none (written as NaN, read back as None).
            heading = float(rng.uniform(-4.0, 4.0)) if rng.random() < 0.7 else None
            scan = Scan(rng.normal(0, 3, 2), np.diag(rng.uniform(0.01, 0.1, 3)),
                        heading=heading)
            msg = landmark_message(header, ids, m, P, 0.5 * P,
                                   classes=rng.integers(0, 4, count), scan=scan)
            sent[id(msg)] = heading
            return msg
        msg = landmark_message(header, ids, m, P)
        msg.data = msg.data[:-3]                    # data_length_mismatch
        return msg
    kinds = ['plain', 'plain', 'scan', 'scan', 'bad', 'scan', 'classes', 'plain', 'plain',
             'scan', 'plain']
    msgs = [cloud(kind, int(rng.integers(0, 4)) if k == 7 else int(rng.integers(1, 30)))
            for k, kind in enumerate(kinds)]
    clouds = [read_cloud_bytes(serialize_message(msg)) for msg in msgs]
    got = read_landmark_clouds(clouds)
    assert len(got) == len(msgs)
    for kind, msg, read in zip(kinds, msgs, got):
        if kind == 'bad':
            assert isinstance(read, CloudError) and read.reason == 'data_length_mismatch'
            with pytest.raises(CloudError):
                read_landmark_cloud(msg)
            continue
        rows, extras = read_landmark_cloud(msg)
        for x, y in zip(read[0], rows):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(read[1].classes, extras.classes)
        if extras.scan is None:
            assert read[1].scan is None
        else:
            assert kind == 'scan'
            for name in ('robot_xy', 'P_pose'):
                np.testing.assert_array_equal(getattr(read[1].scan, name),
                                              getattr(extras.scan, name))
            assert read[1].scan.heading == extras.scan.heading == sent[id(msg)]
    assert read_landmark_clouds([]) == []
