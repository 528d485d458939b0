"""Shared test helpers: a numerical Jacobian, a seeded RNG and random inputs."""

import re
import warnings
import zlib

from landmark_ros.core.pose2 import wrap_angle
import numpy as np
import pytest


def numerical_jacobian(f, x, angle_rows=(), eps=1e-6):
    """
    Return the central-difference Jacobian of ``f`` at ``x``, shape (n_out, n_in).

    ``f`` maps a 1-D array to a 1-D array. The rows of ``f(x + h) - f(x - h)``
    listed in ``angle_rows`` are wrapped to [-pi, pi) before dividing by ``2 h``,
    so angle outputs that jump across +-pi differentiate correctly.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f'x must be 1-D, got shape {x.shape}')
    columns = []
    for j in range(x.size):
        h = np.zeros_like(x)
        h[j] = eps
        diff = np.atleast_1d(np.asarray(f(x + h), dtype=np.float64)
                             - np.asarray(f(x - h), dtype=np.float64))
        rows = list(angle_rows)
        diff[rows] = wrap_angle(diff[rows])
        columns.append(diff / (2.0 * eps))
    return np.stack(columns, axis=-1)


@pytest.fixture
def rng(request):
    """Return a numpy Generator seeded from the test id: reproducible, distinct per test."""
    return np.random.default_rng(zlib.crc32(request.node.nodeid.encode()))


def random_poses(rng, n=None, scale=10.0):
    """Return poses with x, y in [-scale, scale) and theta in [-pi, pi)."""
    shape = () if n is None else (n,)
    xy = rng.uniform(-scale, scale, shape + (2,))
    theta = rng.uniform(-np.pi, np.pi, shape + (1,))
    return np.concatenate([xy, theta], axis=-1)


def random_points(rng, n=None, scale=10.0):
    """Return points with coordinates in [-scale, scale)."""
    return rng.uniform(-scale, scale, (() if n is None else (n,)) + (2,))


def random_observations(rng, n=None, r_min=0.5, r_max=20.0):
    """Return range-bearing observations, range in [r_min, r_max), bearing in [-pi, pi)."""
    shape = () if n is None else (n,)
    return np.stack([rng.uniform(r_min, r_max, shape), rng.uniform(-np.pi, np.pi, shape)],
                    axis=-1)


def random_spd(rng, dim, n=None, scale=1.0, eps=1e-3):
    """Return symmetric positive definite matrices ``A A^T + eps I`` (correlated)."""
    shape = () if n is None else (n,)
    A = scale * rng.standard_normal(shape + (dim, dim))
    return A @ np.swapaxes(A, -1, -2) + eps * np.eye(dim)


def assert_psd(M, atol=1e-12):
    """Assert that every symmetric matrix in ``M`` has eigenvalues >= -atol."""
    M = np.asarray(M)
    np.testing.assert_allclose(M, np.swapaxes(M, -1, -2), rtol=0, atol=atol)
    smallest = np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, -1, -2)))[..., 0]
    assert np.all(smallest >= -atol), f'smallest eigenvalue {np.min(smallest)!r} < -{atol}'


def assert_jacobians(value_fn, jacobian_fn, args, angle_rows=(), atol=1e-6):
    """Assert that each Jacobian ``jacobian_fn(*args)`` returns matches the numerical one."""
    analytic = jacobian_fn(*args)
    analytic = analytic if isinstance(analytic, tuple) else (analytic,)
    assert len(analytic) == len(args)
    for i, J in enumerate(analytic):
        def f(x, i=i):
            return value_fn(*args[:i], x, *args[i + 1:])
        assert J.dtype == np.float64
        np.testing.assert_allclose(
            J, numerical_jacobian(f, args[i], angle_rows), rtol=0, atol=atol,
            err_msg=f'{jacobian_fn.__name__}: Jacobian {i} at {args}')


@pytest.fixture
def ros_env():
    """Return a factory of RosEnv (own context and domain); all are closed in teardown."""
    from rosutil import RosEnv  # rclpy only for the tests that spin nodes
    envs = []

    def make(**kwargs):
        env = RosEnv(**kwargs)
        envs.append(env)
        return env

    yield make
    errors = []
    for env in envs:
        try:
            env.close()
        except Exception as error:  # noqa: B902 - every env must be closed
            errors.append(error)
    assert not errors, f'RosEnv.close failed: {errors}'


@pytest.fixture
def env(ros_env):
    """Return a fresh RosEnv for this test."""
    return ros_env()


@pytest.fixture
def no_warnings():
    """Turn every warning into an error for the duration of a test."""
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        yield


ROS_GRAPH = re.compile(r'rclpy|rosutil|through_nodes|through-nodes|landmark_ros\.demo|'
                       r'launch_rig|startup|colcon|ROS_DOMAIN_ID')
"""What a test module says when its tests join a ROS graph (nodes, processes, domains)."""

CHECKERS = frozenset({'test_flake8.py', 'test_pep257.py', 'test_layers.py',
                      'test_codebase.py', 'test_types.py', 'test_docs.py'})
"""Code checkers: they name ROS in their sources but start nothing."""


def _joins_ros_graph(path):
    """Return whether the tests of module ``path`` join a ROS graph (by its source)."""
    return path.name not in CHECKERS and bool(
        ROS_GRAPH.search(path.read_text(encoding='utf-8')))


def pytest_collection_modifyitems(config, items):
    """
    Under pytest-xdist, run the tests that join a ROS graph one at a time on one worker.

    ``make test`` runs ``-n 2 --dist loadgroup``. The tests whose module names ROS (or
    that take the ``env`` / ``ros_env`` fixtures) form one group, as in a serial run:
    the demo's and the launch tests' checks for leftover shared-memory files are global,
    and with two such tests at once a demo localizer lost its poses (``rosutil`` still
    gives each worker its own domain IDs). The others (maths, Monte Carlo, checkers)
    share both workers.
    """
    if not config.pluginmanager.hasplugin('xdist'):
        return
    joins = {}
    for item in items:
        if item.path not in joins:
            joins[item.path] = _joins_ros_graph(item.path)
        if joins[item.path] or {'env', 'ros_env'} & set(getattr(item, 'fixturenames', ())):
            item.add_marker(pytest.mark.xdist_group('ros_graph'))
