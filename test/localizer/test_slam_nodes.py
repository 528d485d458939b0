"""``landmark_mrclam --slam --through-nodes``: the order of its steps, and the agreement."""

from dataclasses import replace
import json
from pathlib import Path

from landmark_ros.core import sensors
from landmark_ros.eval.slam_loop import LoopConfig
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer, UNKNOWN_ID
from landmark_ros.mrclam.data import Dataset, interpolate_poses, Robot, seconds_to_stamps_ns
from landmark_ros.mrclam.localize_data import RobotExtras
from landmark_ros.mrclam.localize_plan import batches
from landmark_ros.mrclam.slam_plan import offline_reference, plan, start_pose
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.observer.precision import precision_level, precision_topics
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
import numpy as np
import pytest

DATASET = next((p / 'shared' / 'data' / 'mrclam' / 'dataset6'
                for p in Path(__file__).resolve().parents[3:5]
                if (p / 'shared' / 'data' / 'mrclam' / 'dataset6').is_dir()),
               Path('/nonexistent'))

T0 = 100.0
"""Start of the synthetic runs [s] (stamps must be positive)."""


def _robot(number, rng, landmarks, seconds):
    """Return a robot on a circle: sightings (ties, between, before its odometry), odometry."""
    v, w, th0 = 0.3, 0.15 * number, rng.uniform(-np.pi, np.pi)
    gt_times = T0 - 1.0 + np.arange(0.0, seconds + 2.0, 0.005)
    th = th0 + w * (gt_times - T0)
    gt = np.column_stack([number + v / w * (np.sin(th) - np.sin(th0)),
                          -v / w * (np.cos(th) - np.cos(th0)), np.angle(np.exp(1j * th))])
    odom = T0 + np.round(np.cumsum(rng.uniform(0.01, 0.04, int(seconds / 0.02))), 3)
    odom = odom[odom < T0 + seconds]
    if number == 2:  # a gap in the odometry: messages wait, some too long
        odom = odom[(odom < T0 + 5.0) | (odom > T0 + 6.5)]
    twist = np.column_stack([np.full(len(odom), v), np.full(len(odom), w)])
    twist += rng.normal(0.0, 0.01, twist.shape)
    stamps = np.concatenate([rng.choice(odom, 30), np.round(rng.uniform(
        T0, odom[-1] + 0.1, 60), 3), [T0 - 0.5]])  # ties, between, before the first
    if number == 2:  # in the gap: one placed with the last pose (stale), one dropped
        last = odom[odom < T0 + 5.0][-1]
        stamps = np.concatenate([stamps[(stamps < T0 + 5.0) | (stamps > T0 + 6.5)],
                                 np.round([last + 0.05, last + 0.4, last + 0.95], 3)])
    stamps = np.unique(stamps)
    times = np.repeat(stamps, rng.integers(1, 4, len(stamps)))
    ids = rng.choice(sorted(landmarks), len(times))
    poses, _ = interpolate_poses(gt_times, gt, times)
    z = sensors.observe(poses, np.array([landmarks[i] for i in ids]))
    z += rng.normal(0.0, [0.02, 0.01], z.shape)
    extras = RobotExtras(number, odom, twist, np.zeros(0), np.zeros(0, np.int64),
                         np.zeros((0, 2)))
    return Robot(number, times, ids, z, poses, gt_times, gt), extras


def _synthetic(seed, robots=3, seconds=12.0):
    rng = np.random.default_rng(seed)
    landmarks = {10 + i: tuple(rng.uniform(-3.0, 5.0, 2)) for i in range(6)}
    pairs = [_robot(n, rng, landmarks, seconds) for n in range(1, robots + 1)]
    dataset = Dataset(Path('.'), [r for r, _ in pairs], landmarks,
                      {i: (0.001, 0.001) for i in landmarks}, {})
    return dataset, {r.number: ex for r, ex in pairs}


CONFIG = LoopConfig(LocalizerConfig(initial_stddev=(0.01, 0.01, 0.01)),
                    ObserverConfig(range_stddev=0.05, bearing_stddev=0.02),
                    FuserConfig(min_observations=2))


