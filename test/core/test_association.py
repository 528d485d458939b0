"""Tests of landmark_ros.core.association: candidates, NN, GNN, JCBB, scan covariance."""

import itertools

from conftest import numerical_jacobian
from landmark_ros.core import joint_compatibility
from landmark_ros.core.association import (
    ambiguous_rows, candidates, global_nearest_neighbour, joint_thresholds, LandmarkIndex,
    nearest_neighbour, scan_covariance)
from landmark_ros.core.gating import chi2_threshold, mahalanobis_sq
from landmark_ros.core.joint_compatibility import jcbb, joint_mahalanobis_sq
from landmark_ros.core.landmarks import (landmark_to_world, landmark_to_world_dependent,
                                         lever_arm_covariance)
from landmark_ros.core.pose2 import compose
import numpy as np
import pytest

SENSOR_VAR = 0.02 ** 2
"""Independent noise of a row in the crafted scenes [m^2]."""


def isotropic(n, variance):
    """Return ``n`` covariances ``variance * I``, shape (n, 2, 2)."""
    return np.tile(variance * np.eye(2), (n, 1, 1))


def scene(m_map, P_map, z, R, classes_map=None, classes=None):
    """Return the index and the candidates of a scan, every class 0 unless given."""
    classes_map = np.zeros(len(m_map), int) if classes_map is None else classes_map
    classes = np.zeros(len(z), int) if classes is None else classes
    index = LandmarkIndex(m_map, P_map, classes_map)
    return index, candidates(index, z, R, classes)


def rows_seen_from(robot, P_pose, points, rng=None, pose_error=(0.0, 0.0, 0.0)):
    """
    Observe world points from ``robot`` through a pose error and independent noise.

    Returns the rows ``z`` (N, 2) and their total covariance ``R`` (N, 2, 2): the
    lever-arm term of ``P_pose`` plus ``SENSOR_VAR * I``.
    """
    robot = np.asarray(robot, dtype=float)
    c, s = np.cos(pose_error[2]), np.sin(pose_error[2])
    offset = points - robot[:2]
    z = robot[:2] + np.asarray(pose_error[:2]) + offset @ np.array([[c, s], [-s, c]])
    if rng is not None:
        z = z + rng.normal(0.0, np.sqrt(SENSOR_VAR), z.shape)
    R = lever_arm_covariance(z - robot[:2], P_pose) + SENSOR_VAR * np.eye(2)
    return z, R


def all_methods(index, cands, z, C_z):
    """Return the NN, GNN and JCBB results of one scan."""
    return (nearest_neighbour(cands), global_nearest_neighbour(cands),
            jcbb(cands, index, z, C_z))


# --- Thresholds and candidates. ------------------------------------------------------

def test_joint_thresholds_agree_with_the_gaussian_module():
    thresholds = joint_thresholds(50, 0.99)
    assert thresholds[0] == 0.0
    for k in (1, 2, 5, 50):
        assert thresholds[k] == pytest.approx(chi2_threshold(2 * k, 0.99), rel=1e-9)
    with pytest.raises(ValueError):
        joint_thresholds(3, 1.0)


@pytest.mark.parametrize('seed', range(6))
def test_kd_tree_candidates_equal_brute_force_gating(seed):
    rng = np.random.default_rng(seed)
    k, n = 400, 150
    m_map = rng.uniform(0.0, 40.0, (k, 2))
    # Covariance sizes over three orders of magnitude: several tiers, correlated.
    scales = np.exp(rng.uniform(np.log(0.03), np.log(2.0), k))
    A = rng.normal(size=(k, 2, 2)) * scales[:, None, None]
    P_map = A @ np.swapaxes(A, 1, 2) + 1e-6 * np.eye(2)
    classes_map = rng.integers(0, 3, k)
    z = rng.uniform(-2.0, 42.0, (n, 2))
    B = rng.normal(size=(n, 2, 2)) * rng.uniform(0.05, 1.0, n)[:, None, None]
    R = B @ np.swapaxes(B, 1, 2) + 1e-6 * np.eye(2)
    classes = rng.integers(0, 3, n)
    index, cands = scene(m_map, P_map, z, R, classes_map, classes)
    assert len(index.tiers) > 1

    rows, landmarks = np.meshgrid(np.arange(n), np.arange(k), indexing='ij')
    rows, landmarks = rows.ravel(), landmarks.ravel()
    d2 = mahalanobis_sq(z[rows], m_map[landmarks], R[rows] + P_map[landmarks])
    keep = (d2 <= chi2_threshold(2, 0.999)) & (classes[rows] == classes_map[landmarks])
    expected = sorted(zip(rows[keep].tolist(), landmarks[keep].tolist()))
    assert len(expected) > 50
    assert sorted(zip(cands.rows.tolist(), cands.landmarks.tolist())) == expected
    lookup = dict(zip(zip(rows[keep].tolist(), landmarks[keep].tolist()), d2[keep]))
    np.testing.assert_allclose(
        cands.d2, [lookup[pair] for pair in zip(cands.rows.tolist(), cands.landmarks.tolist())],
        rtol=1e-12)
    # Sorted by row, then d2.
    assert np.all(np.diff(cands.rows) >= 0)
    same_row = np.diff(cands.rows) == 0
    assert np.all(np.diff(cands.d2)[same_row] >= 0)


