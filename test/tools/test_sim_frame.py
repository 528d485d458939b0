"""
The simulator's shared map frame error (``sim.frame_error``): declared covariance, shared.

The statistics tests draw thousands of frame errors (one per seed) and compare them with
the declared covariance within bounds several standard errors wide (seeded: they are
deterministic).
"""

from dataclasses import replace
import math

from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.sim import frame_error
from landmark_ros.sim.simulation import _FRAME, rng, SimConfig, Simulation
import numpy as np

FRAME = {'frame_xy_stddev': 0.05, 'frame_yaw_stddev': 0.01}
"""The ``shared_frame`` scenario's frame error."""

DRAWS = 4000


def sample_covariance_within(errors, P, k=5.0):
    """Assert the sample covariance of zero-mean errors matches ``P`` entry by entry."""
    n = len(errors)
    S = errors.T @ errors / n
    # Wishart: var(S_ij) = (P_ii P_jj + P_ij^2) / n for a known zero mean.
    standard_error = np.sqrt((np.outer(np.diag(P), np.diag(P)) + P ** 2) / n)
    assert np.all(np.abs(S - P) <= k * standard_error), (S, P, standard_error)
    # The bounds are tight enough to fail: the covariance without the cross terms does.
    return S


def test_off_by_default_and_the_white_errors_are_unchanged():
    plain, framed = Simulation(SimConfig(seed=5)), Simulation(SimConfig(seed=5, **FRAME))
    assert plain.frame_error is None and framed.frame_error is not None
    _, true, pose, P_pose = plain.reported_pose(0, 7)
    np.testing.assert_array_equal(P_pose, SimConfig().P_pose)
    np.testing.assert_allclose(pose - true, plain.pose_error(0, plain.pose_stamp_ns(7)),
                               atol=1e-15)


def test_frame_errors_at_a_pose_have_the_declared_covariance():
    pose = np.array([8.0, -6.0, 1.0])         # far from the origin: large cross terms
    errors = np.empty((DRAWS, 3))
    for seed in range(DRAWS):
        draw = frame_error.draw(rng(seed, _FRAME), 0.05, 0.01)
        errors[seed] = draw.apply(pose) - pose
    P = frame_error.frame_covariance(pose, np.diag([0.05 ** 2, 0.05 ** 2, 0.01 ** 2]))
    assert abs(P[0, 2]) > 0.0 and abs(P[0, 1]) > 0.0
    S = sample_covariance_within(errors, P)
    # Without the cross terms the same samples fail the same bound.
    diagonal = np.diag(np.diag(P))
    standard_error = np.sqrt((np.outer(np.diag(P), np.diag(P)) + diagonal ** 2) / DRAWS)
    assert not np.all(np.abs(S - diagonal) <= 5.0 * standard_error)
    assert np.all(np.abs(errors.mean(axis=0)) <= 5.0 * np.sqrt(np.diag(P) / DRAWS))


def test_reported_poses_whiten_to_unit_covariance_with_and_without_a_white_part():
    # One run per seed: the reported covariance (at the reported pose) whitens the
    # error of every robot to N(0, I), frame alone and frame plus white error.
    for white in ({'pose_xy_stddev': 0.0, 'pose_yaw_stddev': 0.0}, {}):
        config = SimConfig(landmarks=1, **FRAME, **white)
        whitened = []
        for seed in range(DRAWS // 4):
            sim = Simulation(replace(config, seed=seed))
            robot, k = seed % config.robots, 2 * (seed % 50)
            _, true, pose, P_pose = sim.reported_pose(robot, k)
            error = pose - true
            error[2] = math.remainder(error[2], 2.0 * math.pi)
            whitened.append(np.linalg.solve(np.linalg.cholesky(P_pose), error))
        sample_covariance_within(np.array(whitened), np.eye(3))


def test_every_robot_places_a_landmark_with_the_same_error_and_declared_dependent_part():
    sim = Simulation(SimConfig(seed=3, robots=4, pose_xy_stddev=0.0, pose_yaw_stddev=0.0,
                               **FRAME))
    error = sim.frame_error
    landmark = sim.world.positions[0]
    expected = error.apply(np.array([*landmark, 0.0]))[:2]
    # The observer evaluates its Jacobians at the placed landmark: exactly, not to
    # first order, [I, J (l - p)] A(p) = [I, J l] there.
    Jl = frame_error.J @ expected
    P_expected = 0.05 ** 2 * np.eye(2) + 0.01 ** 2 * np.outer(Jl, Jl)
    for robot in range(sim.robots):
        for k in (0, 17, 150):
            _, true, pose, P_pose = sim.reported_pose(robot, k)
            # First order: (tau + eps J p, eps).
            first_order = np.array([*(error.tau + error.eps * frame_error.J @ true[:2]),
                                    error.eps])
            np.testing.assert_allclose(pose - true, first_order,
                                       atol=error.eps ** 2 * np.linalg.norm(true[:2]) + 1e-12)
            d = landmark - true[:2]
            z = np.array([np.hypot(*d), np.arctan2(d[1], d[0]) - true[2]])
            m, _, P_dep = landmark_to_world_dependent(pose, P_pose, z, np.zeros((2, 2)))
            np.testing.assert_allclose(m, expected, atol=1e-12)     # one shared error
            np.testing.assert_allclose(P_dep, P_expected, rtol=1e-9)  # Cov(tau + eps J l)
