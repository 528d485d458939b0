"""
Tests of the simulator: the ROS-free world (``landmark_ros.sim.simulation``) and the node.

The statistics tests draw thousands of samples and compare them with the
configured noise within bounds several standard errors wide (seeded: they are
deterministic). The node test runs ``landmark_sim`` in a private context and
domain and checks every message it publishes against the ``Simulation``.
"""

from dataclasses import fields, replace
import math
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from landmark_ros.core import sensors
from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.nodes.sim import LandmarkSim
from landmark_ros.ros.cloud import read_columns
from landmark_ros.ros.conversions import pose_from_msg, stamp_ns, yaw_from_quaternion
from landmark_ros.ros.qos import LATCHED
from landmark_ros.ros.schemas import OBSERVATION_FIELDS, read_landmarks
from landmark_ros.sim.simulation import SimConfig, Simulation
from landmark_ros.sim.world import generate_world, load_world, make_paths, visible
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosutil import Collector, RosEnv
from sensor_msgs.msg import PointCloud2
import yaml

DEADLINE_S = 20.0
"""Generous deadline for anything that should happen."""
DEEP = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
"""A queue no test message overflows."""


def within(value, expected, standard_error, k=5.0):
    """Whether ``value`` is within ``k`` standard errors of ``expected``."""
    return abs(value - expected) <= k * standard_error


def std_bounds(samples, stddev, k=5.0):
    """Assert a sample standard deviation matches ``stddev`` (normal samples)."""
    n = len(samples)
    sample = float(np.std(samples, ddof=1))
    # The sample standard deviation of n normal draws has standard error sigma / sqrt(2n).
    assert within(sample, stddev, stddev / math.sqrt(2 * n), k), (sample, stddev, n)


# Determinism --------------------------------------------------------------------------

def test_same_seed_same_world_paths_and_noise():
    a, b = Simulation(SimConfig(seed=7)), Simulation(SimConfig(seed=7))
    np.testing.assert_array_equal(a.world.ids, b.world.ids)
    np.testing.assert_array_equal(a.world.positions, b.world.positions)
    assert a.paths == b.paths
    np.testing.assert_array_equal(a.bias, b.bias)
    for robot, index in [(0, 0), (1, 17), (2, 123)]:
        ma, mb = a.measure(robot, index), b.measure(robot, index)
        np.testing.assert_array_equal(ma.ids, mb.ids)
        np.testing.assert_array_equal(ma.z, mb.z)
        for x, y in zip(a.reported_pose(robot, index), b.reported_pose(robot, index)):
            np.testing.assert_array_equal(x, y)


def test_draws_do_not_depend_on_what_was_drawn_before():
    sim = Simulation(SimConfig(seed=3, range_bias_stddev=0.1))
    first = sim.measure(1, 40)
    for j in range(100):
        sim.measure(0, j)
        sim.reported_pose(2, j)
    again = sim.measure(1, 40)
    np.testing.assert_array_equal(first.z, again.z)


def test_another_seed_another_world():
    a, b = Simulation(SimConfig(seed=1)), Simulation(SimConfig(seed=2))
    assert not np.allclose(a.world.positions, b.world.positions)
    assert a.paths != b.paths


def test_generated_world_is_inside_and_spread():
    world = generate_world(50, 30.0, seed=4)
    np.testing.assert_array_equal(world.ids, np.arange(1, 51))
    assert world.bounds == (-15.0, -15.0, 15.0, 15.0)
    assert np.all(np.abs(world.positions) < 15.0)
    d = np.hypot(*(world.positions[:, None] - world.positions[None]).transpose(2, 0, 1))
    assert np.min(d + 1e9 * np.eye(50)) > 0.5  # no two landmarks on top of each other


# Paths ------------------------------------------------------------------------------

