"""landmark_mrclam --hide-ids on the synthetic dataset of test_mrclam (both modes)."""

import json

from landmark_ros.mrclam.cli import main
import numpy as np
from test_mrclam import LANDMARKS, noisy_dataset, synthetic_config  # noqa: F401, the fixture


def test_hide_ids_associates_the_sightings_and_reports_it(noisy_dataset, tmp_path,  # noqa: F811
                                                          capsys):
    directory, info = noisy_dataset
    out = tmp_path / 'result.json'
    config = synthetic_config(tmp_path)
    assert main([str(directory), '--config', str(config), '--hide-ids', '--fusion',
                 'split_covariance_intersection', '--json', str(out)]) == 0
    assert '== association (IDs hidden)' in capsys.readouterr().out
    (entry,) = json.loads(out.read_text())['summary']
    assert entry['true_landmarks'] == len(LANDMARKS)
    assert entry['tracks_confirmed'] == len(LANDMARKS)
    assert entry['association_accuracy'] >= entry['oracle_accuracy'] - 0.02
    assert entry['gospa_m'] < 0.1 and entry['rmse_m'] < 0.05
    assert sorted(lm['id'] for lm in entry['landmarks']) == sorted(LANDMARKS)


def test_hide_ids_through_nodes_agrees_with_offline(noisy_dataset, tmp_path):  # noqa: F811
    directory, _ = noisy_dataset
    out = tmp_path / 'nodes.json'
    config = synthetic_config(tmp_path)
    code = main([str(directory), '--config', str(config), '--hide-ids', '--through-nodes',
                 '--fusion', 'split_covariance_intersection', '--no-progress',
                 '--json', str(out)])
    document = json.loads(out.read_text())
    assert code == 0, document.get('agreement')
    assert document['mode'] == 'through_nodes'
    (entry,) = document['agreement'].values()
    # Same fuser track IDs, matched to the same true landmarks, same counts.
    assert entry['same_track_ids'] and entry['same_ids'] and entry['same_counts']
    assert entry['max_mean_diff_m'] < 1e-9
    assert entry['max_cov_diff_m2'] < 1e-12 and entry['max_cov_dep_diff_m2'] < 1e-12
    nodes = document['nodes']
    assert not nodes['cloud_mismatch'] and nodes['rows_out'] == nodes['rows']
    # Every change of robot between clouds needed a barrier (one global order).
    assert nodes['barriers'] >= 1
    (summary,) = document['summary']
    assert summary['tracks_confirmed'] == summary['true_landmarks'] == len(LANDMARKS)
    assert summary['association_accuracy'] is not None
    assert summary['association_accuracy'] >= summary['oracle_accuracy'] - 0.02
    assert all(lm['id'] in LANDMARKS for lm in summary['landmarks'])


def test_without_ids_every_cloud_follows_the_one_before_it():
    from landmark_ros.mrclam.replay_plan import sequential
    msg_robot = np.array([0, 0, 1, 0, 2, 2, 1])
    local = np.array([0, 1, 0, 2, 0, 1, 1])
    assert sequential(msg_robot, local) == [
        (), (), ((0, 1),), ((1, 0),), ((0, 2),), (), ((2, 1),)]