def test_classes_separate_candidates():
    m_map = np.array([[0.0, 0.0], [10.0, 0.0]])
    P_map = isotropic(2, 0.01)
    z = np.array([[0.0, 0.0], [10.0, 0.0]])
    R = isotropic(2, 0.01)
    index, cands = scene(m_map, P_map, z, R, np.array([1, 2]), np.array([2, 2]))
    assert cands.rows.tolist() == [1] and cands.landmarks.tolist() == [1]
    C_z = scan_covariance(z, R, [5.0, 0.0], np.zeros((3, 3)))
    for result in all_methods(index, cands, z, C_z):
        assert result.assignment.tolist() == [-1, 1], result.method


def test_empty_scan_and_empty_map():
    index, cands = scene(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.ones((3, 2)),
                         isotropic(3, 1.0))
    C_z = np.eye(6)
    for result in all_methods(index, cands, np.ones((3, 2)), C_z):
        assert result.assignment.tolist() == [-1, -1, -1]
        assert np.all(np.isnan(result.d2))
    index, cands = scene(np.ones((4, 2)), isotropic(4, 1.0), np.zeros((0, 2)),
                         np.zeros((0, 2, 2)))
    for result in all_methods(index, cands, np.zeros((0, 2)), np.zeros((0, 0))):
        assert result.assignment.shape == (0,)


# --- The methods on simple scenes. ---------------------------------------------------

def test_each_method_pairs_a_simple_scan():
    m_map = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [20.0, 20.0]])
    P_map = isotropic(4, 0.01)
    z = m_map[[2, 0, 1]] + np.array([[0.05, 0.0], [0.0, -0.05], [0.02, 0.03]])
    R = isotropic(3, 0.01)
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [1.0, 1.0], np.zeros((3, 3)))
    for result in all_methods(index, cands, z, C_z):
        assert result.assignment.tolist() == [2, 0, 1], result.method
        np.testing.assert_allclose(
            result.d2, mahalanobis_sq(z, m_map[[2, 0, 1]], R + P_map[[2, 0, 1]]), rtol=1e-12)
        assert result.ambiguous.size == 0 and not result.fallback
        assert result.n_assigned == 3
    result = jcbb(cands, index, z, C_z)
    assert result.joint_d2 == pytest.approx(
        joint_mahalanobis_sq(index, z, C_z, [0, 1, 2], [2, 0, 1]), rel=1e-10)
    # Independent rows: the joint d2 is the sum of the individual ones.
    assert result.joint_d2 == pytest.approx(result.d2.sum(), rel=1e-10)


def test_landmarks_three_sigma_apart_stay_distinct():
    # S = P + R = I: the two landmarks are 3 sigma apart, each row sits on its own.
    m_map = np.array([[0.0, 0.0], [3.0, 0.0]])
    P_map = isotropic(2, 0.5)
    z = m_map.copy()
    R = isotropic(2, 0.5)
    index, cands = scene(m_map, P_map, z, R)
    assert cands.counts().tolist() == [2, 2]  # d2 = 9 passes the 13.8 gate
    C_z = scan_covariance(z, R, [1.5, -10.0], np.zeros((3, 3)))
    for result in all_methods(index, cands, z, C_z):
        assert result.assignment.tolist() == [0, 1], result.method
    # One row alone near the pair still takes the nearer landmark, not both.
    index, cands = scene(m_map, P_map, z[1:], R[1:])
    for result in all_methods(index, cands, z[1:], C_z[2:, 2:]):
        assert result.assignment.tolist() == [1], result.method


