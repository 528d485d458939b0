"""Tests of observer.Observer, without ROS: poses, waiting, rows, stamps, status."""

from landmark_ros.core.landmarks import landmark_to_world_dependent
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import ObserverConfig
from landmark_ros.pipeline.pose_buffer import interpolate
from landmark_ros.pipeline.rows import UNKNOWN_ID
import numpy as np
import pytest

S = 1_000_000_000
"""One second in nanoseconds."""

R_TEXTBOOK = np.diag([0.25, 0.04])
CONFIG = ObserverConfig(range_stddev=0.5, bearing_stddev=0.2, max_wait_s=0.5)
POSE = np.array([1.0, 2.0, 0.5])
P_POSE = np.diag([0.08, 0.6, 0.02])


def message(stamp_ns, ids, z, token=None, **extra):
    """Return an ObservationMessage of range-bearing rows."""
    z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    columns = {'id': np.asarray(ids, dtype=np.int64), 'range': z[:, 0], 'bearing': z[:, 1]}
    columns.update({k: np.asarray(v, dtype=np.float64) for k, v in extra.items()})
    return ObservationMessage(int(stamp_ns), columns, token=token)


def problems(observer):
    """Return the non-zero counters that name a rejection reason."""
    quiet = {'poses_in', 'observation_messages_in', 'observations_in', 'landmarks_out'}
    return {k: v for k, v in observer.counters.counts.items() if v and k not in quiet}


