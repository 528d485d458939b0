"""The fuser's partial views with each robot's bias as a consider state (``partial_consider``)."""

import math

from landmark_ros.core.partial import BEARING, RANGE, Views
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.partial_rows import PartialObservations
import numpy as np
import pytest
from scipy.stats import chi2

S = 1_000_000_000
VIEWS = ['/r1/partial_observations', '/r2/partial_observations']
LANDMARKS = ['/r1/landmarks']


LENS = (0.04, 0.0, -0.46)
LIMIT = 0.6
NOISE = {BEARING: 0.005, RANGE: 0.015}
BIAS = {BEARING: 0.01, RANGE: 0.02}


def columns(kind, y, s, group):
    views = Views(kind, s, np.zeros((3, 3)), y, NOISE[kind] ** 2, BIAS[kind] ** 2,
                  LENS if kind == RANGE else (0.0, 0.0, 0.0), LIMIT)
    return PartialObservations(np.array([3]), views, np.array([group])).columns()


def reading(kind, s, m):
    """Return the noise-free view of ``m`` from ``s`` (a range through the lens)."""
    d = m - s[:2]
    b = (math.atan2(d[1], d[0]) - s[2] + math.pi) % (2 * math.pi) - math.pi
    return b if kind == BEARING else math.hypot(*d) * (1 + LENS[0] + LENS[2] * b * b)


def fuser():
    return Fuser(FuserConfig(fusion='split_covariance_intersection',
                             source_correlation='independent', min_observations=1),
                 LANDMARKS, partial_sources=VIEWS)


def circle(f, rng, kind, m_true, biases, steps=30):
    """Two robots circle the landmark, each with its constant bias, looking off-axis."""
    for k in range(steps):
        for r, bias in enumerate(biases):
            a = 2 * np.pi * k / steps + r * np.pi
            s = np.array([*(m_true + 3.0 * np.array([np.cos(a), np.sin(a)])),
                          a + np.pi + rng.uniform(-0.4, 0.4)])
            y = reading(kind, s, m_true) + bias + rng.normal(0, NOISE[kind])
            f.add_partial_observations(VIEWS[r], (2 * k + r + 1) * S,
                                       columns(kind, y, s, 2 * k + r))
            f.fuse_queued()


@pytest.mark.parametrize('kind, carried', [(RANGE, True), (RANGE, False)])
def test_robot_biases_seen_from_every_side_count_once(kind, carried, monkeypatch):
    rng = np.random.default_rng(11)
    runs, m_true, nees = 60, np.array([1.0, -2.0]), []
    for _ in range(runs):
        f = fuser()
        if not carried:
            monkeypatch.setattr(f.partial.biases, 'current', lambda *args: None)
        circle(f, rng, kind, m_true, rng.normal(0, BIAS[kind], 2))
        _, m, P, _, _ = f.snapshot()
        d = m[0] - m_true
        nees.append(d @ np.linalg.solve(P[0], d))
    anees = float(np.mean(nees))
    low, high = chi2.ppf([0.0005, 0.9995], 2 * runs) / runs
    print(f'{kind} carried {carried}: ANEES {anees:.2f}, interval [{low:.2f}, {high:.2f}]')
    assert (low <= anees <= high) == carried, anees


def test_placement_starts_the_cross_covariances_and_another_path_ends_them(rng):
    f = fuser()
    m_true = np.array([1.0, -2.0])
    circle(f, rng, RANGE, m_true, [0.01, -0.01], steps=4)
    estimate = f.map.estimate(3)
    crosses = f.partial.biases.current(3, estimate)
    assert crosses is not None and set(crosses.c) == {(VIEWS[0], RANGE), (VIEWS[1], RANGE)}
    # The map's dependent part holds the biases' part: other paths see them as before.
    assert np.all(np.linalg.eigvalsh(estimate[2] - crosses.bias_part()) > -1e-15)
    R = np.eye(2) * 1e-4
    f.add_landmarks(LANDMARKS[0], LandmarkMessage(99 * S, [3], m_true[None], R[None],
                                                  0.5 * R[None]))
    f.fuse_queued()
    assert f.partial.biases.current(3, f.map.estimate(3)) is None