def test_nearest_neighbour_may_reuse_a_landmark_gnn_does_not():
    m_map = np.array([[0.0, 0.0], [2.5, 0.0]])
    P_map = isotropic(2, 0.25)
    z = np.array([[0.1, 0.0], [0.6, 0.0]])
    R = isotropic(2, 0.25)
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [0.0, -5.0], np.zeros((3, 3)))
    assert nearest_neighbour(cands).assignment.tolist() == [0, 0]
    # GNN: 0.01 / 0.5 + 3.61 / 0.5 beats 0.25 / 0.5 + 5.76 / 0.5 and leaving a row out.
    assert global_nearest_neighbour(cands).assignment.tolist() == [0, 1]
    assert jcbb(cands, index, z, C_z).assignment.tolist() == [0, 1]
    assert ambiguous_rows(cands).tolist() == [0, 1]


def test_clutter_rows_stay_unassigned():
    rng = np.random.default_rng(4)
    m_map = np.array([[10.0, 0.0], [0.0, 10.0], [-10.0, 0.0], [0.0, -10.0]])
    P_map = isotropic(4, 0.01)
    P_pose = np.diag([0.02, 0.02, 0.01]) ** 2
    clutter = np.array([[5.0, 5.0], [-6.0, 4.0], [30.0, 0.0]])
    z, R = rows_seen_from([0.0, 0.0, 0.0], P_pose, np.vstack([m_map, clutter]), rng)
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [0.0, 0.0], P_pose)
    for result in all_methods(index, cands, z, C_z):
        assert result.assignment.tolist() == [0, 1, 2, 3, -1, -1, -1], result.method


def test_jcbb_rejects_a_gated_clutter_row_that_contradicts_the_rest():
    # The robot is well localised; eight rows agree, a ninth (clutter) sits 2 sigma
    # from landmark 8 of its own accord. Individually it passes, jointly it does not
    # once the rest pins the pose error, because the rest says "no error at all".
    angles = np.linspace(0.0, 2 * np.pi, 9, endpoint=False)
    m_map = 10.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    P_map = isotropic(9, 1e-6)
    P_pose = np.diag([0.3, 0.3, 0.0001]) ** 2
    z, R = rows_seen_from([0.0, 0.0, 0.0], P_pose, m_map)
    z[8] += 2.0 * np.sqrt(R[8, 0, 0] + P_map[8, 0, 0]) * np.array([1.0, 0.0])
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [0.0, 0.0], P_pose)
    assert nearest_neighbour(cands).assignment[8] == 8
    result = jcbb(cands, index, z, C_z)
    assert result.assignment.tolist() == list(range(8)) + [-1]


# --- The shared pose error: only the joint test sees it. -----------------------------

def rotated_scene(rng, n=8):
    """
    Return a scan every row of which is nearer a decoy than its own landmark.

    Landmarks on a circle of 20 m, 0.3 rad apart; the robot's heading is off by
    0.03 rad (1.5 sigma), which moves every row 0.6 m along the circle. Each true
    landmark has a decoy 0.03 +- 0.007 rad further on (alternating sign), so each
    row alone is within 0.15 m of a decoy; but the decoys need rotations 0.014 rad
    (0.28 m) apart for neighbouring rows, which the shared pose error does not allow.
    """
    angles = 0.3 * np.arange(n)
    decoy_angles = angles + 0.03 + 0.007 * np.where(np.arange(n) % 2, 1.0, -1.0)
    true = 20.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    decoys = 20.0 * np.column_stack([np.cos(decoy_angles), np.sin(decoy_angles)])
    m_map = np.vstack([true, decoys])
    P_map = isotropic(2 * n, 1e-4)
    P_pose = np.diag([0.05, 0.05, 0.02]) ** 2
    z, R = rows_seen_from([0.0, 0.0, 0.0], P_pose, true, rng, pose_error=(0.0, 0.0, 0.03))
    return m_map, P_map, z, R, P_pose


