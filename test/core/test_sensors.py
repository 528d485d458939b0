"""Tests of landmark_ros.core.sensors: range-bearing models, inverses and Jacobians."""

from conftest import assert_jacobians, random_observations, random_poses
from hypothesis import given, settings
from hypothesis import strategies as st
from landmark_ros.core import sensors
from landmark_ros.core.pose2 import wrap_angle
import numpy as np
import pytest

N_CASES = 200
PI = np.pi
SETTINGS = settings(max_examples=150, deadline=None, derandomize=True)

coordinates = st.floats(-100.0, 100.0, allow_nan=False, allow_infinity=False)
angles = st.floats(-3.0 * PI, 3.0 * PI, allow_nan=False, allow_infinity=False)
ranges = st.floats(1e-3, 100.0, allow_nan=False, allow_infinity=False)
poses = st.tuples(coordinates, coordinates, angles).map(np.array)
observations = st.tuples(ranges, angles).map(np.array)


def _outputs(result):
    return result if isinstance(result, tuple) else (result,)


def landmark_near(rng, pose, r_min=0.5, r_max=20.0):
    """Return a landmark at a random range in [r_min, r_max) from the pose."""
    z = random_observations(rng, r_min=r_min, r_max=r_max)
    return pose[:2] + z[0] * np.array([np.cos(z[1]), np.sin(z[1])])


