"""
Split CI in ``LandmarkMap``: the batch path (compiled run, or rounds) against row by row.

``landmark_map_reference`` is ``core/landmark_map.py`` as it was before issue 12,
with the gate reference of the map of today (see its docstring): it folded every
accepted row's landmark round by round, each weight search starting from the last
weight of that landmark and step. Where the split-CI
objective is concave (every source's dependent part positive semi-definite, as when
each row's dependent part is a fraction of its covariance) the weight is the same
optimum from any start and the maps agree to 1e-9, every gating decision the same.
Where a source's dependent part ``sym(Y^-1 Q)`` is indefinite (rows that mix
different dependent fractions can make it so) the objective has more than one
stationary point and the old result depended on the history of warm starts; the map
now gives what the public functions give (``split_covariance_intersection_omega``
from 0.5), whatever the history.
"""

from collections import Counter

from conftest import random_spd
from landmark_ros.core import _fold_kernel
from landmark_ros.core import _source_sums
from landmark_ros.core import gaussian
from landmark_ros.core.landmark_map import LandmarkMap
import landmark_map_reference  # noqa: I100 - test/core/landmark_map_reference.py
import numpy as np
import pytest

FUSION = 'split_covariance_intersection'


@pytest.fixture(autouse=True, params=['numpy', 'compiled'])
def fold_path(request, monkeypatch):
    """Run every test with the numpy fold (the rounds), and with the compiled kernel."""
    if request.param == 'numpy':     # as without numba: nothing compiled is called
        monkeypatch.setattr(_fold_kernel, 'load', lambda: None)
        monkeypatch.setattr(_fold_kernel, 'AVAILABLE', False)
    elif _fold_kernel.load() is None:
        pytest.skip('numba is not installed: no compiled kernel')
    return request.param