@pytest.mark.parametrize('seed', range(5))
def test_only_the_joint_test_undoes_a_shared_rotation(seed):
    rng = np.random.default_rng(seed)
    n = 8
    m_map, P_map, z, R, P_pose = rotated_scene(rng, n)
    index, cands = scene(m_map, P_map, z, R)
    truth = np.arange(n)
    decoys = n + np.arange(n)
    # Each row alone: its own landmark passes the gate, its decoy is nearer.
    assert np.all(cands.counts() == 2)
    assert nearest_neighbour(cands).assignment.tolist() == decoys.tolist()
    assert global_nearest_neighbour(cands).assignment.tolist() == decoys.tolist()
    # With independent rows, the joint test is fooled just the same.
    C_independent = scan_covariance(z, R, [0.0, 0.0], np.zeros((3, 3)))
    assert jcbb(cands, index, z, C_independent).assignment.tolist() == decoys.tolist()
    # With the shared pose error, only the truth is jointly compatible.
    C_z = scan_covariance(z, R, [0.0, 0.0], P_pose)
    result = jcbb(cands, index, z, C_z)
    assert result.assignment.tolist() == truth.tolist()
    assert not result.fallback and result.ambiguous.size == 0
    assert result.joint_d2 <= joint_thresholds(n)[n]
    assert joint_mahalanobis_sq(index, z, C_z, truth, decoys) > joint_thresholds(n)[n]


def test_jcbb_reports_ties_it_cannot_break():
    # Independent rows, landmarks 3 sigma apart: swapping the two rows' landmarks is
    # jointly compatible too (d2 = 18 <= 18.5 for 4 dof).
    m_map = np.array([[0.0, 0.0], [3.0, 0.0]])
    z = m_map.copy()
    index, cands = scene(m_map, isotropic(2, 0.5), z, isotropic(2, 0.5))
    C_z = scan_covariance(z, isotropic(2, 0.5), [1.5, -10.0], np.zeros((3, 3)))
    assert jcbb(cands, index, z, C_z).ambiguous.tolist() == [0, 1]
    # Landmarks 6 sigma apart: nothing to report.
    m_map = np.array([[0.0, 0.0], [6.0, 0.0]])
    z = m_map.copy()
    index, cands = scene(m_map, isotropic(2, 0.5), z, isotropic(2, 0.5))
    assert jcbb(cands, index, z, C_z).ambiguous.size == 0


def test_search_bound_falls_back_to_gnn():
    rng = np.random.default_rng(1)
    m_map, P_map, z, R, P_pose = rotated_scene(rng, 8)
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [0.0, 0.0], P_pose)
    full = jcbb(cands, index, z, C_z)
    assert full.nodes > 3 and not full.fallback
    bounded = jcbb(cands, index, z, C_z, max_nodes=3)
    assert bounded.fallback and bounded.method == 'jcbb'
    gnn = global_nearest_neighbour(cands)
    np.testing.assert_array_equal(bounded.assignment, gnn.assignment)
    np.testing.assert_array_equal(bounded.ambiguous, ambiguous_rows(cands))
    assert np.isnan(bounded.joint_d2)


# --- JCBB against exhaustive search. -------------------------------------------------

def random_scene(rng, n_landmarks=12, n_rows=6, clutter=2):
    """Return a small random scene with shared pose error: map, rows, P_pose."""
    m_map = rng.uniform(-6.0, 6.0, (n_landmarks, 2)) + np.array([10.0, 0.0])
    P_map = isotropic(n_landmarks, 0.01)
    P_pose = np.diag([0.1, 0.1, 0.03]) ** 2
    seen = rng.choice(n_landmarks, n_rows - clutter, replace=False)
    points = np.vstack([m_map[seen], rng.uniform(-6.0, 6.0, (clutter, 2)) + [10.0, 0.0]])
    error = rng.multivariate_normal(np.zeros(3), P_pose)
    z, R = rows_seen_from([0.0, 0.0, 0.0], P_pose, points, rng, pose_error=error)
    return m_map, P_map, z, R, P_pose


def exhaustive(cands, index, z, C_z):
    """Return every one-to-one hypothesis over the candidates with its joint d2."""
    per_row = [[-1] + cands.landmarks[cands.rows == i].tolist() for i in range(cands.n_rows)]
    for choice in itertools.product(*per_row):
        landmarks = [j for j in choice if j >= 0]
        if len(set(landmarks)) < len(landmarks):
            continue
        rows = [i for i, j in enumerate(choice) if j >= 0]
        yield choice, joint_mahalanobis_sq(index, z, C_z, rows, landmarks)