def assert_observations_close(a, b, atol=1e-10):
    """Assert equal ranges and equal bearings modulo 2 pi."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    np.testing.assert_allclose(a[..., 0], b[..., 0], rtol=0, atol=atol)
    np.testing.assert_allclose(wrap_angle(a[..., 1] - b[..., 1]), 0.0, rtol=0, atol=atol)


# --- known values ------------------------------------------------------------------------

def test_observe_known_values():
    np.testing.assert_allclose(sensors.observe([0.0, 0.0, 0.0], [3.0, 4.0]),
                               [5.0, np.arctan2(4.0, 3.0)], atol=1e-15)
    np.testing.assert_allclose(sensors.observe([1.0, 1.0, PI / 2], [1.0, 3.0]), [2.0, 0.0],
                               atol=1e-15)
    # Behind and to the left of a robot facing +x: bearing +3/4 pi.
    np.testing.assert_allclose(sensors.observe([1.0, 1.0, 0.0], [0.0, 2.0]),
                               [np.sqrt(2.0), 0.75 * PI], atol=1e-15)
    # Bearing exactly behind is -pi, not +pi.
    assert sensors.observe([0.0, 0.0, PI / 2], [0.0, -2.0])[1] == pytest.approx(-PI, abs=1e-15)
    assert sensors.observe_range([0.0, 0.0, 1.0], [3.0, 4.0]) == pytest.approx([5.0])
    np.testing.assert_allclose(sensors.observe_bearing([0.0, 0.0, 1.0], [3.0, 4.0]),
                               [np.arctan2(4.0, 3.0) - 1.0], atol=1e-15)


def test_landmark_from_observation_known_value():
    np.testing.assert_allclose(
        sensors.landmark_from_observation([1.0, 2.0, PI / 2], [3.0, PI / 2]), [-2.0, 2.0],
        atol=1e-15)


def test_polar_cartesian_known_values():
    np.testing.assert_allclose(sensors.polar_to_cartesian([2.0, PI / 2]), [0.0, 2.0],
                               atol=1e-15)
    np.testing.assert_allclose(sensors.cartesian_to_polar([-1.0, 0.0]), [1.0, -PI], atol=0)
    np.testing.assert_allclose(sensors.cartesian_to_polar([0.0, -3.0]), [3.0, -PI / 2],
                               atol=1e-15)


# --- Jacobians against central differences -----------------------------------------------

def _pose_landmark(rng):
    pose = random_poses(rng)
    return pose, landmark_near(rng, pose)


JACOBIAN_CASES = {
    'observe': (sensors.observe, sensors.observe_jacobians, _pose_landmark, (1,)),
    'observe_range': (sensors.observe_range, sensors.observe_range_jacobians, _pose_landmark,
                      ()),
    'observe_bearing': (sensors.observe_bearing, sensors.observe_bearing_jacobians,
                        _pose_landmark, (0,)),
    'landmark_from_observation': (
        sensors.landmark_from_observation, sensors.landmark_from_observation_jacobians,
        lambda rng: (random_poses(rng), random_observations(rng)), ()),
    'polar_to_cartesian': (sensors.polar_to_cartesian, sensors.polar_to_cartesian_jacobian,
                           lambda rng: (random_observations(rng),), ()),
    'cartesian_to_polar': (
        sensors.cartesian_to_polar, sensors.cartesian_to_polar_jacobian,
        lambda rng: (sensors.polar_to_cartesian(random_observations(rng)),), (1,)),
}


@pytest.mark.parametrize('name', sorted(JACOBIAN_CASES))
def test_jacobians_match_numerical(name, rng):
    value_fn, jacobian_fn, draw, angle_rows = JACOBIAN_CASES[name]
    cases = [draw(rng) for _ in range(N_CASES)]
    for args in cases:
        assert_jacobians(value_fn, jacobian_fn, args, angle_rows)
    batch = [np.stack(column) for column in zip(*cases)]
    stacked = _outputs(jacobian_fn(*batch))
    looped = [_outputs(jacobian_fn(*args)) for args in cases]
    for i, J in enumerate(stacked):
        assert J.shape == (N_CASES,) + looped[0][i].shape
        np.testing.assert_allclose(J, np.stack([j[i] for j in looped]), rtol=1e-15, atol=1e-15)


def test_range_and_bearing_jacobians_are_rows_of_observe():
    pose, m = np.array([1.0, -2.0, 0.4]), np.array([-3.0, 1.5])
    J_pose, J_m = sensors.observe_jacobians(pose, m)
    for fn, row in ((sensors.observe_range_jacobians, 0),
                    (sensors.observe_bearing_jacobians, 1)):
        J_r_pose, J_r_m = fn(pose, m)
        assert J_r_pose.shape == (1, 3) and J_r_m.shape == (1, 2)
        np.testing.assert_array_equal(J_r_pose[0], J_pose[row])
        np.testing.assert_array_equal(J_r_m[0], J_m[row])


@pytest.mark.parametrize('theta', [0.0, PI - 1e-9, -PI + 1e-9, PI, -PI, PI / 2])
@pytest.mark.parametrize('side', [1e-9, -1e-9, 0.0, 1e-3, -1e-3])
def test_jacobians_where_the_bearing_crosses_pi(theta, side):
    # A landmark (almost) straight behind the sensor: the bearing is at the +-pi cut.
    pose = np.array([2.0, -1.0, theta])
    behind = np.array([-np.cos(theta), -np.sin(theta)])
    left = np.array([-np.sin(theta), np.cos(theta)])
    m = pose[:2] + 4.0 * behind + side * left
    z = sensors.observe(pose, m)
    assert abs(abs(z[1]) - PI) < 1e-3 + 1e-8
    assert_jacobians(sensors.observe, sensors.observe_jacobians, (pose, m), angle_rows=(1,))
    assert_jacobians(sensors.observe_bearing, sensors.observe_bearing_jacobians, (pose, m),
                     angle_rows=(0,))
    z = np.array([4.0, PI - 1e-9 if side >= 0 else -PI + 1e-9])
    assert_jacobians(sensors.landmark_from_observation,
                     sensors.landmark_from_observation_jacobians, (pose, z))
    assert_jacobians(sensors.polar_to_cartesian, sensors.polar_to_cartesian_jacobian, (z,))
    p = 4.0 * np.array([-1.0, side])
    assert_jacobians(sensors.cartesian_to_polar, sensors.cartesian_to_polar_jacobian, (p,),
                     angle_rows=(1,))


# --- round trips --------------------------------------------------------------------------

@SETTINGS
@given(poses, observations)
def test_observe_inverts_landmark_from_observation(pose, z):
    m = sensors.landmark_from_observation(pose, z)
    scale = 1.0 + np.abs(pose[:2]).max()
    assert_observations_close(sensors.observe(pose, m), z, atol=1e-12 * scale / z[0] + 1e-12)
    np.testing.assert_allclose(sensors.observe(pose, m)[0], z[0], rtol=0, atol=1e-12 * scale)
    assert -PI <= sensors.observe(pose, m)[1] < PI


@SETTINGS
@given(poses, st.tuples(coordinates, coordinates).map(np.array))
def test_landmark_from_observation_inverts_observe(pose, m):
    if np.hypot(*(m - pose[:2])) < 1e-3:
        return
    np.testing.assert_allclose(sensors.landmark_from_observation(pose, sensors.observe(pose, m)),
                               m, rtol=0, atol=1e-12)


@SETTINGS
@given(observations)
def test_polar_cartesian_round_trip(z):
    back = sensors.cartesian_to_polar(sensors.polar_to_cartesian(z))
    assert_observations_close(back, z, atol=1e-12)
    assert -PI <= back[1] < PI
    p = sensors.polar_to_cartesian(z)
    np.testing.assert_allclose(sensors.polar_to_cartesian(sensors.cartesian_to_polar(p)), p,
                               rtol=0, atol=1e-13)


def test_round_trips_in_batches(rng):
    poses_ = random_poses(rng, 1000)
    z = random_observations(rng, 1000, r_min=1e-3, r_max=50.0)
    z[:, 1] *= 2.0   # bearings outside [-pi, pi) too
    back = sensors.observe(poses_, sensors.landmark_from_observation(poses_, z))
    assert_observations_close(back, z, atol=1e-9)
    assert np.all((back[:, 1] >= -PI) & (back[:, 1] < PI))
    assert_observations_close(sensors.cartesian_to_polar(sensors.polar_to_cartesian(z)), z)


# --- batches ------------------------------------------------------------------------------

POSE_LANDMARK = [sensors.observe, sensors.observe_jacobians, sensors.observe_range,
                 sensors.observe_range_jacobians, sensors.observe_bearing,
                 sensors.observe_bearing_jacobians]
POSE_OBSERVATION = [sensors.landmark_from_observation,
                    sensors.landmark_from_observation_jacobians]
ONE_ARGUMENT = [sensors.polar_to_cartesian, sensors.polar_to_cartesian_jacobian,
                sensors.cartesian_to_polar, sensors.cartesian_to_polar_jacobian]
ALL_FUNCTIONS = POSE_LANDMARK + POSE_OBSERVATION + ONE_ARGUMENT


def _batch_args(fn, rng, n):
    poses_ = random_poses(rng, n)
    z = random_observations(rng, n)
    if fn in POSE_LANDMARK:
        # Landmarks at least 0.5 m from every pose, for the broadcast checks too.
        return [poses_, poses_[0, :2] + sensors.polar_to_cartesian(z)]
    if fn in POSE_OBSERVATION:
        return [poses_, z]
    return [z] if fn in (sensors.polar_to_cartesian, sensors.polar_to_cartesian_jacobian) else [
        sensors.polar_to_cartesian(z)]


@pytest.mark.parametrize('fn', ALL_FUNCTIONS, ids=lambda fn: fn.__name__)
def test_batch_equals_loop(fn, rng):
    n = 20
    args = _batch_args(fn, rng, n)
    batch = _outputs(fn(*args))
    single0 = _outputs(fn(*[a[0] for a in args]))
    for k in range(n):
        for out, single in zip(batch, _outputs(fn(*[a[k] for a in args]))):
            assert out.dtype == np.float64 and out.shape == (n,) + single.shape
            np.testing.assert_allclose(out[k], single, rtol=1e-15, atol=1e-15)
    for out, single in zip(_outputs(fn(*[a[:1] for a in args])), single0):
        assert out.shape == (1,) + single.shape
        np.testing.assert_array_equal(out[0], single)
    if len(args) == 2:
        for single_index in (0, 1):
            mixed = [a[0] if i == single_index else a for i, a in enumerate(args)]
            for k, row in enumerate(zip(*_outputs(fn(*mixed)))):
                args_k = [a[0] if i == single_index else a[k] for i, a in enumerate(args)]
                for out, single in zip(row, _outputs(fn(*args_k))):
                    np.testing.assert_allclose(out, single, rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize('fn', ALL_FUNCTIONS, ids=lambda fn: fn.__name__)
def test_integer_inputs_give_float64(fn):
    if fn in POSE_LANDMARK:
        args = [[0, 0, 1], [3, 4]]
    elif fn in POSE_OBSERVATION:
        args = [[0, 0, 1], [3, 1]]
    else:
        args = [[3, 1]]
    for out in _outputs(fn(*args)):
        assert out.dtype == np.float64


def test_range_and_bearing_only_shapes():
    pose, m = np.array([0.0, 0.0, 0.5]), np.array([[3.0, 4.0], [-1.0, 2.0]])
    for fn, column in ((sensors.observe_range, 0), (sensors.observe_bearing, 1)):
        assert fn(pose, m[0]).shape == (1,)
        assert fn(pose, m).shape == (2, 1)
        assert fn(pose, m[:1]).shape == (1, 1)
        np.testing.assert_array_equal(fn(pose, m)[:, 0], sensors.observe(pose, m)[:, column])


# --- invalid input ------------------------------------------------------------------------

RANGE_CALLS = {
    'observe': lambda r: sensors.observe([1.0, 2.0, 0.3], [1.0 + r, 2.0]),
    'observe_jacobians': lambda r: sensors.observe_jacobians([1.0, 2.0, 0.3], [1.0, 2.0 + r]),
    'observe_range': lambda r: sensors.observe_range([1.0, 2.0, 0.3], [1.0 + r, 2.0]),
    'observe_range_jacobians': lambda r: sensors.observe_range_jacobians(
        [1.0, 2.0, 0.3], [1.0 + r, 2.0]),
    'observe_bearing': lambda r: sensors.observe_bearing([1.0, 2.0, 0.3], [1.0, 2.0 - r]),
    'observe_bearing_jacobians': lambda r: sensors.observe_bearing_jacobians(
        [1.0, 2.0, 0.3], [1.0, 2.0 - r]),
    'landmark_from_observation': lambda r: sensors.landmark_from_observation(
        [1.0, 2.0, 0.3], [r, 0.5]),
    'landmark_from_observation_jacobians': lambda r: (
        sensors.landmark_from_observation_jacobians([1.0, 2.0, 0.3], [r, 0.5])),
    'polar_to_cartesian': lambda r: sensors.polar_to_cartesian([r, 0.5]),
    'polar_to_cartesian_jacobian': lambda r: sensors.polar_to_cartesian_jacobian([r, 0.5]),
    'cartesian_to_polar': lambda r: sensors.cartesian_to_polar([r, 0.0]),
    'cartesian_to_polar_jacobian': lambda r: sensors.cartesian_to_polar_jacobian([0.0, r]),
}
NEGATIVE_RANGE_OK = {'observe', 'observe_jacobians', 'observe_range', 'observe_range_jacobians',
                     'observe_bearing', 'observe_bearing_jacobians', 'cartesian_to_polar',
                     'cartesian_to_polar_jacobian'}


@pytest.mark.parametrize('name', sorted(RANGE_CALLS))
def test_zero_range_raises(name):
    call = RANGE_CALLS[name]
    for r in (0.0, 1e-12, 0.5 * sensors.MIN_RANGE):
        with pytest.raises(ValueError, match='zero range'):
            call(r)
    if name not in NEGATIVE_RANGE_OK:
        # A negative range is an invalid observation; for geometric inputs -r is just
        # a point on the other side and is valid.
        with pytest.raises(ValueError, match=r'at least 1e-06 m'):
            call(-1.0)
    for r in (2.0 * sensors.MIN_RANGE, 1.0):   # just above the limit is accepted
        assert all(np.all(np.isfinite(out)) for out in _outputs(call(r)))


def test_zero_range_in_a_batch_names_the_index():
    z = np.array([[1.0, 0.0], [2.0, 0.1], [0.0, 0.3], [-1.0, 0.2]])
    with pytest.raises(ValueError, match='2 value.* first at index 2'):
        sensors.landmark_from_observation([0.0, 0.0, 0.0], z)
    m = np.array([[1.0, 0.0], [2.0, 0.1], [0.0, 0.0]])
    with pytest.raises(ValueError, match='index 2'):
        sensors.observe(np.zeros(3), m)


@pytest.mark.parametrize('fn', POSE_LANDMARK + POSE_OBSERVATION, ids=lambda fn: fn.__name__)
def test_wrong_shapes_raise(fn):
    for pose, second in (([0.0, 0.0], [3.0, 4.0]), ([0.0, 0.0, 0.0, 0.0], [3.0, 4.0]),
                         ([0.0, 0.0, 0.0], [3.0, 4.0, 5.0]), ([0.0, 0.0, 0.0], [3.0]),
                         ([0.0, 0.0, 0.0], np.ones((2, 2, 2))),
                         (np.zeros((1, 1, 3)), [3.0, 4.0])):
        with pytest.raises(ValueError, match='must have shape'):
            fn(pose, second)
    with pytest.raises(ValueError):
        fn(np.zeros((3, 3)), np.ones((4, 2)) + 5.0)


@pytest.mark.parametrize('fn', ONE_ARGUMENT, ids=lambda fn: fn.__name__)
def test_wrong_shapes_raise_one_argument(fn):
    for bad in ([1.0], [1.0, 2.0, 3.0], np.ones((2, 2, 2)), 1.0):
        with pytest.raises(ValueError, match='must have shape'):
            fn(bad)


def test_range_noise_variance_adds_three_stddevs_in_quadrature():
    a, k, c = 0.02, 0.005, 0.002
    r = np.array([0.0, 0.5, 4.0, 10.0])
    var = sensors.range_noise_variance(r, a ** 2, k ** 2, c ** 2)
    np.testing.assert_allclose(var, a ** 2 + (k * r) ** 2 + (c * r ** 2) ** 2,
                               rtol=1e-15, atol=0)
    assert var[2] == pytest.approx(0.001824, rel=1e-12)
    assert sensors.range_noise_variance(7.0, a ** 2) == a ** 2
    assert var.shape == r.shape
