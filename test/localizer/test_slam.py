"""The closed loop of localizers, observers and fuser (``eval.slam_loop``), its tools."""

import dataclasses
import json
from pathlib import Path

from landmark_ros.eval import slam_montecarlo
from landmark_ros.eval.slam_loop import LoopConfig, TeamLoop
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.mrclam import slam
from landmark_ros.mrclam.data import load_dataset
from landmark_ros.mrclam.localize_data import load_all_extras
from landmark_ros.observer.precision import dependent_stddev
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
import numpy as np
import pytest
from test_mrclam_localize import _first_seconds, DATASET

MS = 1_000_000


def _loop(hide_ids=False, precision_sources=1, association='localizer'):
    config = LoopConfig(LocalizerConfig(initial_stddev=(0.01, 0.01, 0.01)),
                        ObserverConfig(range_stddev=0.05, bearing_stddev=0.02,
                                       precision_sources=precision_sources),
                        FuserConfig(min_observations=2, false_track_probability=0.49),
                        hide_ids, association=association)
    loop = TeamLoop(config, ['robot1'])
    loop.start(0, 1 * MS, np.zeros(3), np.diag([1e-4, 1e-4, 1e-4]))
    return loop


def _see(loop, k, landmark=(3.0, 1.0), ids=(7,)):
    """Stand still; one sighting of ``landmark`` between odometry ``k`` and ``k + 1``."""
    loop.odometry(0, (10 * k + 2) * MS, pose=np.zeros(3))
    z = np.array([[np.hypot(*landmark), np.arctan2(landmark[1], landmark[0])]])
    loop.sightings(0, (10 * k + 5) * MS, np.array(ids), z)
    loop.odometry(0, (10 * k + 8) * MS, pose=np.zeros(3))


@pytest.mark.parametrize('hide_ids,association', [(False, 'localizer'), (True, 'localizer'),
                                                  (True, 'fuser')])
def test_a_sighting_updates_the_pose_against_the_map_without_itself(hide_ids, association):
    loop = _loop(hide_ids, association=association)
    loc = loop.localizers[0]
    _see(loop, 0)
    _see(loop, 1)
    # Two agreeing rows confirm the landmark; neither was in the map that updated the
    # pose when it came (the map before its own batch was fused).
    assert len(loop.fuser.snapshot().ids) == 1
    assert loc.counters['rows_used'] == 0
    _see(loop, 2)
    assert loc.counters['rows_used'] == 1
    assert loop.counts['rows_to_localizer'] == 1
    # The observer placed every row with the localizer's pose, the pose error as the
    # dependent part (the localizer's covariance, not the observer's default).
    record = loop.map_records()[0]
    assert np.trace(np.array(record['covariance_dependent'])) > 1e-4


def test_without_ids_the_localizer_names_its_rows_from_its_own_map():
    loop = _loop(True)
    loc = loop.localizers[0]
    for k in range(3):
        _see(loop, k)
    # The third row was paired by the localizer's association (robot frame, pose
    # covariance included) with the one track of the map it held, then used.
    assert loc.counters['associated'] == 1 and loc.counters['rows_used'] == 1
    fused = _loop(True, association='fuser')
    for k in range(3):
        _see(fused, k)
    assert fused.localizers[0].counters['associated'] == 0
    assert fused.localizers[0].counters['rows_used'] == 1


def test_precision_sources_split_a_robot_by_its_dependent_part():
    loop = _loop(precision_sources=4)
    assert [loop.precision_source(np.eye(2)[None] * s ** 2) for s in
            (0.001, 0.03, 0.05, 0.1, 10.0)] == [0, 0, 1, 2, 3]
    assert list(loop.fuser.sources) == ['/robot1/landmarks'] + [
        f'/robot1/landmarks/precision_{k}' for k in (1, 2, 3)]
    assert _loop().precision_source(np.eye(2)[None]) == 0


def test_the_loop_records_each_message_dependent_stddev():
    # rows of largest dependent variance 0.01, 0.04 and 0.09 m^2: median 0.04, 0.2 m
    P_dep = np.array([np.diag([0.01, 0.002]), np.diag([0.001, 0.04]), np.diag([0.09, 0.0])])
    assert dependent_stddev(P_dep) == pytest.approx(0.2, rel=1e-12)
    loop = _loop()
    for k in range(3):
        _see(loop, k)
    # one value per placed message with rows: the pose's uncertainty at the sighting
    assert len(loop.dependent_stddevs) == loop.counts['batches'] == 3
    assert all(0.0 < s < 0.1 for s in loop.dependent_stddevs)


