"""Deletion of confirmed tracks by their score (fuser.track_screen) and its announcement."""

from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fuser.track_score import miss_increment, sprt_thresholds
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.pipeline.scan import Scan
import numpy as np
import pytest

S = 1_000_000_000
SOURCE = '/robot1/landmarks'
SCAN = Scan(np.zeros(2), np.zeros((3, 3)))
TRUTH = np.array([[2.0, 0.0], [0.0, 3.0]])


def _send(fuser, k, z):
    P = np.broadcast_to(0.0025 * np.eye(2), (len(z), 2, 2)).copy()
    fuser.add_landmarks(SOURCE, LandmarkMessage((k + 1) * S, [UNKNOWN_ID] * len(z),
                                                np.asarray(z, float).reshape(-1, 2), P,
                                                0.0 * P, scan=SCAN))
    fuser.fuse_queued()


def _run(rng, gone_after, messages=200, P_D=0.9):
    """Landmark 0 always there, landmark 1 until ``gone_after``; both in view throughout."""
    fuser = Fuser(FuserConfig(delete_confirmed_tracks=True), [SOURCE])
    for k in range(messages):
        present = TRUTH if k < gone_after else TRUTH[:1]
        seen = present[rng.random(len(present)) < P_D]
        _send(fuser, k, seen + rng.normal(0.0, 0.05, seen.shape))
    return fuser


def test_a_confirmed_track_whose_landmark_is_gone_is_deleted_and_announced():
    fuser = _run(np.random.default_rng(1), gone_after=60)
    counts = fuser.sources[SOURCE].counts
    assert counts['confirmed'] == 2 and counts['deleted'] == 1
    (kept,) = fuser.snapshot().ids.tolist()
    assert np.linalg.norm(fuser.snapshot().m[0] - TRUTH[0]) < 0.05
    removed = fuser.take_removed()
    ((gone, into),) = [pair for pair in removed if pair[0] != kept]
    assert gone == into and gone not in fuser.tracker.owned
    rows, merged_into = fuser.removal_rows(removed)
    assert rows.ids.tolist() == [gone] and merged_into.tolist() == [gone]
    assert rows.observations.tolist() == [0]
    assert np.linalg.norm(rows.m[0] - TRUTH[1]) < 0.05     # its last estimate


def test_the_drop_from_the_peak_is_what_deletes():
    # After the landmark leaves, its score falls by ln(1 - P_D) per message in view: the
    # track is deleted at the first message where the fall reaches the threshold.
    fuser = _run(np.random.default_rng(2), gone_after=60, messages=60)
    tracker = fuser.tracker
    (gone,) = [i for i in tracker.scores if np.linalg.norm(
        fuser.map.snapshot(np.array([i])).m[0] - TRUTH[1]) < 0.2]
    score, peak = tracker.scores[gone]
    assert score <= peak
    confirm, _ = sprt_thresholds(fuser.config.false_track_probability,
                                 fuser.config.lost_track_probability)
    for k in range(60, 100):
        before = list(tracker.scores[gone])
        _send(fuser, k, TRUTH[:1])
        P_D = tracker.statistics[SOURCE].detection_probability     # this message's in
        if gone not in tracker.scores:
            assert before[1] - (before[0] + miss_increment(P_D)) >= confirm
            assert before[1] - before[0] < confirm
            break
        assert tracker.scores[gone][0] == pytest.approx(before[0] + miss_increment(P_D))
    else:
        raise AssertionError('never deleted')


def test_landmarks_seen_half_the_time_are_kept():
    fuser = _run(np.random.default_rng(3), gone_after=10 ** 9, messages=400, P_D=0.5)
    counts = fuser.sources[SOURCE].counts
    assert counts['deleted'] == 0 and len(fuser.snapshot().ids) == 2


def test_confirmed_tracks_are_kept_by_default():
    fuser = Fuser(FuserConfig(), [SOURCE])
    rng = np.random.default_rng(1)
    for k in range(200):
        present = TRUTH if k < 60 else TRUTH[:1]
        seen = present[rng.random(len(present)) < 0.9]
        _send(fuser, k, seen + rng.normal(0.0, 0.05, seen.shape))
    assert fuser.sources[SOURCE].counts['deleted'] == 0 and len(fuser.snapshot().ids) == 2