@pytest.mark.parametrize('seed', [0, 5])
def test_paths_are_closed_smooth_and_inside(seed):
    config = SimConfig(seed=seed, robots=6)
    sim = Simulation(config)
    x_min, y_min, x_max, y_max = sim.world.bounds
    dt = 0.01
    kinds, directions = set(), set()
    for path in sim.paths:
        kinds.add(path.kind)
        directions.add(path.direction)
        t = np.arange(0.0, path.period, dt)
        poses = path.pose(t)
        # Closed: one period later the robot is back, heading included.
        later = path.pose(t + path.period)
        np.testing.assert_allclose(later[:, :2], poses[:, :2], atol=1e-9)
        np.testing.assert_allclose(wrap_angle(later[:, 2] - poses[:, 2]), 0.0, atol=1e-9)
        # Inside the world.
        assert np.all((poses[:, 0] > x_min) & (poses[:, 0] < x_max))
        assert np.all((poses[:, 1] > y_min) & (poses[:, 1] < y_max))
        # Smooth: bounded speed and turn rate, no jumps.
        step = np.diff(poses[:, :2], axis=0)
        speed = np.hypot(step[:, 0], step[:, 1]) / dt
        assert 0.2 * config.robot_speed < speed.min() and speed.max() < 3 * config.robot_speed
        assert np.isclose(np.mean(speed), config.robot_speed, rtol=0.05)
        turn = np.abs(wrap_angle(np.diff(poses[:, 2]))) / dt
        assert turn.max() < 3.0  # [rad/s]
        # The heading is the direction of travel.
        np.testing.assert_allclose(
            wrap_angle(np.arctan2(step[:, 1], step[:, 0]) - poses[:-1, 2]), 0.0, atol=0.05)
    assert kinds == {'ellipse', 'eight'}
    assert directions == {1, -1}


def test_robots_drive_different_loops():
    sim = Simulation(SimConfig(seed=2, robots=3))
    t = np.linspace(0.0, 60.0, 600)
    tracks = np.array([sim.true_pose(i, t)[:, :2] for i in range(3)])
    for a in range(3):
        for b in range(a + 1, 3):
            assert np.mean(np.hypot(*(tracks[a] - tracks[b]).T)) > 2.0


def test_paths_fit_a_small_world():
    paths = make_paths(3, (0.0, 0.0, 4.0, 2.0), 0.5, seed=1)
    for path in paths:
        xy = path.pose(np.linspace(0.0, path.period, 500))[:, :2]
        assert np.all((xy >= (0.0, 0.0)) & (xy <= (4.0, 2.0)))


# Time -------------------------------------------------------------------------------

def test_observation_stamps_fall_between_pose_stamps():
    sim = Simulation(SimConfig())
    pose_stamps = np.array([sim.pose_stamp_ns(k) for k in range(400)])
    assert np.all(np.diff(pose_stamps) == 50_000_000)
    for j in range(190):
        stamp = sim.observation_stamp_ns(j)
        k = np.searchsorted(pose_stamps, stamp)
        assert pose_stamps[k - 1] < stamp < pose_stamps[k]
    assert sim.poses_until(-1) == 0 and sim.poses_until(0) == 1
    assert sim.poses_until(sim.pose_stamp_ns(10)) == 11
    assert sim.observations_until(sim.observation_stamp_ns(0) - 1) == 0
    assert sim.observations_until(sim.observation_stamp_ns(5)) == 6


# Measurements -----------------------------------------------------------------------

def test_measurements_within_range_and_field_of_view():
    config = SimConfig(seed=11, landmarks=60, max_range=6.0, min_range=1.0, fov=1.5,
                       range_stddev=0.0, bearing_stddev=0.0)
    sim = Simulation(config)
    seen = 0
    for robot in range(config.robots):
        for j in range(0, 200, 3):
            m = sim.measure(robot, j)
            # Every landmark in range and view is measured, and only those.
            expected = sensors.observe(np.broadcast_to(m.true_pose, (60, 3)),
                                       sim.world.positions)
            inside = ((expected[:, 0] >= 1.0) & (expected[:, 0] <= 6.0)
                      & (np.abs(expected[:, 1]) <= 0.75))
            np.testing.assert_array_equal(m.ids, sim.world.ids[inside])
            np.testing.assert_allclose(m.z_true, expected[inside], atol=1e-12)
            np.testing.assert_allclose(m.z, m.z_true, atol=1e-12)  # no noise configured
            np.testing.assert_allclose(m.true_pose, sim.true_pose(robot, m.stamp_ns * 1e-9))
            seen += len(m.ids)
    assert seen > 200


