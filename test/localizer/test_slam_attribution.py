"""Where the loop's map error comes from (``eval.slam_attribution``, its MRCLAM study)."""

import json

from landmark_ros.eval.slam_attribution import place, rigid_fit, row_parts, shift_nees, to_local
from landmark_ros.eval.slam_loop import LoopConfig
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.mrclam import slam_attribution
from landmark_ros.mrclam.slam_attribution import RecordingLoop
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
import numpy as np
import pytest
from test_mrclam_localize import DATASET

MS = 1_000_000


def _rotate(points, angle, center):
    c, s = np.cos(angle), np.sin(angle)
    return (points - center) @ np.array([[c, -s], [s, c]]).T + center


def test_rigid_fit_recovers_a_shift_and_a_rotation_about_the_centre():
    rng = np.random.default_rng(3)
    truth = rng.uniform(-5, 5, (12, 2))
    center = np.array([1.0, -2.0])
    est = _rotate(truth, 0.03, center) + [0.08, -0.05]
    fit = rigid_fit(est, truth, center)
    assert fit.angle == pytest.approx(0.03, abs=1e-12)
    np.testing.assert_allclose(fit.shift, [0.08, -0.05], atol=1e-12)
    assert fit.residual_rmse < 1e-12
    # A per-landmark error on top stays in the residual, the transform unchanged.
    noise = rng.normal(0, 0.01, truth.shape)
    noise -= noise.mean(axis=0)
    fit = rigid_fit(est + noise, truth, center, rotate=False)
    np.testing.assert_allclose(fit.shift, (est - truth).mean(axis=0), atol=1e-12)
    assert fit.residual_rmse > 0.005


def test_rigid_fit_is_the_least_squares_minimum():
    rng = np.random.default_rng(4)
    truth = rng.uniform(-5, 5, (8, 2))
    est = truth + rng.normal(0, 0.1, truth.shape)
    center = np.zeros(2)
    fit = rigid_fit(est, truth, center)
    for d_angle in (-1e-3, 1e-3):
        other = _rotate(truth, fit.angle + d_angle, center)
        shift = (est - other).mean(axis=0)
        cost = np.sum((est - other - shift) ** 2)
        assert cost > np.sum(fit.residual ** 2)


def test_row_parts_split_a_row_error_into_pose_and_sensor():
    rng = np.random.default_rng(5)
    truth_pose = np.column_stack([rng.uniform(-3, 3, (20, 2)), rng.uniform(-3, 3, 20)])
    landmark = rng.uniform(-4, 4, (20, 2))
    true_local = to_local(truth_pose, landmark)
    np.testing.assert_allclose(place(truth_pose, true_local), landmark, atol=1e-12)
    scale = 0.02
    sensed = true_local * (1 + scale)           # a range scale error alone
    used = truth_pose + [0.05, -0.03, 0.02]     # and a pose error
    m_row = place(used, sensed)
    parts = row_parts(m_row, used, truth_pose, landmark)
    np.testing.assert_allclose(parts['pose'] + parts['sensor'], m_row - landmark, atol=1e-12)
    np.testing.assert_allclose(parts['radial'], scale * parts['range'] / (1 + scale),
                               atol=1e-12)
    np.testing.assert_allclose(parts['tangential'], 0.0, atol=1e-12)
    # The true pose used: no pose part; an exact sensor: no sensor part.
    assert np.abs(row_parts(place(truth_pose, sensed), truth_pose, truth_pose,
                            landmark)['pose']).max() < 1e-12
    assert np.abs(row_parts(place(used, true_local), used, truth_pose,
                            landmark)['sensor']).max() < 1e-12


def test_shift_nees_shared_and_independent():
    P = np.tile(np.diag([0.01, 0.04]), (9, 1, 1))
    nees = shift_nees([0.1, 0.2], P)
    assert nees['shared'] == pytest.approx(0.1 ** 2 / 0.01 + 0.2 ** 2 / 0.04)
    assert nees['independent'] == pytest.approx(9 * nees['shared'])


