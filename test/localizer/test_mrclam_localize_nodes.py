"""``landmark_mrclam --localize --through-nodes``: the order it sends, and the agreement."""

import json
from pathlib import Path
from types import SimpleNamespace

from landmark_ros.localizer.localizer import UNKNOWN_ID
from landmark_ros.mrclam.localize_plan import ODOMETRY, schedule, SIGHTINGS, slice_run
import numpy as np
import pytest

# ../shared beside the repository (a clone), or beside the folder of worktrees
DATASET = next((p / 'shared' / 'data' / 'mrclam' / 'dataset6'
                for p in Path(__file__).resolve().parents[3:5]
                if (p / 'shared' / 'data' / 'mrclam' / 'dataset6').is_dir()),
               Path('/nonexistent'))


LANDMARKS = np.array([[4.0, 1.0], [-3.0, 5.0], [2.0, -4.0], [6.0, 6.0]])


def _localizer(initialise):
    from landmark_ros.localizer.config import LocalizerConfig
    from landmark_ros.localizer.localizer import Localizer
    loc = Localizer(LocalizerConfig(initial_pose=(0.0, 0.0, 0.0), window_s=0.3))
    loc.set_map(np.arange(4), LANDMARKS, np.tile(np.eye(2) * 1e-3, (4, 1, 1)))
    if initialise is not None:  # the offline run starts at the first odometry stamp
        cfg = loc.config
        loc.initialize(initialise, np.array(cfg.initial_pose),
                       np.diag(np.square(cfg.initial_stddev)))
    return loc


@pytest.mark.parametrize('hide', [False, True])
def test_schedule_makes_the_offline_calls_in_the_offline_order(hide):
    from landmark_ros.core import sensors
    from landmark_ros.mrclam.data import seconds_to_stamps_ns
    rng = np.random.default_rng(0)
    odom = np.round(np.cumsum(rng.uniform(0.005, 0.02, 400)), 3)
    twist = rng.normal(0.0, 0.02, (len(odom), 2))
    obs = np.sort(np.concatenate([rng.choice(odom, 25), np.round(rng.uniform(
        odom[0] - 0.05, odom[-1] + 0.05, 40), 3), np.full(2, odom[0] - 0.01)]))
    obs = np.repeat(obs, rng.integers(1, 3, len(obs)))  # batches of one or two rows
    ids = rng.integers(0, 4, len(obs))
    z = sensors.observe(np.zeros((len(obs), 3)), LANDMARKS[ids])
    z += rng.normal(0, 0.02, z.shape)
    if hide:  # the node associates: from the newest pose when it takes the batch
        ids = np.full(len(obs), UNKNOWN_ID, np.int64)
    odom_ns, obs_ns = seconds_to_stamps_ns(odom), seconds_to_stamps_ns(obs)
    plan = schedule(SimpleNamespace(times=obs), SimpleNamespace(odom_times=odom), 0.0, hide)
    assert np.count_nonzero(plan.kind == ODOMETRY) == len(odom)
    assert np.count_nonzero(plan.kind == SIGHTINGS) == len(np.unique(obs))
    # offline (mrclam.localize.run): events by (time, odometry first)
    offline, poses = _localizer(int(odom_ns[0])), []
    starts = np.flatnonzero(np.r_[True, obs[1:] != obs[:-1]])
    ends = np.r_[starts[1:], len(obs)]
    events = sorted([(t, 0, k) for k, t in enumerate(odom_ns)]
                    + [(obs_ns[s], 1, j) for j, s in enumerate(starts)])
    for _, kind, k in events:
        if kind == 0:
            poses.append(offline.add_odometry(odom_ns[k], twist=twist[k]))
        else:
            offline.add_observations(obs_ns[starts[k]], ids[starts[k]:ends[k]],
                                     z[starts[k]:ends[k]])
    # The node, initialised from its parameter, takes a batch anywhere from the moment
    # the player may send it (its poses received: odometry still in flight is taken
    # later) to the barrier before the next odometry: both extremes.
    for earliest in (False, True):
        order = [(i, i) for i in range(len(plan))]
        if earliest:
            odometry = np.cumsum(plan.kind == ODOMETRY)  # odometry sent up to item i
            at, slots = 0, []
            for i in range(len(plan)):
                if plan.kind[i] == SIGHTINGS:
                    at = max(at, int(plan.after_poses[i]))
                    assert at <= odometry[i]
                    slots.append((np.flatnonzero(odometry == at)[0] if at else -1, i))
            batches_at = {}
            for slot, i in slots:
                batches_at.setdefault(slot, []).append(i)
            order = [(-1, i) for i in batches_at.get(-1, [])]
            for i in np.flatnonzero(plan.kind == ODOMETRY):
                order += [(i, i)] + [(i, j) for j in batches_at.get(i, [])]
        node, node_poses = _localizer(None), []
        for _, i in order:
            if plan.kind[i] == ODOMETRY:
                node_poses.append(node.add_odometry(plan.stamp_ns[i],
                                                    twist=twist[plan.index[i]]))
            else:
                a, b = plan.index[i], plan.end[i]
                node.add_observations(plan.stamp_ns[i], ids[a:b], z[a:b])
        assert offline.counters['rows_used'] > 20
        assert not hide or offline.counters['associated'] > 20
        for key in ('rows_used', 'rows_gated', 'too_old', 'associated'):
            assert node.counters[key] == offline.counters[key], key
        for p, q in zip(poses, node_poses):
            assert p.stamp_ns == q.stamp_ns
            np.testing.assert_array_equal(p.x, q.x)
            np.testing.assert_array_equal(p.P, q.P)
    # every batch after the first pose; a barrier before each odometry after sightings
    assert np.all(plan.after_poses[plan.kind == SIGHTINGS] >= 1)
    after_batch = np.flatnonzero((plan.kind[1:] == ODOMETRY) & (plan.kind[:-1] == SIGHTINGS)) + 1
    assert np.array_equal(np.flatnonzero(plan.barrier), after_batch)


