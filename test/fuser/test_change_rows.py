"""Change detection's row bookkeeping: the ring of recent rows and grouped recursions."""

from landmark_ros.fuser.change_rows import Groups, RowLog
import numpy as np


def _rows(n, rng):
    z = rng.standard_normal((n, 2))
    R = rng.uniform(0.1, 1.0, (n, 1, 1)) * np.eye(2)
    return z, R, 0.5 * R, np.array(['a'] * n), 1_000 + np.arange(n, dtype=np.int64)


def test_the_log_gives_a_landmarks_rows_in_order_and_forgets_the_oldest():
    rng = np.random.default_rng(1)
    log = RowLog(capacity=50)
    landmarks = rng.integers(0, 3, 120)
    rows = _rows(120, rng)
    sequence = np.concatenate([log.append(landmarks[k:k + 30], landmarks[k:k + 30] % 2,
                                          np.arange(k, k + 30), rows)
                               for k in range(0, 120, 30)])
    assert sequence.tolist() == list(range(120)) and log.next == 120
    got = log.rows_of(1, 40, ['s0', 's1'], 100)
    kept = [k for k in range(70, 120) if landmarks[k] == 1]   # the last 50 rows only
    assert [o.stamp_ns for o in got] == [1_000 + k for k in kept]
    assert [o.source for o in got] == ['s1'] * len(kept)
    np.testing.assert_array_equal(got[0].z, rows[0][kept[0]])
    np.testing.assert_array_equal(got[0].R_dep, rows[2][kept[0]])
    assert len(log.rows_of(1, 40, ['s0', 's1'], 3)) == 3
    assert log.rows_of(1, 120, ['s0', 's1'], 100) == []


def test_a_batch_longer_than_the_log_keeps_its_last_rows():
    rng = np.random.default_rng(2)
    log = RowLog(capacity=8)
    rows = _rows(20, rng)
    log.append(np.zeros(20, np.int64), np.zeros(20, np.int64), np.arange(20), rows)
    assert [o.stamp_ns for o in log.rows_of(0, 0, ['s'], 100)] == list(range(1_012, 1_020))


def test_grouped_lindley_equals_pages_recursion_per_group():
    rng = np.random.default_rng(3)
    keys = rng.integers(0, 7, 500)
    g = rng.normal(-0.2, 1.0, 500)
    start = rng.uniform(0.0, 2.0, 7)
    groups = Groups(keys)
    statistic = np.empty(500)
    statistic[groups.order] = groups.lindley(g[groups.order], start[groups.unique])
    for key in range(7):
        C = start[key]
        for k in np.flatnonzero(keys == key):
            C = max(0.0, C + g[k])
            assert abs(statistic[k] - C) < 1e-12
