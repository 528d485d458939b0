"""Tests of landmark_ros.core.landmarks: the chapter's operations with uncertainty."""

from conftest import (numerical_jacobian, random_observations, random_points, random_poses,
                      random_spd)
from landmark_ros.core import pose2, sensors
from landmark_ros.core.gating import mahalanobis_sq
from landmark_ros.core.gaussian import fuse
from landmark_ros.core.landmarks import (
    landmark_to_world, landmark_to_world_parts, lever_arm_covariance, nees, polar_covariance,
    predict_observation, relative_pose, sensor_in_world)
import numpy as np
import pytest

# The textbook example.
R = np.diag([0.25, 0.04])
P1_POSE = np.array([1.0, 2.0, 0.5])
P1_COV = np.diag([0.08, 0.6, 0.02])
Z1 = np.array([4.0, 0.7])
P2_POSE = np.array([6.0, 4.0, 2.1])
P2_COV = np.diag([0.20, 0.09, 0.03])
Z2 = np.array([4.0, 0.3])

M1 = np.array([2.44943102, 5.72815634])
P_M1_EXACT_POSE = np.array([[0.58879177, -0.13171532], [-0.13171532, 0.30120823]])
P_M1 = np.array([[0.94677477, -0.23978943], [-0.23978943, 0.94322523]])
P12 = np.array([5.34676389, -0.64196257, 1.6])
P12_COV = np.array([[0.38248035, 0.24115, 0.01283925],
                    [0.24115, 1.16751965, 0.10693528],
                    [0.01283925, 0.10693528, 0.05]])
Z_PRED = np.array([3.94880545, 0.58862004])
P_Z_PRED = np.array([[1.31374309, -0.02614814], [-0.02614814, 0.08555399]])
P_Z_PRED_TEXTBOOK = np.array([[1.41886714, 0.01057848], [0.01057848, 0.07881227]])
M2 = np.array([3.05042514, 6.70185272])
P_M2 = np.array([[0.84693794, 0.4333316], [0.4333316, 0.81306206]])
M_FUSED = np.array([2.58757252, 6.15534036])
P_FUSED = np.array([[0.37966125, 0.07773125], [0.07773125, 0.36999739]])

TEXTBOOK_ATOL = 1e-8