def test_visible_edges():
    positions = np.array([[2.0, 0.0], [0.0, 2.0], [-2.0, 0.0], [10.0, 0.0], [0.1, 0.0]])
    mask, z = visible([0.0, 0.0, 0.0], positions, 0.5, 5.0, math.pi)
    np.testing.assert_array_equal(mask, [True, True, False, False, False])
    np.testing.assert_allclose(z[:, 0], [2.0, 2.0, 2.0, 10.0, 0.1])
    mask, _ = visible([0.0, 0.0, 0.0], positions, 0.5, 5.0, 2.0 * math.pi)
    np.testing.assert_array_equal(mask, [True, True, True, False, False])


def all_around(**kwargs):
    """Return a config whose sensor sees every landmark (many rows per message)."""
    return SimConfig(landmarks=40, max_range=100.0, fov=2.0 * math.pi, **kwargs)


def test_measurement_noise_statistics():
    config = all_around(seed=21, range_stddev=0.2, bearing_stddev=0.03)
    sim = Simulation(config)
    residuals = np.concatenate([
        np.array(sim.measure(r, j).z) - sim.measure(r, j).z_true
        for r in range(config.robots) for j in range(60)])
    residuals[:, 1] = wrap_angle(residuals[:, 1])
    n = len(residuals)
    assert n > 5000
    for column, stddev in ((0, 0.2), (1, 0.03)):
        assert within(residuals[:, column].mean(), 0.0, stddev / math.sqrt(n))
        std_bounds(residuals[:, column], stddev)
    assert abs(np.corrcoef(residuals.T)[0, 1]) < 5.0 / math.sqrt(n)


def test_bias_is_constant_per_robot_and_drawn_from_its_stddev():
    config = all_around(seed=5, range_stddev=0.05, bearing_stddev=0.005,
                        range_bias_stddev=0.3, bearing_bias_stddev=0.04)
    sim = Simulation(config)
    for robot in range(config.robots):
        residuals = np.concatenate([sim.measure(robot, j).z - sim.measure(robot, j).z_true
                                    for j in range(30)])
        residuals[:, 1] = wrap_angle(residuals[:, 1])
        n = len(residuals)
        np.testing.assert_allclose(residuals.mean(axis=0), sim.bias[robot],
                                   atol=5.0 * 0.05 / math.sqrt(n))
    biases = np.concatenate([
        Simulation(SimConfig(seed=s, robots=100, landmarks=1, range_bias_stddev=0.3,
                             bearing_bias_stddev=0.04)).bias for s in range(5)])
    assert len(biases) == 500
    for column, stddev in ((0, 0.3), (1, 0.04)):
        assert within(biases[:, column].mean(), 0.0, stddev / math.sqrt(500))
        std_bounds(biases[:, column], stddev)


def test_no_bias_by_default():
    np.testing.assert_array_equal(Simulation(SimConfig()).bias, 0.0)


def test_reported_pose_is_the_true_pose_plus_a_sample_of_its_covariance():
    config = SimConfig(seed=8, pose_xy_stddev=0.2, pose_yaw_stddev=0.05)
    sim = Simulation(config)
    errors = []
    for robot in range(config.robots):
        for k in range(0, 1000, 2):  # one pose per observation period: independent
            stamp, true, pose, P_pose = sim.reported_pose(robot, k)
            assert stamp == sim.pose_stamp_ns(k)
            np.testing.assert_allclose(true, sim.true_pose(robot, stamp * 1e-9))
            np.testing.assert_allclose(P_pose, np.diag([0.04, 0.04, 0.0025]))
            error = pose - true
            error[2] = wrap_angle(error[2])
            errors.append(error)
    errors = np.array(errors)
    n = len(errors)
    for column, stddev in ((0, 0.2), (1, 0.2), (2, 0.05)):
        assert within(errors[:, column].mean(), 0.0, stddev / math.sqrt(n))
        std_bounds(errors[:, column], stddev)
    correlation = np.corrcoef(errors.T)
    assert np.all(np.abs(correlation[np.triu_indices(3, 1)]) < 5.0 / math.sqrt(n))


