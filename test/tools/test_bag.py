"""
landmark_bag and the MRCLAM bag export: a dataset as a bag, the bag through the pipeline.

A small synthetic MRCLAM dataset (``test_mrclam.make_dataset``, noisy, two robots) is
exported, processed with ``landmark_bag`` and compared with the offline replay of
``landmark_mrclam``: the same map to 1e-9. The output bag is read back with ``rosbags``.
Bad bags (a missing topic, a truncated file, a topic of an unknown type) exit with code 2
and leave nothing behind. The output is MCAP or SQLite 3 (``--storage``, by default the
input's), read back with ``rosbags`` either way. The dataset-6 test runs the first two
minutes of the real data and skips when the data is absent.
"""

from dataclasses import replace
import json
import os
from pathlib import Path
import sys

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.bag import cli as bag_cli
from landmark_ros.bag.export import export_dataset, pose_stddev_from_config
from landmark_ros.bag.params import key_pattern, load_config, node_parameters, read_document
from landmark_ros.bag.process import process_bag
from landmark_ros.bag.storage import BagError, BagOutput, open_bag, storage_of, typestore
from landmark_ros.mrclam.config import load_config as load_replay_config
from landmark_ros.mrclam.data import load_dataset
from landmark_ros.mrclam.offline import run_offline
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.ros.cloud import read_columns
from landmark_ros.ros.conversions import pose_from_msg, stamp_ns
from landmark_ros.ros.schemas import OBSERVATION_FIELDS, read_landmarks
import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Writer
from sensor_msgs.msg import PointCloud2
from test_mrclam import make_dataset, static_config
from visualization_msgs.msg import MarkerArray
import yaml

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

REPO_ROOT = Path(__file__).resolve().parents[2]
DATASET6 = REPO_ROOT.parent / 'shared' / 'data' / 'mrclam' / 'dataset6'
CONFIG = REPO_ROOT / 'config' / 'mrclam.yaml'
SPLIT_CI = 'split_covariance_intersection'
CLASSES = {'geometry_msgs/msg/PoseWithCovarianceStamped': PoseWithCovarianceStamped,
           'sensor_msgs/msg/PointCloud2': PointCloud2,
           'visualization_msgs/msg/MarkerArray': MarkerArray,
           'diagnostic_msgs/msg/DiagnosticArray': DiagnosticArray}


def read_bag(path):
    """Return ``topic -> (msgtype, [(bag time, message), ...])`` of a whole bag."""
    reader = open_bag(path)
    try:
        topics = {topic: (info.msgtype, []) for topic, info in reader.topics.items()}
        for connection, time_ns, raw in reader.messages():
            message = deserialize_message(bytes(raw), CLASSES[connection.msgtype])
            topics[connection.topic][1].append((time_ns, message))
    finally:
        reader.close()
    return topics


def offline_records(directory, config_path=CONFIG, dataset=None):
    """Return the offline replay's split-CI map (``landmark_mrclam``'s ``MethodResult``)."""
    config = load_replay_config(config_path)
    dataset = dataset if dataset is not None else load_dataset(directory, config.pose_stddev)
    return run_offline(dataset, config, [SPLIT_CI]).results[SPLIT_CI]


def assert_same_map(records, expected, atol=1e-9):
    """Assert two lists of map records agree: IDs, counts, means and covariances."""
    records = sorted(records, key=lambda r: r['id'])
    expected = sorted(expected, key=lambda r: r['id'])
    assert [r['id'] for r in records] == [r['id'] for r in expected]
    assert [r['observations'] for r in records] == [r['observations'] for r in expected]
    for key in ('mean', 'covariance', 'covariance_dependent'):
        np.testing.assert_allclose(np.array([r[key] for r in records], dtype=float),
                                   np.array([r[key] for r in expected], dtype=float),
                                   rtol=0, atol=atol, err_msg=key)


