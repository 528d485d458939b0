"""
landmark_mrclam: the MRCLAM reader, the offline and through-the-nodes replays, calibration.

A synthetic dataset in the MRCLAM format (CRLF, ``#`` headers, tabs and trailing blanks)
is written into ``tmp_path``: robots moving with position and heading linear in time
(so linear interpolation of the ground truth is exact and the heading wraps across
+-pi many times), landmarks all in view, plus a robot sighting, an unknown barcode
and a sighting before the ground truth.
"""

import json
import math
import os
from pathlib import Path
import re

from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.fusion.landmark_map import FUSION_METHODS
from landmark_ros.mrclam import offline
from landmark_ros.mrclam.calibrate import calibrate
from landmark_ros.mrclam.cli import main
from landmark_ros.mrclam.config import load_config
from landmark_ros.mrclam.data import (interpolate_poses, load_dataset, read_table,
                                      seconds_to_stamps_ns)
from landmark_ros.observer.observer import Observer
from landmark_ros.observer.rows import landmarks_from_rows, observation_noise
from landmark_ros.ros.conversions import seconds_to_ns
import numpy as np
import pytest

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

REPO_ROOT = Path(__file__).resolve().parents[2]
DATASET6 = REPO_ROOT.parent / 'shared' / 'data' / 'mrclam' / 'dataset6'
CONFIG = REPO_ROOT / 'config' / 'mrclam.yaml'


def synthetic_config(directory):
    """
    Write ``config/mrclam.yaml`` with the sensor model of ``noisy_dataset`` into ``directory``.

    The synthetic datasets have no range scale error (the MRCLAM camera's calibrated
    correction would put one in), no camera delay and the noise of ``noisy_dataset``.
    Returns the path.
    """
    text = CONFIG.read_text()
    for name, value in (('range_stddev', 0.02), ('range_stddev_per_m', 0.03),
                        ('range_stddev_per_m2', 0.0), ('camera_delay_s', 0.0),
                        ('bearing_stddev', 0.01), ('range_bias_stddev', 0.02),
                        ('bearing_bias_stddev', 0.004)):
        text, count = re.subn(rf'\b{name}: [0-9.e-]+', f'{name}: {value}', text)
        assert count >= 1, name
    for pattern, value in ((r'range_scale_coeffs: \[[^\]]*\]',
                            'range_scale_coeffs: [0.0, 0.0, 0.0]'),
                           (r'range_scale_per_m: [-0-9.e]+', 'range_scale_per_m: 0.0'),
                           (r'range_scale_no_bearing: \[[^\]]*\]',
                            'range_scale_no_bearing: [0.0, 0.0]')):
        text, count = re.subn(pattern, value, text)
        assert count >= 1, pattern
    path = Path(directory) / 'synthetic_mrclam.yaml'
    path.write_text(text)
    return path


T0 = 1248444000.0
ROBOT_BARCODES = {1: 5, 2: 14, 3: 41, 4: 32, 5: 23}
LANDMARK_BARCODES = [63, 81, 7, 70, 45, 27, 18, 54, 61, 90]
UNKNOWN_BARCODE = 99
LANDMARKS = {6: (3.0, 2.0), 7: (-2.5, 3.0), 8: (1.0, -3.5), 9: (-3.0, -2.0)}


def write_table(path, header, rows, formats):
    """Write a MRCLAM-style file: '#' header lines, tab separated, trailing blank, CRLF."""
    lines = [f'# {line}' for line in header]
    for row in rows:
        lines.append(' ' + ' \t '.join(f % v for f, v in zip(formats, row)) + ' ')
    Path(path).write_bytes(('\r\n'.join(lines) + '\r\n').encode())


def robot_motion(number):
    """Return the (linear in time) motion of a robot: pose at T0 and its rates."""
    start = np.array([-1.0 + 0.8 * number, 0.5 - 0.4 * number, -2.0 + number])
    rates = np.array([0.03, -0.02 * number, 0.7 + 0.2 * number])
    return start, rates


def true_pose(number, t):
    """Return the exact pose of a robot at times ``t``, shape (N, 3)."""
    start, rates = robot_motion(number)
    dt = np.asarray(t, dtype=np.float64)[:, None] - T0
    pose = start + rates * dt
    pose[:, 2] = wrap_angle(pose[:, 2])
    return pose


