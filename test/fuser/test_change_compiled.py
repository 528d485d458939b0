"""Change detection's compiled loops (fusion.compiled) against the numpy code they replace."""

import functools

from hypothesis import given, settings, strategies as st
from landmark_ros.core.gating import chi2_threshold
from landmark_ros.eval import moved_landmark
from landmark_ros.fuser.change_detection import increment, MoveDetector
from landmark_ros.fuser.change_reference import NoiseModel, ReferenceFilter
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fusion import compiled, records
from landmark_ros.fusion.methods import SplitCovarianceIntersection
from landmark_ros.fusion.records import Observation
from landmark_ros.pipeline.config import FuserConfig
import numpy as np
import pytest

CLIP = chi2_threshold(2, 0.999)
KERNELS = ('cusum', 'reference', 'agree')


def _path(monkeypatch, which):
    """Make the detection use numpy (``'numpy'``) or the plain Python kernels."""
    for name in KERNELS:
        original = getattr(compiled, name)
        if which == 'numpy':
            monkeypatch.setattr(compiled, name, lambda *args, **kwargs: None)
        else:
            monkeypatch.setattr(compiled, name, functools.partial(original, python=True))


def _batches(seed, landmarks, count, sources):
    """Rows of static landmarks with some wild ones and one move; batches of 1 to 40."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-5.0, 5.0, (landmarks, 2))
    ids = rng.integers(0, landmarks, count)
    z_true = truth[ids].copy()
    after = np.arange(count) > count // 2
    z_true[after] += (ids[after] == 0)[:, None] * 0.3         # landmark 0 moves
    scale = 10.0 ** rng.uniform(-1.5, -0.5, count)
    P = scale[:, None, None] ** 2 * np.array([[1.0, 0.3], [0.3, 0.8]])
    z = z_true + np.einsum('nij,nj->ni', np.linalg.cholesky(P), rng.standard_normal((count, 2)))
    z[rng.uniform(size=count) < 0.02] += 5.0              # wild rows
    names = np.array([f'/robot{k}' for k in range(sources)])[rng.integers(0, sources, count)]
    cuts = np.unique(np.concatenate([[0, count], rng.integers(0, count, count // 20)]))
    stamps = np.arange(count, dtype=np.int64) * 10_000_000
    return [(ids[a:b], z[a:b], P[a:b], 0.3 * P[a:b], names[a:b], stamps[a:b])
            for a, b in zip(cuts[:-1], cuts[1:])]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), landmarks=st.integers(1, 8),
       count=st.integers(1, 400))
def test_the_plain_reference_loop_is_the_numpy_filter_to_rounding(seed, landmarks, count):
    numpy_path, loop = ReferenceFilter(NoiseModel(), CLIP), ReferenceFilter(NoiseModel(), CLIP)
    for k, (ids, z, P, P_dep, names, stamps) in enumerate(_batches(seed, landmarks, count, 3)):
        if k % 7 == 3:                  # a restarted landmark starts again from its next row
            numpy_path.reset([int(ids[0])])
            loop.reset([int(ids[0])])
        want = numpy_path._white(ids, z, P)
        slots = np.array([loop._slot(int(i)) for i in ids], np.int64)
        got = compiled.reference((loop.x, loop.X, loop.live), slots, z,
                                 np.column_stack([P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]]),
                                 CLIP, python=True)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)
    for i, slot in numpy_path.slots.items():
        np.testing.assert_allclose(loop.x[loop.slots[i]], numpy_path.x[slot], rtol=0, atol=1e-12)
        np.testing.assert_allclose(loop.X[loop.slots[i]], numpy_path.X[slot], rtol=1e-8)


def _cusum_rows(seed, count, sources):
    rng = np.random.default_rng(seed)
    slots = rng.integers(0, 6, count)
    shift = np.where((slots == 0) & (np.arange(count) > count // 3), 4.0, 0.0)
    d2 = np.array([rng.noncentral_chisquare(2, s) if s else rng.chisquare(2) for s in shift])
    g = increment(np.minimum(d2, CLIP), 1.75 ** 2)
    return slots, rng.integers(0, sources, count), g, np.arange(count, dtype=np.int64)


@pytest.mark.parametrize('min_sources', [1, 2, 3])
@pytest.mark.parametrize('seed', range(4))
def test_the_plain_cusum_loop_is_the_row_loop_bit_for_bit(seed, min_sources):
    loop, kernel = (MoveDetector(1e-3, 1.75, CLIP, min_sources=min_sources) for _ in range(2))
    slots, codes, g, sequence = _cusum_rows(seed, 3000, 3)
    for detector in (loop, kernel):
        detector._slots_of((np.arange(6), np.arange(6)))
        for name in ('a', 'b', 'c'):
            detector._code(name)
    alarms = [0, 0]
    for part in np.array_split(np.arange(len(slots)), 37):
        raised = loop._loop(slots[part], codes[part], g[part], sequence[part])
        alarm = compiled.cusum((kernel._E, kernel._C, kernel._first),
                               (slots[part], codes[part], g[part], sequence[part]),
                               kernel.threshold * (1.0 - 1e-12), kernel.cap, python=True)
        assert raised == kernel._raise(slots[part][alarm])
        alarms[0] += len(raised)
        np.testing.assert_array_equal(kernel._E, loop._E)
        np.testing.assert_array_equal(kernel._C, loop._C)
        np.testing.assert_array_equal(kernel._first, loop._first)
    assert alarms[0] > 0                # the shifted landmark raised alarms


def _agreeing_rows(seed, count):
    rng = np.random.default_rng(seed)
    truth = np.zeros((count, 2))
    truth[rng.uniform(size=count) < 0.3] += rng.normal(0.0, 0.5, 2)
    m, P, P_dep = moved_landmark.draw_rows(rng, truth)
    P_dep = P_dep * rng.uniform(0.0, 1.5, (count, 1, 1))
    return [Observation(m[i], P[i] - P_dep[i], P_dep[i], f's{i % 4}', i) for i in range(count)]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), count=st.integers(1, 40))
def test_the_plain_agreeing_loop_is_split_cis_bit_for_bit(seed, count):
    observations = _agreeing_rows(seed, count)
    fuse = SplitCovarianceIntersection().fuse
    want = records.agreeing(observations, CLIP, fuse)          # numpy's fuse row by row
    with pytest.MonkeyPatch.context() as patch:
        _path(patch, 'python')
        got = records.agreeing(observations, CLIP, fuse, 'split_covariance_intersection')
    assert [o.stamp_ns for o in got] == [o.stamp_ns for o in want]


def test_the_compiled_loops_are_the_plain_ones_bit_for_bit_or_absent():
    observations = _agreeing_rows(5, 64)
    z = np.array([o.z for o in observations])
    R = np.array([[o.R_ind[0, 0], o.R_ind[0, 1], o.R_ind[1, 1], o.R_dep[0, 0], o.R_dep[0, 1],
                   o.R_dep[1, 1]] for o in observations])
    members = np.arange(64)
    slots, codes, g, sequence = _cusum_rows(1, 2000, 3)
    states = [(np.zeros((6, 3)), np.zeros(6), np.zeros(6, np.int64)) for _ in range(2)]
    filters = [(np.zeros((6, 2)), np.zeros((6, 2, 2)), np.zeros(6, bool)) for _ in range(2)]
    W = np.tile([0.02, 0.003, 0.01], (2000, 1))
    if not compiled.load():
        assert compiled.agree(z, R, members, 3, CLIP) is None and not compiled.ready()
        return
    runs = []
    for python, state, reference in zip((True, False), states, filters):
        runs.append((compiled.agree(z, R, members, 3, CLIP, python),
                     compiled.cusum(state, (slots, codes, g, sequence), 8.7, 4.35, python),
                     compiled.reference(reference, slots, g[:, None] * [1.0, 0.5], W, CLIP,
                                        python)))
    for plain, fast in zip(*runs):
        np.testing.assert_array_equal(fast, plain)
    for plain, fast in zip(states[0] + filters[0], states[1] + filters[1]):
        np.testing.assert_array_equal(fast, plain)


def _moved_landmark_run(seed):
    """Return a fuser's alarms and map: 3 robots, 12 landmarks, landmark 0 moves 0.35 m."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-10.0, 10.0, (12, 2))
    sources = ['/robot1/landmarks', '/robot2/landmarks', '/robot3/landmarks']
    fuser = Fuser(FuserConfig(move_false_alarm_rate=1e-3), sources)
    stamp = 1_000_000_000
    for k in range(240):
        if k == 120:
            truth[0] += [0.35, 0.0]
        ids = np.arange(12)
        m, P, P_dep = moved_landmark.draw_rows(rng, truth)
        fuser.add_landmarks(sources[k % 3], LandmarkMessage(stamp, ids, m, P, P_dep))
        stamp += 50_000_000
        if k % 4 == 3:
            fuser.fuse_queued()
    snapshot = fuser.snapshot()
    return dict(fuser.moves.alarms), fuser.counters['landmark_moved'], snapshot


@pytest.mark.parametrize('seed', range(3))
def test_the_fuser_detects_the_same_with_the_loops_as_with_numpy(seed, monkeypatch):
    runs = []
    for which in ('numpy', 'python'):
        with monkeypatch.context() as patch:
            _path(patch, which)
            runs.append(_moved_landmark_run(seed))
    (alarms, moved, want), (alarms_loop, moved_loop, got) = runs
    assert alarms == alarms_loop and moved == moved_loop and moved >= 1
    np.testing.assert_array_equal(got.ids, want.ids)
    np.testing.assert_allclose(got.m, want.m, rtol=0, atol=1e-9)