def assert_nothing_left(directory, output):
    """Assert no output and no temporary directory was left in ``directory``."""
    assert not output.exists()
    assert not [p.name for p in directory.iterdir() if p.name.startswith('.')]


@pytest.fixture
def noisy(tmp_path):
    """Return the directory of a small noisy dataset and its exported bag."""
    directory = tmp_path / 'noisy'
    make_dataset(directory, noise=(0.02, 0.03, 0.01), bias=(0.02, 0.004),
                 rng=np.random.default_rng(7))
    bag = tmp_path / 'noisy_bag'
    export_dataset(load_dataset(directory), pose_stddev_from_config(CONFIG), bag)
    return directory, bag


# Export ----------------------------------------------------------------------------------

def test_export_writes_poses_then_observations_at_the_measurement_stamps(noisy):
    directory, bag = noisy
    dataset = load_dataset(directory)
    rows = dataset.rows()
    starts, ends = rows.messages()
    topics = read_bag(bag)
    assert set(topics) == {'/ground_truth_landmarks', '/robot1/pose', '/robot1/observations',
                           '/robot2/pose', '/robot2/observations'}
    assert topics['/robot1/pose'][0] == 'geometry_msgs/msg/PoseWithCovarianceStamped'
    assert topics['/robot1/observations'][0] == 'sensor_msgs/msg/PointCloud2'
    (time_ns, truth), = topics['/ground_truth_landmarks'][1]
    landmarks = read_landmarks(truth)
    assert {int(i): tuple(m) for i, m in zip(landmarks.ids, landmarks.m)} == dataset.landmarks
    assert not landmarks.P.any() and not landmarks.P_dep.any()
    P_pose = np.diag(np.square(pose_stddev_from_config(CONFIG)))
    for robot_index, robot in enumerate(dataset.robots):
        messages = np.flatnonzero(rows.robot[starts] == robot_index)
        poses = topics[f'/{robot.name}/pose'][1]
        clouds = topics[f'/{robot.name}/observations'][1]
        assert len(poses) == len(clouds) == len(messages)
        for j, (bag_ns, pose_msg), (cloud_ns, cloud) in zip(messages, poses, clouds):
            a, b = starts[j], ends[j]
            assert bag_ns == cloud_ns == stamp_ns(pose_msg.header.stamp) == stamp_ns(
                cloud.header.stamp)
            assert abs(bag_ns * 1e-9 - rows.times[a]) < 1e-6
            pose, P = pose_from_msg(pose_msg, 'map')
            np.testing.assert_allclose(pose, rows.poses[a], atol=1e-12)
            np.testing.assert_allclose(P, P_pose, rtol=1e-15)
            columns = read_columns(cloud, OBSERVATION_FIELDS)
            assert cloud.header.frame_id == f'{robot.name}/camera'
            np.testing.assert_array_equal(columns['id'], rows.ids[a:b])
            np.testing.assert_array_equal(columns['range'], rows.z[a:b, 0])
    # Each pose comes right before its observations in the bag.
    reader = open_bag(bag)
    try:
        order = [c.topic for c, _, _ in reader.messages() if c.topic != '/ground_truth_landmarks']
    finally:
        reader.close()
    assert all(order[i].endswith('/pose') and order[i + 1] == order[i][:-4] + 'observations'
               for i in range(0, len(order), 2))


def test_export_refuses_an_existing_output(noisy):
    directory, bag = noisy
    before = sorted(p.name for p in bag.iterdir())
    with pytest.raises(BagError, match='exists'):
        export_dataset(directory, (0.002, 0.002, 0.002), bag)
    assert sorted(p.name for p in bag.iterdir()) == before


# Processing: the replay's map ------------------------------------------------------------