def make_dataset(directory, robots=2, landmarks=LANDMARKS, duration=30.0, rate_hz=4.0,
                 noise=(0.0, 0.0, 0.0), bias=(0.0, 0.0), rng=None, extras=True, delay_s=0.0):
    """
    Write a synthetic MRCLAM dataset.

    Parameters
    ----------
    directory : Path
        Where to write the files (created).
    robots : int
        Robots 1 to ``robots`` (at most 5).
    landmarks : dict
        Subject (6 and up) -> true (x, y).
    duration : float
        Seconds of sightings.
    rate_hz : float
        Sightings per second and robot, each of every landmark.
    noise : (a, k, sigma_b)
        Range noise sd ``sqrt(a^2 + (k r)^2)`` [m], bearing noise sd [rad].
    bias : (range, bearing)
        Standard deviations of a bias per robot, shared by all its sightings.
    rng : numpy.random.Generator, optional
        Noise source.
    extras : bool
        Add the rows the reader must drop: robot sightings, an unknown barcode and a
        sighting before the ground truth.
    delay_s : float
        Camera delay [s]: each sighting is taken this long before its stamp.

    Returns
    -------
    dict
        ``dropped``: the counts the reader must report; ``rows``: kept sightings.

    """
    rng = rng if rng is not None else np.random.default_rng(0)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    subjects = sorted(landmarks)
    barcodes = dict(ROBOT_BARCODES)
    barcodes.update({s: LANDMARK_BARCODES[i] for i, s in enumerate(subjects)})
    write_table(directory / 'Barcodes.dat', ['Barcode Data Format:', 'Subject #    Barcode #'],
                sorted(barcodes.items()), ['%3d', '%3d'])
    write_table(directory / 'Landmark_Groundtruth.dat',
                ['Landmark Groundtruth Data Format:', 'Subject # x [m] y [m] x sd y sd'],
                [(s, *landmarks[s], 1e-4, 1e-4) for s in subjects],
                ['%3d', '%.8f', '%.8f', '%.8f', '%.8f'])
    a, k, sigma_b = noise
    dropped = {'robot_sightings': 0, 'unknown_barcode': 0, 'outside_groundtruth': 0}
    kept = 0
    biases = []
    for number in range(1, robots + 1):
        gt_t = T0 - 1.0 + 0.05 * np.arange(int((duration + 2.0) / 0.05) + 1)
        gt = true_pose(number, gt_t)
        write_table(directory / f'Robot{number}_Groundtruth.dat',
                    ['Robot Groundtruth Data Format:', 'Time [s] x [m] y [m] orientation [rad]'],
                    [(t, *p) for t, p in zip(gt_t, gt)], ['%.3f', '%.9f', '%.9f', '%.9f'])
        robot_bias = (rng.normal(0.0, bias[0]) if bias[0] else 0.0,
                      rng.normal(0.0, bias[1]) if bias[1] else 0.0)
        biases.append(robot_bias)
        stamps = np.round(T0 + 0.011 * number + np.arange(0.0, duration, 1.0 / rate_hz), 3)
        poses = true_pose(number, stamps - delay_s)
        rows = []
        for t, pose in zip(stamps, poses):
            for s in subjects:
                d = np.asarray(landmarks[s]) - pose[:2]
                r = math.hypot(*d)
                b = wrap_angle(math.atan2(d[1], d[0]) - pose[2])
                if a or k:
                    r += rng.normal(0.0, math.sqrt(a * a + (k * r) ** 2))
                if sigma_b:
                    b = wrap_angle(b + rng.normal(0.0, sigma_b))
                r, b = r + robot_bias[0], wrap_angle(b + robot_bias[1])
                rows.append((t, barcodes[s], r, b))
                kept += 1
        if extras:
            other = 2 if number == 1 else 1
            rows.insert(3, (stamps[1], ROBOT_BARCODES[other], 2.0, 0.1))
            dropped['robot_sightings'] += 1
            if number == 1:
                rows.insert(5, (stamps[2], UNKNOWN_BARCODE, 3.0, 0.2))
                rows.insert(0, (T0 - 5.0, barcodes[subjects[0]], 3.0, 0.2))
                dropped['unknown_barcode'] += 1
                dropped['outside_groundtruth'] += 1
        write_table(directory / f'Robot{number}_Measurement.dat',
                    ['Measurement Data Format:', 'Time [s] Subject # range [m] bearing [rad]'],
                    rows, ['%.3f', '%3d', '%.9f', '%.9f'])
    return {'dropped': dropped, 'rows': kept, 'biases': np.array(biases)}


