"""The localizer takes only map landmarks that pass the live row checks."""

from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
import numpy as np


def test_bad_map_landmarks_are_left_out_by_reason():
    localizer = Localizer(LocalizerConfig())
    ids = np.array([1, 2, 3, 4], np.int64)
    m = np.array([[1.0, 2.0], [np.nan, 0.0], [3.0, 4.0], [2e7, 0.0]])
    P = np.broadcast_to(np.eye(2) * 0.01, (4, 2, 2)).copy()
    P[2] = np.eye(2) * 1e-200
    localizer.set_map(ids, m, P)
    assert localizer.map_size == 1
    assert localizer.counters['map_landmark_nonfinite'] == 1
    assert localizer.counters['map_covariance_too_small'] == 1
    assert localizer.counters['map_landmark_out_of_range'] == 1
