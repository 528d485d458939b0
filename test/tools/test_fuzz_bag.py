"""
Damaged bags through ``landmark_bag``: the readable part processed, the rest counted.

A good bag is written with ``rosbags`` (MCAP through ``BagOutput``, and sqlite3), then
damaged: one message record's channel id changed, the file cut short, bytes
overwritten anywhere (a hypothesis fuzz). The property: ``process_bag`` returns (with
``damage`` counting what was skipped, by reason) or raises ``BagError``; the CLI exits
0, 2 or 3 without a traceback.
"""

import json
import os
from pathlib import Path
import shutil
import struct

from geometry_msgs.msg import PoseWithCovarianceStamped
from hypothesis import given, HealthCheck, settings, strategies as st
from landmark_ros.bag import cli as bag_cli
from landmark_ros.bag.process import process_bag
from landmark_ros.bag.storage import BagError, BagOutput, open_bag, typestore
from landmark_ros.ros.schemas import make_header, observation_message, pose_message
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from sensor_msgs.msg import PointCloud2

COUNT = 60
"""Poses and observation messages each: 120 messages."""
EXAMPLES = max(10, int(os.environ.get('LANDMARK_FUZZ_EXAMPLES', '150')) // 50)


def messages():
    """Yield ``(topic, time_ns, message)`` of one robot seeing two landmarks."""
    for k in range(COUNT):
        t = 1.0 + 0.1 * k
        yield '/robot1/pose', int(t * 1e9), pose_message(t, [0.1 * k, 0.0, 0.0],
                                                         np.eye(3) * 1e-3)
        yield '/robot1/observations', int(t * 1e9) + 1000, observation_message(
            make_header(t, ''), [1, 2], np.array([[4.0, 0.3], [5.0, -0.4]]))


def write_mcap(path):
    with BagOutput(path) as out:
        out.add_topic('/robot1/pose', PoseWithCovarianceStamped)
        out.add_topic('/robot1/observations', PointCloud2)
        for topic, time_ns, msg in messages():
            out.write(topic, time_ns, msg)
    return next(Path(path).glob('*.mcap'))


def write_sqlite(path):
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3)
    writer.open()
    classes = {'/robot1/pose': 'geometry_msgs/msg/PoseWithCovarianceStamped',
               '/robot1/observations': 'sensor_msgs/msg/PointCloud2'}
    connections = {topic: writer.add_connection(topic, name, typestore=typestore())
                   for topic, name in classes.items()}
    for topic, time_ns, msg in messages():
        writer.write(connections[topic], time_ns, serialize_message(msg))
    writer.close()
    return next(Path(path).glob('*.db3'))


@pytest.fixture(scope='module')
def good_bags(tmp_path_factory):
    base = tmp_path_factory.mktemp('bags')
    return {'mcap': write_mcap(base / 'mcap'), 'sqlite3': write_sqlite(base / 'sqlite3')}


def run(bag_file, out, capsys):
    code = bag_cli.main([str(bag_file), '-o', str(out), '--no-progress'])
    captured = capsys.readouterr()
    assert 'Traceback' not in captured.err
    return code, captured


def test_a_whole_bag_exits_0_with_no_damage(good_bags, tmp_path, capsys):
    code, captured = run(good_bags['mcap'], tmp_path / 'out', capsys)
    assert code == 0 and 'damaged' not in captured.out


def test_an_unknown_channel_id_is_a_reported_shortfall(good_bags, tmp_path):
    bag = tmp_path / 'bag.mcap'
    data = bytearray(good_bags['mcap'].read_bytes())
    raw = serialize_message(pose_message(1.0 + 0.1 * 30, [3.0, 0.0, 0.0], np.eye(3) * 1e-3))
    at = bytes(data).find(raw)
    assert at > 0
    # A message record: opcode, length, channel id (uint16), sequence, two times, data.
    struct.pack_into('<H', data, at - 22, 0xFFFF)
    bag.write_bytes(bytes(data))
    result = process_bag(bag, tmp_path / 'out')
    assert result.messages_expected == 2 * COUNT and result.messages_in == 2 * COUNT - 1
    assert result.damage == {'unknown_channel': 1, 'messages_missing': 1}
    assert result.counts['/robot1/landmarks'] == COUNT
    code = bag_cli.main([str(bag), '-o', str(tmp_path / 'out2'), '--no-progress',
                         '--json', str(tmp_path / 'r.json')])
    assert code == bag_cli.EXIT_DAMAGED
    report = json.loads((tmp_path / 'r.json').read_text())
    assert report['input_damage'] == result.damage
    assert (report['messages_read'], report['messages_expected']) == (119, 120)


def write_zstd_chunks(path):
    """Write a zstd-compressed MCAP bag of about three chunks; return its file."""
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    classes = {'/robot1/pose': 'geometry_msgs/msg/PoseWithCovarianceStamped',
               '/robot1/observations': 'sensor_msgs/msg/PointCloud2'}
    connections = {topic: writer.add_connection(topic, name, typestore=typestore())
                   for topic, name in classes.items()}
    for topic, time_ns, msg in messages():
        if topic.endswith('observations'):      # padded rows: 40 kB a message
            msg.point_step, msg.row_step = 20000, 40000
            rows = np.frombuffer(bytes(msg.data), np.uint8).reshape(2, -1)
            padded = np.zeros((2, 20000), np.uint8)
            padded[:, :rows.shape[1]] = rows
            msg.data = padded.tobytes()
        writer.write(connections[topic], time_ns, serialize_message(msg))
    writer.close()
    return next(Path(path).glob('*.mcap'))