def assert_matrices_close(actual, expected, tol):
    """Assert ``|actual - expected| <= tol * max(1, max |expected|)`` per matrix."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape
    scale = np.maximum(1.0, np.abs(expected).max(axis=(-2, -1), keepdims=True))
    error = np.abs(actual - expected)
    assert np.all(error <= tol * scale), f'max scaled error {np.max(error / scale)!r} > {tol}'


def generic_landmark(pose, P_pose, z, R, sensor_pose=None):
    """Return ``m`` and the two covariance terms from the generic Jacobians."""
    s, P_s = sensor_in_world(pose, P_pose, sensor_pose)
    J_m_s, J_m_z = sensors.landmark_from_observation_jacobians(s, z)
    T = np.swapaxes
    return (sensors.landmark_from_observation(s, z), J_m_s @ P_s @ T(J_m_s, -1, -2),
            J_m_z @ R @ T(J_m_z, -1, -2))


def random_case(rng, n=None):
    """Return random pose, P_pose, z, R and sensor_pose (batches of ``n`` if given)."""
    return (random_poses(rng, n), random_spd(rng, 3, n, scale=0.3), random_observations(rng, n),
            random_spd(rng, 2, n, scale=0.2), random_poses(rng, n, scale=0.5))


# --- the textbook numbers -----------------------------------------------------------------

def test_textbook_case_1_exact_pose():
    m1, P_m1 = landmark_to_world(P1_POSE, np.zeros((3, 3)), Z1, R)
    np.testing.assert_allclose(m1, M1, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(P_m1, P_M1_EXACT_POSE, rtol=0, atol=TEXTBOOK_ATOL)


def test_textbook_case_2_uncertain_pose():
    m1, P_m1 = landmark_to_world(P1_POSE, P1_COV, Z1, R)
    np.testing.assert_allclose(m1, M1, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(P_m1, P_M1, rtol=0, atol=TEXTBOOK_ATOL)
    # The sensor term alone is case 1.
    _, P_pose_term, P_sensor_term = landmark_to_world_parts(P1_POSE, P1_COV, Z1, R)
    np.testing.assert_allclose(P_sensor_term, P_M1_EXACT_POSE, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(P_pose_term + P_sensor_term, P_M1, rtol=0, atol=TEXTBOOK_ATOL)


@pytest.mark.parametrize('method', ['between', 'composition'])
def test_textbook_case_3_relative_pose(method):
    p12, P12_cov = relative_pose(P1_POSE, P1_COV, P2_POSE, P2_COV, method=method)
    np.testing.assert_allclose(p12, P12, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(P12_cov, P12_COV, rtol=0, atol=TEXTBOOK_ATOL)


def test_textbook_case_4_predicted_observation():
    m1, P_m1 = landmark_to_world(P1_POSE, P1_COV, Z1, R)
    z, P_z = predict_observation(P2_POSE, P2_COV, m1, P_m1)
    np.testing.assert_allclose(z, Z_PRED, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(P_z, P_Z_PRED, rtol=0, atol=TEXTBOOK_ATOL)


def _covariance_in_robot_2_frame():
    """Return ``q``, m1 in R2's frame, and its covariance, via transform_point."""
    m1, P_m1 = landmark_to_world(P1_POSE, P1_COV, Z1, R)
    inv = pose2.inverse(P2_POSE)
    J_inv = pose2.inverse_jacobian(P2_POSE)
    P_inv = J_inv @ P2_COV @ J_inv.T
    q = pose2.transform_point(inv, m1)
    J_q_inv, J_q_m = pose2.transform_point_jacobians(inv, m1)
    return m1, q, J_q_inv @ P_inv @ J_q_inv.T + J_q_m @ P_m1 @ J_q_m.T


