"""The camera delay of a MRCLAM dataset: its estimate and Dataset.with_camera_delay."""

from collections import Counter
import math
from pathlib import Path

from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.mrclam.camera_delay import estimate_camera_delay, format_camera_delay
from landmark_ros.mrclam.data import Dataset, interpolate_poses, Robot
import numpy as np
import pytest

LANDMARKS = {6: (3.0, 2.0), 7: (-2.5, 3.0), 8: (1.0, -3.5), 9: (-3.0, -2.0), 10: (4.0, -1.0)}


def moving_pose(number, t):
    """Return a robot's pose at times ``t``: a slow circle with a varying turn rate."""
    t = np.asarray(t, dtype=np.float64)
    heading = 0.3 * number + 0.6 * t + 0.8 * np.sin(0.7 * t + number)
    return np.stack([0.5 * np.cos(0.2 * t) + 0.1 * number, 0.5 * np.sin(0.2 * t),
                     wrap_angle(heading)], axis=1)


def delayed_dataset(delay_s, robots=3, duration=60.0, sigma_b=0.01, seed=0):
    """
    Return a dataset whose sightings were taken ``delay_s`` before their stamps.

    Ground truth at 100 Hz; every landmark seen at 5 Hz with bearing noise ``sigma_b``
    and, in 2 % of the sightings, a wrong bearing (uniform): the tail the robust loss
    must ignore.
    """
    rng = np.random.default_rng(seed)
    out = []
    for number in range(1, robots + 1):
        gt_t = np.arange(-2.0, duration + 2.0, 0.01)
        stamps = np.repeat(np.arange(0.0, duration, 0.2) + 0.013 * number, len(LANDMARKS))
        ids = np.tile(np.array(sorted(LANDMARKS)), len(stamps) // len(LANDMARKS))
        taken = moving_pose(number, stamps - delay_s)
        truth = np.array([LANDMARKS[i] for i in ids.tolist()])
        d = truth - taken[:, :2]
        bearing = np.arctan2(d[:, 1], d[:, 0]) - taken[:, 2] + rng.normal(0, sigma_b, len(ids))
        wrong = rng.random(len(ids)) < 0.02
        bearing[wrong] = rng.uniform(-math.pi, math.pi, int(wrong.sum()))
        z = np.stack([np.hypot(d[:, 0], d[:, 1]), wrap_angle(bearing)], axis=1)
        out.append(Robot(number, stamps, ids, z, moving_pose(number, stamps), gt_t,
                         moving_pose(number, gt_t), Counter(kept=len(ids))))
    return Dataset(Path('synthetic'), out, dict(LANDMARKS), {}, {},
                   counts=Counter(kept=sum(len(r.times) for r in out)))


@pytest.mark.parametrize('delay_s', [0.038, -0.02, 0.0])
def test_the_estimate_recovers_a_known_delay(delay_s):
    result = estimate_camera_delay(delayed_dataset(delay_s))
    assert result.minimum_s == pytest.approx(delay_s, abs=0.003)
    assert 0.0 < result.stderr_s < 0.002
    # Applied when significant; the no-delay data give a minimum within 3 errors of 0.
    assert result.delay_s == (result.minimum_s if delay_s else 0.0)
    for robot_delay, stderr in result.robots.values():
        assert robot_delay == pytest.approx(delay_s, abs=max(0.006, 4 * stderr))
    if delay_s:
        assert result.bearing_sd < result.bearing_sd_raw
    assert f'{1e3 * result.delay_s:+.1f} ms' in format_camera_delay(result)


def test_a_delay_that_a_bias_explains_as_well_is_not_applied():
    # Robots turning at one constant rate: a shift of the stamps moves every bearing of
    # a robot alike, as a bearing bias does; the data cannot tell them apart.
    dataset = delayed_dataset(0.0)
    for robot in dataset.robots:
        robot.gt_poses[:, 2] = wrap_angle(0.9 * robot.gt_times + robot.number)
        robot.poses[:, 2] = wrap_angle(0.9 * robot.times + robot.number)
        truth = np.array([LANDMARKS[i] for i in robot.ids.tolist()])
        d = truth - robot.poses[:, :2]
        robot.z[:, 1] = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - robot.poses[:, 2]
                                   + 0.01 * np.sin(np.arange(len(d))))
    result = estimate_camera_delay(dataset)
    assert result.delay_s == 0.0 and result.stderr_s > abs(result.minimum_s) / 3.0