def test_poses_bracketing_an_observation_share_their_error():
    # Interpolating the two reported poses around an observation gives the true
    # pose there plus one sample of the covariance, independent between observations.
    sim = Simulation(SimConfig(seed=9, pose_xy_stddev=0.1, pose_yaw_stddev=0.02))
    period = sim.pose_period_ns
    errors = []
    for j in range(400):
        stamp = sim.observation_stamp_ns(j)
        k = stamp // period
        _, true0, pose0, _ = sim.reported_pose(0, k)
        _, true1, pose1, _ = sim.reported_pose(0, k + 1)
        error0, error1 = pose0 - true0, pose1 - true1
        error0[2], error1[2] = wrap_angle(error0[2]), wrap_angle(error1[2])
        np.testing.assert_allclose(error0, error1, atol=1e-12)
        errors.append(error0)
    errors = np.array(errors)
    lag_correlation = np.corrcoef(errors[:-1, 0], errors[1:, 0])[0, 1]
    assert abs(lag_correlation) < 5.0 / math.sqrt(len(errors))
    std_bounds(errors[:, 0], 0.1)


# World files ------------------------------------------------------------------------

def test_world_file_as_list_or_mapping(tmp_path):
    entries = [{'id': 30, 'x': 1.0, 'y': 2.0}, {'id': 4, 'x': -3, 'y': 0.5},
               {'id': 12, 'x': 5.0, 'y': -6.0}]
    for document in (entries, {'landmarks': entries}):
        path = tmp_path / 'world.yaml'
        path.write_text(yaml.safe_dump(document))
        world = load_world(str(path))
        np.testing.assert_array_equal(world.ids, [4, 12, 30])
        np.testing.assert_array_equal(world.positions, [[-3.0, 0.5], [5.0, -6.0], [1.0, 2.0]])
        x_min, y_min, x_max, y_max = world.bounds
        assert x_min < -3.0 and x_max > 5.0 and y_min < -6.0 and y_max > 2.0
    assert world.truth() == {4: (-3.0, 0.5), 12: (5.0, -6.0), 30: (1.0, 2.0)}


def test_world_file_drives_the_simulation(tmp_path):
    path = tmp_path / 'world.yaml'
    path.write_text(yaml.safe_dump([{'id': 7, 'x': 1.0, 'y': 1.0},
                                    {'id': 8, 'x': -1.0, 'y': -1.0}]))
    sim = Simulation(SimConfig(world_file=str(path), landmarks=99, world_size=10.0))
    np.testing.assert_array_equal(sim.world.ids, [7, 8])
    assert sim.world.bounds == (-5.0, -5.0, 5.0, 5.0)  # grown to world_size
    for path_ in sim.paths:
        xy = path_.pose(np.linspace(0.0, path_.period, 200))[:, :2]
        assert np.all(np.abs(xy) < 5.0)


@pytest.mark.parametrize('text', [
    '[]',
    'landmarks: 3',
    '[{id: 1, x: 0.0}]',
    '[{id: 1, x: 0.0, y: .nan}]',
    '[{id: -1, x: 0.0, y: 0.0}]',
    '[{id: 4294967296, x: 0.0, y: 0.0}]',
    '[{id: 1.5, x: 0.0, y: 0.0}]',
    '[{id: 1, x: 0.0, y: 0.0}, {id: 1, x: 1.0, y: 0.0}]',
    '[{id: 1, x: abc, y: 0.0}]',
    '[{id: 1, x: 0.0, y: 0.0}',
])
def test_bad_world_file_is_refused(tmp_path, text):
    path = tmp_path / 'world.yaml'
    path.write_text(text)
    with pytest.raises(ValueError):
        load_world(str(path))