@pytest.fixture
def clean_dataset(tmp_path):
    directory = tmp_path / 'clean'
    info = make_dataset(directory)
    return directory, info


@pytest.fixture
def noisy_dataset(tmp_path):
    directory = tmp_path / 'noisy'
    # The noise that synthetic_config describes.
    info = make_dataset(directory, noise=(0.02, 0.03, 0.01), bias=(0.02, 0.004),
                        rng=np.random.default_rng(7))
    return directory, info


# Reader ----------------------------------------------------------------------------------

def test_read_table_handles_crlf_comments_and_trailing_blanks(tmp_path):
    path = tmp_path / 'table.dat'
    path.write_bytes(b'# header\r\n# more\r\n 1 \t 2.5 \r\n\r\n3\t-4e-1  \r\n# end\r\n')
    np.testing.assert_array_equal(read_table(path, 2), [[1.0, 2.5], [3.0, -0.4]])
    with pytest.raises(ValueError, match='columns'):
        read_table(path, 3)
    path.write_bytes(b'# only a header\r\n')
    assert read_table(path, 4).shape == (0, 4)


def test_reader_drops_and_counts_and_interpolates(clean_dataset):
    directory, info = clean_dataset
    dataset = load_dataset(directory, pose_stddev=(0.01, 0.02, 0.03))
    assert [r.number for r in dataset.robots] == [1, 2]
    assert [r.name for r in dataset.robots] == ['robot1', 'robot2']
    assert dataset.robots[0].landmarks_topic == '/robot1/landmarks'
    counts = dataset.counts
    for reason, count in info['dropped'].items():
        assert counts[reason] == count, reason
    assert counts['kept'] == info['rows']
    assert counts['read'] == info['rows'] + sum(info['dropped'].values())
    assert dataset.landmarks == LANDMARKS
    np.testing.assert_allclose(dataset.P_pose, np.diag([1e-4, 4e-4, 9e-4]))
    for robot in dataset.robots:
        assert set(robot.ids.tolist()) == set(LANDMARKS)
        assert np.all(np.diff(robot.times) >= 0)
        expected = true_pose(robot.number, robot.times)
        np.testing.assert_allclose(robot.poses[:, :2], expected[:, :2], atol=1e-9)
        np.testing.assert_allclose(wrap_angle(robot.poses[:, 2] - expected[:, 2]), 0.0,
                                   atol=1e-9)
        # The heading wrapped across +-pi several times in the run.
        assert np.sum(np.abs(np.diff(robot.gt_poses[:, 2])) > np.pi) >= 2


def test_heading_is_interpolated_on_the_shortest_arc():
    t = np.array([0.0, 1.0, 2.0])
    gt = np.array([[0.0, 0.0, 3.0], [1.0, 2.0, -3.0], [2.0, 0.0, -2.5]])
    poses, inside = interpolate_poses(t, gt, np.array([-0.5, 0.25, 0.5, 1.5, 2.5]))
    assert inside.tolist() == [False, True, True, True, False]
    step = 2.0 * np.pi - 6.0  # from 3.0 forward across pi to -3.0
    np.testing.assert_allclose(poses[1], [0.25, 0.5, 3.0 + 0.25 * step], atol=1e-12)
    assert abs(abs(poses[2, 2]) - np.pi) < 1e-12
    np.testing.assert_allclose(poses[3], [1.5, 1.0, -2.75], atol=1e-12)