def test_the_replay_section_sets_the_precision_sources():
    from types import SimpleNamespace
    replay = SimpleNamespace(observer=ObserverConfig(), fuser=FuserConfig())
    default = slam.loop_config(replay, LocalizerConfig())
    observer = default.observer
    assert (observer.precision_sources, observer.precision_base_m) == (1, 0.02)
    config = slam.loop_config(replay, LocalizerConfig(), {'slam_precision_sources': 4,
                                                          'slam_precision_base_m': 0.1})
    assert (config.observer.precision_sources, config.observer.precision_base_m) == (4, 0.1)
    assert config.localizer.correlated_noise == 'count'     # the localizer section's
    dependent = slam.loop_config(replay, LocalizerConfig(),
                                 {'slam_correlated_noise': 'dependent'})
    assert dependent.localizer.correlated_noise == 'dependent'
    loop = TeamLoop(config, ['robot1'])
    # Doubling from 0.1 m: below 0.2 m, to 0.4 m, to 0.8 m, beyond.
    assert [loop.precision_source(np.eye(2)[None] * s ** 2) for s in
            (0.05, 0.15, 0.3, 0.5, 2.0)] == [0, 0, 1, 2, 3]
    assert len(loop.fuser.sources) == 4
    assert default.association == 'fuser'
    assert slam.loop_config(replay, LocalizerConfig(),
                            {'slam_association': 'localizer'}).association == 'localizer'
    with pytest.raises(ValueError):
        slam.loop_config(replay, LocalizerConfig(), {'slam_association': 'both'})
    # a map built from the loop's own poses is not independent of them: never consider
    for correlation, expected in (('consider', 'split_ci'), ('split_ci', 'split_ci'),
                                  ('independent', 'independent')):
        cfg = slam.loop_config(replay, LocalizerConfig(correlation=correlation))
        assert cfg.localizer.correlation == expected


def test_the_loop_runs_without_the_range_scale_state_unless_the_section_says():
    from types import SimpleNamespace
    replay = SimpleNamespace(observer=ObserverConfig(range_bias_stddev=0.032),
                             fuser=FuserConfig())
    state = LocalizerConfig(range_scale_state_stddev=0.0099, range_bias_stddev=0.0)
    off = slam.loop_config(replay, state).localizer
    assert (off.range_scale_state_stddev, off.range_bias_stddev) == (0.0, 0.032)
    on = slam.loop_config(replay, state, {'slam_range_scale_state': True}).localizer
    assert (on.range_scale_state_stddev, on.range_bias_stddev) == (0.0099, 0.0)
    plain = LocalizerConfig(range_scale_state_stddev=0.0, range_bias_stddev=0.01)
    assert slam.loop_config(replay, plain).localizer == plain
    loop = TeamLoop(slam.loop_config(replay, state), ['robot1'])
    loop.start(0, 0, np.zeros(3), np.eye(3) * 1e-4)
    assert loop.localizers[0].range_scale() is None


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
def test_the_mrclam_config_gives_the_loop_its_precision_sources():
    from landmark_ros.mrclam.config import load_config
    from landmark_ros.mrclam.localize_cli import _sections
    replay = load_config(None)
    from landmark_ros.mrclam.localize import localizer_config
    localizer_values, replay_values = _sections(replay.path)
    assert localizer_config(localizer_values).range_scale_state_stddev > 0.0
    config = slam.loop_config(replay, localizer_config(localizer_values), replay_values)
    observer = config.observer
    assert observer.precision_sources == int(replay_values['slam_precision_sources']) > 1
    assert observer.precision_base_m == float(replay_values['slam_precision_base_m'])
    assert replay_values['slam_range_scale_state'] is False
    assert config.localizer.range_scale_state_stddev == 0.0
    assert config.localizer.range_bias_stddev == replay.observer.range_bias_stddev > 0.0
    # IDs hidden: as a team of nodes, each localizer pairs its rows, ambiguous ones by PDA
    assert config.association == 'localizer' and config.localizer.association_merge_ambiguous


@pytest.mark.slow
def test_monte_carlo_of_the_loop_is_not_over_confident():
    results = [slam_montecarlo.run_seed(seed, robots=3, duration_s=30.0) for seed in range(4)]
    summary = slam_montecarlo.summarise(results, 3)
    # The map is conservative with one source per robot (below its interval), never
    # above it; the poses are consistent.
    _, high = summary['map_anees_interval']
    assert summary['map_anees'] <= high, summary
    assert 1.5 <= summary['pose_anees'] <= 4.5, summary
    assert summary['landmarks_scored'] >= 20