def test_config_is_validated():
    with pytest.raises(ValueError, match='min_range'):
        SimConfig(min_range=5.0, max_range=4.0)
    with pytest.raises(ValueError, match='robots'):
        SimConfig(robots=0)
    with pytest.raises(ValueError):
        SimConfig(fov=7.0)


def test_shipped_yaml_lists_every_parameter_with_its_default():
    path = Path(__file__).resolve().parents[2] / 'config' / 'sim.yaml'
    document = yaml.safe_load(path.read_text())
    values = document['/**/landmark_sim']['ros__parameters']
    defaults = {spec.name: getattr(SimConfig(), spec.name) for spec in fields(SimConfig)}
    defaults = {k: list(v) if isinstance(v, tuple) else v for k, v in defaults.items()}
    assert values == defaults


# The node ---------------------------------------------------------------------------

@pytest.fixture
def env():
    """Return a private context and domain; closed after the test."""
    ros = RosEnv()
    yield ros
    ros.close()


@pytest.mark.parametrize('frame_error', [False, True])
def test_node_publishes_poses_observations_and_ground_truth(env, frame_error):
    # With a shared frame error each pose carries its own covariance.
    duration_s, robots = 1.0, 2
    frame = [Parameter('frame_xy_stddev', value=0.05),
             Parameter('frame_yaw_stddev', value=0.01)] if frame_error else []
    sim = env.add(LandmarkSim(context=env.context, parameter_overrides=frame + [
        Parameter('robots', value=robots), Parameter('seed', value=4),
        Parameter('fov', value=2.0 * math.pi), Parameter('duration_s', value=duration_s),
        Parameter('time_scale', value=2.0), Parameter('wait_for_subscribers_s', value=10.0),
        Parameter('ground_truth_period_s', value=0.1),
        Parameter('diagnostics_period_s', value=0.1)]))
    tester = env.node('sim_tester')
    poses = [Collector(tester, PoseWithCovarianceStamped, f'/robot{i + 1}/pose', DEEP)
             for i in range(robots)]
    true_poses = [Collector(tester, PoseStamped, f'/robot{i + 1}/true_pose', DEEP)
                  for i in range(robots)]
    observations = [Collector(tester, PointCloud2, f'/robot{i + 1}/observations', DEEP)
                    for i in range(robots)]
    truth = Collector(tester, PointCloud2, '/ground_truth_landmarks', LATCHED)
    diagnostics = Collector(tester, DiagnosticArray, '/diagnostics', DEEP)
    # The simulator waits for the subscribers, then runs 1 s of simulated time.
    assert env.spin_until(lambda: sim.finished, DEADLINE_S)
    poses_expected = sim.sim.poses_until(int(duration_s * 1e9))
    observations_expected = sim.sim.observations_until(int(duration_s * 1e9))
    assert env.spin_until(
        lambda: all(len(c.messages) == poses_expected for c in poses + true_poses)
        and all(len(c.messages) == observations_expected for c in observations)
        and truth.messages and read_landmarks(truth.messages[-1]).observations.sum()
        == sim.robot_counts.sum()
        and any(s.message == 'finished' for d in diagnostics.messages for s in d.status),
        DEADLINE_S)

    start = sim._start_ns
    for robot in range(robots):
        pose_stamps = []
        for k, (msg, true_msg) in enumerate(zip(poses[robot].messages,
                                                true_poses[robot].messages)):
            stamp, true, pose, P_pose = sim.sim.reported_pose(robot, k)
            assert stamp_ns(msg.header.stamp) == start + stamp
            assert true_msg.header == msg.header
            assert msg.header.frame_id == 'map'
            got, got_P = pose_from_msg(msg, 'map')
            np.testing.assert_allclose(got, pose, atol=1e-9)
            np.testing.assert_allclose(got_P, P_pose)
            assert (abs(P_pose[0, 2]) > 0.0) == frame_error
            position, q = true_msg.pose.position, true_msg.pose.orientation
            np.testing.assert_allclose(
                [position.x, position.y, yaw_from_quaternion(q.x, q.y, q.z, q.w)], true,
                atol=1e-9)
            pose_stamps.append(stamp_ns(msg.header.stamp))
        assert np.all(np.diff(pose_stamps) == sim.sim.pose_period_ns)
        rows = 0
        for j, msg in enumerate(observations[robot].messages):
            assert msg.header.frame_id == f'robot{robot + 1}/sensor'
            stamp = stamp_ns(msg.header.stamp)
            assert stamp == start + sim.sim.observation_stamp_ns(j)
            # Between two published poses: an observer can interpolate.
            k = np.searchsorted(pose_stamps, stamp)
            assert 0 < k < len(pose_stamps)
            assert pose_stamps[k - 1] < stamp < pose_stamps[k]
            columns = read_columns(msg, OBSERVATION_FIELDS)
            measured = sim.sim.measure(robot, j)
            np.testing.assert_array_equal(columns['id'], measured.ids)
            np.testing.assert_allclose(np.stack([columns['range'], columns['bearing']], 1),
                                       measured.z)
            rows += len(measured.ids)
        assert rows == sim.robot_counts[robot] > 0

    landmarks = read_landmarks(truth.messages[-1])
    world = sim.sim.world
    np.testing.assert_array_equal(landmarks.ids, world.ids)
    np.testing.assert_array_equal(landmarks.m, world.positions)
    np.testing.assert_array_equal(landmarks.P, 0.0)
    assert truth.messages[-1].header.frame_id == 'map'
    counts = np.zeros(len(world.ids), int)
    for robot in range(robots):
        for j in range(observations_expected):
            counts[np.searchsorted(world.ids, sim.sim.measure(robot, j).ids)] += 1
    np.testing.assert_array_equal(landmarks.observations, counts)

    final = [s for d in diagnostics.messages for s in d.status if s.message == 'finished'][-1]
    values = {kv.key: kv.value for kv in final.values}
    assert values['finished'] == 'true'
    assert float(values['sim_time_s']) == pytest.approx(duration_s)
    assert int(values['observations_out']) == counts.sum()
    assert int(values['start_stamp_ns']) == start