def test_rows_are_in_global_time_order_and_split_into_clouds(clean_dataset):
    dataset = load_dataset(clean_dataset[0])
    rows = dataset.rows()
    assert len(rows) == dataset.counts['kept']
    order = np.lexsort((rows.robot, rows.times))
    np.testing.assert_array_equal(order, np.arange(len(rows)))
    starts, ends = rows.messages()
    assert len(starts) == sum(len(np.unique(r.times)) for r in dataset.robots)
    for a, b in zip(starts, ends):
        assert len(set(rows.robot[a:b].tolist())) == 1
        assert len(set(rows.times[a:b].tolist())) == 1


# Configuration ---------------------------------------------------------------------------

def test_config_file_sections():
    config = load_config(CONFIG)
    # The calibrated MRCLAM camera model (landmark_mrclam --calibrate on dataset 6).
    assert config.observer.range_scale_coeffs == (0.0455, -0.0050, -0.4646)
    assert config.observer.range_scale_per_m == -0.00325
    assert config.observer.range_stddev == 0.0215
    assert config.observer.range_stddev_per_m == 0.0053
    assert config.observer.range_stddev_per_m2 == 0.00195
    assert config.observer.bearing_stddev == 0.0146
    assert config.observer.range_bias_stddev == 0.0327
    assert config.observer.bearing_bias_stddev == 0.0065
    assert config.camera_delay_s == 0.036
    assert config.fuser.gate_probability == 0.999
    assert config.fuser.min_observations == 2
    assert config.fuser.source_correlation == 'independent'   # motion-capture poses
    assert config.pose_stddev == (0.002, 0.002, 0.002)