class _Nodes:
    """The nodes' pipeline objects, driven the way ``slam_nodes.SlamPlayer`` drives them."""

    def __init__(self, dataset, extras, delay_s, config):
        self.robots = dataset.robots
        self.extras = [extras[r.number] for r in dataset.robots]
        self.locs = [Localizer(replace(config.localizer, initial_pose=tuple(
            start_pose(r, extras, delay_s)))) for r in dataset.robots]
        self.observers = [Observer(config.observer) for _ in dataset.robots]
        self.topics = [precision_topics(f'/{r.name}/landmarks',
                                        config.observer.precision_sources)
                       for r in dataset.robots]
        self.fuser = Fuser(config.fuser, [t for topics in self.topics for t in topics])
        self.observer_config = config.observer
        self.hide_ids = config.hide_ids
        self.held = [None] * len(self.robots)
        self.the_map = self.fuser.snapshot()
        self.odom_ns = [seconds_to_stamps_ns(ex.odom_times + delay_s) for ex in self.extras]
        self.sent = [0] * len(self.robots)
        self.published = [[] for _ in self.robots]

    def odometry(self, r, upto):
        """Send robot ``r``'s odometry up to ``upto``; return what its observer placed."""
        placed = []
        while self.sent[r] < upto:
            stamp = int(self.odom_ns[r][self.sent[r]])
            est = self.locs[r].add_odometry(stamp, twist=self.extras[r].odom_twist[self.sent[r]])
            self.published[r].append((est.stamp_ns, est.x.copy(), est.P.copy()))
            placed += self.observers[r].add_pose(stamp, est.x, est.P, now_ns=stamp)
            self.sent[r] += 1
        return placed

    def step(self, r, stamp, rows, hold, stale=False):
        """Give the sightings to the localizer (against the map), then observer and fuser."""
        ids, z = rows
        if self.hide_ids:  # the player's clouds: every row UNKNOWN_ID
            ids = np.full(len(ids), UNKNOWN_ID, np.int64)
        if self.held[r] is not self.the_map:  # the node takes each map once
            self.locs[r].set_map(*self.the_map[:3])
            self.held[r] = self.the_map
        self.locs[r].add_observations(stamp, ids, z)
        message = ObservationMessage(stamp, {'id': ids, 'range': z[:, 0], 'bearing': z[:, 1]})
        placed = self.observers[r].add_observations([message], now_ns=stamp)
        if stale:  # the player lets the node's observer time out on it
            assert not placed
            placed = self.observers[r].drain(now_ns=stamp + 10 ** 12)
        while not placed:  # before the first pose: placed when it comes
            assert self.sent[r] < hold
            placed = self.odometry(r, self.sent[r] + 1)
        (batch,) = placed
        if len(batch.ids):
            level = precision_level(batch.P_dep, self.observer_config.precision_sources,
                                    self.observer_config.precision_base_m)
            self.fuser.add_landmarks(self.topics[r][level], LandmarkMessage(
                batch.stamp_ns, batch.ids, batch.m, batch.P, batch.P_dep,
                classes=batch.classes, scan=batch.scan))
            self.fuser.fuse_queued()
            if self.fuser.map_changed:
                self.the_map = self.fuser.snapshot()


def _play(dataset, extras, delay_s, rng, config=CONFIG):
    """Play the steps; every other robot's odometry runs ahead by a random amount."""
    steps = plan(dataset, extras, delay_s, config.observer)
    nodes = _Nodes(dataset, extras, delay_s, config)
    count = len(dataset.robots)
    hold = [len(n) for n in nodes.odom_ns]
    for i in range(len(steps) - 1, -1, -1):
        hold[int(steps.robot[i])] = int(steps.poses[i])
    for i in range(len(steps)):
        r = int(steps.robot[i])
        for q in range(count):  # the others anywhere up to their own next step
            assert not nodes.odometry(q, int(rng.integers(nodes.sent[q], hold[q] + 1)))
        assert not nodes.odometry(r, int(steps.poses[i]))
        later = np.flatnonzero(steps.robot[i + 1:] == r)
        hold[r] = int(steps.poses[i + 1 + later[0]]) if len(later) else len(nodes.odom_ns[r])
        a, b = int(steps.start[i]), int(steps.end[i])
        robot = dataset.robots[r]
        nodes.step(r, int(steps.stamp_ns[i]), (robot.ids[a:b], robot.z[a:b]), hold[r],
                   bool(steps.stale[i]))
    for q in range(count):
        assert not nodes.odometry(q, len(nodes.odom_ns[q]))
    return steps, nodes


