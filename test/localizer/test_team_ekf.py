"""The team EKF (``eval.team_ekf``): the loop's reference that keeps every correlation."""

from dataclasses import replace
import json
import math

from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.eval import slam_montecarlo
from landmark_ros.eval.slam_loop import LoopConfig
from landmark_ros.eval.team_ekf import _joint_hypothesis, FIRST_TRACK_ID, place, SKIP, TeamEKF
from landmark_ros.localizer import motion
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.update import observe
from landmark_ros.mrclam import slam_cli
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
import numpy as np
import pytest
from test_mrclam_localize import DATASET

MS = 1_000_000
ALPHAS = (0.05, 0.5, 0.05, 0.01)


def _config(**localizer):
    return LoopConfig(LocalizerConfig(odometry_alphas=ALPHAS, **localizer), ObserverConfig(),
                      FuserConfig())


@pytest.mark.parametrize('x', [np.array([1.0, -2.0, 0.7]),
                               np.array([1.0, -2.0, 0.7, 0.03]),
                               np.array([1.0, -2.0, 0.7, 0.03, -0.05])])
def test_place_inverts_the_reading_with_the_range_scale_and_its_jacobians(x):
    z = np.array([3.2, -0.4])
    m, J_m_x, J_m_z = place(x, z)
    h, _, _ = observe(x, m[None])
    np.testing.assert_allclose(h[0], z, atol=1e-12)
    eps = 1e-6
    for k in range(len(x)):
        d = np.zeros(len(x))
        d[k] = eps
        numeric = (place(x + d, z)[0] - place(x - d, z)[0]) / (2 * eps)
        np.testing.assert_allclose(J_m_x[:, k], numeric, atol=1e-8)
    for k in range(2):
        d = np.zeros(2)
        d[k] = eps
        numeric = (place(x, z + d)[0] - place(x, z - d)[0]) / (2 * eps)
        np.testing.assert_allclose(J_m_z[:, k], numeric, atol=1e-8)