def test_config_rejects_invalid_values(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text('/**/landmark_observer:\n  ros__parameters:\n    range_stddev: -1.0\n')
    with pytest.raises(ValueError, match='range_stddev'):
        load_config(path)
    for value in ('.nan', '2.0', 'late', 'true'):
        path.write_text(f'landmark_mrclam:\n  ros__parameters:\n    camera_delay_s: {value}\n')
        with pytest.raises(ValueError, match='camera_delay_s'):
            load_config(path)
    path.write_text('landmark_mrclam:\n  ros__parameters:\n    pose_stddev_x: 0.002\n')
    assert load_config(path).camera_delay_s == 0.0  # none unless the file says so


# Offline ---------------------------------------------------------------------------------

def test_stamps_are_the_nanoseconds_the_player_publishes(clean_dataset):
    rows = load_dataset(clean_dataset[0]).rows()
    times = np.concatenate([rows.times, [0.0, 0.9999999999, 1.5, 2.0000000004, 1e9 + 0.25]])
    expected = [seconds_to_ns(float(t)) for t in times]
    assert seconds_to_stamps_ns(times).tolist() == expected
    assert rows.stamps_ns.dtype == np.int64
    assert rows.stamps_ns.tolist() == expected[:len(rows)]


def test_offline_observers_equal_the_vectorised_core(noisy_dataset):
    dataset = load_dataset(noisy_dataset[0])
    config = load_config(CONFIG)
    observer_config = type(config.observer).from_values(
        {'range_stddev': 0.05, 'range_stddev_per_m': 0.02, 'bearing_stddev': 0.01,
         'range_bias_stddev': 0.01, 'bearing_bias_stddev': 0.002})
    rows = dataset.rows()
    observers = [Observer(observer_config) for _ in dataset.robots]
    batches = list(offline.observe(rows, observers, config.P_pose))
    starts, _ = rows.messages()
    # One batch per message, in global time order, with the message's stamp and robot.
    assert [robot for robot, _ in batches] == rows.robot[starts].tolist()
    assert [b.stamp_ns for _, b in batches] == rows.stamps_ns[starts].tolist()
    # The reference: one core call over all rows with per-row poses.
    R = observation_noise({'range': rows.z[:, 0]}, 0.05 ** 2, 0.01 ** 2, 0.02 ** 2)
    kept, m, P, P_dep, reasons = landmarks_from_rows(
        rows.ids, rows.z, R, rows.poses, config.P_pose, None,
        np.diag([0.01 ** 2, 0.002 ** 2]))
    assert kept.all() and not reasons
    np.testing.assert_array_equal(np.concatenate([b.ids for _, b in batches]), rows.ids)
    np.testing.assert_allclose(np.concatenate([b.m for _, b in batches]), m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([b.P for _, b in batches]), P, rtol=1e-12,
                               atol=1e-18)
    np.testing.assert_allclose(np.concatenate([b.P_dep for _, b in batches]), P_dep,
                               rtol=1e-12, atol=1e-18)
    assert np.all(P_dep[:, 0, 0] > 0.0)
    for observer in observers:
        assert observer.counters['landmarks_out'] == observer.counters['observations_in'] > 0


def static_config(path):
    """
    Return ``CONFIG`` with change detection off, written to ``path``.

    Change detection tests a batch's rows after the batch is fused (a landmark confirmed
    in a batch is tested from the next one, an alarm's rebuild takes the batch's later
    rows), so only without it does the map not depend on how the rows are batched.
    These synthetic data, read with the MRCLAM camera's range scale correction that they
    do not have, raise many alarms.
    """
    text, count = re.subn(r'(/\*\*/landmark_fuser:\n  ros__parameters:\n)',
                          r'\1    move_false_alarm_rate: 0.0\n', CONFIG.read_text())
    assert count == 1 and 'move_false_alarm_rate: 2' not in text
    path.write_text(text)
    return path


def test_fusion_in_chunks_equals_row_by_row(noisy_dataset, tmp_path):
    dataset = load_dataset(noisy_dataset[0])
    config = load_config(static_config(tmp_path / 'static.yaml'))
    assert config.fuser.move_false_alarm_rate == 0.0
    one = offline.run_offline(dataset, config, FUSION_METHODS, chunk=1)
    many = offline.run_offline(dataset, config, FUSION_METHODS, chunk=37)
    assert one.messages == many.messages == len(dataset.rows().messages()[0])
    assert not one.problems and not many.problems
    for method in FUSION_METHODS:
        x_result, y_result = one.results[method], many.results[method]
        assert x_result.observations_used == y_result.observations_used
        assert x_result.observations_rejected == y_result.observations_rejected
        a, b = x_result.records, y_result.records
        assert [r['id'] for r in a] == [r['id'] for r in b]
        for x, y in zip(a, b):
            np.testing.assert_allclose(x['mean'], y['mean'], rtol=0, atol=1e-12)
            np.testing.assert_allclose(x['covariance'], y['covariance'], rtol=1e-10, atol=0)
            assert x['observations'] == y['observations']
            assert x['rejections'] == y['rejections']
            assert x['last_stamp_ns'] == y['last_stamp_ns']


def test_offline_noise_free_recovers_the_truth_and_writes_json(
        clean_dataset, tmp_path, capsys):
    directory, info = clean_dataset
    out = tmp_path / 'result.json'
    config = synthetic_config(tmp_path)
    assert main([str(directory), '--config', str(config), '--json', str(out)]) == 0
    printed = capsys.readouterr().out
    assert '== summary' in printed
    for method in FUSION_METHODS:
        assert f'== {method}:' in printed
    document = json.loads(out.read_text())
    assert document['mode'] == 'offline'
    assert document['dataset']['counts']['robot_sightings'] == 2
    summary = document['summary']
    assert [entry['fusion'] for entry in summary] == list(FUSION_METHODS)
    for entry in summary:
        assert set(entry) >= {'fusion', 'rmse_m', 'anees', 'anees_interval',
                              'landmarks_fused', 'observations_used',
                              'observations_rejected', 'landmarks'}
        assert entry['landmarks_fused'] == len(LANDMARKS)
        assert entry['rmse_m'] < 1e-6
        assert entry['observations_used'] + entry['observations_rejected'] == info['rows']
        low, high = entry['anees_interval']
        assert 0.0 < low < 2.0 < high
        assert [lm['id'] for lm in entry['landmarks']] == sorted(LANDMARKS)
        for landmark in entry['landmarks']:
            assert set(landmark) >= {'id', 'x', 'y', 'cov', 'error_m', 'nees', 'observations'}
            np.testing.assert_allclose([landmark['x'], landmark['y']],
                                       LANDMARKS[landmark['id']], atol=1e-6)
            cov = np.array(landmark['cov'])
            assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) > 0.0)
            assert landmark['error_m'] < 1e-6


