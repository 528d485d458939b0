"""The Monte Carlo study of landmarks without IDs computes its quantities right."""

from dataclasses import replace

from landmark_ros.eval import association_study as study
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.sim.world import World
import numpy as np
import pytest

S = 1_000_000_000


@pytest.mark.parametrize('spacing', [1.0, 0.25])
def test_paired_world_puts_each_pair_spacing_apart(spacing):
    world = study.paired_world(10, spacing, 20.0, seed=3)
    assert world.ids.tolist() == list(range(1, 21))
    pairs = world.positions.reshape(10, 2, 2)
    np.testing.assert_allclose(np.linalg.norm(pairs[:, 0] - pairs[:, 1], axis=1), spacing)
    distance = np.linalg.norm(world.positions[:, None] - world.positions[None], axis=-1)
    np.fill_diagonal(distance, np.inf)
    assert distance.min() == pytest.approx(spacing)


def test_score_counts_matches_duplicates_false_tracks_and_sightings():
    world = World(np.array([1, 2, 3], np.int64),
                  np.array([[0.0, 0.0], [1.0, 0.0], [10.0, 10.0]]),
                  (-20.0, -20.0, 20.0, 20.0))
    sources = ['/robot1/landmarks', '/robot2/landmarks']
    fuser = Fuser(FuserConfig(min_observations=1), sources)
    P = np.broadcast_to(0.01 * np.eye(2), (4, 2, 2)).copy()
    # Tracks: 101 on landmark 1, 102 on landmark 2, 103 a second track on landmark 2
    # (0.1 m off), 104 far from everything; landmark 3 never tracked.
    fuser.map.update(np.array([101, 102, 103, 104]),
                     np.array([[0.02, 0.0], [1.0, 0.01], [1.1, 0.0], [5.0, 5.0]]), P,
                     0 * P, 'r', S)
    fuser.association_log = [
        (sources[0], 1 * S, np.array([101, 102, 104])),   # truth 1, 1, clutter
        (sources[1], 2 * S, np.array([103, -1])),         # truth 2, clutter (dropped)
        (sources[1], 3 * S, np.array([101]))]             # no measurement logged: unscored
    measurements = {(0, 1 * S): np.array([1, 1, UNKNOWN_ID]),
                    (1, 2 * S): np.array([2, UNKNOWN_ID]),
                    (0, 9 * S): np.array([3])}
    score = study.score_fuser(fuser, measurements, world, spacing=1.0, min_observations=2)
    assert (score.tracks, score.matched, score.duplicates, score.false_tracks) == (4, 2, 1, 1)
    # Observable: detected at least twice (landmark 1 only).
    assert (score.observable, score.found) == (1, 1)
    # Sightings: 1->101 right, 1->102 wrong, 2->103 (the duplicate) wrong.
    assert (score.sightings, score.right) == (3, 1)
    assert (score.clutter_rows, score.clutter_absorbed) == (2, 0)
    assert score.unscored_messages == 1
    assert len(score.nees) == 2 and score.seed_anees == [pytest.approx(np.mean(score.nees))]
    s = score.summary()
    assert s['precision'] == 0.5 and s['recall'] == 1.0
    assert s['association_accuracy'] == pytest.approx(1 / 3)


def test_scores_add_up_over_seeds():
    a, b = study.Score(tracks=4, matched=3, nees=[1.0, 3.0], seed_anees=[2.0]), study.Score(
        tracks=2, matched=2, nees=[4.0], seed_anees=[4.0])
    a.add(b)
    s = a.summary()
    assert s['precision'] == 5 / 6 and s['anees'] == pytest.approx(8 / 3)
    assert s['seed_anees_mean'] == 3.0 and s['seeds'] == 2
    assert s['seed_anees_half_width'] == pytest.approx(1.96 * np.std([2.0, 4.0], ddof=1)
                                                       / np.sqrt(2))


def test_one_short_case_scores_every_row_of_every_fuser():
    configs = study.study_configs(references=True)
    scores = study.run_case(1.0, 1.0, seed=0, configs=configs, duration_s=3.0, pairs=4)
    assert sorted(scores) == sorted(configs)
    rows = None
    for name, score in scores.items():
        s = score.summary()
        assert 0.0 <= s['precision'] <= 1.0 and 0.0 <= s['recall'] <= 1.0, name
        assert score.unscored_messages == 0, name
        # Every fuser saw the same rows: the same true sightings and clutter rows.
        if rows is None:
            rows = (score.sightings, score.clutter_rows)
        assert (score.sightings, score.clutter_rows) == rows, name
        assert score.matched + score.duplicates + score.false_tracks == score.tracks, name
    assert rows[0] > 0 and rows[1] > 0


def test_the_shared_frame_case_scores_the_frame_averaged_anees():
    configs = study.frame_configs()
    assert [c.fusion for c in configs.values()] == [
        'split_covariance_intersection', 'independent', 'covariance_intersection']
    assert all(c.association == FuserConfig().association for c in configs.values())
    framed = study.run_case(1.0, 0.0, seed=1, configs=configs, duration_s=3.0, pairs=4,
                            scenario=study.FRAME_SCENARIO)
    for name, score in framed.items():
        assert len(score.frame_seed_anees) == 1 and score.matched >= 1, name
        assert 'frame_anees_mean' in score.summary()
    # The product of Gaussians averages the shared frame error down.
    assert (framed['independent'].frame_seed_anees[0]
            > 2.0 * framed[FuserConfig().association].frame_seed_anees[0])
    plain = study.run_case(1.0, 0.0, seed=1, configs=configs, duration_s=3.0, pairs=4)
    assert all(not score.frame_seed_anees and 'frame_anees_mean' not in score.summary()
               for score in plain.values())


def test_the_study_runs_the_package_defaults():
    configs = study.study_configs(references=True)
    assert study.STUDY_SETTING == {}
    for method in study.METHODS:
        assert configs[method] == replace(FuserConfig(), association=method), method
    assert configs['independent'] == replace(FuserConfig(), fusion='independent')