@pytest.mark.parametrize('seed', range(25))
def test_jcbb_finds_the_most_pairings_exhaustive_search_does(seed):
    rng = np.random.default_rng(seed)
    m_map, P_map, z, R, P_pose = random_scene(rng)
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [0.0, 0.0], P_pose)
    result = jcbb(cands, index, z, C_z)
    assert not result.fallback
    k = result.n_assigned
    thresholds = joint_thresholds(cands.n_rows)
    rows = np.flatnonzero(result.assignment >= 0)
    assert result.joint_d2 == pytest.approx(
        joint_mahalanobis_sq(index, z, C_z, rows, result.assignment[rows]), rel=1e-9, abs=1e-12)
    assert result.joint_d2 <= thresholds[k]
    # Upper bound: hypotheses that pass the joint gate as a whole. Lower bound: those
    # whose every sub-hypothesis passes too (reachable in any visiting order).
    most = most_strong = 0
    for choice, d2 in exhaustive(cands, index, z, C_z):
        size = sum(j >= 0 for j in choice)
        if d2 > thresholds[size]:
            continue
        most = max(most, size)
        if size > most_strong and all(
                joint_mahalanobis_sq(index, z, C_z, sub, [choice[i] for i in sub])
                <= thresholds[len(sub)]
                for r in range(1, size) for sub in itertools.combinations(
                    [i for i, j in enumerate(choice) if j >= 0], r)):
            most_strong = size
    assert most_strong <= k <= most


@pytest.mark.parametrize('seed', range(10))
def test_block_descent_equals_one_row_at_a_time(seed, monkeypatch):
    rng = np.random.default_rng(100 + seed)
    m_map, P_map, z, R, P_pose = random_scene(rng, n_landmarks=40, n_rows=14, clutter=4)
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [0.0, 0.0], P_pose)
    block = jcbb(cands, index, z, C_z)
    monkeypatch.setattr(joint_compatibility._Search, '_run', lambda self, p, k, d2: False)
    single = jcbb(cands, index, z, C_z)
    np.testing.assert_array_equal(block.assignment, single.assignment)
    assert block.joint_d2 == pytest.approx(single.joint_d2, rel=1e-9, abs=1e-12)


# --- Scan covariance. ----------------------------------------------------------------

def test_scan_covariance_blocks_are_the_pose_jacobians():
    rng = np.random.default_rng(7)
    pose = np.array([2.0, -1.0, 0.4])
    sensor_pose = np.array([0.3, 0.1, -0.2])
    obs = np.column_stack([rng.uniform(1.0, 15.0, 5), rng.uniform(-np.pi, np.pi, 5)])
    P_pose = np.diag([0.1, 0.2, 0.05]) ** 2
    P_pose[0, 2] = P_pose[2, 0] = 0.5 * 0.1 * 0.05
    R_obs = np.diag([0.05, 0.01]) ** 2
    z, R = landmark_to_world(pose, P_pose, obs, R_obs, sensor_pose)
    C_z = scan_covariance(z, R, pose[:2], P_pose)

    def row(p, o):
        return landmark_to_world(p, P_pose, o, R_obs, sensor_pose)[0]

    J = [numerical_jacobian(lambda p, o=o: row(p, o), pose) for o in obs]
    for i, j in itertools.product(range(5), repeat=2):
        expected = R[i] if i == j else J[i] @ P_pose @ J[j].T
        np.testing.assert_allclose(C_z[2 * i:2 * i + 2, 2 * j:2 * j + 2], expected,
                                   rtol=0, atol=1e-9)
    assert np.linalg.eigvalsh(C_z)[0] > 0.0


def test_scan_covariance_matches_monte_carlo_with_a_shared_bias():
    rng = np.random.default_rng(11)
    pose = np.array([1.0, 2.0, 0.3])
    obs = np.column_stack([rng.uniform(3.0, 12.0, 4), rng.uniform(-np.pi, np.pi, 4)])
    P_pose = np.diag([0.03, 0.03, 0.01]) ** 2
    R_obs = np.diag([0.02, 0.004]) ** 2
    R_bias = np.diag([0.03, 0.006]) ** 2
    z, R, _ = landmark_to_world_dependent(pose, P_pose, obs, R_obs, R_bias)
    C_z = scan_covariance(z, R, pose[:2], P_pose, R_bias=R_bias)

    draws = 200_000
    poses = pose + rng.multivariate_normal(np.zeros(3), P_pose, draws)
    bias = rng.multivariate_normal(np.zeros(2), R_bias, draws)
    samples = np.empty((draws, 2 * len(obs)))
    for i, o in enumerate(obs):
        noisy = o + bias + rng.multivariate_normal(np.zeros(2), R_obs, draws)
        point = np.column_stack([noisy[:, 0] * np.cos(noisy[:, 1]),
                                 noisy[:, 0] * np.sin(noisy[:, 1]), np.zeros(draws)])
        samples[:, 2 * i:2 * i + 2] = compose(poses, point)[:, :2]
    empirical = np.cov(samples, rowvar=False)
    scale = np.sqrt(np.outer(np.diag(C_z), np.diag(C_z)))
    # Correlation-scale agreement: sampling error ~ 1 / sqrt(draws), plus second order.
    assert np.max(np.abs(empirical - C_z) / scale) < 0.02
    # Without the bias term the off-diagonal blocks are visibly wrong.
    C_no_bias = scan_covariance(z, R, pose[:2], P_pose)
    assert np.max(np.abs(empirical - C_no_bias) / scale) > 0.1


