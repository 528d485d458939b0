"""The odometry scale calibration recovers the scales of synthetic odometry."""

from types import SimpleNamespace

from landmark_ros.localizer import motion
from landmark_ros.mrclam.localize_data import odometry_scales, window_samples
import numpy as np
import pytest


def _robot_and_odometry(number, speed_scale, yaw_scale, seed):
    """Return a robot with ground truth and odometry that over-reads by 1/scale."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0, 0.015)
    v = 0.15 + 0.1 * np.sin(0.05 * t + seed) + 0.02 * rng.standard_normal(len(t))
    w = 0.4 * np.sin(0.13 * t + 2.0 * seed)
    truth, _ = motion.integrate_twists(t, np.stack([v, w], 1))
    robot = SimpleNamespace(number=number, gt_times=t, gt_poses=truth)
    odom = SimpleNamespace(odom_times=t, odom_twist=np.stack([v / speed_scale,
                                                              w / yaw_scale], 1))
    return robot, odom


@pytest.mark.parametrize('speed_scale, yaw_scale', [(0.93, 0.9), (1.0, 1.0), (1.08, 0.95)])
def test_odometry_scales_recover_the_true_scales(speed_scale, yaw_scale):
    robots, extras = [], {}
    for number in (1, 2, 3):
        robot, odom = _robot_and_odometry(number, speed_scale, yaw_scale, number)
        robots.append(robot)
        extras[number] = odom
    dataset = SimpleNamespace(robots=robots)
    speed, yaw = odometry_scales(dataset, extras, [1, 2, 3], 0.0)
    assert speed == pytest.approx(speed_scale, rel=2e-3)
    assert yaw == pytest.approx(yaw_scale, rel=2e-3)
    # with the scales applied the windows of integrated odometry match the truth
    errors, _ = window_samples(dataset, extras, [1, 2, 3], 2.0, 0.0, (speed, yaw))
    raw, _ = window_samples(dataset, extras, [1, 2, 3], 2.0, 0.0)
    assert np.sqrt(np.mean(errors ** 2)) < max(0.05 * np.sqrt(np.mean(raw ** 2)), 1e-3)
