"""Tests of the association metrics of eval.metrics (landmarks without IDs)."""

import math

from landmark_ros.eval.metrics import (evaluate_association, gospa, match_tracks,
                                       oracle_nearest)
import numpy as np


def test_gospa_counts_localisation_misses_and_false_tracks():
    truth = np.array([[0.0, 0.0], [10.0, 0.0]])
    assert gospa(truth, truth) == 0.0
    # One track 0.3 m off, one missed landmark, one false track: 0.09 + 0.5 + 0.5.
    estimated = np.array([[0.3, 0.0], [50.0, 50.0]])
    assert math.isclose(gospa(estimated, truth), math.sqrt(0.09 + 1.0), rel_tol=1e-12)
    # A track beyond c counts as a miss plus a false track, not as its distance.
    assert math.isclose(gospa([[3.0, 0.0]], [[0.0, 0.0]]), 1.0, rel_tol=1e-12)
    assert math.isclose(gospa(np.zeros((0, 2)), truth), 1.0, rel_tol=1e-12)


def test_tracks_match_by_optimal_assignment_within_the_distance():
    match = match_tracks([[0.0, 0.0], [1.0, 0.0], [9.0, 9.0]], [[0.9, 0.0], [0.1, 0.0]], 1.0)
    assert match.tolist() == [1, 0, -1]


def test_oracle_uses_the_mahalanobis_distance():
    # Along x the row is uncertain: the landmark 0.8 m away in x beats 0.3 m in y.
    R = np.array([[[1.0, 0.0], [0.0, 0.001]]])
    assert oracle_nearest([[0.0, 0.0]], R, [1, 2], [[0.8, 0.0], [0.0, 0.3]]).tolist() == [1]


def test_association_accuracy_counts_rows_through_the_matched_tracks():
    truth = {1: (0.0, 0.0), 2: (5.0, 0.0)}
    z = np.array([[0.0, 0.1], [5.0, 0.1], [5.0, -0.1], [0.1, 0.0]])
    R = np.broadcast_to(0.01 * np.eye(2), (4, 2, 2))
    summary = evaluate_association([100, 101, 101, 101], [1, 2, 2, 1], z, R, [100, 101],
                                   [[0.0, 0.05], [5.0, 0.0]], truth)
    assert summary.track_to_true == {100: 1, 101: 2}
    assert summary.association_accuracy == 0.75 and summary.oracle_accuracy == 1.0
    assert summary.confusion == {(1, 2): 1}
    assert summary.tracks_confirmed == 2 and summary.true_landmarks == 2
    assert math.isclose(summary.gospa_m, 0.05, rel_tol=1e-9)