def test_bag_gives_the_offline_replay_map(noisy, tmp_path, capsys, monkeypatch):
    directory, bag = noisy
    out, report = tmp_path / 'out', tmp_path / 'report.json'
    config = static_config(tmp_path / 'static.yaml')   # the same map whatever the batches
    monkeypatch.setattr(sys.stderr, 'isatty', lambda: True)    # a terminal: the bar shows
    code = bag_cli.main([str(bag), '-o', str(out), '--config', str(config), '--json',
                         str(report)])
    captured = capsys.readouterr()
    printed = captured.out
    assert code == 0
    assert '100%' in captured.err  # the progress bar ran to the end
    assert 'x real time' in printed and 'RMSE' in printed
    offline = offline_records(directory, config)
    document = json.loads(report.read_text())
    entry, = document['summary']
    assert entry['fusion'] == SPLIT_CI
    assert entry['landmarks_fused'] == len(offline.records)
    assert entry['observations_used'] == offline.observations_used
    assert entry['observations_rejected'] == offline.observations_rejected
    expected = offline.to_dict()
    for key in ('rmse_m', 'anees'):
        assert entry[key] == pytest.approx(expected[key], rel=1e-9)
    assert entry['anees_interval'] == expected['anees_interval']
    for got, want in zip(entry['landmarks'], expected['landmarks']):
        assert got['id'] == want['id'] and got['observations'] == want['observations']
        assert set(got) >= {'id', 'x', 'y', 'cov', 'error_m', 'nees', 'observations'}
        np.testing.assert_allclose([got['x'], got['y']], [want['x'], want['y']], atol=1e-9)
        np.testing.assert_allclose(got['cov'], want['cov'], atol=1e-12)
    # The last map written to the output bag is that map too, and so is the fuser's.
    topics = read_bag(out)
    final = read_landmarks(topics['/fused_landmarks'][1][-1][1])
    records = [{'id': int(i), 'mean': m, 'covariance': P, 'covariance_dependent': D,
                'observations': int(n)}
               for i, m, P, D, n in zip(final.ids, final.m, final.P, final.P_dep,
                                        final.observations)]
    assert_same_map(records, offline.records)


def test_output_bag_topics_types_and_counts(noisy, tmp_path):
    directory, bag = noisy
    out = tmp_path / 'out'
    fuser = {'publish_rate_hz': 2.0, 'diagnostics_period_s': 0.5}
    document = {'/**/landmark_fuser': {'ros__parameters': fuser}}
    result = process_bag(bag, out, document)
    dataset = load_dataset(directory)
    rows = dataset.rows()
    starts, _ = rows.messages()
    topics = read_bag(out)
    assert {topic: kind for topic, (kind, _) in topics.items()} == {
        '/robot1/landmarks': 'sensor_msgs/msg/PointCloud2',
        '/robot2/landmarks': 'sensor_msgs/msg/PointCloud2',
        '/fused_landmarks': 'sensor_msgs/msg/PointCloud2',
        '/fused_landmark_updates': 'sensor_msgs/msg/PointCloud2',
        '/fused_markers': 'visualization_msgs/msg/MarkerArray',
        '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray'}
    assert {t: len(m) for t, (_, m) in topics.items()} == result.counts
    for index, robot in enumerate(dataset.robots):
        clouds = topics[f'/{robot.name}/landmarks'][1]
        expected_ns = [stamp_ns(m.header.stamp) for _, m in clouds]
        assert len(clouds) == int(np.sum(rows.robot[starts] == index))
        assert all(m.header.frame_id == 'map' for _, m in clouds)
        assert [t for t, _ in clouds] == expected_ns  # placed as the pose came in
    duration = result.bag_duration_s
    # The map at most publish_rate_hz, only when changed; on the fuser's timer grid.
    maps = [t for t, _ in topics['/fused_landmarks'][1]]
    assert 1 < len(maps) <= duration * 2.0 + 2
    assert min(np.diff(maps)) >= 0.5e9
    assert all(stamp_ns(m.header.stamp) == t for t, m in topics['/fused_landmarks'][1])
    # One diagnostics array per period: the fuser and its sources every 0.5 s, the
    # observers (default period) every other array.
    diagnostics = topics['/diagnostics'][1]
    assert abs(len(diagnostics) - duration / 0.5) <= 3
    assert all(np.diff([t for t, _ in diagnostics]) == 500_000_000)
    observers = [t for t, array in diagnostics
                 if '/robot1/landmark_observer' in {s.name for s in array.status}]
    assert all(np.diff(observers) == 1_000_000_000)
    names = {status.name for status in diagnostics[-1][1].status + diagnostics[-2][1].status}
    assert names == {'/landmark_fuser', '/landmark_fuser: /robot1/landmarks',
                     '/landmark_fuser: /robot2/landmarks', '/robot1/landmark_observer',
                     '/robot2/landmark_observer'}
    markers = topics['/fused_markers'][1]
    assert markers and all(m.markers for _, m in markers)
    assert {m.ns for _, array in markers for m in array.markers} == {'ellipses', 'labels'}
    # What the reader found in the bag, and the result's bookkeeping.
    assert result.robots == ['robot1', 'robot2'] and result.truth == dataset.landmarks
    assert result.messages_in == 2 * len(starts) + 1
    assert result.fuser.config.publish_rate_hz == 2.0