def _dense_prediction(x, P, deltas, Qs):
    """Predict pose ``x`` (3,) of a dense state ``P`` step by step, every column moved."""
    x = x.copy()
    for delta, Q in zip(deltas, Qs):
        c, s = math.cos(x[2]), math.sin(x[2])
        F = np.eye(len(P))
        F[0, 2], F[1, 2] = -s * delta[0] - c * delta[1], c * delta[0] - s * delta[1]
        G = np.zeros((len(P), 3))
        G[:3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        P = F @ P @ F.T + G @ Q @ G.T
        x = motion.predict(x, np.zeros((3, 3)), delta, np.zeros((3, 3)))[0]
    return x, P


def test_lazy_prediction_equals_moving_the_full_covariance_at_every_step():
    ekf = TeamEKF(_config(), ['robot1', 'robot2'])
    rng = np.random.default_rng(3)
    starts = [np.array([0.0, 0.0, 0.3]), np.array([2.0, 1.0, -1.0])]
    for i, x in enumerate(starts):
        ekf.start(i, 1 * MS, x, np.diag([1e-3, 2e-3, 1e-4]))
    # Both robots see one landmark: their poses become correlated through it.
    for i in range(2):
        ekf.odometry(i, 2 * MS, pose=np.zeros(3))
        ekf.sightings(i, 3 * MS, np.array([4]), np.array([[3.0, 0.5]]))
    x0, P0 = ekf.x.copy(), ekf.P.copy()
    odom, deltas, Qs = np.zeros(3), [], []
    for k in range(40):
        delta = np.array([0.05, 0.002, 0.03]) + rng.normal(0.0, 0.01, 3)
        odom = motion.compose(odom, delta)
        ekf.odometry(0, (3 + 50 * (k + 1)) * MS, pose=odom)
        d = motion.scale_motion(delta, 0.05)
        deltas.append(d)
        period = LocalizerConfig().odometry_alphas_period_s
        scale = period / 0.05 if period > 0.0 else 1.0
        Qs.append(motion.odometry_noise(d, ALPHAS) * scale + np.eye(3) * 1e-10)
    x, P = _dense_prediction(x0[:3], P0, deltas, Qs)
    est = ekf.estimate(0)
    np.testing.assert_allclose(est.x, x, atol=1e-12)
    np.testing.assert_allclose(est.P, P[:3, :3], atol=1e-12)
    ekf._apply(0)
    np.testing.assert_allclose(ekf.P, P, atol=1e-12)


def test_a_new_landmark_carries_its_cross_covariance_with_the_poses():
    ekf = TeamEKF(_config(), ['robot1', 'robot2'])
    for i in range(2):
        ekf.start(i, 1 * MS, np.array([float(i), 0.0, 0.0]), np.diag([1e-2, 1e-2, 1e-3]))
    ekf.sightings(0, 2 * MS, np.array([9]), np.array([[2.0, 0.3]]))
    _, J_m_x, _ = place(ekf.x[:3], np.array([2.0, 0.3]))
    np.testing.assert_allclose(ekf.P[6:8, :3], J_m_x @ ekf.P[:3, :3], atol=1e-15)
    np.testing.assert_allclose(ekf.P[6:8, 3:6], 0.0)
    assert np.all(np.linalg.eigvalsh(ekf.P) > -1e-15)
    # The second robot's sighting of it correlates the two robots' poses.
    ekf.sightings(1, 3 * MS, np.array([9]), np.array([[1.5, 0.6]]))
    assert np.abs(ekf.P[:3, 3:6]).max() > 1e-5


class _NoCrossCovariance(TeamEKF):
    """A broken reference: each landmark enters as if independent of every pose."""

    def _add_landmark(self, robot, landmark_id, z, R):
        super()._add_landmark(robot, landmark_id, z, R)
        c = self.landmarks[landmark_id]
        block = self.P[c:c + 2, c:c + 2].copy()
        self.P[c:c + 2, :] = 0.0
        self.P[:, c:c + 2] = 0.0
        self.P[c:c + 2, c:c + 2] = block


def test_monte_carlo_the_reference_is_consistent_and_tighter_than_the_loop(monkeypatch):
    seeds, robots, duration = range(8), 3, 60.0
    ekf = slam_montecarlo.Variant(estimator='team_ekf')
    reference = slam_montecarlo.summarise(
        [slam_montecarlo.run_seed(s, robots, duration, variant=ekf) for s in seeds], robots)
    loop = slam_montecarlo.summarise(
        [slam_montecarlo.run_seed(s, robots, duration) for s in seeds], robots)
    low, high = reference['map_joint_anees_interval']
    assert low <= reference['map_joint_anees'] <= high, reference
    assert 2.0 <= reference['pose_anees'] <= 4.0, reference
    # Same seeds, same models: what the loop's bounds give up.
    assert reference['map_rmse_m'] < 0.9 * loop['map_rmse_m'], (reference, loop)
    assert reference['position_rmse_m'] < 0.9 * loop['position_rmse_m'], (reference, loop)
    assert 'map_joint_anees' not in loop
    # The same test fails on a reference that forgets the landmarks' correlation with
    # the poses that placed them: over-confident.
    monkeypatch.setitem(slam_montecarlo.ESTIMATORS, 'team_ekf', _NoCrossCovariance)
    broken = slam_montecarlo.summarise(
        [slam_montecarlo.run_seed(s, robots, duration, variant=ekf) for s in seeds], robots)
    assert broken['map_joint_anees'] > high, broken


def test_robot_sightings_move_both_poses_and_keep_the_heading_wrapped():
    ekf = TeamEKF(_config(robot_stddev_floor=0.01), ['robot1', 'robot2'])
    ekf.start(0, 1 * MS, np.array([0.0, 0.0, math.pi - 0.01]), np.diag([0.04, 0.04, 0.01]))
    ekf.start(1, 1 * MS, np.array([-2.0, 0.1, 0.0]), np.diag([0.04, 0.04, 0.01]))
    before = ekf.P[:6, :6].copy()
    assert ekf.robot_sighting(0, 2 * MS, 1, np.array([2.0, wrap_angle(0.05)]))
    assert ekf.robot_counts(0)['robot_rows_used'] == 1
    assert np.trace(ekf.P[:2, :2]) < np.trace(before[:2, :2])
    assert np.trace(ekf.P[3:5, 3:5]) < np.trace(before[3:5, 3:5])
    assert -math.pi <= ekf.x[2] <= math.pi
    assert not ekf.robot_sighting(0, 3 * MS, 1, np.array([np.nan, 0.0]))
    # Odometry without a finite motion, or stamped back in time, is skipped and counted.
    ekf.odometry(0, 4 * MS, twist=np.array([0.1, 0.0]))
    assert ekf.odometry(0, 5 * MS, twist=np.array([np.nan, 0.0])) is None
    assert ekf.odometry(0, 3 * MS, twist=np.array([0.1, 0.0])) is None
    assert ekf.odometry(0, 6 * MS) is None
    assert ekf.counts['odometry_skipped'] == 3
    assert np.all(np.isfinite(ekf.estimate(0).x))


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
@pytest.mark.parametrize('mode', [[], ['--anchors'], ['--hide-ids']])
def test_mrclam_reference_runs_the_first_minute_and_scores_the_joint_map(
        tmp_path, capsys, mode):
    out = tmp_path / 'ekf.json'
    assert slam_cli.main([str(DATASET), '--duration', '60', '--estimator', 'team_ekf',
                          '--range-scale-state', '--json', str(out)] + mode) == 0
    entry, = json.loads(out.read_text())['slam']
    assert entry['estimator'] == 'team_ekf'
    assert entry['anchors'] == ('--anchors' in mode)
    assert entry['ids_hidden'] == ('--hide-ids' in mode)
    assert entry['map_joint_dof'] == 2 * entry['map_landmarks_scored'] > 0
    assert entry['map_joint_nees'] > 0.0 and entry['position_rmse_m'] < 0.3
    assert entry['map_rmse_m'] < (0.05 if mode == ['--anchors'] else 0.3)
    assert 'map joint NEES' in capsys.readouterr().out


def test_the_joint_hypothesis_takes_the_most_pairs_then_the_least_nees():
    cost = {(0, 'a'): 1.0, (0, 'b'): 0.5, (1, 'a'): 0.2, (1, 'b'): 3.0}

    def nees(pairs):
        return sum(cost[p] for p in pairs)

    # Two pairs beat one; of the two-pair hypotheses the cheaper (0-b, 1-a).
    assert _joint_hypothesis(nees, [['a', 'b'], ['a', 'b']], lambda n: 10.0) == [
        (0, 'b'), (1, 'a')]
    # A joint gate that two pairs cannot pass: one pair, the cheapest.
    assert _joint_hypothesis(nees, [['a', 'b'], ['a', 'b']], lambda n: 0.9 if n == 1 else
                             0.0) == [(1, 'a')]
    assert _joint_hypothesis(nees, [[], []], lambda n: 10.0) == []


def _reading(pose, m):
    d = np.asarray(m) - pose[:2]
    return np.array([np.hypot(*d), wrap_angle(math.atan2(d[1], d[0]) - pose[2])])


def test_without_ids_rows_start_tracks_then_join_them_and_ambiguous_rows_wait():
    ekf = TeamEKF(replace(_config(), hide_ids=True), ['robot1'])
    pose = np.array([0.0, 0.0, 0.0])
    ekf.start(0, 1 * MS, pose, np.diag([1e-6, 1e-6, 1e-6]))
    far = [(3.0, 1.0), (2.0, -2.0)]
    z = np.array([_reading(pose, m) for m in far])
    ekf.sightings(0, 2 * MS, np.array([0, 0]), z)
    assert sorted(ekf.landmarks) == [FIRST_TRACK_ID, FIRST_TRACK_ID + 1]
    assert ekf.map_records() == []  # one row each: not confirmed yet (min_observations)
    ekf.sightings(0, 3 * MS, np.array([0, 0]), z[::-1])  # the same two, order swapped
    assert len(ekf.landmarks) == 2
    assert {r['id'] for r in ekf.map_records()} == {FIRST_TRACK_ID, FIRST_TRACK_ID + 1}
    # Two rows compatible with one landmark only: one pairs with it, the other is
    # neither paired nor new (SKIP); a row far from both landmarks starts a track.
    one = TeamEKF(replace(_config(), hide_ids=True), ['robot1'])
    one.start(0, 1 * MS, pose, np.diag([1e-6, 1e-6, 1e-6]))
    one._insert(5, np.array([3.0, 0.0]), np.eye(2) * 0.01)
    one._insert(6, np.array([0.0, 3.0]), np.eye(2) * 0.01)
    rows = np.array([_reading(pose, (3.02, 0.0)), _reading(pose, (3.0, 0.01)),
                     _reading(pose, (-3.0, 0.0))])
    ids = one._name_rows(0, rows)
    assert sorted(ids[:2].tolist()) == [SKIP, 5]
    assert ids[2] == FIRST_TRACK_ID and FIRST_TRACK_ID not in one.landmarks
    one.sightings(0, 2 * MS, np.array([0, 0, 0]), rows)
    assert sorted(one.landmarks) == [5, 6, FIRST_TRACK_ID + 1]
    assert one.rows_per_landmark[5] == 1


def test_the_monte_carlo_judges_a_joint_map_by_its_joint_nees():
    summary = {'pose_anees_interval': [2.5, 3.5], 'map_anees': 1.0,
               'map_anees_interval': [1.8, 2.2]}
    assert not slam_montecarlo.consistent(summary)
    joint = dict(summary, map_joint_anees=1.0, map_joint_anees_interval=[0.9, 1.1])
    assert slam_montecarlo.consistent(joint)
    assert not slam_montecarlo.consistent(dict(joint, map_joint_anees=1.2))