def stream(rng, count=1500, landmarks=40, sources=6, outliers=0.03, movers=2,
           proportional=False):
    """
    Return rows ``ids, z, R, R_dep, sources, stamps`` with repeats, outliers and moves.

    Landmarks come in bursts (several rows of one landmark next to each other), a few
    move half way (their later rows fail the gate until they are rebuilt) and some
    rows are gross outliers. ``proportional``: each row's dependent part is a random
    fraction of its covariance.
    """
    truth = rng.uniform(-30.0, 30.0, (landmarks, 2))
    which = rng.integers(0, landmarks, count)
    for i in rng.choice(count - 6, count // 20):
        which[i:i + 6] = which[i]
    R_ind = random_spd(rng, 2, count, scale=0.15, eps=0.01)
    R_dep = random_spd(rng, 2, count, scale=0.15, eps=0.0) * rng.uniform(0, 1, (count, 1, 1))
    if proportional:
        fraction = rng.uniform(0.1, 0.9, (count, 1, 1))
        R_ind, R_dep = (1.0 - fraction) * R_ind, fraction * R_ind
    R = R_ind + R_dep
    positions = truth[which].copy()
    for mover in range(movers):
        positions[(np.arange(count) > count // 2) & (which == mover)] += [25.0, -15.0]
    z = positions + (np.linalg.cholesky(R) @ rng.standard_normal((count, 2, 1)))[..., 0]
    bad = rng.uniform(size=count) < outliers
    z[bad] += rng.uniform(10.0, 40.0, (bad.sum(), 1)) * np.array([1.0, -0.7])
    names = rng.choice([f'robot{k}' for k in range(sources)], count)
    stamps = 10 ** 9 + np.arange(count, dtype=np.int64) * 10 ** 7
    return which + 100, z, R, R_dep, names, stamps


def feed(cls, rows, chunks, **kwargs):
    """Feed ``rows`` to a new map of ``cls`` in ``chunks``; return it and merged results."""
    landmark_map = cls(FUSION, **kwargs)
    total = [Counter(), Counter(), [], []]
    for part in chunks:
        ids, z, R, R_dep, names, stamps = (x[part] for x in rows)
        result = landmark_map.update(ids, z, R, R_dep, names.tolist(), stamps)
        total[0] += result.accepted
        total[1] += result.rejected
        total[2] += result.confirmed
        total[3] += result.reinitialised
    return landmark_map, (total[0], total[1], sorted(total[2]), sorted(total[3]))


def chunked(count, size):
    """Return slices of ``size`` rows covering ``range(count)``."""
    return [slice(k, min(k + size, count)) for k in range(0, count, size)]


def assert_same_map(a, b):
    """Assert two maps' snapshots and records are bitwise equal."""
    for x, y in zip(a.snapshot(), b.snapshot()):
        np.testing.assert_array_equal(x, y)
    assert a.to_records() == b.to_records()
    # What later batches depend on: rejection streaks and the recent rejections kept
    # (by ID: a batch allocates the rows of new IDs in ID order, row by row in arrival
    # order).
    rows_a, rows_b = (np.argsort(m.ids[:m._count], kind='stable') for m in (a, b))
    np.testing.assert_array_equal(a.ids[rows_a], b.ids[rows_b])
    for name in ('consecutive', 'rejections', 'last_stamp_ns', 'observations', 'confirmed'):
        np.testing.assert_array_equal(getattr(a, name)[rows_a], getattr(b, name)[rows_b])

    def recent(m):
        return {int(m.ids[row]): [(o.z.tolist(), o.source, o.stamp_ns) for o in kept]
                for row, kept in m._buffers.items()}
    assert recent(a) == recent(b)


@pytest.mark.parametrize('size', [50, 400, 1500])
def test_batches_equal_the_reference_implementation(size, rng):
    rows = stream(rng, proportional=True)
    count = len(rows[0])
    new, new_result = feed(LandmarkMap, rows, chunked(count, size),
                           max_consecutive_rejections=3)
    old, old_result = feed(landmark_map_reference.LandmarkMap, rows, chunked(count, size),
                           max_consecutive_rejections=3)
    # The stream exercises gating, rebuilding and several sources.
    assert sum(new_result[1].values()) >= 30 and new_result[3]
    assert new_result == old_result            # the same decisions, row for row
    a, b = new.snapshot(), old.snapshot()
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.observations, b.observations)
    np.testing.assert_allclose(a.m, b.m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.P_dep, b.P_dep, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize('trial', range(20))
def test_the_fold_equals_split_ci_with_the_public_functions(trial, rng):
    # Sources sorted by determinant, folded pairwise with the public split CI and
    # its weight (searched from 0.5, as the map's fold does), dependent parts
    # indefinite or not.
    count = 6
    R_ind = random_spd(rng, 2, count, scale=0.2, eps=0.01)
    R_dep = random_spd(rng, 2, count, scale=0.2, eps=0.0) * rng.uniform(0, 1, (count, 1, 1))
    z = rng.normal(0.0, 0.3, (count, 2))
    parts = _source_sums._SourceParts()
    rows = np.zeros(count, np.int64)
    parts.add(rows, np.arange(count), z, R_ind, R_dep)
    m, P_ind, P_dep = parts.combine(np.array([0]))
    estimates = []
    for Y, y, Q in zip(parts.Y[:count], parts.y[:count], parts.Q[:count]):
        P_i = np.linalg.inv(np.array([[Y[0], Y[1]], [Y[1], Y[2]]]))
        D = P_i @ Q.reshape(2, 2)
        estimates.append((P_i @ y, P_i, 0.5 * (D + D.T)))
    estimates.sort(key=lambda e: np.linalg.det(e[1] + e[2]))
    m_ref, P_i_ref, P_d_ref = estimates[0]
    for m2, P_i2, P_d2 in estimates[1:]:
        omega = gaussian.split_covariance_intersection_omega(P_i_ref, P_d_ref, P_i2, P_d2)
        m_ref, P_i_ref, P_d_ref = gaussian.split_covariance_intersection(
            m_ref, P_i_ref, P_d_ref, m2, P_i2, P_d2, omega)
    np.testing.assert_allclose(m[0], m_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(P_ind[0], P_i_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(P_dep[0], P_d_ref, rtol=1e-9, atol=1e-12)


def test_batch_equals_rows_one_by_one_with_many_rejections(rng):
    # Outliers and moves: rows rejected, landmarks rebuilt in the middle of a batch
    # (the compiled run gives way to the rounds then).
    rows = stream(rng, count=900, landmarks=15, outliers=0.15, movers=3)
    count = len(rows[0])
    one_by_one, expected = feed(LandmarkMap, rows, chunked(count, 1),
                                max_consecutive_rejections=3)
    assert sum(expected[1].values()) >= 100 and len(expected[3]) >= 3
    for size in (7, 150, count):
        batched, result = feed(LandmarkMap, rows, chunked(count, size),
                               max_consecutive_rejections=3)
        assert result == expected
        assert_same_map(batched, one_by_one)


@pytest.mark.parametrize('seed', range(6))
def test_rebuilds_in_a_batch_leave_the_others_streaks_as_row_by_row(seed):
    # Many landmarks rebuilt part way through small batches: the landmarks the batch
    # keeps take their rejection streaks from the run without the rebuilt ones' rows
    # (a streak array of the whole run, read at the kept rows, fails this).
    rows = stream(np.random.default_rng(seed), count=600, landmarks=8, outliers=0.3,
                  movers=4)
    count = len(rows[0])
    one_by_one, _ = feed(LandmarkMap, rows, chunked(count, 1), max_consecutive_rejections=3)
    for size in (20, 60):
        batched, _ = feed(LandmarkMap, rows, chunked(count, size), max_consecutive_rejections=3)
        assert_same_map(batched, one_by_one)


def test_rows_are_gated_against_a_reference_refreshed_on_schedule(rng, fold_path):
    # The reference is the estimate after the last observation at which gate_due
    # held: row by row, and after batches of any size.
    rows = stream(rng, count=1200, landmarks=6, outliers=0.05, movers=0, sources=3)
    count = len(rows[0])
    expected = {}
    landmark_map = LandmarkMap(FUSION)
    for part in chunked(count, 1):
        ids, z, R, R_dep, names, stamps = (x[part] for x in rows)
        landmark_map.update(ids, z, R, R_dep, names.tolist(), stamps)
        row = landmark_map._lookup(ids)[0]
        n = int(landmark_map.observations[row])
        if landmark_map.confirmed[row] and _fold_kernel.gate_due(n) and n not in expected.get(
                row, {}):
            P = landmark_map.cov_ind[row] + landmark_map.cov_dep[row]
            expected.setdefault(row, {})[n] = np.concatenate(
                [landmark_map.mean[row], P[[0, 0, 1], [0, 1, 1]]])
        last = max(k for k in expected.get(row, {0: None}) if k <= n) if row in expected else 0
        if last:
            np.testing.assert_array_equal(landmark_map.gate[row], expected[row][last])
    assert min(landmark_map.observations[:landmark_map._count]) > 100
    stale = ~np.all(landmark_map.gate[:6, :2] == landmark_map.mean[:6], axis=1)
    assert stale.any()
    batched, _ = feed(LandmarkMap, rows, chunked(count, 300))
    for m in (batched, landmark_map):
        assert m._count == 6
    np.testing.assert_array_equal(batched.gate[np.argsort(batched.ids[:6])],
                                  landmark_map.gate[np.argsort(landmark_map.ids[:6])])


def test_loaded_landmarks_are_gated_against_their_loaded_estimate(rng):
    # A loaded estimate need not be the fold of its sums; the first row of a batch is
    # gated against the estimate the map holds, as row by row.
    rows = stream(rng, count=600, landmarks=20, outliers=0.05, movers=0)
    first, _ = feed(LandmarkMap, rows, [slice(0, 300)])
    records = first.to_records()
    for record in records:          # the estimate moved away from its sums' fold
        record['mean'] = [x + 0.05 for x in record['mean']]
    maps = []
    for chunks in (chunked(300, 1), [slice(0, 300)]):
        landmark_map = LandmarkMap(FUSION)
        landmark_map.load_records(records)
        for part in chunks:
            ids, z, R, R_dep, names, stamps = (x[300:][part] for x in rows)
            landmark_map.update(ids, z, R, R_dep, names.tolist(), stamps)
        maps.append(landmark_map)
    assert_same_map(*maps)


def assert_kept_folds_are_current(landmark_map):
    """Assert every kept fold is the fresh fold of its landmark's sums, and the map's."""
    parts = landmark_map._method.parts
    rows = np.flatnonzero(parts.kept[:landmark_map._count])
    for row in rows.tolist():
        lo, hi = np.searchsorted(parts.keys, [row << _source_sums._SOURCE_BITS,
                                              (row + 1) << _source_sums._SOURCE_BITS])
        table = parts.table[parts.slots[lo:hi]]
        assert (table[:, _fold_kernel.VALID] == 1.0).all()
        rank = table[:, _fold_kernel.RANK].astype(int)
        assert sorted(rank.tolist()) == list(range(hi - lo))
        last = table[rank == hi - lo - 1][0, _fold_kernel.PREFIX:_fold_kernel.PREFIX + 8]
        m, P_ind, P_dep = (v[0] for v in parts.combine(np.array([row], np.int64)))
        np.testing.assert_array_equal(last, np.concatenate(
            [m, P_ind[[0, 0, 1], [0, 1, 1]], P_dep[[0, 0, 1], [0, 1, 1]]]))
        np.testing.assert_array_equal(landmark_map.mean[row], m)
        np.testing.assert_array_equal(landmark_map.cov_ind[row], P_ind)
    return len(rows)


@pytest.mark.parametrize('lazy', [False, True])
def test_kept_folds_stay_current_through_every_other_change(rng, monkeypatch, fold_path, lazy):
    # The compiled batch keeps each landmark's fold between batches; rebuilds, merges,
    # estimates set from outside, forgetting, a batch the map rolls back and an update
    # that fails half way each leave a kept fold current or drop it. Lazy: updates
    # leave folds pending (settle=False), two batches at a time, across those changes.
    if fold_path == 'numpy':
        pytest.skip('only the compiled batch keeps folds')
    rows = stream(rng, count=2400, landmarks=30, outliers=0.08, movers=3)
    count = len(rows[0])
    landmark_map = LandmarkMap(FUSION, max_consecutive_rejections=3)
    twin = LandmarkMap(FUSION, max_consecutive_rejections=3)     # never fails
    original, rebuilt_in = LandmarkMap._apply_run, LandmarkMap._rebuilt_in
    failures, outcomes = [], []

    def failing(self, *args):
        original(self, *args)
        if self is landmark_map and failures:
            failures.pop()
            raise RuntimeError('failed half way')

    def noting(self, run):
        rebuilt, streak = rebuilt_in(self, run)
        if self is landmark_map:      # all taken, some landmarks undone, all undone
            outcomes.append('all' if not rebuilt.any() else 'none' if rebuilt.all() else 'some')
        return rebuilt, streak
    monkeypatch.setattr(LandmarkMap, '_apply_run', failing)
    monkeypatch.setattr(LandmarkMap, '_rebuilt_in', noting)
    kept, pending = [], []
    for k, part in enumerate(chunked(count, 200)):
        ids, z, R, R_dep, names, stamps = (x[part] for x in rows)
        if k == 3:      # other rows than the next batch's: nothing of them may stay
            failures.append(True)
            other = slice(part.start + 1000, part.stop + 1000)
            with pytest.raises(RuntimeError):
                landmark_map.update(*(x[other] for x in rows[:4]), rows[4][other].tolist(),
                                    rows[5][other], settle=not lazy)
            assert_same_map(landmark_map, twin)
        for target in (landmark_map, twin):
            target.update(ids, z, R, R_dep, names.tolist(), stamps,
                          settle=target is twin or not lazy)
            if k == 5:
                confirmed = target.ids[:target._count][target.confirmed[:target._count]]
                assert target.merge(int(confirmed[0]), int(confirmed[1]))
                target.set_estimate(int(confirmed[2]), [1.0, 2.0], np.eye(2), 0.5 * np.eye(2),
                                    'outside')
                target.forget([int(confirmed[3])])
        if lazy and k % 2 == 0:
            pending.append(int((landmark_map._method.parts.pending != -1).sum()))
            continue
        assert_same_map(landmark_map, twin)
        kept.append(assert_kept_folds_are_current(landmark_map))
    assert {'all', 'some'} <= set(outcomes)       # kept, and partly rolled back
    assert sum(k > 20 for k in kept) >= (4 if lazy else 8)
    assert not lazy or max(pending) > 10


def test_a_long_stream_of_many_sources_is_the_same_compiled_numpy_and_row_by_row(
        rng, monkeypatch, fold_path):
    # 30 sources, rebuilds and outliers, cut at random places: the compiled batch
    # with its kept folds, the numpy batch and the rows one by one give the same map,
    # bit for bit, and the same decisions.
    if fold_path == 'numpy':
        pytest.skip('compares both paths itself')
    rows = stream(rng, count=2000, landmarks=40, sources=30, outliers=0.05, movers=3)
    cuts = np.sort(rng.choice(np.arange(1, 2000), 25, replace=False))
    chunks = [slice(a, b) for a, b in zip(np.r_[0, cuts], np.r_[cuts, 2000])]
    compiled, expected = feed(LandmarkMap, rows, chunks, max_consecutive_rejections=3)
    one_by_one, result = feed(LandmarkMap, rows, chunked(2000, 1), max_consecutive_rejections=3)
    assert result == expected and sum(expected[1].values()) >= 50 and expected[3]
    assert_same_map(compiled, one_by_one)
    monkeypatch.setattr(_fold_kernel, 'load', lambda: None)
    monkeypatch.setattr(_fold_kernel, 'AVAILABLE', False)
    numpy_map, result = feed(LandmarkMap, rows, chunks, max_consecutive_rejections=3)
    assert result == expected
    assert_same_map(numpy_map, compiled)


@pytest.mark.parametrize('size', [1, 40, 333])
def test_lazy_updates_read_the_same_map_as_settled_ones(rng, fold_path, size):
    # update(settle=False) then reads at random times (estimate, snapshot of some
    # IDs, records): the same numbers as updates that settle, row by row.
    rows = stream(rng, count=1500, landmarks=25, sources=8, outliers=0.05, movers=2)
    count = len(rows[0])
    expected, result = feed(LandmarkMap, rows, chunked(count, 1), max_consecutive_rejections=3)
    lazy = LandmarkMap(FUSION, max_consecutive_rejections=3)
    total = [Counter(), Counter(), [], []]
    left = 0
    for k, part in enumerate(chunked(count, size)):
        ids, z, R, R_dep, names, stamps = (x[part] for x in rows)
        got = lazy.update(ids, z, R, R_dep, names.tolist(), stamps, settle=False)
        for i, value in enumerate((got.accepted, got.rejected, got.confirmed, got.reinitialised)):
            total[i] += value
        if fold_path == 'compiled':
            left = max(left, int((lazy._method.parts.pending != -1).sum()))
        if rng.uniform() < 0.1:
            some = rng.choice(ids, 3)
            snapshot = lazy.snapshot(some)
            for landmark_id, m in zip(snapshot.ids.tolist(), snapshot.m):
                np.testing.assert_array_equal(lazy.estimate(landmark_id)[0], m)
    assert (total[0], total[1], sorted(total[2]), sorted(total[3])) == result
    assert_same_map(lazy, expected)
    assert left > (0 if fold_path == 'compiled' and size > 1 else -1)