def test_the_replay_moves_the_sightings_back_by_camera_delay_s(tmp_path, capsys):
    # Noise-free sightings taken 50 ms before their stamps: at the raw stamps the poses
    # are off (the robots turn at about 1 rad/s); moved back, the truth comes out.
    directory = tmp_path / 'late'
    make_dataset(directory, delay_s=0.05, extras=False)
    config = synthetic_config(tmp_path)
    late = tmp_path / 'late.yaml'
    late.write_text(config.read_text().replace('camera_delay_s: 0.0', 'camera_delay_s: 0.05'))
    rmse = {}
    for path in (config, late):
        out = tmp_path / f'{path.stem}.json'
        assert main([str(directory), '--config', str(path), '--fusion', 'independent',
                     '--json', str(out)]) == 0
        rmse[path.stem] = json.loads(out.read_text())['summary'][0]['rmse_m']
    assert 'moved back by camera_delay_s = 0.05 s' in capsys.readouterr().out
    assert rmse['late'] < 1e-6 < 0.01 < rmse['synthetic_mrclam']
    # --calibrate estimates it from the raw stamps (whatever the config says).
    assert main([str(directory), '--config', str(config), '--calibrate']) == 0
    printed = capsys.readouterr().out
    assert re.search(r'camera delay \(.*\): \+(49\.[5-9]|50\.[0-4]) ms', printed), printed
    assert 'camera_delay_s: 0.050' in printed


def test_one_method_and_plot(noisy_dataset, tmp_path):
    pytest.importorskip('matplotlib')
    out, image = tmp_path / 'one.json', tmp_path / 'map.png'
    assert main([str(noisy_dataset[0]), '--fusion', 'independent', '--config',
                 str(synthetic_config(tmp_path)), '--json', str(out), '--plot', str(image)]) == 0
    document = json.loads(out.read_text())
    assert [entry['fusion'] for entry in document['summary']] == ['independent']
    assert document['summary'][0]['rmse_m'] < 0.1
    assert image.stat().st_size > 10000


def test_export_bag_then_landmark_bag_gives_the_replay_map(noisy_dataset, tmp_path, capsys):
    # landmark_bag --from-mrclam, then landmark_bag on the bag.
    from landmark_ros.bag import cli as bag_cli
    # The export writes the raw stamps (no camera_delay_s): the replay it is compared
    # with takes a config without the delay.
    directory = noisy_dataset[0]
    static = static_config(tmp_path / 'static.yaml')
    config = tmp_path / 'no_delay.yaml'
    config.write_text(re.sub(r'camera_delay_s: [0-9.]+', 'camera_delay_s: 0.0',
                             static.read_text()))
    bag, fused = tmp_path / 'dataset_bag', tmp_path / 'fused'
    assert bag_cli.main(['--from-mrclam', str(directory), '-o', str(bag),
                         '--config', str(CONFIG)]) == 0
    printed = capsys.readouterr().out
    assert f'wrote {bag}:' in printed
    assert '== summary' not in printed  # the export stops before any replay
    assert list(bag.glob('*.mcap'))
    replay, processed = tmp_path / 'replay.json', tmp_path / 'bag.json'
    assert main([str(directory), '--fusion', 'split_covariance_intersection',
                 '--config', str(config), '--json', str(replay)]) == 0
    assert bag_cli.main([str(bag), '-o', str(fused), '--config', str(static), '--json',
                         str(processed), '--no-progress']) == 0
    expected = json.loads(replay.read_text())['summary'][0]
    entry = json.loads(processed.read_text())['summary'][0]
    assert [lm['id'] for lm in entry['landmarks']] == [lm['id'] for lm in expected['landmarks']]
    for key in ('rmse_m', 'anees'):
        assert entry[key] == pytest.approx(expected[key], rel=1e-9, abs=1e-12)
    # An existing output: one line on stderr, exit code 2, the bag left as it was.
    before = sorted(p.name for p in bag.iterdir())
    assert bag_cli.main(['--from-mrclam', str(directory), '-o', str(bag)]) == 2
    error = capsys.readouterr().err
    assert error.startswith('landmark_bag: ') and error.count('\n') == 1, error
    assert sorted(p.name for p in bag.iterdir()) == before


