"""The compiled split-CI fold and batch run (``core._fold_kernel``) against numpy."""

from conftest import random_spd
from landmark_ros.core import _fold_kernel
from landmark_ros.core import _pair_index
from landmark_ros.core import _source_sums
from landmark_ros.fusion import landmark_map as landmark_map_module
from landmark_ros.core._arrays import mahalanobis_sq_2x2, power_of_4_scale
import numpy as np
import pytest


@pytest.fixture
def compiled():
    """Return the compiled fold; skip without numba."""
    kernel = _fold_kernel.load()
    if kernel is None:
        pytest.skip('numba is not installed: no compiled kernel')
    return kernel


def random_sums(rng, count, width, extreme=False):
    """Return per-source sums ``Y, y, Q, valid`` of ``count`` landmarks, ``width`` sources."""
    A = rng.normal(0.0, 1.0, (count, width, 2, 2))
    R = A @ np.swapaxes(A, -1, -2) + 0.01 * np.eye(2)
    B = rng.normal(0.0, 1.0, (count, width, 2, 2))
    D = B @ np.swapaxes(B, -1, -2) * rng.uniform(0.0, 2.0, (count, width, 1, 1))
    if extreme:
        R *= 10.0 ** rng.uniform(-6.0, 6.0, (count, width, 1, 1))
    D[rng.uniform(size=(count, width)) < 0.1] = 0.0      # no dependent part
    z = rng.normal(0.0, 100.0, (count, width, 2))
    Y, y, Q = _source_sums._terms(z.reshape(-1, 2), R.reshape(-1, 2, 2),
                                  D.reshape(-1, 2, 2))
    n = rng.integers(1, 40, (count, width, 1))
    Y, y, Q = Y.reshape(count, width, 3) * n, y.reshape(count, width, 2) * n, Q.reshape(
        count, width, 4) * n
    Q[rng.uniform(size=(count, width)) < 0.1, 1] *= -3.0   # indefinite sym(Y^-1 Q)
    valid = rng.uniform(size=(count, width)) < 0.7
    valid[np.arange(count), rng.integers(0, width, count)] = True
    return Y, y, Q, valid