def test_a_corrupt_zstd_chunk_costs_only_its_messages(tmp_path, capsys):
    source = write_zstd_chunks(tmp_path / 'zstd')
    reader = open_bag(source)
    chunks = sorted(reader.storage.chunks, key=lambda c: c.chunk_start_offset)
    reader.close()
    assert len(chunks) >= 3
    middle = chunks[1]
    data = bytearray(source.read_bytes())
    # The zstd frame's magic number: opcode, length, three times and the CRC, 'zstd'.
    at = middle.chunk_start_offset + 9 + 28 + 4 + len('zstd') + 8
    assert bytes(data[at:at + 4]) == b'\x28\xb5\x2f\xfd'
    data[at:at + 4] = b'\xff' * 4
    bag = tmp_path / 'bad.mcap'
    bag.write_bytes(bytes(data))
    result = process_bag(bag, tmp_path / 'out')
    lost = 2 * COUNT - result.messages_in
    assert result.damage == {'chunk_undecompressable': 1, 'messages_missing': lost}
    # The first and the last chunk read: only the middle one's messages are lost.
    assert 0 < lost < 2 * COUNT // 2
    assert result.counts['/robot1/landmarks'] > 0
    code, captured = run(bag, tmp_path / 'out2', capsys)
    assert code == bag_cli.EXIT_DAMAGED and 'chunk_undecompressable' in captured.out
    written = open_bag(tmp_path / 'out2')
    assert written.message_count == sum(result.counts.values())
    written.close()


def message_record(data, k):
    """Return the offset of the message record of pose ``k`` in an uncompressed MCAP."""
    raw = serialize_message(pose_message(1.0 + 0.1 * k, [0.1 * k, 0.0, 0.0], np.eye(3) * 1e-3))
    at = bytes(data).find(raw)
    assert at > 0
    return at - 22 - 9          # opcode, length, then channel id, sequence, two times


@pytest.mark.parametrize('damage, reason', [('length', 'record_length_invalid'),
                                            ('opcode', 'opcode_invalid')])
def test_one_bad_record_is_counted_and_what_can_be_read_is(good_bags, tmp_path, damage,
                                                           reason):
    data = bytearray(good_bags['mcap'].read_bytes())
    at = message_record(data, 30)
    if damage == 'length':
        struct.pack_into('<Q', data, at + 1, 2 ** 40)
    else:
        data[at] = 0x42
    bag = tmp_path / 'bad.mcap'
    bag.write_bytes(bytes(data))
    result = process_bag(bag, tmp_path / 'out')
    assert result.damage[reason] == 1
    assert result.damage['messages_missing'] == 2 * COUNT - result.messages_in
    # A bad opcode costs one message; a bad length the rest of its chunk (nothing says
    # where the next record starts), never what came before.
    assert result.messages_in == (2 * COUNT - 1 if damage == 'opcode' else 60)


@pytest.mark.parametrize('kind', ['mcap', 'sqlite3'])
def test_a_bag_cut_short_is_processed_or_refused_in_one_line(good_bags, tmp_path, capsys, kind):
    source = good_bags[kind]
    bag = tmp_path / source.name
    data = source.read_bytes()
    bag.write_bytes(data[:int(len(data) * 0.6)])
    code, captured = run(bag, tmp_path / 'out', capsys)
    assert code in (2, bag_cli.EXIT_DAMAGED)
    if code == 2:
        assert captured.err.count('\n') == 1 and not (tmp_path / 'out').exists()
    else:
        assert 'input damaged' in captured.out


@settings(max_examples=EXAMPLES, deadline=None, derandomize=os.environ.get(
    'LANDMARK_FUZZ_RANDOM', '') != '1', database=None, suppress_health_check=list(HealthCheck))
@given(kind=st.sampled_from(['mcap', 'sqlite3']), where=st.floats(0.0, 1.0),
       junk=st.binary(min_size=1, max_size=16))
def test_damaged_bytes_anywhere_give_damage_counts_or_a_bag_error(
        good_bags, tmp_path_factory, kind, where, junk):
    source = good_bags[kind]
    directory = tmp_path_factory.mktemp('fuzz')
    bag = directory / source.name
    data = bytearray(source.read_bytes())
    at = min(int(where * len(data)), len(data) - len(junk))
    data[at:at + len(junk)] = junk
    bag.write_bytes(bytes(data))
    try:
        result = process_bag(bag, directory / 'out')
    except BagError:
        assert not (directory / 'out').exists()
    else:
        missing = result.messages_expected - result.messages_in
        assert missing <= 0 or result.damage.get('messages_missing') == missing
    shutil.rmtree(directory, ignore_errors=True)
