"""
Every record the live path can save loads back: landmarks, tracks, waiting partial observations.

A property test over noise scales across the whole accepted range (and at its ends):
labelled rows fused many times, unlabelled rows (tracks), range-only and bearing-only
rows (placed landmarks and waiting ones) go through the fuser, which saves its map; a
second fuser loads it. Nothing may be rejected or quarantined, and what was saved is
what is loaded. Fusing many rows at the variance floor gives a covariance below it:
the map saves it floored (``fusion.records.floored``), so it loads back too.
"""

import json

from hypothesis import given, HealthCheck, settings, strategies as st
from landmark_ros.core.covariance import MAX_VARIANCE, MIN_VARIANCE
from landmark_ros.core.partial import BEARING, RANGE, Views
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.partial_rows import PartialObservations
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.pipeline.scan import Scan
import numpy as np
import pytest

S = 10 ** 9
LANDMARKS = ['/a/landmarks']
VIEWS = ['/a/partial_observations']


LOWEST = np.log10(MIN_VARIANCE * 40)
"""Smallest input variance exponent of the property: 40 rows fused stay above the floor,
so what is loaded is what was saved, bit for bit (below it, the saved covariance is
floored: ``test_rows_fused_below_the_variance_floor_load_back``)."""


def partial_columns(ids, kind, y, sensors, variance):
    views = Views(np.asarray(kind), np.asarray(sensors, np.float64),
                  np.zeros((len(ids), 3, 3)), np.asarray(y, np.float64),
                  np.full(len(ids), variance), np.zeros(len(ids)))
    return PartialObservations(np.asarray(ids, np.int64), views, np.arange(len(ids))).columns()


def feed(fuser, scale, repeats, rng):
    """Send every kind of input the fuser can keep, with variances of ``scale``."""
    C = np.eye(2) * scale
    for k in range(repeats):
        m = np.array([[1.0, 2.0], [5.0, -3.0]]) + rng.normal(0.0, np.sqrt(scale), (2, 2))
        fuser.add_landmarks(LANDMARKS[0], LandmarkMessage((k + 1) * S, np.array([1, 2]), m,
                            np.stack([C, C]), np.stack([C, C]) * 0.5))
    # Unlabelled rows: a tentative track (seen once).
    fuser.add_landmarks(LANDMARKS[0], LandmarkMessage((repeats + 1) * S, np.array([UNKNOWN_ID]),
                        np.array([[-20.0, 7.0]]), C[None], 0 * C[None],
                        classes=np.array([0]), scan=Scan(np.zeros(2), np.eye(3) * scale)))
    # Two bearings place landmark 7; one range keeps landmark 8 waiting.
    target = np.array([3.0, 4.0])
    sensors = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 0.0]])
    bearings = np.arctan2(target[1] - sensors[:, 1], target[0] - sensors[:, 0])
    fuser.add_partial_observations(VIEWS[0], (repeats + 2) * S, partial_columns(
        [7, 7], [BEARING, BEARING], bearings, sensors, min(scale, 1e-2)))
    fuser.add_partial_observations(VIEWS[0], (repeats + 3) * S, partial_columns(
        [8], [RANGE], [2.5], sensors[:1], scale))
    fuser.fuse_queued()


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(exponent=st.one_of(st.sampled_from([LOWEST, np.log10(MAX_VARIANCE) - 6]),
                          st.floats(LOWEST, np.log10(MAX_VARIANCE) - 6)),
       repeats=st.integers(1, 40),
       fusion=st.sampled_from(['independent', 'covariance_intersection',
                               'split_covariance_intersection']))
def test_whatever_the_live_path_saves_loads_back(tmp_path_factory, exponent, repeats, fusion):
    path = str(tmp_path_factory.mktemp('map') / 'map.json')
    config = FuserConfig(map_file=path, fusion=fusion, min_observations=1)
    fuser = Fuser(config, LANDMARKS, partial_sources=VIEWS)
    feed(fuser, 10.0 ** exponent, repeats, np.random.default_rng(repeats))
    assert fuser.save()
    with open(path) as stream:
        document = json.load(stream)
    again = Fuser(config, LANDMARKS, partial_sources=VIEWS)
    again.load()
    assert again.counters['map_records_rejected'] == 0
    assert again.counters['map_file_rejected'] == 0
    for a, b in zip(again.snapshot(), fuser.snapshot(), strict=True):
        np.testing.assert_array_equal(a, b)
    waiting = document.get('waiting_partial_observations', [])
    assert len(again.partial.waiting_records()) == len(waiting)
    assert again.tracker.to_dict() == fuser.tracker.to_dict()


@pytest.mark.parametrize('fusion', ['independent', 'covariance_intersection',
                                    'split_covariance_intersection'])
def test_rows_fused_below_the_variance_floor_load_back(tmp_path, fusion):
    path = str(tmp_path / 'map.json')
    fuser = Fuser(FuserConfig(map_file=path, fusion=fusion, min_observations=1), LANDMARKS)
    C = np.eye(2)[None] * MIN_VARIANCE
    for k in range(2):
        fuser.add_landmarks(LANDMARKS[0], LandmarkMessage(
            (k + 1) * S, np.array([1]), np.array([[1.0, 2.0]]), C, 0 * C))
    fuser.fuse_queued()
    assert fuser.save()
    again = Fuser(FuserConfig(map_file=path, fusion=fusion), LANDMARKS)
    again.load()
    assert again.counters['map_records_rejected'] == 0
    assert len(again.map) == 1
    saved = np.array(again.map.to_records()[0]['covariance'])
    live = fuser.map.snapshot().P[0]
    # floored, so never smaller than the live estimate: still consistent
    assert np.linalg.eigvalsh(saved - live).min() >= -1e-25
    assert np.linalg.eigvalsh(saved).min() >= MIN_VARIANCE


def test_the_issue_example_never_reaches_the_map_file(tmp_path):
    path = str(tmp_path / 'map.json')
    fuser = Fuser(FuserConfig(map_file=path), LANDMARKS, partial_sources=VIEWS)
    sensors = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 0.0]])
    fuser.add_partial_observations(VIEWS[0], S, partial_columns(
        [9, 9], [RANGE, RANGE], [5.0, 5.0], sensors, 1e-200))
    fuser.fuse_queued()
    assert fuser.counters['variance_out_of_range'] == 2
    assert fuser.save()
    again = Fuser(FuserConfig(map_file=path), LANDMARKS, partial_sources=VIEWS)
    again.load()
    assert again.counters['map_records_rejected'] == 0


def test_a_partial_observation_in_the_reserved_id_range_is_refused():
    fuser = Fuser(FuserConfig(), LANDMARKS, partial_sources=VIEWS)
    first = FuserConfig().first_new_id
    sensors = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 0.0]])
    queued = fuser.add_partial_observations(VIEWS[0], S, partial_columns(
        [9, first + 1], [RANGE, RANGE], [5.0, 5.0], sensors, 0.01))
    assert queued == 1 and fuser.counters['id_reserved'] == 1