HIDDEN = replace(CONFIG, hide_ids=True, association='localizer',
                 localizer=replace(CONFIG.localizer, association_merge_ambiguous=True))


def _assert_same(reference, nodes):
    loop = reference.loop
    for pub, mine, loc, offline in zip(reference.published, nodes.published, nodes.locs,
                                       loop.localizers):
        assert [s for s, _, _ in mine] == pub['stamps_ns'].tolist()
        np.testing.assert_array_equal(np.array([x for _, x, _ in mine]), pub['x'])
        np.testing.assert_array_equal(np.array([P for _, _, P in mine]), pub['P'])
        for key in ('rows_used', 'rows_gated', 'refiltered', 'no_id', 'association_merged'):
            assert loc.counters[key] == offline.counters[key], key
    for a, b in zip(nodes.fuser.map.snapshot(), loop.fuser.map.snapshot()):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('seed, delay_s', [(0, 0.0), (1, 0.0), (2, 0.013)])
def test_the_steps_make_the_offline_loops_calls(seed, delay_s):
    dataset, extras = _synthetic(seed)
    reference = offline_reference(dataset, extras, CONFIG, delay_s)
    steps, nodes = _play(dataset, extras, delay_s, np.random.default_rng(seed))
    loop = reference.loop
    assert len(steps) == loop.counts['batches'] and steps.dropped >= len(dataset.robots) + 1
    assert np.count_nonzero(steps.stale) >= 1
    assert loop.counts['rows_to_localizer'] > 100 and len(loop.map_records()) >= 4
    _assert_same(reference, nodes)


def test_the_steps_with_precision_sources_make_the_offline_loops_calls():
    # Each observer sends a message to the topic of its precision level, the fuser
    # takes each topic as a source: as the loop splits a robot's rows.
    config = replace(CONFIG, observer=replace(CONFIG.observer, precision_sources=3,
                                              precision_base_m=0.01))
    dataset, extras = _synthetic(5)
    reference = offline_reference(dataset, extras, config, 0.0)
    _, nodes = _play(dataset, extras, 0.0, np.random.default_rng(5), config)
    sources = reference.loop.fuser.sources
    assert list(sources) == [t for topics in nodes.topics for t in topics]
    fed = [name for name, source in sources.items() if source.counts['fused']]
    assert len(fed) > len(dataset.robots) and any('precision_2' in name for name in fed)
    assert {n: s.counts['fused'] for n, s in nodes.fuser.sources.items()} == {
        n: s.counts['fused'] for n, s in sources.items()}
    _assert_same(reference, nodes)