def test_monte_carlo_variants_reach_the_loop():
    # The landmark bound makes the same seeds' poses and map less confident; the best
    # rigid transform of the map onto the truth leaves at most its error.
    bound = slam_montecarlo.Variant(landmark_correlation='unknown')
    plain = [slam_montecarlo.run_seed(seed, robots=2, duration_s=12.0) for seed in (0, 1)]
    tight = [slam_montecarlo.run_seed(seed, robots=2, duration_s=12.0, variant=bound)
             for seed in (0, 1)]
    a, b = (slam_montecarlo.summarise(r, 2) for r in (plain, tight))
    assert b['pose_anees'] < a['pose_anees'] and b['map_anees'] < a['map_anees']
    assert 0.0 < a['map_rigid_residual_rmse_m'] <= a['map_rmse_m']
    assert a['map_predicted_rmse_m'] > 0.0
    config = slam_montecarlo.loop_config(variant=slam_montecarlo.Variant(
        2, (0.01, 0.02, 0.003), 'independent', 'unknown'))
    assert config.observer.precision_sources == 2
    assert config.fuser.source_correlation == 'independent'
    assert config.localizer.initial_stddev == (0.01, 0.02, 0.003)
    assert config.localizer.landmark_correlation == 'unknown'


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
def test_mrclam_slam_on_the_first_minute_reports_the_issue_keys(tmp_path):
    dataset = load_dataset(DATASET)
    dataset, extras = _first_seconds(dataset, load_all_extras(dataset), 60.0, (3, 5))
    config = LoopConfig(LocalizerConfig(odometry_alphas=(2.0, 6.8, 1.6, 0.26),
                                        range_stddev=0.04, range_stddev_per_m=0.05,
                                        bearing_stddev=0.017,
                                        initial_stddev=(0.02, 0.02, 0.02)),
                        ObserverConfig(range_stddev=0.03, range_stddev_per_m=0.05,
                                       bearing_stddev=0.017), FuserConfig())
    results = slam.run_all(dataset, extras, config, (6, 11, 19), 0.175,
                           modes=(slam.SlamMode(True, False), slam.SlamMode(False, True)))
    keys = {'ids_hidden', 'anchors', 'position_rmse_m', 'heading_rmse_rad', 'anees',
            'inside_95_fraction', 'robots', 'map_rmse_m', 'map_anees', 'map_anees_interval',
            'tracks_confirmed', 'true_landmarks'}
    for result in results:
        entry = result.entry
        assert keys <= set(entry)
        assert [r['robot'] for r in entry['robots']] == [3, 5]
        assert entry['rows_used'] > 0 and entry['tracks_confirmed'] > 0
        assert entry['position_rmse_m'] < 1.0
        dep = entry['dependent_stddev_m']
        assert 0.0 < dep['min'] <= dep['median'] <= dep['p95']
        json.dumps(entry)
    hidden, anchored = (r.entry for r in results)
    assert hidden['ids_hidden'] and not hidden['anchors']
    assert anchored['anchors'] and not anchored['ids_hidden']
    # The anchors are in the fused map (loaded from the map file).
    assert {6, 11, 19} <= {r['id'] for r in results[1].records}
    assert len(slam.targets(results)) == 5
    path = Path(tmp_path) / 'anchors.json'
    assert slam.write_anchor_file(path, dataset, {6, 11, 19}) == 3
    assert dataclasses.is_dataclass(results[0].mode)


def _source_rows(rng, n):
    """Rows of one source: thin independent parts and dependent parts of every size."""
    R_ind, R_dep = [], []
    for _ in range(n):
        a = rng.uniform(0.0, np.pi)
        U = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        R_ind.append(U @ np.diag([0.02 ** 2, rng.uniform(0.05, 0.3) ** 2]) @ U.T)
        b = rng.uniform(0.0, np.pi)
        V = np.array([[np.cos(b), -np.sin(b)], [np.sin(b), np.cos(b)]])
        R_dep.append(V @ np.diag(rng.uniform(0.01, 1.0, 2) ** 2) @ V.T)
    return np.array(R_ind), np.array(R_dep)