@pytest.mark.parametrize('width', [1, 2, 5, 50])
@pytest.mark.parametrize('extreme', [False, True])
def test_compiled_fold_equals_numpy_bit_for_bit(compiled, rng, width, extreme):
    Y, y, Q, valid = random_sums(rng, max(2000 // width, 20), width, extreme)
    expected = _source_sums._fold_numpy(Y, y, Q, valid)
    got = compiled(Y, y, Q, valid)
    for a, b in zip(expected, got):
        assert a.shape == b.shape
        np.testing.assert_array_equal(a, b)


def test_fold_dispatches_to_the_kernel(compiled, rng):
    Y, y, Q, valid = random_sums(rng, 50, 4)
    for a, b in zip(_source_sums._fold(Y, y, Q, valid), compiled(Y, y, Q, valid)):
        np.testing.assert_array_equal(a, b)


def fold_one(sums, valid, lo, hi):
    """Return the packed numpy fold of the pairs ``lo:hi``."""
    m, P_ind, P_dep = _source_sums._fold_numpy(
        sums[None, lo:hi, :3], sums[None, lo:hi, 3:5], sums[None, lo:hi, 5:],
        valid[None, lo:hi])
    return np.concatenate([m[0], P_ind[0][[0, 0, 1], [0, 1, 1]], P_dep[0][[0, 0, 1], [0, 1, 1]]])


def packed_gate(m):
    """Return the gate reference (mean, entries of ``P_ind + P_dep``) of a packed estimate."""
    return np.concatenate([m[:2], m[2:5] + m[5:8]])


def loop_run(landmark, pair, terms, z, R, start, sums, valid, state, gate, observations,
             threshold):
    """
    Row by row with the numpy gate and fold: what ``_fold_kernel.run`` must give.

    Also counts the rows that the current estimate would have decided the other way
    (the reference is older): the test is blind to the reference unless there are some.
    """
    accepted = np.zeros(len(landmark), bool)
    other_way = 0
    for i, k in enumerate(landmark.tolist()):
        g = gate[k]
        d2 = mahalanobis_sq_2x2(np.array(z[i, 0] - g[0]), np.array(z[i, 1] - g[1]),
                                *(g[2:5] + R[i, :3] + R[i, 3:]))
        m = state[k]
        now = mahalanobis_sq_2x2(np.array(z[i, 0] - m[0]), np.array(z[i, 1] - m[1]),
                                 *((m[2:5] + m[5:8]) + R[i, :3] + R[i, 3:]))
        other_way += bool(d2 <= threshold) != bool(now <= threshold)
        if not d2 <= threshold:
            continue
        accepted[i] = True
        sums[pair[i]] += terms[i]
        valid[pair[i]] = True
        state[k] = fold_one(sums, valid, start[k], start[k + 1])
        observations[k] += 1
        if _fold_kernel.gate_due(observations[k]):
            gate[k] = packed_gate(state[k])
    return accepted, other_way


@pytest.mark.parametrize('lazy, dependent', [(False, 1.0), (True, 1.0), (True, 0.98)])
@pytest.mark.parametrize('sources', [5, 50])
def test_run_equals_gating_and_folding_row_by_row_batch_after_batch(
        compiled, rng, sources, lazy, dependent):
    # The run keeps each landmark's fold per slot between batches and refolds from
    # the first place that changed: one changed source moves to its new place, with
    # several the changed ones get new estimates and the unchanged first places keep
    # theirs. Pairs are reached through a shuffled slot index, some hold no
    # observation yet. Rows are gated against references refreshed on the schedule of
    # ``gate_due``. Lazy: folds left pending carry over to the next batch; ``settle``
    # does them. ``dependent``: least fraction of a row's covariance that is dependent
    # (0.98: a source's estimate can grow and move to a later place).
    landmarks, count = 30, 300
    width = rng.integers(1, sources + 1, landmarks)
    start = np.concatenate([[0], np.cumsum(width)])
    Y, y, Q, _ = random_sums(rng, int(start[-1]), 1)
    sums = np.concatenate([Y[:, 0], y[:, 0], Q[:, 0]], axis=1)
    valid = rng.uniform(size=len(sums)) < 0.7
    valid[start[:-1]] = True
    state = np.empty((landmarks, 8))
    for k in range(landmarks):
        state[k] = fold_one(sums, valid, start[k], start[k + 1])
    gate = np.array([packed_gate(m) for m in state])
    observations = rng.integers(1, 300, landmarks)
    key_slots = rng.permutation(len(sums) + 7)[:len(sums)]
    table = np.full((len(sums) + 7, _fold_kernel.COLUMNS), np.nan)
    table[key_slots, :9] = sums
    table[key_slots, _fold_kernel.VALID] = valid
    kept = np.zeros(landmarks, bool)
    new_state, new_gate, new_observations = state.copy(), gate.copy(), observations.copy()
    pending = np.full(landmarks, -1, np.int64)
    threshold = 9.21
    other_way = 0
    for batch in range(3):
        landmark = rng.integers(0, landmarks, count)
        pair = start[landmark] + rng.integers(0, 1 << 30, count) % width[landmark]
        R_ind = np.stack([np.full(count, 0.04), rng.uniform(-0.01, 0.01, count),
                          np.full(count, 0.05)], axis=1)
        R_dep = R_ind * rng.uniform(1.0 - dependent, 1.0, (count, 1))
        R_full = np.zeros((count, 2, 2))
        R_full[:, 0, 0], R_full[:, 0, 1], R_full[:, 1, 0], R_full[:, 1, 1] = (
            R_ind[:, 0], R_ind[:, 1], R_ind[:, 1], R_ind[:, 2])
        D_full = R_full * (R_dep[:, :1] / R_ind[:, :1])[:, :, None]
        # About a third of the rows far off: rejected.
        z = state[landmark, :2] + rng.normal(0.0, 0.2, (count, 2)) * np.where(
            rng.uniform(size=(count, 1)) < 0.3, 30.0, 1.0)
        terms = np.concatenate(_source_sums._terms(z, R_full - D_full, D_full), axis=1)
        R = np.concatenate([R_ind - R_dep, R_dep], axis=1)
        args = (landmark, pair, terms, z, R, start)
        expected, flipped = loop_run(*args, sums, valid, state, gate, observations, threshold)
        other_way += flipped
        at = rng.permutation(count)         # the rows' places in the batch arrays
        z_at, R_ind_at, R_dep_at = (np.empty_like(x) for x in (z, R_full, D_full))
        z_at[at], R_ind_at[at], R_dep_at[at] = z, R_full - D_full, D_full
        order = np.argsort(landmark, kind='stable')
        before = table[:, :9].copy()
        accepted, (slots, saved, owner) = _fold_kernel.run(
            landmark, order, pair, at, z_at, R_ind_at, R_dep_at, start[:-1], start[1:],
            key_slots, table, kept, new_state, new_gate, new_observations, pending, lazy,
            threshold)
        assert 10 < accepted.sum() < count - 10     # both branches, many times
        np.testing.assert_array_equal(accepted, expected)
        # The slots the batch changed, once each, with their sums before it and their
        # landmark.
        pair_of = np.full(len(table), -1)
        pair_of[key_slots] = np.arange(len(key_slots))
        assert sorted(slots.tolist()) == sorted(key_slots[np.unique(pair[accepted])].tolist())
        np.testing.assert_array_equal(saved, before[slots])
        np.testing.assert_array_equal(owner, np.searchsorted(start, pair_of[slots], 'right') - 1)
        left = pending != -1
        assert left.any() == lazy
        if lazy and batch and sources == 5:    # one changed pair or several, kept folds
            assert (pending[left] == -2).any() and (pending[left] >= 0).any()
            assert (kept & (pending >= 0)).any()
        # Several batches pile up pending folds before one settle.
        if not lazy or batch == 2:
            _fold_kernel.settle(start[:-1], start[1:], pending, key_slots, table, kept,
                                new_state)
            assert (pending == -1).all()
            np.testing.assert_array_equal(new_state, state)
            assert kept[np.unique(landmark[accepted])].all()
        np.testing.assert_array_equal(new_gate, gate)
        np.testing.assert_array_equal(new_observations, observations)
        np.testing.assert_array_equal(table[key_slots, :9], sums)
        np.testing.assert_array_equal(table[key_slots, _fold_kernel.VALID] != 0, valid)
    assert other_way > 0


def test_a_partial_refold_is_the_whole_refold_bit_for_bit(compiled, rng):
    # Several sources of a landmark with a kept fold changed: their estimates are
    # redone, the others' kept, the fold redone from the first place that changed.
    # Changed sources move either way (a large dependent part can grow an estimate),
    # which shifts unchanged ones to other places before the first changed one.
    width, limits = 5, _fold_kernel._limits()
    Y, y, Q, _ = random_sums(rng, 2000 * width, 1)
    shifted = 0
    for trial in range(2000):
        table = np.zeros((width, _fold_kernel.COLUMNS))
        rows = slice(trial * width, (trial + 1) * width)
        table[:, :9] = np.concatenate([Y[rows, 0], y[rows, 0], Q[rows, 0]], axis=1)
        table[:, _fold_kernel.VALID] = 1.0
        key_slots, order = rng.permutation(width), np.empty(width, np.int64)
        _fold_kernel._refold(0, width, key_slots, table, order, limits, False)
        rank = table[:, _fold_kernel.RANK].copy()
        changed = rng.choice(width, rng.integers(2, 4), replace=False)
        for j in changed:
            R = random_spd(rng, 2)
            share = rng.uniform(0.9, 0.999)
            _fold_kernel._add_terms(table[j], 0.1, -0.2, (1.0 - share) * R, share * R)
            table[j, _fold_kernel.SIZE] = np.nan
        whole = table.copy()
        last = _fold_kernel._refold(0, width, key_slots, table, order, limits, True)
        expected = _fold_kernel._refold(0, width, key_slots, whole, order, limits, False)
        np.testing.assert_array_equal(table[last, _fold_kernel.PREFIX:],
                                      whole[expected, _fold_kernel.PREFIX:])
        np.testing.assert_array_equal(table[:, _fold_kernel.RANK], whole[:, _fold_kernel.RANK])
        first = min(int(whole[j, _fold_kernel.RANK]) for j in changed)
        place = whole[:, _fold_kernel.RANK]
        shifted += bool(((place < first) & (place != rank)).any())
    assert shifted > 100


def test_the_gate_schedule_is_the_kernels_and_refreshes_4_times_per_doubling(compiled):
    n = np.arange(0, 5000)
    due = _fold_kernel.gate_due(n)
    assert due[:8].all()
    assert np.flatnonzero(due[8:64]).tolist() == [i - 8 for i in (
        8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56)]
    for lo in (64, 128, 1024, 2048):
        assert due[lo:2 * lo].sum() == 4
    assert all(_fold_kernel._gate_due(int(k)) == bool(d) for k, d in zip(n, due))
    # The reference never holds less than 4/5 of the observations, and gets close.
    last = np.maximum.accumulate(np.where(due, n, 0))
    assert 4 / 5 - 1e-12 <= (last[1:] / n[1:]).min() < 0.81


def test_group_is_a_stable_argsort_and_unique(compiled, rng):
    for rows in (rng.integers(0, 50, 1000), rng.integers(0, 100_000, 300), np.array([7]),
                 np.zeros(5, np.int64)):
        order, distinct, index = _pair_index.group(rows)
        expected, inverse = np.unique(rows, return_inverse=True)
        np.testing.assert_array_equal(order, np.argsort(rows, kind='stable'))
        np.testing.assert_array_equal(distinct, expected)
        np.testing.assert_array_equal(index, inverse.reshape(-1))


def test_bounds_is_searchsorted_of_both_ends(compiled, rng):
    shift = 24
    for size, count in ((3000, 500), (0, 4), (5, 1), (3000, 2000)):
        keys = np.unique((rng.integers(0, 2000, size) << shift) | rng.integers(0, 50, size))
        landmarks = np.unique(rng.integers(0, 2100, count))   # some without keys
        lo, hi = _pair_index.bounds(keys, landmarks, shift)
        np.testing.assert_array_equal(lo, np.searchsorted(keys, landmarks << shift))
        np.testing.assert_array_equal(hi, np.searchsorted(keys, (landmarks + 1) << shift))
        assert size < 1000 or (hi > lo).any()


def test_locate_finds_each_key_among_its_landmarks_pairs(compiled, rng):
    keys = np.unique(rng.integers(0, 10_000, 3000))
    rows = keys // 100
    landmarks = np.unique(rows)
    lo, hi = np.searchsorted(rows, landmarks), np.searchsorted(rows, landmarks, side='right')
    landmark = rng.integers(0, len(landmarks), 2000)
    wanted = landmarks[landmark] * 100 + rng.integers(0, 100, 2000)
    position = _pair_index.locate(keys, lo, hi, landmark, wanted)
    there = np.isin(wanted, keys)
    assert there.any() and not there.all()
    np.testing.assert_array_equal(position[~there], -1)
    np.testing.assert_array_equal(keys[position[there]], wanted[there])


def test_merge_is_insert_at_the_sorted_places(compiled, rng):
    for size, extra in ((0, 5), (1000, 0), (1000, 300), (10, 1000)):
        both = rng.choice(1 << 40, size + extra, replace=False)
        keys, new = np.sort(both[:size]), np.sort(both[size:])
        slots, new_slots = rng.integers(0, 1 << 20, size), rng.integers(0, 1 << 20, extra)
        got_keys, got_slots = _pair_index.merge(keys, slots, new, new_slots)
        at = np.searchsorted(keys, new)
        np.testing.assert_array_equal(got_keys, np.insert(keys, at, new))
        np.testing.assert_array_equal(got_slots, np.insert(slots, at, new_slots))


def test_turned_off_by_the_environment(monkeypatch):
    monkeypatch.setattr(_fold_kernel, '_tried', False)
    monkeypatch.setattr(_fold_kernel, 'fold', None)
    monkeypatch.setattr(_fold_kernel, 'AVAILABLE', False)
    monkeypatch.setenv('LANDMARK_ROS_NUMBA', '0')
    assert _fold_kernel.load() is None
    assert not _fold_kernel.AVAILABLE


def test_a_clean_batch_is_taken_at_once_and_only_a_rebuilt_landmark_goes_round_by_round(
        compiled, rng, monkeypatch):
    # The kernel's outcome is taken for every landmark the batch does not rebuild; the
    # rows of the one it rebuilds go through the rounds (and only those).
    applied, rounds = [], []
    apply_run = landmark_map_module.LandmarkMap._apply_run
    update_confirmed = landmark_map_module.LandmarkMap._update_confirmed

    def spy_apply(self, rows, *args):
        applied.append(sorted(set(self.ids[rows].tolist())))
        return apply_run(self, rows, *args)

    def spy_rounds(self, rows, *args):
        rounds.append(sorted(set(self.ids[rows].tolist())))
        return update_confirmed(self, rows, *args)
    monkeypatch.setattr(landmark_map_module.LandmarkMap, '_apply_run', spy_apply)
    monkeypatch.setattr(landmark_map_module.LandmarkMap, '_update_confirmed', spy_rounds)
    landmark_map = landmark_map_module.LandmarkMap(max_consecutive_rejections=2)
    truth = rng.uniform(-20.0, 20.0, (10, 2))
    ids = np.repeat(np.arange(10), 4)
    R = np.tile(0.01 * np.eye(2), (len(ids), 1, 1))
    names = [f'robot{k % 3}' for k in range(len(ids))]
    z = truth[ids] + rng.normal(0.0, 0.1, (len(ids), 2))
    landmark_map.update(ids, z, R, 0.5 * R, names, 1)          # confirms all ten
    assert len(landmark_map) == 10 and not applied
    rounds.clear()      # rows of landmarks confirmed earlier in that batch
    z = truth[ids] + rng.normal(0.0, 0.1, (len(ids), 2))
    result = landmark_map.update(ids, z, R, 0.5 * R, names, 2)
    assert applied == [list(range(10))] and not rounds
    assert sum(result.accepted.values()) == len(ids)
    z = truth[ids] + rng.normal(0.0, 0.1, (len(ids), 2))
    z[ids == 3] += 5.0                                          # landmark 3 moved
    result = landmark_map.update(ids, z, R, 0.5 * R, names, 3)
    assert applied[1:] == [[k for k in range(10) if k != 3]]
    assert rounds == [[3]] * 4 and result.reinitialised == [3]
    assert sum(result.accepted.values()) == len(ids) - 2       # two rejected, then rebuilt


def test_the_compiled_scale_is_the_numpy_scale_at_every_magnitude(compiled, rng):
    # The kernel reads frexp's exponent from the bits of normal numbers and calls
    # frexp / ldexp otherwise: subnormal, huge, zero, inf and NaN entries included.
    special = np.array([0.0, 5e-324, 1e-310, 2.2250738585072014e-308, 1e-300, 0.3, 1.0, 3.0,
                        4.0, 4.0000000000000001, 1e300, 1.7976931348623157e308, np.inf, np.nan,
                        -2.5, -1e-320])
    a = np.concatenate([np.repeat(special, len(special)), rng.normal(0, 1, 500) * 10.0 ** (
        rng.uniform(-320, 308, 500))])
    c = np.concatenate([np.tile(special, len(special)), rng.normal(0, 1, 500) * 10.0 ** (
        rng.uniform(-320, 308, 500))])
    with np.errstate(all='ignore'):
        expected = power_of_4_scale(a, c)
        got = np.array([_fold_kernel._scale4(x, y, 0.0, 0.0) for x, y in zip(a, c)])
    np.testing.assert_array_equal(got, expected)
    assert np.isinf(got).any() and (got < 2.3e-308).any()    # both ends reached


@pytest.mark.parametrize('settle', [True, False])
def test_pairs_of_gated_out_rows_give_their_slots_back(compiled, rng, settle):
    # Rows gated out on (landmark, source) pairs new to the map, batch after batch,
    # leave no slot behind, and moving the used new slots down over the unused ones
    # (pending folds included) keeps the map what row-by-row updates give.
    batched = landmark_map_module.LandmarkMap(max_consecutive_rejections=1000)
    single = landmark_map_module.LandmarkMap(max_consecutive_rejections=1000)
    truth = rng.uniform(-20.0, 20.0, (20, 2))

    def batch(index, count):
        ids = rng.integers(0, 20, count)
        R = np.tile(0.01 * np.eye(2), (count, 1, 1))
        z = truth[ids] + rng.normal(0.0, 0.1, (count, 2))
        names = [f'robot{k}' for k in rng.integers(0, 3, count)]
        for k in rng.choice(count, 4, replace=False):
            names[k] = f'intruder{index}'                   # a new pair, gated out
            z[k] += 5.0
        for k in rng.choice(count, 2, replace=False):
            names[k] = f'late{index}'                       # a new pair, accepted
        return ids, z, R, 0.5 * R, names

    # 40 observations each: a landmark's gate reference is then refreshed every 8th,
    # so its fold may wait with one changed (new) slot pending.
    ids = np.repeat(np.arange(20), 40)
    first = (ids, truth[ids] + rng.normal(0.0, 0.1, (800, 2)),
             np.tile(0.01 * np.eye(2), (800, 1, 1)))
    for landmark_map in (batched, single):
        landmark_map.update(*first, np.tile(0.005 * np.eye(2), (800, 1, 1)),
                            [f'robot{k % 3}' for k in range(800)], 1)
    rejected = 0
    for index in range(12):
        ids, z, R, R_dep, names = batch(index, 30)
        result = batched.update(ids, z, R, R_dep, names, 2 + index, settle=settle)
        rejected += sum(result.rejected.values())
        for k in range(len(ids)):
            single.update(ids[k:k + 1], z[k:k + 1], R[k:k + 1], R_dep[k:k + 1], names[k:k + 1],
                          2 + index, settle=settle)
        for landmark_map in (batched, single):
            parts = landmark_map._method.parts
            # Every slot holds a pair: none left over from a gated-out row.
            assert parts.count == len(parts.keys)
            assert sorted(parts.slots.tolist()) == list(range(parts.count))
            assert_pending_slots_are_own(parts, len(landmark_map))
    assert rejected >= 12 * 4 - 8
    for got, expected in zip(batched.snapshot(), single.snapshot()):
        np.testing.assert_array_equal(got, expected)


def assert_pending_slots_are_own(parts, rows):
    """Assert that a landmark's pending single changed slot is one of its own pairs'."""
    for row, slot in enumerate(parts.pending[:rows].tolist()):
        if slot >= 0:
            lo, hi = parts._bounds(np.array([row]))
            assert slot in parts.slots[lo[0]:hi[0]].tolist()


def test_a_batch_rebuilt_whole_gives_its_new_slots_back(compiled, rng):
    # Every landmark of the batch rebuilt: the whole run is undone, its new pairs and
    # their slots with it.
    landmark_map = landmark_map_module.LandmarkMap(max_consecutive_rejections=2)
    R = np.tile(0.01 * np.eye(2), (6, 1, 1))
    landmark_map.update(np.zeros(6, int), rng.normal(0.0, 0.1, (6, 2)), R, 0.5 * R,
                        [f'robot{k % 2}' for k in range(6)], 1)
    parts = landmark_map._method.parts
    before = parts.count
    result = landmark_map.update(np.zeros(3, int), 5.0 + rng.normal(0.0, 0.1, (3, 2)), R[:3],
                                 0.5 * R[:3], ['intruder'] * 3, 2)
    assert result.reinitialised == [0]
    # The run is undone with its new slot; the rounds then rebuild the landmark from
    # the new source: its old pairs go (their slots wait for a compaction), one comes.
    assert len(parts.keys) == 1 and parts.count == before + 1


def test_a_compaction_keeps_the_map_and_gives_back_every_free_slot(compiled, rng, monkeypatch):
    # Landmarks rebuilt and forgotten leave slots without pairs; past the slack a
    # compaction moves the live ones to the front, pending folds included, and the
    # map goes on as one that never compacted.
    maps = [landmark_map_module.LandmarkMap(max_consecutive_rejections=2) for _ in range(2)]
    compactions = []
    compact = _source_sums._SourceParts._compact

    def spy(self):
        compactions.append(int((self.pending >= 0).sum()))
        compact(self)
    monkeypatch.setattr(_source_sums._SourceParts, '_compact', spy)
    truth = rng.uniform(-20.0, 20.0, (30, 2))
    for step in range(10):
        # 40 observations of each first (its fold may then wait with one changed slot
        # pending: gate refreshes every 8th), then a few rows at a time.
        ids = np.repeat(np.arange(30), 40) if step == 0 else rng.integers(0, 30, 45)
        R = np.tile(0.01 * np.eye(2), (len(ids), 1, 1))
        z = truth[ids] + rng.normal(0.0, 0.1, (len(ids), 2))
        moved = rng.choice(30, 3, replace=False)
        truth[moved] += 3.0                                 # rebuilt when next seen
        names = [f'robot{k}' for k in rng.integers(0, 4, len(ids))]
        for index, landmark_map in enumerate(maps):
            monkeypatch.setattr(_source_sums, '_COMPACT_SLACK', 0 if index == 0 else 10 ** 9)
            landmark_map.update(ids, z, R, 0.5 * R, names, 1 + step, settle=step == 0)
            assert_pending_slots_are_own(landmark_map._method.parts, len(landmark_map))
            if step == 5:
                landmark_map.forget(int(moved[0]))
    compacted, other = (landmark_map._method.parts for landmark_map in maps)
    assert compactions and max(compactions) > 0        # with single pending slots
    assert len(compacted.keys) == len(other.keys)
    assert compacted.count - len(compacted.keys) <= len(compacted.keys) // 2
    assert other.count - len(other.keys) > len(other.keys) // 2      # what it gave back
    assert_pending_slots_are_own(compacted, len(maps[0]))
    for got, expected in zip(maps[0].snapshot(), maps[1].snapshot()):
        np.testing.assert_array_equal(got, expected)