def test_robots_option_and_per_robot_sections(noisy, tmp_path):
    _, bag = noisy
    document = {
        '/**': {'ros__parameters': {'range_stddev': 0.5, 'marker_sigma': 3.0}},
        '/robot1/landmark_observer': {'ros__parameters': {'range_stddev': 0.25}}}
    result = process_bag(bag, tmp_path / 'one', document, robots=['robot1'])
    assert result.robots == ['robot1'] and list(result.fuser.sources) == ['/robot1/landmarks']
    assert result.observers['robot1'].config.range_stddev == 0.25
    assert result.fuser.config.marker_sigma == 3.0
    assert set(read_bag(tmp_path / 'one')) >= {'/robot1/landmarks'}
    assert '/robot2/landmarks' not in read_bag(tmp_path / 'one')


# Bad bags: one line, exit code 2, nothing left behind -------------------------------------

def run_cli(capsys, *args):
    code = bag_cli.main([str(a) for a in args] + ['--no-progress'])
    captured = capsys.readouterr()
    return code, captured.err.strip()


def test_missing_topic(noisy, tmp_path, capsys):
    _, bag = noisy
    code, error = run_cli(capsys, bag, '-o', tmp_path / 'out', '--robots', 'robot1,robot3')
    assert code == 2
    assert error == 'landmark_bag: error: the bag has no topic /robot3/pose ' \
                    '(geometry_msgs/msg/PoseWithCovarianceStamped)'
    assert_nothing_left(tmp_path, tmp_path / 'out')
    empty = tmp_path / 'empty'
    with BagOutput(empty) as writer:
        writer.add_topic('/chatter', PointCloud2)
    code, error = run_cli(capsys, empty, '-o', tmp_path / 'out')
    assert code == 2 and 'no topic /<robot>/observations' in error
    assert_nothing_left(tmp_path, tmp_path / 'out')