@pytest.mark.parametrize('seed', [0, 4])
def test_the_steps_without_ids_make_the_offline_loops_calls(seed):
    # The localizer names the rows itself against the map it holds (the node's own
    # association), the fuser's association places them: the node wiring, no track IDs.
    dataset, extras = _synthetic(seed)
    reference = offline_reference(dataset, extras, HIDDEN, 0.0)
    _, nodes = _play(dataset, extras, 0.0, np.random.default_rng(seed), HIDDEN)
    loop = reference.loop
    assert loop.counts['rows_to_localizer'] > 100 and len(loop.map_records()) >= 4
    assert sum(loc.counters['no_id'] for loc in nodes.locs) > 0.9 * sum(
        len(r.ids) for r in dataset.robots)
    assert sum(loc.counters['rows_used'] for loc in nodes.locs) > 100
    _assert_same(reference, nodes)


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
@pytest.mark.parametrize('hide_ids', [False, True])
def test_the_steps_on_mrclam_make_the_offline_loops_calls(hide_ids):
    from landmark_ros.mrclam import slam
    from landmark_ros.mrclam.config import load_config
    from landmark_ros.mrclam.data import load_dataset
    from landmark_ros.mrclam.localize import localizer_config
    from landmark_ros.mrclam.localize_cli import _sections
    from landmark_ros.mrclam.localize_data import load_all_extras
    from landmark_ros.mrclam.localize_plan import slice_run
    from landmark_ros.mrclam.slam_plan import without_robot_sightings
    replay = load_config(None)
    dataset = load_dataset(DATASET, replay.pose_stddev)
    extras = without_robot_sightings(load_all_extras(dataset))
    dataset, extras = slice_run(dataset, extras, 45.0)  # robot5 drops two messages
    localizer_values, replay_values = _sections(replay.path)
    # The file's loop, its precision sources as the observers publish them (slam_cli).
    config = replace(slam.loop_config(replay, localizer_config(localizer_values),
                                      replay_values), hide_ids=hide_ids)
    assert config.observer.precision_sources > 1
    assert config.association == 'localizer'  # config/mrclam.yaml: the node wiring
    delay_s = float(replay_values['odometry_delay_s'])
    reference = offline_reference(dataset, extras, config, delay_s)
    steps, nodes = _play(dataset, extras, delay_s, np.random.default_rng(0), config)
    assert len(steps) == reference.loop.counts['batches'] > 300 and steps.dropped == 2
    _assert_same(reference, nodes)


def test_a_step_waits_for_the_pose_after_its_stamp_or_tied_with_it():
    dataset, extras = _synthetic(3, robots=1)
    steps = plan(dataset, extras, 0.0, CONFIG.observer)
    odom_ns = seconds_to_stamps_ns(extras[1].odom_times)
    starts, _ = batches(dataset.robots[0].times)
    stamps = seconds_to_stamps_ns(dataset.robots[0].times[starts])
    # every message but the one long before the first odometry and those after the
    # last (no pose after them), once, in time order
    assert steps.dropped == 1 and np.count_nonzero(stamps > odom_ns[-1]) > 0
    assert steps.stamp_ns.tolist() == [s for s in stamps.tolist()
                                       if odom_ns[0] - 100_000_000 <= s <= odom_ns[-1]]
    newest = odom_ns[steps.poses - 1]
    assert np.all(newest >= steps.stamp_ns)  # the pose at or after its stamp is out
    previous = np.where(steps.poses >= 2, odom_ns[np.maximum(steps.poses - 2, 0)], 0)
    assert np.all(previous < steps.stamp_ns)  # and no later one


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
@pytest.mark.parametrize('hide_ids', [False, True])
def test_through_the_nodes_agrees_with_the_offline_loop(tmp_path, hide_ids):
    pytest.importorskip('rclpy')
    from landmark_ros.mrclam.cli import main
    from rosutil import next_domain_id
    out = tmp_path / 'slam.json'
    code = main([str(DATASET), '--slam', '--through-nodes', '--duration', '12',
                 '--no-progress', '--domain-id', str(next_domain_id()), '--json', str(out)]
                + ['--hide-ids'] * hide_ids)
    assert code == 0
    document = json.loads(out.read_text())
    (a,) = document['slam_agreement']
    # The same calls in the same order: every step waits for what the nodes report they
    # took (the map in use, the sightings, the fused cloud), never for DDS to order two
    # writers. Equal but for the heading's quaternion round trip.
    assert a['same_stamps'] and a['same_rows'] and a['same_map_ids']
    assert a['max_position_diff_m'] < 1e-12 and a['max_heading_diff_rad'] < 1e-12
    assert a['max_cov_diff'] < 1e-12 and a['max_figure_diff'] < 1e-9
    assert a['max_map_mean_diff_m'] < 1e-12 and a['max_map_cov_diff'] < 1e-12
    (entry,) = document['slam_nodes']
    assert entry['ids_hidden'] == hide_ids
    assert entry['rows_used'] > 50 and entry['tracks_confirmed'] >= 5
    assert entry['player']['maps_expected'] > 20 and entry['player']['map_waits'] > 0
    # loop_counts and dependent_stddev_m are the offline TeamLoop's own records
    assert set(entry) >= set(document['slam'][0]) - {'seconds', 'loop_counts', 'cpu_seconds',
                                                     'robot_rows_used', 'dependent_stddev_m'}
