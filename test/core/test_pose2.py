"""Tests of landmark_ros.core.pose2: SE(2) composition, inverse, between, points."""

from conftest import assert_jacobians, numerical_jacobian, random_points, random_poses
from hypothesis import given, settings
from hypothesis import strategies as st
from landmark_ros.core import pose2
from landmark_ros.core.pose2 import wrap_angle
import numpy as np
import pytest

N_CASES = 200
PI = np.pi
SETTINGS = settings(max_examples=150, deadline=None, derandomize=True)

coordinates = st.floats(-100.0, 100.0, allow_nan=False, allow_infinity=False)
angles = st.floats(-3.0 * PI, 3.0 * PI, allow_nan=False, allow_infinity=False)
poses = st.tuples(coordinates, coordinates, angles).map(np.array)
points = st.tuples(coordinates, coordinates).map(np.array)


def assert_poses_close(a, b, atol=1e-9):
    """Assert equal positions and equal headings modulo 2 pi."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    np.testing.assert_allclose(a[..., :2], b[..., :2], rtol=0, atol=atol)
    np.testing.assert_allclose(wrap_angle(a[..., 2] - b[..., 2]), 0.0, rtol=0, atol=atol)


def _outputs(result):
    return result if isinstance(result, tuple) else (result,)


# --- the numerical Jacobian helper itself ---------------------------------------------

def test_numerical_jacobian_of_linear_map():
    A = np.array([[1.0, -2.0, 0.5], [3.0, 0.25, -4.0]])
    np.testing.assert_allclose(
        numerical_jacobian(lambda x: A @ x, np.array([0.3, -1.0, 2.0])), A, atol=1e-9)


def test_numerical_jacobian_wraps_angle_rows_only_when_asked():
    # theta + 1e-9 - pi jumps from ~-pi to ~+pi across x = pi - 1e-9.
    def f(x):
        return np.array([wrap_angle(x[0]), 2.0 * x[0]])

    x = np.array([PI - 1e-9])
    np.testing.assert_allclose(numerical_jacobian(f, x, angle_rows=(0,)), [[1.0], [2.0]],
                               atol=1e-6)
    assert abs(numerical_jacobian(f, x)[0, 0]) > 1e5


# --- wrap_angle -------------------------------------------------------------------------

@pytest.mark.parametrize('angle, expected', [
    (0.0, 0.0),
    (PI, -PI),
    (-PI, -PI),
    (3.0 * PI, -PI),
    (-3.0 * PI, -PI),
    (2.0 * PI, 0.0),
    (-2.0 * PI, 0.0),
    (-1e-17, 0.0),
    (1e-17, 1e-17),
    (0.5, 0.5),
    (PI / 2 + 4.0 * PI, PI / 2),
    (-PI / 2 - 10.0 * PI, -PI / 2),
])
def test_wrap_angle_values(angle, expected):
    for value in (angle, np.array(angle), np.array([angle])):
        wrapped = wrap_angle(value)
        assert np.all(-PI <= wrapped) and np.all(wrapped < PI)
        np.testing.assert_allclose(wrapped, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize('angle', [
    PI, -PI, 3.0 * PI, -3.0 * PI, -1e-17, 1e-300, -1e-300, -PI - 1e-16, np.nextafter(PI, 0.0),
    np.nextafter(-PI, -4.0), 1e6 * PI, -1e6 * PI, 2.0 ** 40, -(2.0 ** 40), 1e15, 7.0 * PI,
])
def test_wrap_angle_in_half_open_range(angle):
    # Plain floats, 0-d and 1-d arrays (the implementation may treat them apart).
    for value in (float(angle), np.array(angle), np.array([angle, angle])):
        wrapped = wrap_angle(value)
        assert np.shape(wrapped) == np.shape(value)
        assert np.all(-PI <= wrapped) and np.all(wrapped < PI)
        # The same direction (the rounding of large inputs aside).
        np.testing.assert_allclose(np.cos(wrapped), np.cos(angle), rtol=0,
                                   atol=1e-9 * max(1.0, abs(angle)))
        np.testing.assert_allclose(np.sin(wrapped), np.sin(angle), rtol=0,
                                   atol=1e-9 * max(1.0, abs(angle)))


def test_wrap_angle_arrays_keep_shape_and_range(rng):
    angles = np.concatenate([rng.uniform(-1e4, 1e4, 1000), PI * np.arange(-50, 51),
                             [-1e-17, 1e-17, -0.0, PI, -PI, 3.0 * PI, -3.0 * PI]])
    wrapped = wrap_angle(angles)
    assert wrapped.shape == angles.shape and wrapped.dtype == np.float64
    assert np.all((wrapped >= -PI) & (wrapped < PI))
    np.testing.assert_allclose(np.cos(wrapped), np.cos(angles), atol=1e-9)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(angles), atol=1e-9)
    np.testing.assert_array_equal(wrap_angle(wrapped), wrapped)
    assert wrap_angle(angles.reshape(-1, 2, 1)).shape == (angles.size // 2, 2, 1)
    assert np.ndim(wrap_angle(1.0)) == 0


@SETTINGS
@given(angles)
def test_wrap_angle_property(angle):
    wrapped = wrap_angle(angle)
    assert -PI <= wrapped < PI
    turns = (angle - wrapped) / (2.0 * PI)
    assert turns == pytest.approx(round(turns), abs=1e-12)


# --- known values -------------------------------------------------------------------------

def test_compose_known_value():
    np.testing.assert_allclose(pose2.compose([1.0, 2.0, PI / 2], [3.0, 1.0, PI / 4]),
                               [0.0, 5.0, 3.0 * PI / 4], atol=1e-15)
    c = pose2.compose([0.0, 0.0, 3.0], [0.0, 0.0, 0.5])
    assert c[2] == pytest.approx(3.5 - 2.0 * PI, abs=1e-15)


def test_inverse_known_value():
    np.testing.assert_allclose(pose2.inverse([1.0, 2.0, PI / 2]), [-2.0, 1.0, -PI / 2],
                               atol=1e-15)
    assert pose2.inverse([0.0, 0.0, -PI])[2] == -PI
    assert pose2.inverse([0.0, 0.0, PI])[2] == -PI


def test_between_known_value():
    np.testing.assert_allclose(pose2.between([1.0, 2.0, PI / 2], [1.0, 5.0, PI]),
                               [3.0, 0.0, PI / 2], atol=1e-15)
    # Headings on both sides of the cut.
    b = pose2.between([0.0, 0.0, PI - 0.1], [0.0, 0.0, -PI + 0.1])
    assert b[2] == pytest.approx(0.2, abs=1e-14)


def test_transform_point_known_value():
    np.testing.assert_allclose(pose2.transform_point([1.0, 2.0, PI / 2], [3.0, 1.0]),
                               [0.0, 5.0], atol=1e-15)


# --- Jacobians against central differences -----------------------------------------------

def _pose_pair(rng):
    return random_poses(rng), random_poses(rng)


JACOBIAN_CASES = {
    'compose': (pose2.compose, pose2.compose_jacobians, _pose_pair, (2,)),
    'inverse': (pose2.inverse, pose2.inverse_jacobian, lambda rng: (random_poses(rng),), (2,)),
    'between': (pose2.between, pose2.between_jacobians, _pose_pair, (2,)),
    'transform_point': (pose2.transform_point, pose2.transform_point_jacobians,
                        lambda rng: (random_poses(rng), random_points(rng)), ()),
}


@pytest.mark.parametrize('name', sorted(JACOBIAN_CASES))
def test_jacobians_match_numerical(name, rng):
    value_fn, jacobian_fn, draw, angle_rows = JACOBIAN_CASES[name]
    cases = [draw(rng) for _ in range(N_CASES)]
    for args in cases:
        assert_jacobians(value_fn, jacobian_fn, args, angle_rows)
    # The same cases as one batch give the same Jacobians, stacked.
    batch = [np.stack(column) for column in zip(*cases)]
    stacked = _outputs(jacobian_fn(*batch))
    looped = [_outputs(jacobian_fn(*args)) for args in cases]
    for i, J in enumerate(stacked):
        np.testing.assert_allclose(J, np.stack([j[i] for j in looped]), rtol=1e-15, atol=1e-15)


EDGE_THETAS = [PI - 1e-9, -PI + 1e-9, PI, -PI, 1e-9, -1e-9, 3.0, -3.0]


@pytest.mark.parametrize('theta_a', EDGE_THETAS)
@pytest.mark.parametrize('theta_b', EDGE_THETAS + [0.2, -0.2, 1e-9 - PI])
def test_jacobians_at_the_angle_cut(theta_a, theta_b):
    # compose and between results land on or cross +-pi for many of these pairs.
    a = np.array([1.5, -0.7, theta_a])
    b = np.array([-2.0, 3.1, theta_b])
    for value_fn, jacobian_fn in ((pose2.compose, pose2.compose_jacobians),
                                  (pose2.between, pose2.between_jacobians)):
        assert_jacobians(value_fn, jacobian_fn, (a, b), angle_rows=(2,))
    assert_jacobians(pose2.inverse, pose2.inverse_jacobian, (a,), angle_rows=(2,))
    assert_jacobians(pose2.transform_point, pose2.transform_point_jacobians, (a, b[:2]))


def test_compose_crossing_the_cut_is_wrapped():
    c = pose2.compose([0.0, 0.0, PI - 1e-9], [1.0, 0.0, 2e-9])
    assert c[2] == pytest.approx(-PI + 1e-9, abs=1e-15)
    c = pose2.compose([0.0, 0.0, -PI + 1e-9], [1.0, 0.0, -2e-9])
    assert c[2] == pytest.approx(PI - 1e-9, abs=1e-15)


# --- batches ------------------------------------------------------------------------------

TWO_POSE_FUNCTIONS = [pose2.compose, pose2.compose_jacobians, pose2.between,
                      pose2.between_jacobians]
ONE_POSE_FUNCTIONS = [pose2.inverse, pose2.inverse_jacobian]
POINT_FUNCTIONS = [pose2.transform_point, pose2.transform_point_jacobians]


def _check_batch(fn, batch_args, single_index=None):
    """Compare ``fn`` on a batch with a loop of single calls; optionally one arg single."""
    n = len(batch_args[0]) if single_index != 0 else len(batch_args[1])
    batch = _outputs(fn(*batch_args))
    for k in range(n):
        args = [a if i == single_index else a[k] for i, a in enumerate(batch_args)]
        single = _outputs(fn(*args))
        for out_batch, out_single in zip(batch, single):
            assert out_batch.dtype == np.float64 and out_single.dtype == np.float64
            np.testing.assert_allclose(out_batch[k], out_single, rtol=1e-15, atol=1e-15)
    return batch


@pytest.mark.parametrize('fn', TWO_POSE_FUNCTIONS + ONE_POSE_FUNCTIONS + POINT_FUNCTIONS,
                         ids=lambda fn: fn.__name__)
def test_batch_equals_loop(fn, rng):
    n = 25
    if fn in ONE_POSE_FUNCTIONS:
        args = [random_poses(rng, n)]
    elif fn in POINT_FUNCTIONS:
        args = [random_poses(rng, n), random_points(rng, n)]
    else:
        args = [random_poses(rng, n), random_poses(rng, n)]
    batch = _check_batch(fn, args)
    for out, single in zip(batch, _outputs(fn(*[a[0] for a in args]))):
        assert out.shape == (n,) + single.shape
    # A batch of one stays a batch.
    for out, single in zip(_outputs(fn(*[a[:1] for a in args])), _outputs(
            fn(*[a[0] for a in args]))):
        assert out.shape == (1,) + single.shape
        np.testing.assert_array_equal(out[0], single)
    # Single items broadcast against batches, in either position.
    for single_index in range(len(args)):
        if len(args) > 1:
            mixed = [a[0] if i == single_index else a for i, a in enumerate(args)]
            _check_batch(fn, mixed, single_index)
            assert all(o.shape[0] == n for o in _outputs(fn(*mixed)))


@pytest.mark.parametrize('fn', TWO_POSE_FUNCTIONS + ONE_POSE_FUNCTIONS + POINT_FUNCTIONS,
                         ids=lambda fn: fn.__name__)
def test_integer_inputs_give_float64(fn):
    args = [[1, 2, 1]] if fn in ONE_POSE_FUNCTIONS else (
        [[1, 2, 1], [3, -1]] if fn in POINT_FUNCTIONS else [[1, 2, 1], [0, 1, 2]])
    for out in _outputs(fn(*args)):
        assert out.dtype == np.float64


@pytest.mark.parametrize('fn', TWO_POSE_FUNCTIONS + POINT_FUNCTIONS,
                         ids=lambda fn: fn.__name__)
@pytest.mark.parametrize('bad', [np.zeros(2), np.zeros(4), np.zeros((2, 2, 3)), np.zeros(()),
                                 np.zeros((3, 2))])
def test_wrong_shapes_raise(fn, bad):
    good_pose = np.array([1.0, 2.0, 0.3])
    good_second = np.array([3.0, 4.0]) if fn in POINT_FUNCTIONS else np.array([0.5, 0.1, 1.0])
    with pytest.raises(ValueError, match='must have shape'):
        fn(bad, good_second)
    if fn not in POINT_FUNCTIONS or bad.shape[-1:] != (2,) or bad.ndim > 2:
        with pytest.raises(ValueError, match='must have shape'):
            fn(good_pose, bad)


def test_mismatched_batches_raise():
    with pytest.raises(ValueError):
        pose2.compose(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError):
        pose2.between_jacobians(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match='must have shape'):
        pose2.inverse(np.zeros(2))


# --- properties ---------------------------------------------------------------------------

@SETTINGS
@given(poses)
def test_compose_with_inverse_is_identity(a):
    assert_poses_close(pose2.compose(a, pose2.inverse(a)), np.zeros(3), atol=1e-12 * 200)
    assert_poses_close(pose2.compose(pose2.inverse(a), a), np.zeros(3), atol=1e-12 * 200)
    assert_poses_close(pose2.inverse(pose2.inverse(a)), a, atol=1e-12 * 200)


@SETTINGS
@given(poses, poses)
def test_between_is_inverse_then_compose(a, b):
    assert_poses_close(pose2.between(a, b), pose2.compose(pose2.inverse(a), b), atol=1e-10)
    assert_poses_close(pose2.compose(a, pose2.between(a, b)), b, atol=1e-10)


@SETTINGS
@given(poses, poses, poses)
def test_compose_is_associative(a, b, c):
    left = pose2.compose(pose2.compose(a, b), c)
    right = pose2.compose(a, pose2.compose(b, c))
    assert_poses_close(left, right, atol=1e-10)


@SETTINGS
@given(poses, points)
def test_transform_point_is_compose_with_zero_heading(pose, point):
    as_pose = np.array([point[0], point[1], 0.0])
    np.testing.assert_allclose(pose2.transform_point(pose, point),
                               pose2.compose(pose, as_pose)[:2], rtol=0, atol=1e-12)
    # And back: the point seen from the pose.
    np.testing.assert_allclose(
        pose2.transform_point(pose2.inverse(pose), pose2.transform_point(pose, point)), point,
        rtol=0, atol=1e-10)


def test_outputs_are_wrapped(rng):
    a = random_poses(rng, 500)
    b = random_poses(rng, 500)
    a[:, 2] *= 3.0   # unwrapped inputs are accepted
    for out in (pose2.compose(a, b), pose2.inverse(a), pose2.between(a, b)):
        assert np.all((out[:, 2] >= -PI) & (out[:, 2] < PI))
