"""Range-only rows of a camera whose range scale depends on the bearing: observer to fuser."""

import math

from landmark_ros.core import range_scale
from landmark_ros.core.partial import observe_views, RANGE
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
import numpy as np
import pytest

S = 1_000_000_000
LENS = {'range_scale_coeffs': (0.0455, -0.005, -0.4646), 'range_scale_per_m': -0.00325,
        'range_scale_no_bearing': (0.0034, 0.0413), 'range_stddev': 0.01}
LIMIT = 0.592
LANDMARK = np.array([2.0, 1.0])


def reading(pose, m=LANDMARK):
    """Return the camera's noise-free range reading of ``m`` and its true bearing."""
    d = m - pose[:2]
    rho, b = math.hypot(*d), math.atan2(d[1], d[0]) - pose[2]
    return rho * float(range_scale.scale([rho, b], LENS['range_scale_coeffs'],
                                         LENS['range_scale_per_m'])), b


def poses(count, rng):
    """Return robot poses around the landmark, each seeing it inside the field of view."""
    angles = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    xy = LANDMARK + rng.uniform(1.5, 4.0, (count, 1)) * np.column_stack(
        [np.cos(angles), np.sin(angles)])
    heading = np.arctan2(*(LANDMARK - xy).T[::-1]) - rng.uniform(-0.5, 0.5, count)
    return np.column_stack([xy, heading])


def observe(observer, pose, k):
    observer.add_pose(k * S, pose, np.diag([1e-8, 1e-8, 1e-9]))
    r, _ = reading(pose)
    batch, = observer.add_observations([ObservationMessage(
        k * S, {'id': np.array([4]), 'range': np.array([r])})])
    return batch.partial_observations


@pytest.mark.parametrize('limit', [LIMIT, 0.0])
def test_a_range_only_row_carries_the_scale_model_or_its_spread_as_noise(rng, limit):
    observer = Observer(ObserverConfig(range_scale_bearing_limit=limit, **LENS))
    pose = poses(1, rng)[0]
    views = observe(observer, pose, 1).views
    r, b = reading(pose)
    mean, spread = LENS['range_scale_no_bearing']
    g = 1.0 + mean + LENS['range_scale_per_m'] * r
    np.testing.assert_allclose(views.y, [r / g], rtol=1e-12)
    if limit:
        c0, c1, c2 = LENS['range_scale_coeffs']
        np.testing.assert_allclose(views.range_scale, [[(c0 - mean) / g, c1 / g, c2 / g]],
                                   rtol=1e-12)
        np.testing.assert_allclose(views.range_scale_bearing_limit, [limit])
        np.testing.assert_allclose(views.R, [0.01 ** 2 / g ** 2], rtol=1e-12)
        # At the true landmark the model predicts the corrected reading, up to the
        # per-metre term taken at the reading instead of the true range.
        rho = math.hypot(*(LANDMARK - pose[:2]))
        bound = abs(LENS['range_scale_per_m'] * (r - rho)) * rho / g + 1e-12
        assert abs(observe_views(views, LANDMARK)[0] - r / g) <= bound
    else:
        np.testing.assert_array_equal(views.range_scale, [[0.0, 0.0, 0.0]])
        np.testing.assert_allclose(views.R, [0.01 ** 2 / g ** 2 + (spread * r / g) ** 2],
                                   rtol=1e-12)


@pytest.mark.parametrize('limit', [LIMIT, 0.0])
def test_the_fuser_places_the_landmark_of_lens_scaled_ranges(rng, limit):
    observer = Observer(ObserverConfig(range_scale_bearing_limit=limit, **LENS))
    fuser = Fuser(FuserConfig(), [], partial_sources=['/r1/partial_observations'])
    for k, pose in enumerate(poses(12, rng), start=1):
        found = observe(observer, pose, k)
        fuser.add_partial_observations('/r1/partial_observations', k * S, found.columns())
        fuser.fuse_queued()
    ids, m, P, _, _ = fuser.snapshot()
    assert ids.tolist() == [4]
    error = float(np.hypot(*(m[0] - LANDMARK)))
    if limit:
        assert error < 2e-3, error      # the per-metre term at the reading: millimetres
    else:
        assert error > 5e-3, error      # the scale at each bearing is left as noise


def test_the_fuser_rejects_a_row_whose_range_scale_is_not_a_lens_and_keeps_the_rest(rng):
    observer = Observer(ObserverConfig(range_scale_bearing_limit=LIMIT, **LENS))
    fuser = Fuser(FuserConfig(), [], partial_sources=['/r1/partial_observations'])
    first, second = (observe(observer, pose, k).columns()
                     for k, pose in enumerate(poses(2, rng), start=1))
    both = {name: np.concatenate([first[name], second[name]]) for name in first}
    both['range_scale_q2'] = np.array([both['range_scale_q2'][0], -9.0])
    both['id'] = np.array([4, 5])
    assert both['kind'].tolist() == [RANGE, RANGE]
    assert fuser.add_partial_observations('/r1/partial_observations', S, both) == 1
    assert fuser.sources['/r1/partial_observations'].counts['range_scale_invalid'] == 1