def _worst_dependent_covariance(R_ind, R_dep, rng, draws=200):
    """Largest eigenvalue margin over dependent errors ``d_i = L_i U_i xi`` (one ``xi``)."""
    W = np.linalg.inv(R_ind)
    B = np.linalg.solve(W.sum(axis=0), W)       # Y^-1 W_i: the rows' weights in the mean
    L = np.linalg.cholesky(R_dep)
    worst = []
    for _ in range(draws):
        # Fully correlated errors, each row's turned by its own rotation (any such joint
        # law has the stated marginals): A = sum B_i L_i U_i, Cov = A A^T.
        angles = rng.uniform(0.0, 2.0 * np.pi, len(W))
        U = np.stack([np.cos(angles), -np.sin(angles), np.sin(angles), np.cos(angles)],
                     axis=1).reshape(-1, 2, 2)
        A = np.einsum('nij,njk,nkl->il', B, L, U)
        worst.append(A @ A.T)
    return worst


def test_a_source_bound_holds_for_any_correlation_of_the_dependent_parts():
    from landmark_ros.fusion.source_sums import SourceSums
    rng = np.random.default_rng(13)
    for trial in range(20):
        R_ind, R_dep = _source_rows(rng, 12)
        sums = SourceSums()
        n = len(R_ind)
        sums.add(np.zeros(n, np.int64), np.zeros(n, np.int64), rng.normal(size=(n, 2)),
                 R_ind, R_dep)
        D = sums.fold(np.array([0])).P_dep[0]
        for C in _worst_dependent_covariance(R_ind, R_dep, rng):
            assert np.linalg.eigvalsh(D - C).min() >= -1e-12 * np.trace(D), trial


def test_the_matrix_weighted_mean_of_dependent_parts_is_no_bound():
    # The earlier per-source bound, psd(sym(Y^-1 sum W_i R_dep_i)), for the same rows:
    # some joint law of the dependent errors exceeds it (what made landmark 13 of
    # MRCLAM dataset 6 claim 5 mm in one direction).
    from landmark_ros.core.arrays import psd_projection_2x2, symmetric_2x2
    rng = np.random.default_rng(13)
    exceeded = 0
    for _ in range(20):
        R_ind, R_dep = _source_rows(rng, 12)
        W = np.linalg.inv(R_ind)
        M = np.linalg.solve(W.sum(axis=0), np.einsum('nij,njk->ik', W, R_dep))
        old = symmetric_2x2(*psd_projection_2x2(M[0, 0], 0.5 * (M[0, 1] + M[1, 0]), M[1, 1]))
        exceeded += any(np.linalg.eigvalsh(old - C).min() < 0.0
                        for C in _worst_dependent_covariance(R_ind, R_dep, rng, 50))
    assert exceeded > 0


def test_equal_rows_keep_their_dependent_part_and_rows_of_one_shape_average_sqrt():
    from landmark_ros.fusion.source_sums import SourceSums
    R_ind = np.tile(np.diag([0.01, 0.04]), (4, 1, 1))
    scales = np.array([0.01, 0.04, 0.09, 0.16])
    R_dep = scales[:, None, None] * np.diag([1.0, 3.0])[None]
    sums = SourceSums()
    sums.add(np.zeros(4, np.int64), np.zeros(4, np.int64), np.zeros((4, 2)), R_ind, R_dep)
    D = sums.fold(np.array([0])).P_dep[0]
    # (mean sqrt(scale))^2 = 0.25^2 of the common shape: less than the mean, 0.075.
    np.testing.assert_allclose(D, 0.0625 * np.diag([1.0, 3.0]), rtol=1e-12)
    sums = SourceSums()
    sums.add(np.zeros(3, np.int64), np.zeros(3, np.int64), np.zeros((3, 2)),
             np.tile(np.diag([0.01, 0.04]), (3, 1, 1)), np.tile(np.diag([0.2, 0.1]), (3, 1, 1)))
    np.testing.assert_allclose(sums.fold(np.array([0])).P_dep[0], np.diag([0.2, 0.1]),
                               rtol=1e-12)


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
def test_slam_cli_takes_the_precision_sources_and_can_leave_out_robot_sightings(tmp_path):
    from landmark_ros.mrclam import slam_cli
    entries = []
    for extra in ([], ['--precision-sources', '1', '--no-robot-sightings']):
        out = tmp_path / f'slam{len(extra)}.json'
        assert slam_cli.main([str(DATASET), '--duration', '30', '--json', str(out)]
                             + extra) == 0
        entries.append(json.loads(out.read_text())['slam'][0])
    full, bare = entries
    assert full['options']['precision_sources'] == 4 and full['options']['robot_sightings']
    assert bare['options']['precision_sources'] == 1
    assert not bare['options']['robot_sightings']
    assert full['robot_rows_used'] > 0
    assert bare['robot_rows_used'] == 0