def test_slice_run_keeps_the_first_seconds():
    robot = SimpleNamespace(times=np.array([0.0, 1.0, 2.0, 3.0]), ids=np.arange(4),
                            z=np.zeros((4, 2)), poses=np.zeros((4, 3)))
    from landmark_ros.mrclam.data import Dataset, Robot
    from landmark_ros.mrclam.localize_data import RobotExtras
    r = Robot(1, robot.times, robot.ids, robot.z, robot.poses, np.array([0.0, 9.0]),
              np.zeros((2, 3)))
    d = Dataset(Path('.'), [r], {}, {}, {})
    ex = {1: RobotExtras(1, np.arange(0.0, 4.0, 0.5), np.zeros((8, 2)), np.array([0.5, 2.5]),
                         np.array([2, 3]), np.zeros((2, 2)))}
    d2, ex2 = slice_run(d, ex, 2.0)
    assert d2.robots[0].times.tolist() == [0.0, 1.0]
    assert ex2[1].odom_times.tolist() == [0.0, 0.5, 1.0, 1.5]
    assert ex2[1].sighting_robot.tolist() == [2] and len(d2.robots[0].gt_times) == 2
    # a later window (--start): from the start on, to its end, the truth whole
    d3, ex3 = slice_run(d, ex, 1.5, start_s=1.5)
    assert d3.robots[0].times.tolist() == [2.0]
    assert ex3[1].odom_times.tolist() == [1.5, 2.0, 2.5]
    assert ex3[1].sighting_robot.tolist() == [3] and len(d3.robots[0].gt_times) == 2
    d4, ex4 = slice_run(d, ex, None, start_s=2.5)
    assert d4.robots[0].times.tolist() == [3.0] and ex4[1].odom_times.tolist() == [2.5, 3.0, 3.5]


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
def test_through_the_nodes_equals_the_offline_run(tmp_path):
    from landmark_ros.mrclam.cli import main
    from rosutil import next_domain_id
    out = tmp_path / 'loc.json'
    code = main([str(DATASET), '--localize', '--through-nodes', '--duration', '10',
                 '--no-progress', '--domain-id', str(next_domain_id()), '--json', str(out)])
    assert code == 0
    document = json.loads(out.read_text())
    agreement = {a['map']: a for a in document['localization_agreement']}
    assert set(agreement) == {'dead_reckoning', 'surveyed', 'fused'}
    for a in agreement.values():
        assert a['same_stamps'] and a['same_counts']
        # the same calls in the same order: equal but for the heading's quaternion
        assert a['max_position_diff_m'] == 0.0 and a['max_cov_diff'] == 0.0
        assert a['max_heading_diff_rad'] < 1e-12 and a['max_metric_diff'] < 1e-12
    nodes = {e['map']: e for e in document['localization_nodes']}
    assert nodes['surveyed']['rows_used'] > 50
    assert set(nodes['surveyed']) >= set(document['localization'][0]) - {'seconds'}