def test_textbook_case2_equals_the_core():
    observer = Observer(CONFIG)
    observer.add_pose(10 * S, POSE, P_POSE)
    batches = observer.add_observations([message(10 * S, [7], [[4.0, 0.7]], token='h')])
    assert len(batches) == 1 and batches[0].token == 'h' and batches[0].stamp_ns == 10 * S
    m, P, P_dep = landmark_to_world_dependent(POSE, P_POSE, np.array([[4.0, 0.7]]), R_TEXTBOOK)
    np.testing.assert_allclose(batches[0].m, m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(batches[0].P, P, rtol=0, atol=1e-12)
    np.testing.assert_allclose(batches[0].P_dep, P_dep, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(batches[0].ids, [7])
    assert batches[0].ids.dtype == np.int64
    assert not problems(observer)


def test_observation_between_poses_takes_the_interpolated_pose():
    observer = Observer(CONFIG)
    pose_b, P_b = np.array([3.0, 1.0, 1.0]), np.diag([0.02, 0.03, 0.002])
    observer.add_pose(10 * S, POSE, P_POSE)
    assert observer.add_observations([message(10 * S + S // 4, [1], [[2.0, 0.5]])]) == []
    batches = observer.add_pose(11 * S, pose_b, P_b)
    pose, P_pose = interpolate(POSE, P_POSE, pose_b, P_b, 0.25)
    m, P, _ = landmark_to_world_dependent(pose, P_pose, np.array([[2.0, 0.5]]), R_TEXTBOOK)
    np.testing.assert_allclose(batches[0].m, m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(batches[0].P, P, rtol=0, atol=1e-12)


def test_waiting_observation_expires_by_the_callers_clock():
    observer = Observer(CONFIG)
    observer.add_pose(10 * S, POSE, P_POSE)
    assert observer.add_observations([message(10 * S + 1, [1], [[2.0, 0.5]])], now_ns=0) == []
    assert observer.drain(now_ns=S // 4) == []              # still within max_wait_s
    batches = observer.drain(now_ns=S)                      # waited: the newest pose serves
    assert len(batches) == 1 and len(batches[0].ids) == 1
    observer.add_observations([message(20 * S, [1], [[2.0, 0.5]])], now_ns=S)
    assert observer.drain(now_ns=3 * S) == []               # 10 s past the newest pose
    assert problems(observer) == {'no_pose_in_time': 1}


def test_batch_of_messages_equals_one_at_a_time(rng):
    messages = [message(10 * S + k, rng.integers(0, 50, 5),
                        np.column_stack([rng.uniform(1, 9, 5), rng.uniform(-3, 3, 5)]),
                        range_variance=rng.uniform(0.01, 0.1, 5))
                for k in range(4)]
    one = Observer(CONFIG)
    one.add_pose(10 * S, POSE, P_POSE)
    one.add_pose(11 * S, POSE + 0.5, P_POSE)
    alone = [one.add_observations([m])[0] for m in messages]
    many = Observer(CONFIG)
    many.add_pose(10 * S, POSE, P_POSE)
    many.add_pose(11 * S, POSE + 0.5, P_POSE)
    together = many.add_observations(messages)
    for a, b in zip(alone, together, strict=True):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_allclose(a.m, b.m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-12)


def test_bad_rows_are_rejected_and_good_rows_of_the_message_placed():
    observer = Observer(CONFIG)
    observer.add_pose(10 * S, POSE, P_POSE)
    batch, = observer.add_observations([message(10 * S, [1, 2, -3, 4], [
        [4.0, 0.7], [np.inf, 0.1], [2.0, 0.1], [0.0, 0.2]])])
    np.testing.assert_array_equal(batch.ids, [1])
    assert problems(observer) == {'observation_nonfinite': 1, 'invalid_id': 1,
                                  'range_not_positive': 1}


@pytest.mark.parametrize('pose, P, reason', [
    ([np.nan, 0.0, 0.0], np.eye(3), 'pose_nonfinite'),
    ([0.0, 0.0, 0.0], -np.eye(3), 'pose_covariance_not_psd'),
])
def test_bad_pose_is_dropped(pose, P, reason):
    observer = Observer(CONFIG)
    assert observer.add_pose(10 * S, pose, P) == []
    assert problems(observer) == {reason: 1} and len(observer.poses) == 0


def test_zero_stamps_are_never_valid():
    observer = Observer(CONFIG)
    observer.add_pose(0, POSE, P_POSE)
    observer.add_pose(10 * S, POSE, P_POSE)
    assert observer.add_observations([message(0, [1, 2], [[4.0, 0.7], [3.0, 0.1]])]) == []
    assert problems(observer) == {'pose_stamp_zero': 1, 'observation_stamp_zero': 2}


def test_frozen_stamps_do_not_place_landmarks_with_a_stale_pose():
    """A driver whose clock is frozen at 2000 s while the robot drives from x = 0 to 2 m."""
    observer = Observer(CONFIG)
    frozen = 2000 * S
    placed = []
    for x in np.linspace(0.0, 2.0, 5):
        placed += observer.add_pose(frozen, [x, 0.0, 0.0], np.diag([1e-4, 1e-4, 1e-6]))
        placed += observer.add_observations([message(frozen, [9], [[5.0 - x, 0.0]])])
    # Only the first observation (made at the first pose, the one held) is placed, at
    # the true landmark; every later one needs the pose at the frozen stamp, which
    # came again with other values.
    assert [len(b.ids) for b in placed] == [1]
    np.testing.assert_allclose(placed[0].m, [[5.0, 0.0]], atol=1e-12)
    assert problems(observer) == {'pose_stamp_repeated': 4, 'observation_pose_ambiguous': 4}


def test_a_repeated_identical_pose_is_a_harmless_duplicate():
    observer = Observer(CONFIG)
    observer.add_pose(10 * S, POSE, P_POSE)
    observer.add_pose(10 * S, POSE, P_POSE)
    batch, = observer.add_observations([message(10 * S, [1], [[4.0, 0.7]])])
    assert len(batch.ids) == 1 and problems(observer) == {'pose_duplicate': 1}


def test_repeated_stamp_rejects_only_observations_that_need_that_pose():
    observer = Observer(CONFIG)
    observer.add_pose(10 * S, POSE, P_POSE)
    observer.add_pose(11 * S, POSE, P_POSE)
    observer.add_pose(11 * S, POSE + 1.0, P_POSE)             # frozen for one message
    observer.add_pose(12 * S, POSE, P_POSE)
    out = observer.add_observations([message(10 * S, [1], [[4.0, 0.7]]),       # before it
                                     message(10 * S + S // 2, [2], [[4.0, 0.7]]),  # needs it
                                     message(11 * S + S // 2, [3], [[4.0, 0.7]])])  # after
    assert [b.ids.tolist() for b in out] == [[1], [3]]
    assert problems(observer) == {'pose_stamp_repeated': 1, 'observation_pose_ambiguous': 1}


def test_time_jump_back_clears_the_history():
    observer = Observer(ObserverConfig(max_wait_s=5.0, time_jump_s=1.0))
    observer.add_pose(100 * S, POSE, P_POSE)
    observer.add_observations([message(101 * S, [1], [[4.0, 0.7]])])
    observer.add_pose(100 * S - S // 2, POSE, P_POSE)          # 0.5 s back: out of order
    observer.add_pose(10 * S, POSE, P_POSE)                    # 90 s back: a new run
    assert len(observer.poses) == 1 and not observer.pending
    assert problems(observer) == {'pose_out_of_order': 1, 'time_jump_back': 1,
                                  'dropped_on_time_jump': 1}


def test_backlog_drops_the_oldest_waiting_message():
    observer = Observer(ObserverConfig(max_wait_s=5.0, max_pending=2))
    observer.add_pose(10 * S, POSE, P_POSE)
    for k in range(3):
        observer.add_observations([message(11 * S + k, [k], [[4.0, 0.7]])])
    assert len(observer.pending) == 2 and problems(observer) == {'backlog_dropped': 1}


def test_sensor_frame_is_checked():
    observer = Observer(ObserverConfig(sensor_frame='camera'))
    observer.add_pose(10 * S, POSE, P_POSE)
    msg = message(10 * S, [1], [[4.0, 0.7]])
    msg.frame_id = 'lidar'
    assert observer.add_observations([msg]) == []
    assert problems(observer) == {'observation_wrong_frame': 1}


def test_status_reports_problems_once_then_ok():
    observer = Observer(CONFIG)
    assert observer.status().level == 'warn'                  # no pose yet
    observer.add_pose(10 * S, POSE, P_POSE)
    observer.add_observations([message(10 * S, [1, 2], [[4.0, 0.7], [np.inf, 0.0]])])
    status = observer.status()
    assert status.level == 'warn' and 'observation_nonfinite 1' in status.message
    assert status.counts['landmarks_out'] == 1 and status.extra['pose_buffer_size'] == 1
    assert observer.status().level == 'ok'


def test_sensor_pose_and_bias_reach_the_core():
    config = ObserverConfig(range_stddev=0.5, bearing_stddev=0.2, sensor_pose=(0.3, 0.1, 0.2),
                            range_bias_stddev=0.05, bearing_bias_stddev=0.01)
    observer = Observer(config)
    observer.add_pose(10 * S, POSE, P_POSE)
    batch, = observer.add_observations([message(10 * S, [1], [[4.0, 0.7]])])
    m, P, P_dep = landmark_to_world_dependent(
        POSE, P_POSE, np.array([[4.0, 0.7]]), R_TEXTBOOK, np.diag([0.05 ** 2, 0.01 ** 2]),
        np.array([0.3, 0.1, 0.2]))
    np.testing.assert_allclose(batch.m, m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(batch.P_dep, P_dep, rtol=0, atol=1e-12)


def test_range_noise_grows_with_the_square_of_the_range():
    # sigma_r^2 = a^2 + (k r)^2 + (c r^2)^2; a row at bearing 0 from an exact pose at the
    # origin lies along x: its x variance is the range variance, its y variance
    # (r sigma_b)^2.
    a, k, c, sigma_b, r = 0.01, 0.02, 0.003, 0.01, 4.0
    observer = Observer(ObserverConfig(range_stddev=a, range_stddev_per_m=k,
                                       range_stddev_per_m2=c, bearing_stddev=sigma_b))
    expected_rr = 1e-4 + 0.08 ** 2 + 0.048 ** 2  # 0.008804 m^2, by hand
    R = observer.noise({'range': np.array([r, 1.0])})
    np.testing.assert_allclose(R[:, 0, 0], [expected_rr, 1e-4 + 0.02 ** 2 + 0.003 ** 2],
                               rtol=1e-12)
    observer.add_pose(10 * S, np.zeros(3), np.zeros((3, 3)))
    batch = observer.add_observations([message(10 * S, [7], [[r, 0.0]])])[0]
    np.testing.assert_allclose(batch.P[0], np.diag([expected_rr, (r * sigma_b) ** 2]),
                               rtol=1e-9, atol=1e-15)
    # Without the quadratic part the same row is 0.0023 m^2 less uncertain.
    plain = Observer(ObserverConfig(range_stddev=a, range_stddev_per_m=k,
                                    bearing_stddev=sigma_b))
    assert plain.noise({'range': np.array([r])})[0, 0, 0] == pytest.approx(0.0065, rel=1e-12)


def test_range_scale_bias_reaches_rows_views_and_scan():
    # A shared scale error s: the dependent range variance of a row at range r grows by
    # (s r)^2, in the full rows, the range-only views and the association's Scan alike.
    s, b = 0.01, 0.02
    config = ObserverConfig(range_stddev=0.05, bearing_stddev=0.01, range_bias_stddev=b,
                            range_scale_bias_stddev=s)
    observer = Observer(config)
    observer.add_pose(10 * S, np.zeros(3), np.zeros((3, 3)))
    z = np.array([[2.0, 0.0], [5.0, 0.0]])
    batch, = observer.add_observations([message(10 * S, [UNKNOWN_ID, UNKNOWN_ID], z)])
    np.testing.assert_allclose(batch.P_dep[:, 0, 0], b ** 2 + (s * z[:, 0]) ** 2, rtol=1e-9)
    assert batch.scan is not None and batch.scan.range_scale_variance == pytest.approx(s * s)
    ranges = np.array([2.0, 5.0])
    columns = {'id': np.array([1, 2]), 'range': ranges, 'bearing': np.full(2, np.nan)}
    batch, = observer.add_observations([ObservationMessage(10 * S, columns)])
    views = batch.partial_observations.views
    np.testing.assert_allclose(views.R_bias, b ** 2 + (s * ranges) ** 2, rtol=1e-9)
    # Without it: the offset alone.
    plain = Observer(ObserverConfig(range_stddev=0.05, bearing_stddev=0.01,
                                    range_bias_stddev=b))
    plain.add_pose(10 * S, np.zeros(3), np.zeros((3, 3)))
    batch, = plain.add_observations([message(10 * S, [UNKNOWN_ID, UNKNOWN_ID], z)])
    np.testing.assert_allclose(batch.P_dep[:, 0, 0], b ** 2, rtol=1e-9)
    assert batch.scan.range_scale_variance == 0.0
