"""
Property tests of ``LandmarkMap``: a batch equals its rows one by one through ``core.gaussian``.

The reference below takes the rows one at a time with the plain functions of
``core.gaussian`` and ``core.gating`` (``fuse``, ``covariance_intersection``,
``split_covariance_intersection``, ``information``, ``mahalanobis_sq``): general
matrix code, none of the map's 2x2 closed forms, sums or folds. The map takes the
same rows in one batch (or several); estimates agree to 1e-12.
"""

from hypothesis import given, settings, strategies as st
from landmark_ros.core import gaussian
from landmark_ros.core.gating import chi2_threshold, mahalanobis_sq
from landmark_ros.fusion import compiled
from landmark_ros.fusion.landmark_map import FUSION_METHODS, LandmarkMap
import numpy as np
import pytest


def stream(seed, landmarks, sources, count):
    """Return rows ``ids, z, R, R_dep, names``: inliers near the truth, a few far outliers."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-20.0, 20.0, (landmarks, 2))
    ids = rng.integers(0, landmarks, count)
    ids[:landmarks] = np.arange(landmarks)      # every landmark first, to confirm it
    A = rng.normal(0.0, 0.3, (count, 2, 2))
    R = A @ np.swapaxes(A, 1, 2) + 0.01 * np.eye(2)
    # Dependent parts proportional to R: a source's weighted mean of them is a covariance.
    R_dep = rng.uniform(0.0, 0.9, (count, 1, 1)) * R
    z = truth[ids] + 0.1 * rng.normal(size=(count, 2)) * np.sqrt(
        np.stack([R[:, 0, 0], R[:, 1, 1]], axis=1))
    z[rng.uniform(size=count) < 0.1] += 50.0       # far outside any gate
    z[:landmarks] = truth
    names = np.array([f'robot{k}' for k in rng.integers(0, sources, count)])
    return ids, z, R, R_dep, names


def refreshed(count):
    """Whether the gate reference follows the estimate after observation ``count``."""
    # Every one of the first 7, then 4 times per doubling of the count.
    return count < 8 or count % (1 << (count.bit_length() - 3)) == 0


class Reference:
    """One landmark map, row by row, with the plain ``core.gaussian`` functions."""

    def __init__(self, fusion):
        self.fusion = fusion
        self.threshold = chi2_threshold(2, 0.999)
        self.landmarks = {}

    def add(self, landmark_id, z, R, R_dep, name):
        entry = self.landmarks.get(landmark_id)
        if entry is None:       # min_observations = 1: the first row confirms
            entry = self.landmarks[landmark_id] = {'count': 0, 'sources': {}}
            self._fuse(entry, z, R, R_dep, name)
            entry['gate'] = entry['m'], entry['P_ind'] + entry['P_dep']
            return
        m_ref, P_ref = entry['gate']
        if mahalanobis_sq(z, m_ref, P_ref + R) > self.threshold:
            return
        self._fuse(entry, z, R, R_dep, name)
        if refreshed(entry['count']):
            entry['gate'] = entry['m'], entry['P_ind'] + entry['P_dep']

    def _fuse(self, entry, z, R, R_dep, name):
        entry['count'] += 1
        R_ind = R - R_dep
        if self.fusion == 'split_covariance_intersection':
            sums = entry['sources'].setdefault(name, [np.zeros((2, 2)), np.zeros(2),
                                                      np.zeros((2, 2)), 0.0])
            Y = gaussian.information(R_ind + 1e-12 * np.trace(R_ind) * np.eye(2))
            T = Y @ (0.5 * (R_dep + R_dep.T)) @ Y
            c = np.sqrt(np.trace(T))
            sums[0], sums[1] = sums[0] + Y, sums[1] + Y @ z
            sums[2], sums[3] = sums[2] + (T / c if c > 0.0 else 0.0 * T), sums[3] + c
            entry['m'], entry['P_ind'], entry['P_dep'] = self._fold(entry['sources'])
        elif entry['count'] == 1:
            P = R if self.fusion == 'independent' else np.zeros((2, 2))
            entry['m'], entry['P_ind'], entry['P_dep'] = z, P, R - P
        elif self.fusion == 'independent':
            m, P = gaussian.fuse(entry['m'], entry['P_ind'], z, R)
            entry['m'], entry['P_ind'], entry['P_dep'] = m, P, np.zeros((2, 2))
        else:
            m, P = gaussian.covariance_intersection(entry['m'], entry['P_dep'], z, R)
            entry['m'], entry['P_ind'], entry['P_dep'] = m, np.zeros((2, 2)), P

    @staticmethod
    def _fold(sources):
        parts = []
        for name in sources:      # in the order the sources first came (their codes)
            Y, y, S, C = sources[name]
            P_ind = np.linalg.inv(Y)
            # The dependent bound of source_sums: C Y^-1 S Y^-1.
            parts.append((P_ind @ y, P_ind, C * P_ind @ S @ P_ind))
        order = sorted(range(len(parts)), key=lambda k: np.linalg.det(parts[k][1] + parts[k][2]))
        m, P_ind, P_dep = parts[order[0]]
        for k in order[1:]:
            m, P_ind, P_dep = gaussian.split_covariance_intersection(m, P_ind, P_dep,
                                                                     *parts[k])
        return m, P_ind, P_dep


def feed(fusion, rows, cuts):
    """Return a map fed ``rows`` in the batches that ``cuts`` (positions) separate."""
    ids, z, R, R_dep, names = rows
    landmark_map = LandmarkMap(fusion, min_observations=1, max_consecutive_rejections=10 ** 6)
    bounds = [0, *sorted(set(cuts)), len(ids)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        landmark_map.update(ids[a:b], z[a:b], R[a:b], R_dep[a:b], names[a:b].tolist())
    return landmark_map


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), landmarks=st.integers(1, 5),
       sources=st.integers(1, 4), count=st.integers(5, 60),
       fusion=st.sampled_from(FUSION_METHODS))
def test_a_batch_equals_its_rows_one_by_one_through_core_gaussian(seed, landmarks, sources,
                                                                  count, fusion):
    rows = stream(seed, landmarks, sources, count)
    reference = Reference(fusion)
    for row in zip(*rows):
        reference.add(int(row[0]), *row[1:4], str(row[4]))
    # The landmarks confirmed by their first rows, then the rest in one batch.
    landmark_map = feed(fusion, rows, [landmarks])
    ids, m, P, P_dep, observations = landmark_map.snapshot()
    assert ids.tolist() == sorted(reference.landmarks)
    for k, landmark_id in enumerate(ids.tolist()):
        entry = reference.landmarks[landmark_id]
        assert observations[k] == entry['count']
        gate = landmark_map.gate[np.flatnonzero(landmark_map.ids == landmark_id)[0]]
        m_ref, P_ref = entry['gate']
        np.testing.assert_allclose(gate, [*m_ref, *P_ref[[0, 0, 1], [0, 1, 1]]], rtol=0.0,
                                   atol=1e-12 * max(20.0, np.abs(P_ref).max()))
        np.testing.assert_allclose(m[k], entry['m'], rtol=0.0, atol=1e-12 * 20.0)
        scale = np.abs(entry['P_ind'] + entry['P_dep']).max()
        np.testing.assert_allclose(P[k], entry['P_ind'] + entry['P_dep'], rtol=0.0,
                                   atol=1e-12 * scale)
        np.testing.assert_allclose(P_dep[k], entry['P_dep'], rtol=0.0, atol=1e-12 * scale)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), count=st.integers(5, 80),
       cuts=st.lists(st.integers(1, 79), max_size=6), fusion=st.sampled_from(FUSION_METHODS))
def test_any_split_into_batches_gives_the_same_bits(seed, count, cuts, fusion):
    rows = stream(seed, 4, 3, count)
    one_by_one = feed(fusion, rows, range(1, count))
    batched = feed(fusion, rows, [c for c in cuts if c < count])
    for a, b in zip(one_by_one.snapshot(), batched.snapshot()):
        np.testing.assert_array_equal(a, b)
    assert one_by_one.to_records() == batched.to_records()


@pytest.mark.parametrize('fusion', FUSION_METHODS)
def test_the_compiled_fold_changes_no_bit(fusion, monkeypatch):
    # The same rows with the compiled fold (when numba is there) and with numpy's.
    rows = stream(7, 30, 6, 2000)
    compiled.load()
    with_kernel = feed(fusion, rows, [30, 500, 1200])
    monkeypatch.setitem(compiled._state, 'kernel', None)
    without = feed(fusion, rows, [30, 500, 1200])
    for a, b in zip(with_kernel.snapshot(), without.snapshot()):
        np.testing.assert_array_equal(a, b)