def test_a_delay_outside_the_search_is_not_invented():
    # The estimate stays inside the searched shifts; the edge says the search was short.
    result = estimate_camera_delay(delayed_dataset(0.05), search=(-0.02, 0.02))
    assert result.minimum_s == pytest.approx(0.02)


def test_invalid_search_and_no_sightings_raise():
    with pytest.raises(ValueError, match='invalid delay search'):
        estimate_camera_delay(delayed_dataset(0.0), search=(0.1, -0.1))
    empty = Dataset(Path('none'), [], dict(LANDMARKS), {}, {})
    with pytest.raises(ValueError, match='no sighting'):
        estimate_camera_delay(empty)


def test_with_camera_delay_moves_the_stamps_and_their_poses():
    dataset = delayed_dataset(0.0, robots=2, duration=10.0)
    moved = dataset.with_camera_delay(0.038)
    for before, after in zip(dataset.robots, moved.robots):
        np.testing.assert_allclose(after.times, before.times - 0.038, rtol=0, atol=1e-12)
        expected, _ = interpolate_poses(before.gt_times, before.gt_poses, after.times)
        np.testing.assert_allclose(after.poses, expected, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(after.z, before.z)
        np.testing.assert_array_equal(after.ids, before.ids)
    # The original is left as it was.
    np.testing.assert_allclose(dataset.robots[0].poses,
                               moving_pose(1, dataset.robots[0].times), atol=1e-12)
    # Moved by the true delay, the poses are where the sightings were taken.
    delayed = delayed_dataset(0.05, robots=1, duration=10.0)
    robot = delayed.with_camera_delay(0.05).robots[0]
    np.testing.assert_allclose(robot.poses, moving_pose(1, delayed.robots[0].times - 0.05),
                               atol=1e-4)


def test_with_camera_delay_zero_is_a_no_op_and_drops_what_leaves_the_ground_truth():
    dataset = delayed_dataset(0.0, robots=2, duration=10.0)
    assert dataset.with_camera_delay(0.0) is dataset
    # 2.5 s earlier: the sightings of the first 0.5 s leave the ground truth (from -2 s).
    moved = dataset.with_camera_delay(2.5)
    for before, after in zip(dataset.robots, moved.robots):
        dropped = int(np.sum(before.times - 2.5 < before.gt_times[0]))
        assert dropped > 0 and len(after.times) == len(before.times) - dropped
        assert after.counts['outside_groundtruth'] == dropped
        assert after.counts['kept'] == len(after.times)
    assert moved.counts['kept'] == sum(len(r.times) for r in moved.robots)
    with pytest.raises(ValueError, match='finite'):
        dataset.with_camera_delay(float('nan'))


def test_the_localization_replay_moves_robot_sightings_back_too():
    from landmark_ros.mrclam.localize_data import RobotExtras, with_camera_delay
    dataset = delayed_dataset(0.04, robots=2)
    extras = {r.number: RobotExtras(r.number, np.arange(0.0, 10.0, 0.015),
                                    np.ones((667, 2)), np.array([1.0, 2.5]),
                                    np.array([3 - r.number] * 2), np.ones((2, 2)))
              for r in dataset.robots}
    moved, moved_extras = with_camera_delay(dataset, extras, 0.04)
    for before, after in zip(dataset.robots, moved.robots):
        np.testing.assert_allclose(after.times, before.times - 0.04)
        e, f = extras[before.number], moved_extras[before.number]
        np.testing.assert_allclose(f.sighting_times, e.sighting_times - 0.04)
        np.testing.assert_array_equal(f.odom_times, e.odom_times)  # the odometry stays
        np.testing.assert_array_equal(f.sighting_z, e.sighting_z)
    same, same_extras = with_camera_delay(dataset, extras, 0.0)
    assert same is dataset and same_extras is extras
    with pytest.raises(ValueError):
        with_camera_delay(dataset, extras, math.nan)