def test_the_deprecated_export_bag_option_still_writes_the_bag(noisy_dataset, tmp_path, capsys):
    directory = noisy_dataset[0]
    bag = tmp_path / 'dataset_bag'
    assert main([str(directory), '--export-bag', str(bag)]) == 0
    out = capsys.readouterr()
    assert '--export-bag is deprecated' in out.err and 'landmark_bag --from-mrclam' in out.err
    assert f'wrote {bag}:' in out.out and list(bag.glob('*.mcap'))
    assert '== summary' not in out.out  # the export stops before any replay
    # Its errors keep the replay's prefix and exit code.
    assert main([str(directory), '--export-bag', str(bag)]) == 2
    error = capsys.readouterr().err.splitlines()
    assert error[-1].startswith('landmark_mrclam: error: '), error


def test_missing_dataset_is_an_error(tmp_path, capsys):
    assert main([str(tmp_path / 'nowhere')]) == 2
    assert 'no MRCLAM dataset directory' in capsys.readouterr().err


# Calibration -----------------------------------------------------------------------------

def test_calibration_recovers_the_synthetic_sensor_model(tmp_path, capsys):
    landmarks = {6 + i: (6.0 * math.cos(0.8 * i), 4.0 * math.sin(0.8 * i) + 0.3 * i)
                 for i in range(8)}
    truth = {'a': 0.03, 'k': 0.025, 'sigma_b': 0.01, 'bias_r': 0.03, 'bias_b': 0.005}
    info = make_dataset(tmp_path / 'cal', robots=5, landmarks=landmarks, duration=40.0,
                        rate_hz=10.0, noise=(truth['a'], truth['k'], truth['sigma_b']),
                        bias=(truth['bias_r'], truth['bias_b']),
                        rng=np.random.default_rng(11), extras=False)
    # Five robots draw five biases: compare with what they drew, not with the prior.
    drawn_r, drawn_b = np.sqrt(np.mean(info['biases'] ** 2, axis=0))
    out = tmp_path / 'cal.json'
    assert main([str(tmp_path / 'cal'), '--calibrate', '--json', str(out)]) == 0
    printed = capsys.readouterr().out
    assert 'suggested values:' in printed and 'range_stddev_per_m:' in printed
    cal = json.loads(out.read_text())['calibration']
    assert cal['range_stddev'] == pytest.approx(truth['a'], rel=0.25)
    assert cal['range_stddev_per_m'] == pytest.approx(truth['k'], rel=0.15)
    assert cal['bearing_stddev'] == pytest.approx(truth['sigma_b'], rel=0.1)
    assert cal['range_bias_stddev'] == pytest.approx(drawn_r, rel=0.25)
    assert cal['bearing_bias_stddev'] == pytest.approx(drawn_b, rel=0.25)
    assert cal['residual_tails']['range'] < 0.01
    assert cal['pairs'] == 5 * 8
    assert abs(cal['camera_delay_s']) < 0.003  # the synthetic camera has none
    # Each robot's range error by true range: the synthetic bias is an offset, flat.
    for robot in cal['robots']:
        medians = [b['median'] for b in robot['range_by_range'] if b['n'] >= 100]
        assert len(medians) >= 2 and np.ptp(medians) < 0.04  # noise 0.025 r: ~1 cm
        assert np.median(medians) == pytest.approx(robot['range_median'], abs=0.01)
        assert sum(b['n'] for b in robot['range_by_range']) == robot['n']
    assert 'range by true range:' in printed


def test_calibration_without_bias_finds_none(tmp_path):
    make_dataset(tmp_path / 'cal', robots=3, duration=40.0, noise=(0.05, 0.0, 0.02),
                 rng=np.random.default_rng(3), extras=False)
    cal = calibrate(load_dataset(tmp_path / 'cal'))
    assert cal.range_stddev == pytest.approx(0.05, rel=0.15)
    assert cal.range_stddev_per_m < 0.01
    assert cal.bearing_stddev == pytest.approx(0.02, rel=0.1)
    assert cal.range_bias_stddev < 0.01 and cal.bearing_bias_stddev < 0.004


# Real data -------------------------------------------------------------------------------