def test_truncated_bag(noisy, tmp_path, capsys):
    _, bag = noisy
    broken = tmp_path / 'broken'
    broken.mkdir()
    for path in bag.iterdir():
        data = path.read_bytes()
        (broken / path.name).write_bytes(data[:len(data) // 2] if path.suffix == '.mcap'
                                         else data)
    code, error = run_cli(capsys, broken, '-o', tmp_path / 'out')
    assert code == 2 and error.startswith(f'landmark_bag: error: {broken}: ')
    assert '\n' not in error
    assert_nothing_left(tmp_path, tmp_path / 'out')
    code, error = run_cli(capsys, tmp_path / 'nothing', '-o', tmp_path / 'out')
    assert code == 2 and 'no such bag' in error


def test_unknown_message_type(tmp_path, capsys):
    bag = tmp_path / 'odd'
    writer = Writer(bag, version=9)
    writer.open()
    writer.add_connection('/robot1/pose', 'acme_msgs/msg/RobotPose', msgdef='float64 x',
                          rihs01='RIHS01_' + '0' * 64)
    writer.add_connection('/robot1/observations', 'sensor_msgs/msg/PointCloud2',
                          typestore=typestore())
    writer.close()
    code, error = run_cli(capsys, bag, '-o', tmp_path / 'out')
    assert code == 2
    assert error == ('landmark_bag: error: topic /robot1/pose has message type '
                     'acme_msgs/msg/RobotPose, expected '
                     'geometry_msgs/msg/PoseWithCovarianceStamped')
    assert_nothing_left(tmp_path, tmp_path / 'out')


def test_existing_output_and_bad_parameters(noisy, tmp_path, capsys):
    _, bag = noisy
    existing = tmp_path / 'existing'
    existing.mkdir()
    code, error = run_cli(capsys, bag, '-o', existing)
    assert code == 2 and 'exists already' in error and not any(existing.iterdir())
    params = tmp_path / 'bad.yaml'
    params.write_text('/**/landmark_observer:\n  ros__parameters:\n    range_stddev: -1.0\n')
    code, error = run_cli(capsys, bag, '-o', tmp_path / 'out', '--config', params)
    assert code == 2
    assert error.startswith('landmark_bag: error: /robot1/landmark_observer: range_stddev')
    assert_nothing_left(tmp_path, tmp_path / 'out')


# Parameter files ---------------------------------------------------------------------------

@pytest.mark.parametrize('key, fqn, matches', [
    ('/**', '/robot1/landmark_observer', True),
    ('/**/landmark_observer', '/robot1/landmark_observer', True),
    ('/**/landmark_observer', '/landmark_observer', True),
    ('/**/landmark_observer', '/landmark_fuser', False),
    ('landmark_fuser', '/landmark_fuser', True),
    ('/robot1/landmark_observer', '/robot2/landmark_observer', False),
    ('/*/landmark_observer', '/team/robot1/landmark_observer', False),
    ('/*/landmark_observer', '/robot1/landmark_observer', True),
])
def test_section_keys_match_as_ros_does(key, fqn, matches):
    assert bool(key_pattern(key).match(fqn)) is matches


def test_shipped_config_files_load():
    document = {'/**/landmark_observer': {'ros__parameters': {'range_stddev': 1}},
                '/robot2/landmark_observer': {'ros__parameters': {'range_stddev': 2.0}}}
    assert node_parameters(document, '/robot2/landmark_observer') == {'range_stddev': 2.0}
    assert load_config(ObserverConfig, document, '/robot1/landmark_observer').range_stddev == 1.0
    assert load_config(FuserConfig, None, '/landmark_fuser') == FuserConfig()
    assert pose_stddev_from_config(CONFIG) == load_replay_config(CONFIG).pose_stddev


# Real data ---------------------------------------------------------------------------------

@pytest.mark.skipif(not DATASET6.is_dir(), reason=f'no MRCLAM dataset at {DATASET6}')
def test_dataset6_first_minutes_give_the_replay_map(tmp_path):
    config = load_replay_config(CONFIG)
    full = load_dataset(DATASET6, config.pose_stddev)
    end = full.time_span[0] + 120.0
    dataset = replace(full, robots=[
        replace(r, times=r.times[keep], ids=r.ids[keep], z=r.z[keep], poses=r.poses[keep])
        for r in full.robots for keep in [r.times < end]])
    bag, out = tmp_path / 'dataset6', tmp_path / 'out'
    counts = export_dataset(dataset, config.pose_stddev, bag)
    assert counts['/ground_truth_landmarks'] == 1 and len(counts) == 11
    result = process_bag(bag, out, read_document(CONFIG))
    offline = offline_records(None, dataset=dataset)
    assert len(offline.records) >= 10
    assert_same_map(result.fuser.map.to_records(), offline.records)
    assert result.speedup > 1.0


# Storage: MCAP or SQLite 3, by default the input's ----------------------------------------

def copy_bag(bag, path, storage):
    """Write every message of ``bag`` into a new bag of ``storage`` at ``path``."""
    reader = open_bag(bag)
    try:
        with BagOutput(path, storage) as out:
            for topic, info in reader.topics.items():
                out.add_topic(topic, CLASSES[info.msgtype])
            for connection, time_ns, raw in reader.messages():
                out.write(connection.topic, time_ns,
                          deserialize_message(bytes(raw), CLASSES[connection.msgtype]))
    finally:
        reader.close()


def bag_storage(path):
    """Return the storage identifier ``metadata.yaml`` names and the storage files' suffixes."""
    metadata = yaml.safe_load((path / 'metadata.yaml').read_text())
    information = metadata['rosbag2_bagfile_information']
    suffixes = {Path(name).suffix for name in information['relative_file_paths']}
    return information['storage_identifier'], suffixes


@pytest.mark.parametrize('given, option, expected', [
    ('mcap', None, 'mcap'), ('sqlite3', None, 'sqlite3'),
    ('mcap', 'sqlite3', 'sqlite3'), ('sqlite3', 'mcap', 'mcap')])
def test_output_storage_is_the_inputs_unless_chosen(noisy, tmp_path, capsys, given, option,
                                                    expected):
    _, bag = noisy
    if given != 'mcap':
        copy_bag(bag, tmp_path / 'input', given)
        bag = tmp_path / 'input'
    assert bag_storage(bag)[0] == given
    out = tmp_path / 'out'
    code, err = run_cli(capsys, bag, '-o', out, '--config', CONFIG,
                        *(['--storage', option] if option else []))
    assert code == 0, err
    assert bag_storage(out) == (expected, {'.mcap' if expected == 'mcap' else '.db3'})
    # rosbags reads it back, and the map is that of the MCAP input with default storage.
    final = read_landmarks(read_bag(out)['/fused_landmarks'][1][-1][1])
    reference = tmp_path / 'reference'
    process_bag(noisy[1], reference, read_document(CONFIG))
    want = read_landmarks(read_bag(reference)['/fused_landmarks'][1][-1][1])
    assert final.ids.tolist() == want.ids.tolist()
    np.testing.assert_array_equal(final.m, want.m)
    np.testing.assert_array_equal(final.P, want.P)


def test_single_file_inputs_give_their_storage(noisy, tmp_path):
    _, bag = noisy
    copy_bag(bag, tmp_path / 'lite', 'sqlite3')
    db3, = (tmp_path / 'lite').glob('*.db3')
    mcap, = bag.glob('*.mcap')
    assert storage_of(db3) == 'sqlite3' and storage_of(mcap) == 'mcap'
    assert storage_of(tmp_path / 'lite') == 'sqlite3' and storage_of(bag) == 'mcap'


def test_unknown_storage_is_a_usage_error(noisy, tmp_path, capsys):
    _, bag = noisy
    with pytest.raises(SystemExit) as exit_:
        bag_cli.main([str(bag), '-o', str(tmp_path / 'out'), '--storage', 'parquet'])
    assert exit_.value.code == 2
    assert "invalid choice: 'parquet'" in capsys.readouterr().err
    with pytest.raises(ValueError, match='storage must be one of'):
        BagOutput(tmp_path / 'out', 'parquet')
    assert_nothing_left(tmp_path, tmp_path / 'out')


def test_no_progress_bar_into_a_pipe(monkeypatch, capsys):
    monkeypatch.setattr(sys.stderr, 'isatty', lambda: False)
    update, close = bag_cli._progress_bar(True)
    close()
    assert update is None and capsys.readouterr().err == ''
    monkeypatch.setattr(sys.stderr, 'isatty', lambda: True)
    update, close = bag_cli._progress_bar(True)
    update(3, 10)
    close()
    assert '30%' in capsys.readouterr().err