def test_the_recording_loop_keeps_each_row_with_the_pose_it_was_placed_with():
    config = LoopConfig(LocalizerConfig(initial_stddev=(0.01, 0.01, 0.01)),
                        ObserverConfig(range_stddev=0.05, bearing_stddev=0.02),
                        FuserConfig(min_observations=2, false_track_probability=0.49))
    loop = RecordingLoop(config, ['robot1'])
    start = np.array([1.0, 2.0, 0.5])
    loop.start(0, 1 * MS, start, np.diag([1e-4, 1e-4, 1e-4]))
    landmark = np.array([4.0, 3.0])
    local = to_local(start, landmark)[0]
    z = np.array([[np.hypot(*local), np.arctan2(local[1], local[0])]])
    for k in range(3):
        loop.odometry(0, (10 * k + 2) * MS, pose=start)
        loop.sightings(0, (10 * k + 5) * MS, np.array([7]), z)
        loop.odometry(0, (10 * k + 8) * MS, pose=start)
    rows = loop.rows.arrays()
    assert rows['true_id'].tolist() == [7, 7, 7]
    assert rows['stamp_ns'].tolist() == [5 * MS, 15 * MS, 25 * MS]
    np.testing.assert_allclose(rows['pose'], np.tile(start, (3, 1)), atol=1e-6)
    np.testing.assert_allclose(rows['m'], np.tile(landmark, (3, 1)), atol=1e-6)


@pytest.mark.skipif(not DATASET.is_dir(), reason='MRCLAM dataset 6 not available')
def test_the_study_on_twenty_seconds_of_dataset_6(tmp_path, capsys):
    out = tmp_path / 'attribution.json'
    assert slam_attribution.main([str(DATASET), '--duration', '20', '--json', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'one shift' in text and 'pose error at the rows' in text
    document = json.loads(out.read_text())
    landmarks = document['landmarks']
    assert landmarks and document['map']['rmse_m'] == pytest.approx(
        document['scores']['map_rmse_m'])
    # The transform never leaves more than the raw error.
    assert document['map']['rigid_residual_rmse_m'] <= document['map']['shift_residual_rmse_m']
    assert document['map']['shift_residual_rmse_m'] <= document['map']['rmse_m'] + 1e-12
    for entry in landmarks:
        rows = np.add(entry['pose_part'], entry['sensor_part'])
        np.testing.assert_allclose(rows, entry['rows_mean_error'], atol=1e-9)


def _turning_robot(k, c, scale, seed=0):
    """Return a robot whose true turn is ``k scale w + c |v|`` for random commanded twists."""
    from types import SimpleNamespace
    from landmark_ros.mrclam.localize_data import RobotExtras
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 200.0, 0.1)
    v = rng.choice([0.0, 0.07, 0.1], len(t))
    w = rng.choice([-0.4, 0.0, 0.4], len(t))
    rate = k * scale * w + c * np.abs(v)
    heading = np.concatenate([[0.0], np.cumsum(rate[:-1] * 0.1)])
    gt = np.column_stack([np.zeros(len(t)), np.zeros(len(t)), np.angle(np.exp(1j * heading))])
    robot = SimpleNamespace(number=1, gt_times=t, gt_poses=gt)
    empty = np.zeros(0)
    extras = {1: RobotExtras(1, t, np.column_stack([v, w]), empty, empty.astype(np.int64),
                             np.zeros((0, 2)))}
    return SimpleNamespace(robots=[robot]), extras


def test_fit_yaw_finds_the_turn_factor_and_the_veer_and_the_correction_removes_them():
    scale = 0.9
    dataset, extras = _turning_robot(1.05, -0.04, scale)
    k, c = slam_attribution.fit_yaw(dataset, extras, 0.0, scale)
    assert k == pytest.approx(1.05, abs=1e-3) and c == pytest.approx(-0.04, abs=1e-3)
    fixed = slam_attribution.corrected_twists(extras, k, c, scale)
    k, c = slam_attribution.fit_yaw(dataset, fixed, 0.0, scale)
    assert k == pytest.approx(1.0, abs=1e-3) and c == pytest.approx(0.0, abs=1e-3)