@pytest.mark.skipif(not DATASET6.is_dir(), reason=f'no MRCLAM dataset at {DATASET6}')
def test_dataset6_offline_fuses_all_15_landmarks():
    config = load_config(CONFIG)
    dataset = load_dataset(DATASET6, config.pose_stddev)
    assert len(dataset.robots) == 5 and len(dataset.landmarks) == 15
    assert dataset.counts['unknown_barcode'] > 0 and dataset.counts['robot_sightings'] > 0
    run = offline.run_offline(dataset, config, FUSION_METHODS)
    stamps_ns = set(dataset.rows().stamps_ns.tolist())
    for method, result in run.results.items():
        assert len(result.records) == 15, method
        assert result.summary.landmarks == 15
        assert result.summary.rmse_m < 0.2, method
        assert all(r['last_stamp_ns'] in stamps_ns for r in result.records), method


# Through the nodes -----------------------------------------------------------------------

def test_through_nodes_agrees_with_offline(noisy_dataset, tmp_path):
    out = tmp_path / 'nodes.json'
    # The sensor model of the data (no camera delay, no range scale): with MRCLAM's,
    # over half the rows sit at the gate, where CI's result depends on the order in
    # which two robots' messages of one step reach the fuser.
    code = main([str(noisy_dataset[0]), '--through-nodes', '--no-progress', '--config',
                 str(synthetic_config(tmp_path)), '--json', str(out)])
    document = json.loads(out.read_text())
    assert code == 0, document.get('agreement')
    assert document['mode'] == 'through_nodes'
    assert [entry['fusion'] for entry in document['summary']] == list(FUSION_METHODS)
    for method, entry in document['agreement'].items():
        assert entry['same_ids'] and entry['same_counts'], method
        assert entry['max_mean_diff_m'] < 1e-9, method
        assert entry['max_cov_diff_m2'] < 1e-12, method
        assert entry['max_cov_dep_diff_m2'] < 1e-12, method
    nodes = document['nodes']
    assert not nodes['cloud_mismatch']
    assert nodes['rows_out'] == nodes['rows']
    for robot, values in nodes['observers'].items():
        assert int(values['landmarks_out']) == int(values['observations_in']), robot
    for entry in document['summary']:
        assert entry['landmarks_fused'] == len(LANDMARKS)
    assert document['timing']['play_wall_s'] > 0.0


# Partial sensors -------------------------------------------------------------------------

@pytest.mark.parametrize('sensor', ['bearing', 'range'])
def test_offline_with_one_column_dropped_places_every_landmark_from_views(
        noisy_dataset, tmp_path, sensor):
    out = tmp_path / f'{sensor}.json'
    # The synthetic errors are white: the shipped camera's time correlation is off.
    white = tmp_path / 'white.yaml'
    white.write_text(re.sub(r'noise_correlation_time_s: [0-9.]+',
                            'noise_correlation_time_s: 0.0',
                            synthetic_config(tmp_path).read_text()))
    assert 'noise_correlation_time_s: 0.0' in white.read_text()
    assert main([str(noisy_dataset[0]), '--sensor', sensor, '--fusion',
                 'split_covariance_intersection', '--json', str(out),
                 '--config', str(white)]) == 0
    entry, = json.loads(out.read_text())['summary']
    assert entry['sensor'] == sensor
    assert entry['landmarks_fused'] == entry['landmarks_initialised']
    # The synthetic robots drive straight lines, about a metre in all: ranges from a line
    # cannot tell a landmark from its mirror image, so some wait ('ambiguous') for good,
    # and one more waits until its uncertainty is small against its range.
    if sensor == 'bearing':
        assert entry['landmarks_initialised'] == len(LANDMARKS)
    else:
        assert entry['landmarks_initialised'] <= 2  # others wait: 'too_curved' (core.curvature)
    # Placed where the covariance says (a far one from two close robots: 0.6 m, NEES 2.5).
    assert all(landmark['error_m'] < 1.0 and landmark['nees'] < 13.8
               for landmark in entry['landmarks'])
    # Through the nodes: test_mrclam_sensor_nodes; without IDs partial rows are refused.
    assert main([str(noisy_dataset[0]), '--sensor', sensor, '--through-nodes',
                 '--hide-ids']) == 2