def test_scan_covariance_matches_monte_carlo_with_a_shared_scale_error():
    rng = np.random.default_rng(12)
    pose = np.array([1.0, 2.0, 0.3])
    obs = np.column_stack([rng.uniform(1.0, 8.0, 4), rng.uniform(-np.pi, np.pi, 4)])
    P_pose = np.diag([0.01, 0.01, 0.005]) ** 2
    R_obs = np.diag([0.02, 0.004]) ** 2
    R_bias = np.diag([0.01, 0.003]) ** 2
    scale_var = 0.02 ** 2
    R_rows = np.repeat(R_bias[None], len(obs), axis=0)
    R_rows[:, 0, 0] += scale_var * obs[:, 0] ** 2
    z, R, _ = landmark_to_world_dependent(pose, P_pose, obs, R_obs, R_rows)
    C_z = scan_covariance(z, R, pose[:2], P_pose, R_bias, None, scale_var)

    draws = 200_000
    poses = pose + rng.multivariate_normal(np.zeros(3), P_pose, draws)
    bias = rng.multivariate_normal(np.zeros(2), R_bias, draws)
    scale = rng.normal(0.0, np.sqrt(scale_var), draws)
    samples = np.empty((draws, 2 * len(obs)))
    for i, o in enumerate(obs):
        noisy = o + bias + rng.multivariate_normal(np.zeros(2), R_obs, draws)
        noisy[:, 0] += scale * o[0]
        point = np.column_stack([noisy[:, 0] * np.cos(noisy[:, 1]),
                                 noisy[:, 0] * np.sin(noisy[:, 1]), np.zeros(draws)])
        samples[:, 2 * i:2 * i + 2] = compose(poses, point)[:, :2]
    empirical = np.cov(samples, rowvar=False)
    norm = np.sqrt(np.outer(np.diag(C_z), np.diag(C_z)))
    assert np.max(np.abs(empirical - C_z) / norm) < 0.02
    # Without the scale term the off-diagonal blocks are visibly wrong.
    C_offset = scan_covariance(z, R, pose[:2], P_pose, R_bias)
    assert np.max(np.abs(empirical - C_offset) / norm) > 0.1


def test_scan_covariance_rejects_rows_smaller_than_the_shared_part():
    z = np.array([[10.0, 0.0], [0.0, 10.0]])
    P_pose = np.diag([0.1, 0.1, 0.1]) ** 2
    with pytest.raises(ValueError, match='rows \\[0, 1\\]'):
        scan_covariance(z, isotropic(2, 0.01), [0.0, 0.0], P_pose)
    with pytest.raises(ValueError):
        scan_covariance(z, isotropic(3, 0.01), [0.0, 0.0], P_pose)
    C_z = scan_covariance(z, isotropic(2, 0.01), [0.0, 0.0], np.zeros((3, 3)))
    np.testing.assert_array_equal(C_z, 0.01 * np.eye(4))


@pytest.mark.parametrize('seed', range(10))
def test_ambiguity_swap_test_equals_recomputing_each_swapped_hypothesis(seed):
    rng = np.random.default_rng(200 + seed)
    m_map, P_map, z, R, P_pose = random_scene(rng, n_landmarks=30, n_rows=8, clutter=1)
    P_map = isotropic(len(m_map), 0.1)  # wide landmarks: several candidates per row
    index, cands = scene(m_map, P_map, z, R)
    C_z = scan_covariance(z, R, [0.0, 0.0], P_pose)
    result = jcbb(cands, index, z, C_z)
    rows = np.flatnonzero(result.assignment >= 0)
    threshold = joint_thresholds(len(rows))[len(rows)]
    expected = set()
    for position, row in enumerate(rows):
        for landmark in cands.landmarks[cands.rows == row]:
            if landmark == result.assignment[row]:
                continue
            swapped = result.assignment[rows].copy()
            swapped[position] = landmark
            if joint_mahalanobis_sq(index, z, C_z, rows, swapped) <= threshold:
                expected.add(int(row))
    assert sorted(expected) == result.ambiguous.tolist()