def test_node_refuses_a_bad_world_file(env, tmp_path):
    path = tmp_path / 'world.yaml'
    path.write_text('[{id: 1, x: 0.0}]')
    with pytest.raises(ValueError):
        LandmarkSim(context=env.context,
                    parameter_overrides=[Parameter('world_file', value=str(path))])


def test_sensor_kinds_blank_the_column_a_robot_does_not_measure():
    base = replace(SimConfig(), robots=3, seed=4)
    mixed = Simulation(replace(base, sensor_kinds=('rb', 'range', 'bearing')))
    plain = Simulation(base)
    assert [mixed.config.sensor_kind(r) for r in range(4)] == ['rb', 'range', 'bearing', 'rb']
    seen = 0
    for robot in range(3):
        for j in range(0, 40, 7):
            a, b = mixed.measure(robot, j), plain.measure(robot, j)
            np.testing.assert_array_equal(a.ids, b.ids)
            keep = {0: [0, 1], 1: [0], 2: [1]}[robot]
            np.testing.assert_array_equal(a.z[:, keep], b.z[:, keep])   # the same draws
            assert np.isnan(np.delete(a.z, keep, axis=1)).all()
            seen += len(a.ids)
    assert seen > 10
    with pytest.raises(ValueError, match='sensor_kinds'):
        replace(base, sensor_kinds=('rb', 'sonar'))
    with pytest.raises(ValueError, match='sensor_kinds'):
        replace(base, sensor_kinds=())