def test_textbook_case_4_figure_uses_the_world_frame_jacobian():
    m1, q, P_q = _covariance_in_robot_2_frame()
    # The textbook evaluates the polar Jacobian at the world-frame difference ...
    J_world = sensors.cartesian_to_polar_jacobian(m1 - P2_POSE[:2])
    np.testing.assert_allclose(J_world @ P_q @ J_world.T, P_Z_PRED_TEXTBOOK, rtol=0,
                               atol=TEXTBOOK_ATOL)
    # ... the correct one is at q, in R2's frame, and equals predict_observation.
    J_q = sensors.cartesian_to_polar_jacobian(q)
    np.testing.assert_allclose(J_q @ P_q @ J_q.T, P_Z_PRED, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(sensors.cartesian_to_polar(q), Z_PRED, rtol=0,
                               atol=TEXTBOOK_ATOL)
    # Same range, bearing off by the heading: only the Jacobian rows rotate.
    assert np.linalg.norm(q) == pytest.approx(np.linalg.norm(m1 - P2_POSE[:2]), abs=1e-12)
    assert np.abs(P_Z_PRED - P_Z_PRED_TEXTBOOK).max() > 0.03


def _sample_observations(scale, n, seed):
    """Return the sample covariance of observe() with p2 and m1 drawn from their Gaussians."""
    rng = np.random.default_rng(seed)
    m1, P_m1 = landmark_to_world(P1_POSE, P1_COV, Z1, R)
    poses = P2_POSE + rng.standard_normal((n, 3)) @ np.linalg.cholesky(scale * P2_COV).T
    points = m1 + rng.standard_normal((n, 2)) @ np.linalg.cholesky(scale * P_m1).T
    z = sensors.observe(poses, points)
    error = z - Z_PRED
    error[:, 1] = pose2.wrap_angle(error[:, 1])
    error -= error.mean(axis=0)
    return error.T @ error / (n - 1)


def test_textbook_case_4_monte_carlo_small_noise():
    # With the covariances scaled down the first-order propagation is exact up to
    # sampling error, so the sample covariance pins down which P_z is right.
    n, scale = 400_000, 1e-4
    sample = _sample_observations(scale, n, seed=4) / scale
    # Standard error of each sample covariance entry: sqrt((P_ii P_jj + P_ij^2) / n).
    diag = np.diag(P_Z_PRED)
    sigma = np.sqrt((np.outer(diag, diag) + P_Z_PRED ** 2) / n)
    assert np.all(np.abs(sample - P_Z_PRED) < 5.0 * sigma), (sample, P_Z_PRED)
    np.testing.assert_allclose(sample, P_Z_PRED, rtol=0.02, atol=1.2e-3)
    # The textbook's figure is many standard errors away.
    assert np.max(np.abs(sample - P_Z_PRED_TEXTBOOK) / sigma) > 30.0


def test_textbook_case_4_monte_carlo_full_noise():
    # At the textbook's noise the linearisation itself is off by several percent
    # (bearing variance about +14 %), but the sign of the range-bearing covariance and
    # the overall distance still single out the Jacobian at q.
    sample = _sample_observations(1.0, 400_000, seed=44)
    assert sample[0, 1] < 0.0 < P_Z_PRED_TEXTBOOK[0, 1]
    assert sample[0, 1] == pytest.approx(P_Z_PRED[0, 1], abs=0.005)
    assert sample[0, 0] == pytest.approx(P_Z_PRED[0, 0], rel=0.08)
    assert sample[1, 1] == pytest.approx(P_Z_PRED[1, 1], rel=0.2)
    correct = np.linalg.norm(sample - P_Z_PRED)
    textbook = np.linalg.norm(sample - P_Z_PRED_TEXTBOOK)
    assert correct < 0.5 * textbook, (correct, textbook)


def test_textbook_case_5_second_robot_and_fusion():
    m1, P_m1 = landmark_to_world(P1_POSE, P1_COV, Z1, R)
    m2, P_m2 = landmark_to_world(P2_POSE, P2_COV, Z2, R)
    np.testing.assert_allclose(m2, M2, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(P_m2, P_M2, rtol=0, atol=TEXTBOOK_ATOL)
    m, P = fuse(m1, P_m1, m2, P_m2)
    np.testing.assert_allclose(m, M_FUSED, rtol=0, atol=TEXTBOOK_ATOL)
    np.testing.assert_allclose(P, P_FUSED, rtol=0, atol=TEXTBOOK_ATOL)


# --- closed forms against the generic Jacobian propagation ------------------------------

@pytest.mark.parametrize('with_sensor', [False, True])
def test_landmark_to_world_matches_generic_propagation(with_sensor, rng):
    n = 300
    pose, P_pose, z, R_batch, sensor_pose = random_case(rng, n)
    sensor_pose = sensor_pose if with_sensor else None
    m_ref, P_pose_ref, P_sensor_ref = generic_landmark(pose, P_pose, z, R_batch, sensor_pose)
    m, P_m = landmark_to_world(pose, P_pose, z, R_batch, sensor_pose)
    m_parts, P_m_pose, P_m_sensor = landmark_to_world_parts(
        pose, P_pose, z, R_batch, sensor_pose)
    np.testing.assert_allclose(m, m_ref, rtol=0, atol=1e-12 * np.abs(m_ref).max())
    np.testing.assert_array_equal(m_parts, m)
    assert_matrices_close(P_m, P_pose_ref + P_sensor_ref, 1e-12)
    assert_matrices_close(P_m_pose, P_pose_ref, 1e-12)
    assert_matrices_close(P_m_sensor, P_sensor_ref, 1e-12)
    for P in (P_m, P_m_pose, P_m_sensor):
        np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
    # Single calls too.
    args = [a[7] for a in (pose, P_pose, z, R_batch)] + [
        None if sensor_pose is None else sensor_pose[7]]
    m7, P7 = landmark_to_world(*args)
    m7_ref, P7_pose, P7_sensor = generic_landmark(*args)
    np.testing.assert_allclose(m7, m7_ref, rtol=0, atol=1e-12 * np.abs(m7_ref).max())
    assert_matrices_close(P7, P7_pose + P7_sensor, 1e-12)


def test_landmark_to_world_matches_numerical_jacobians(rng):
    # Independent of the library's own Jacobians: differentiate the whole chain.
    for _ in range(30):
        pose, P_pose, z, R_one, sensor_pose = random_case(rng)
        J_pose = numerical_jacobian(
            lambda x: sensors.landmark_from_observation(pose2.compose(x, sensor_pose), z), pose)
        J_z = numerical_jacobian(
            lambda x: sensors.landmark_from_observation(pose2.compose(pose, sensor_pose), x), z)
        _, P_m = landmark_to_world(pose, P_pose, z, R_one, sensor_pose)
        assert_matrices_close(P_m, J_pose @ P_pose @ J_pose.T + J_z @ R_one @ J_z.T, 1e-6)


def test_lever_arm_and_polar_covariance_match_sandwiches(rng):
    n = 200
    e = random_points(rng, n)
    P_pose = random_spd(rng, 3, n)
    J = np.zeros((n, 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2], J[:, 1, 2] = -e[:, 1], e[:, 0]
    expected = J @ P_pose @ np.swapaxes(J, -1, -2)
    assert_matrices_close(lever_arm_covariance(e, P_pose), expected, 1e-12)
    assert_matrices_close(lever_arm_covariance(e[3], P_pose[3]), expected[3], 1e-12)
    z = random_observations(rng, n)
    R_batch = random_spd(rng, 2, n)
    J_p_z = sensors.polar_to_cartesian_jacobian(z)
    expected = J_p_z @ R_batch @ np.swapaxes(J_p_z, -1, -2)
    assert_matrices_close(polar_covariance(z[:, 0], z[:, 1], R_batch), expected, 1e-12)
    assert_matrices_close(polar_covariance(z[5, 0], z[5, 1], R_batch[5]), expected[5], 1e-12)
    # One R for a batch of measurements.
    expected = J_p_z @ R_batch[0] @ np.swapaxes(J_p_z, -1, -2)
    assert_matrices_close(polar_covariance(z[:, 0], z[:, 1], R_batch[0]), expected, 1e-12)


def test_sensor_in_world(rng):
    pose, P_pose, _, _, sensor_pose = random_case(rng)
    s, P_s = sensor_in_world(pose, P_pose)
    np.testing.assert_array_equal(s, pose)
    np.testing.assert_array_equal(P_s, P_pose)
    s, P_s = sensor_in_world([1, 2, 0], np.eye(3, dtype=int))
    assert s.dtype == np.float64 and P_s.dtype == np.float64
    s, P_s = sensor_in_world(pose, P_pose, sensor_pose)
    np.testing.assert_array_equal(s, pose2.compose(pose, sensor_pose))
    J = numerical_jacobian(lambda x: pose2.compose(x, sensor_pose), pose, angle_rows=(2,))
    assert_matrices_close(P_s, J @ P_pose @ J.T, 1e-8)
    np.testing.assert_array_equal(P_s, P_s.T)


# --- landmark_to_world in blocks ----------------------------------------------------------

@pytest.mark.parametrize('n', [16384, 16385, 40000])
def test_landmark_to_world_large_batches(n, rng):
    pose, P_pose, z, R_batch, sensor_pose = random_case(rng, n)
    for sensor in (None, sensor_pose):
        m, P_m = landmark_to_world(pose, P_pose, z, R_batch, sensor)
        assert m.shape == (n, 2) and P_m.shape == (n, 2, 2)
        m_parts, P_m_pose, P_m_sensor = landmark_to_world_parts(
            pose, P_pose, z, R_batch, sensor)
        np.testing.assert_array_equal(m, m_parts)
        np.testing.assert_array_equal(P_m, P_m_pose + P_m_sensor)
        m_ref, P_pose_ref, P_sensor_ref = generic_landmark(pose, P_pose, z, R_batch, sensor)
        np.testing.assert_allclose(m, m_ref, rtol=0, atol=1e-11)
        assert_matrices_close(P_m, P_pose_ref + P_sensor_ref, 1e-12)


def test_landmark_to_world_large_batch_from_one_pose(rng):
    n = 40000
    pose, P_pose, _, R_one, sensor_pose = random_case(rng)
    z = random_observations(rng, n)
    for sensor in (None, sensor_pose):
        m, P_m = landmark_to_world(pose, P_pose, z, R_one, sensor)
        assert m.shape == (n, 2) and P_m.shape == (n, 2, 2)
        m_ref, P_pose_ref, P_sensor_ref = generic_landmark(pose, P_pose, z, R_one, sensor)
        np.testing.assert_allclose(m, m_ref, rtol=0, atol=1e-11)
        assert_matrices_close(P_m, P_pose_ref + P_sensor_ref, 1e-12)
        # Rows from every block equal single calls.
        for k in (0, 16383, 16384, 32767, 32768, n - 1):
            m_k, P_k = landmark_to_world(pose, P_pose, z[k], R_one, sensor)
            np.testing.assert_allclose(m[k], m_k, rtol=1e-15, atol=1e-14)
            assert_matrices_close(P_m[k], P_k, 1e-14)
    # A batch of sensor poses with everything else single.
    sensors_ = random_poses(rng, n, scale=0.5)
    m, P_m = landmark_to_world(pose, P_pose, z[0], R_one, sensors_)
    m_ref, P_pose_ref, P_sensor_ref = generic_landmark(pose, P_pose, z[0], R_one, sensors_)
    np.testing.assert_allclose(m, m_ref, rtol=0, atol=1e-11)
    assert_matrices_close(P_m, P_pose_ref + P_sensor_ref, 1e-12)


def test_landmark_to_world_batch_of_one_broadcasts_in_large_batches(rng):
    # A batch of one broadcasts against a batch of N as in numpy (and as
    # landmark_to_world_parts does), also past the first block of rows.
    n = 40000
    failures = []
    for which in ('pose', 'P_pose', 'z', 'R', 'sensor_pose'):
        args = dict(zip(['pose', 'P_pose', 'z', 'R', 'sensor_pose'], random_case(rng, n)))
        if which == 'z':
            args = {name: a[:1] for name, a in args.items()}
            args['z'] = random_observations(rng, n)
        else:
            args[which] = args[which][:1]
        m_parts, P_m_pose, P_m_sensor = landmark_to_world_parts(**args)
        try:
            m, P_m = landmark_to_world(**args)
        except ValueError as error:
            failures.append(f'{which} of shape {args[which].shape}: {error}')
            continue
        assert m.shape == (n, 2) and P_m.shape == (n, 2, 2)
        np.testing.assert_allclose(m, m_parts, rtol=1e-15, atol=1e-14)
        assert_matrices_close(P_m, P_m_pose + P_m_sensor, 1e-14)
    assert not failures, 'landmark_to_world failed with a batch of one for ' + '; '.join(
        failures)


# --- batches equal loops ------------------------------------------------------------------

def _outputs(result):
    return result if isinstance(result, tuple) else (result,)


def _landmark_args(rng, n):
    pose, P_pose, z, R_batch, sensor_pose = random_case(rng, n)
    return [pose, P_pose, z, R_batch, sensor_pose]


def _predict_args(rng, n):
    pose, P_pose, z, _, sensor_pose = random_case(rng, n)
    # Landmarks 0.5 to 20 m from the sensor.
    m = sensors.landmark_from_observation(pose2.compose(pose, sensor_pose), z)
    return [pose, P_pose, m, random_spd(rng, 2, n), sensor_pose]


def _relative_args(rng, n):
    return [random_poses(rng, n), random_spd(rng, 3, n), random_poses(rng, n),
            random_spd(rng, 3, n)]


def _nees_args(rng, n):
    return [random_points(rng, n), random_spd(rng, 2, n), random_points(rng, n)]


BATCH_CASES = {
    'landmark_to_world': (landmark_to_world, _landmark_args),
    'landmark_to_world_no_sensor': (
        lambda *a: landmark_to_world(*a[:4]), _landmark_args),
    'landmark_to_world_parts': (landmark_to_world_parts, _landmark_args),
    'landmark_to_world_parts_no_sensor': (
        lambda *a: landmark_to_world_parts(*a[:4]), _landmark_args),
    'relative_pose_between': (
        lambda *a: relative_pose(*a, method='between'), _relative_args),
    'relative_pose_composition': (
        lambda *a: relative_pose(*a, method='composition'), _relative_args),
    'predict_observation': (predict_observation, _predict_args),
    'predict_observation_no_sensor': (lambda *a: predict_observation(*a[:4]), _predict_args),
    'sensor_in_world': (lambda p, P, *a: sensor_in_world(p, P, a[-1]), _landmark_args),
    'sensor_in_world_no_sensor': (lambda p, P, *a: sensor_in_world(p, P), _landmark_args),
    'nees': (nees, _nees_args),
}


@pytest.mark.parametrize('name', sorted(BATCH_CASES))
def test_batch_equals_loop(name, rng):
    fn, draw = BATCH_CASES[name]
    n = 20
    args = draw(rng, n)
    batch = _outputs(fn(*args))
    singles = [_outputs(fn(*[a[k] for a in args])) for k in range(n)]
    for i, out in enumerate(batch):
        out = np.asarray(out)
        assert out.dtype == np.float64
        assert out.shape == (n,) + np.shape(singles[0][i])
        for k in range(n):
            np.testing.assert_allclose(out[k], singles[k][i], rtol=1e-14, atol=1e-14)
    for out, single in zip(_outputs(fn(*[a[:1] for a in args])), singles[0]):
        assert np.shape(out) == (1,) + np.shape(single)
        np.testing.assert_allclose(np.asarray(out)[0], single, rtol=1e-14, atol=1e-14)
    # Each argument on its own as a single item, broadcast against the others' batches.
    for single_index in range(len(args)):
        mixed = [a[0] if i == single_index else a for i, a in enumerate(args)]
        if single_index not in USED_ARGUMENTS.get(name, range(len(args))):
            continue
        if name == 'sensor_in_world_no_sensor':
            continue   # one batched argument: see the next test
        outs = _outputs(fn(*mixed))
        for k in (0, 7, n - 1):
            expected = _outputs(fn(*[a[0] if i == single_index else a[k]
                                     for i, a in enumerate(args)]))
            for out, single in zip(outs, expected):
                assert np.shape(out)[0] == n
                np.testing.assert_allclose(np.asarray(out)[k], single, rtol=1e-14, atol=1e-14)


USED_ARGUMENTS = {
    'landmark_to_world_no_sensor': (0, 1, 2, 3),
    'landmark_to_world_parts_no_sensor': (0, 1, 2, 3),
    'predict_observation_no_sensor': (0, 1, 2, 3),
    'sensor_in_world': (0, 1, 4),
    'sensor_in_world_no_sensor': (0, 1),
}


def test_one_batched_argument_makes_every_output_a_batch(rng):
    # Single items broadcast against batches: with one argument a batch of N (a mean or
    # a covariance) every output is a batch of N, so that m[k] goes with P[k]
    # (zip(m, P) pairs them). Checked for all functions at once, reporting every case.
    n = 6
    problems = []
    for name in sorted(BATCH_CASES):
        fn, draw = BATCH_CASES[name]
        args = draw(rng, n)
        for index in USED_ARGUMENTS.get(name, range(len(args))):
            mixed = [a if i == index else a[0] for i, a in enumerate(args)]
            outs = _outputs(fn(*mixed))
            shapes = [np.shape(out) for out in outs]
            if any(shape[:1] != (n,) for shape in shapes):
                problems.append(f'{name} with only argument {index} batched: output shapes '
                                f'{shapes}')
                continue
            for k in range(n):
                expected = _outputs(fn(*[a[k] if i == index else a[0]
                                         for i, a in enumerate(args)]))
                for out, single in zip(outs, expected):
                    np.testing.assert_allclose(out[k], single, rtol=1e-14, atol=1e-14)
    assert not problems, '\n'.join(problems)


# --- relative pose, prediction, NEES --------------------------------------------------------

def test_relative_pose_methods_agree(rng):
    n = 1000
    p1, P1, p2, P2 = _relative_args(rng, n)
    p1[:3, 2] = [np.pi - 1e-9, -np.pi, -np.pi + 1e-9]   # headings at the cut
    p_b, P_b = relative_pose(p1, P1, p2, P2, method='between')
    p_c, P_c = relative_pose(p1, P1, p2, P2, method='composition')
    np.testing.assert_allclose(p_b[:, :2], p_c[:, :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(pose2.wrap_angle(p_b[:, 2] - p_c[:, 2]), 0.0, atol=1e-14)
    assert_matrices_close(P_b, P_c, 1e-11)
    # And both equal the numerical-Jacobian propagation.
    for k in range(0, n, 50):
        J1 = numerical_jacobian(lambda x: pose2.between(x, p2[k]), p1[k], angle_rows=(2,))
        J2 = numerical_jacobian(lambda x: pose2.between(p1[k], x), p2[k], angle_rows=(2,))
        assert_matrices_close(P_b[k], J1 @ P1[k] @ J1.T + J2 @ P2[k] @ J2.T, 1e-7)


def test_relative_pose_rejects_unknown_method():
    with pytest.raises(ValueError, match="'between' or 'composition'"):
        relative_pose(P1_POSE, P1_COV, P2_POSE, P2_COV, method='compose')


def test_predict_observation_matches_generic_propagation(rng):
    pose, P_pose, m, P_m, sensor_pose = _predict_args(rng, 50)
    for sensor in (None, sensor_pose):
        z, P_z = predict_observation(pose, P_pose, m, P_m, sensor)
        s = pose if sensor is None else pose2.compose(pose, sensor)
        np.testing.assert_array_equal(z, sensors.observe(s, m))
        for k in range(0, 50, 5):
            J_pose = numerical_jacobian(
                lambda x: sensors.observe(x if sensor is None else pose2.compose(x, sensor[k]),
                                          m[k]), pose[k], angle_rows=(1,))
            J_m = numerical_jacobian(lambda x: sensors.observe(s[k], x), m[k], angle_rows=(1,))
            expected = J_pose @ P_pose[k] @ J_pose.T + J_m @ P_m[k] @ J_m.T
            assert_matrices_close(P_z[k], expected, 1e-6)


def test_nees_is_mahalanobis_of_truth(rng):
    m, P_m, truth = _nees_args(rng, 100)
    d = truth - m
    expected = np.einsum('ni,nij,nj->n', d, np.linalg.inv(P_m), d)
    np.testing.assert_allclose(nees(m, P_m, truth), expected, rtol=1e-9)
    np.testing.assert_array_equal(nees(m, P_m, truth), mahalanobis_sq(truth, m, P_m))
    assert nees(m[0], P_m[0], truth[0]) == pytest.approx(expected[0], rel=1e-9)
    assert nees([1.0, 2.0], np.diag([4.0, 1.0]), [3.0, 2.0]) == pytest.approx(1.0)


def test_nees_of_consistent_landmarks_is_chi_square(rng):
    # Landmarks placed from noisy poses and observations: mean NEES = 2 to first order
    # (small noise keeps the linearisation accurate).
    n = 100_000
    pose, z_true = P1_POSE, Z1
    P_pose, R_small = 1e-4 * P1_COV, 1e-4 * R
    truth = sensors.landmark_from_observation(pose, z_true)
    poses = pose + rng.standard_normal((n, 3)) @ np.linalg.cholesky(P_pose).T
    z = z_true + rng.standard_normal((n, 2)) @ np.linalg.cholesky(R_small).T
    # The robot believes it is at `poses` and measures z; the landmark is at truth.
    m, P_m = landmark_to_world(poses, P_pose, z, R_small)
    assert np.mean(nees(m, P_m, truth)) == pytest.approx(2.0, abs=0.05)


# --- invalid input ---------------------------------------------------------------------------

@pytest.mark.parametrize('fn', [landmark_to_world, landmark_to_world_parts],
                         ids=lambda fn: fn.__name__)
def test_landmark_to_world_rejects_zero_and_negative_range(fn):
    for r in (0.0, 1e-9, 0.5 * sensors.MIN_RANGE):
        with pytest.raises(ValueError, match='zero range'):
            fn(P1_POSE, P1_COV, [r, 0.2], R)
    with pytest.raises(ValueError, match='at least 1e-06 m'):
        fn(P1_POSE, P1_COV, [-4.0, 0.2], R)
    z = np.array([[4.0, 0.2], [3.0, 0.1], [-1.0, 0.0]])
    with pytest.raises(ValueError, match='first at index 2'):
        fn(P1_POSE, P1_COV, z, R)
    big = np.tile([4.0, 0.2], (40000, 1))
    big[30000, 0] = 0.0
    with pytest.raises(ValueError, match='first at index 30000'):
        fn(P1_POSE, P1_COV, big, R)


def test_predict_observation_rejects_landmark_at_the_sensor():
    with pytest.raises(ValueError, match='zero range'):
        predict_observation(P2_POSE, P2_COV, P2_POSE[:2], np.eye(2))
    with pytest.raises(ValueError, match='zero range'):
        predict_observation(P2_POSE, P2_COV, pose2.compose(P2_POSE, [1.0, 0.0, 0.0])[:2],
                            np.eye(2), sensor_pose=[1.0, 0.0, 0.0])


@pytest.mark.parametrize('fn', [landmark_to_world, landmark_to_world_parts],
                         ids=lambda fn: fn.__name__)
@pytest.mark.parametrize('bad', ['pose', 'P_pose', 'z', 'R', 'sensor_pose'])
def test_landmark_to_world_rejects_wrong_shapes(fn, bad):
    good = {'pose': P1_POSE, 'P_pose': P1_COV, 'z': Z1, 'R': R, 'sensor_pose': P2_POSE}
    wrong = {'pose': [1.0, 2.0], 'P_pose': np.eye(2), 'z': [4.0, 0.7, 0.0], 'R': np.eye(3),
             'sensor_pose': [0.0, 0.0]}
    with pytest.raises(ValueError, match=f'{bad} must have shape'):
        fn(**{**good, bad: wrong[bad]})
    with pytest.raises(ValueError, match='must have shape'):
        fn(**{**good, bad: np.zeros((2, 2, 2, 2))})


def test_batch_size_mismatch_raises(rng):
    pose, P_pose, z, R_batch, sensor_pose = random_case(rng, 5)
    with pytest.raises(ValueError):
        landmark_to_world(pose, P_pose, z[:4], R_batch)
    with pytest.raises(ValueError):
        relative_pose(pose, P_pose, pose[:3], P_pose[:3])


@pytest.mark.parametrize('fn, args', [
    (relative_pose, (P1_POSE, np.eye(2), P2_POSE, P2_COV)),
    (relative_pose, (P1_POSE, P1_COV, P2_POSE, np.eye(4))),
    (relative_pose, (P1_POSE[:2], P1_COV, P2_POSE, P2_COV)),
    (predict_observation, (P2_POSE, P2_COV, M1, np.eye(3))),
    (predict_observation, (P2_POSE, np.eye(2), M1, P_M1)),
    (predict_observation, (P2_POSE, P2_COV, [1.0, 2.0, 3.0], P_M1)),
    (sensor_in_world, (P1_POSE, np.eye(2))),
    (sensor_in_world, ([1.0, 2.0], P1_COV)),
    (sensor_in_world, (P1_POSE, P1_COV, [1.0, 2.0])),
])
def test_other_functions_reject_wrong_shapes(fn, args):
    with pytest.raises(ValueError, match='must have shape'):
        fn(*args)
