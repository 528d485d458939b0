"""
``landmark_mrclam --localize --through-nodes``: the localization through the real nodes.

Per map (dead reckoning, surveyed, fused; landmark sightings only) one
``landmark_localizer`` process per robot (namespace ``robotN``, started by
``landmark_ros.ros.launcher`` in a private ROS domain on the loopback interface) with
``--params-file`` the replay's config plus a file of its own: ``initial_pose`` (the
ground truth at its first odometry stamp, the offline run's start), ``map_file`` (the
map written in the fuser's map-file format: JSON, every float exact) and the transport
``LOCALIZER_TRANSPORT``; its ``odometry`` and ``observations`` inputs reliable (QoS
override parameters). A player in this process publishes each robot's odometry
(``nav_msgs/Odometry``, twist only, as the offline run feeds it) and its sighting
batches (the observation cloud: ``id``, ``range``, ``bearing`` in float64) in the order
of ``localize_plan.schedule``, at most ``WINDOW`` odometry messages in flight per robot
(each gives one ``pose``), and collects the poses. The node's diagnostics give the
rows used and gated, and the sighting messages taken in (``observation_messages_in``):
an odometry message after sightings waits until they are all in. ``compare`` measures
the agreement with the offline tracks.

With rows without IDs (``--hide-ids``) every batch also waits for the pose of the
odometry before it (``schedule(strict=True)``): the association uses the newest pose at
or before the batch's stamp, which must be the offline run's.

The robot-to-robot sightings are not replayed through the nodes: the node applies a
sighting with the other robot's latest published pose, the offline run with the other's
pose at the sighting's stamp, and the two differ by design.
"""

from dataclasses import dataclass, replace
import math
import os
from pathlib import Path
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.fuser import map_file
from landmark_ros.localizer.localizer import UNKNOWN_ID
from landmark_ros.mrclam.data import interpolate_poses, seconds_to_stamps_ns
from landmark_ros.mrclam.localize import Track
from landmark_ros.mrclam.localize_plan import ODOMETRY, schedule
from landmark_ros.mrclam.replay_plan import cpu_seconds, ReplayError
from landmark_ros.ros import qos
from landmark_ros.ros.conversions import pose_from_msg, stamp_ns
from landmark_ros.ros.launcher import Launcher, write_params_file
from landmark_ros.ros.schemas import observation_message
from nav_msgs.msg import Odometry
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

LOCALIZER_TRANSPORT = {'input_depth': 10000, 'diagnostics_period_s': 0.01}
"""Localizer parameters the replay sets on top of the config file (transport only): the
player waits for the diagnostics that count the sightings in."""

WINDOW = 100
"""Odometry messages in flight per robot (sent, pose not received yet)."""

STALL_S = 120.0
"""A replay that makes no progress this long fails."""


def _time(ns):
    return Time(sec=int(ns) // 1_000_000_000, nanosec=int(ns) % 1_000_000_000)


def write_map(path, the_map):
    """Write ``(ids, m, P_m)`` as a map file in the map frame; return its path."""
    ids, m, P = the_map
    records = [{'id': int(i), 'mean': [float(v) for v in mean],
                'covariance': [[float(v) for v in row] for row in cov], 'observations': 0}
               for i, mean, cov in zip(ids, m, P)]
    map_file.save(str(path), records, 'map', 'mrclam')
    return path


def localizer_arguments(robot, config_path, params_path):
    """Return the ROS arguments of a robot's localizer process."""
    ns = f'/{robot.name}'
    arguments = ['-r', f'__ns:={ns}', '--params-file', str(config_path),
                 '--params-file', str(params_path)]
    for topic in ('odometry', 'observations'):
        arguments += ['-p', f'qos_overrides.{ns}/{topic}.subscription.reliability:=reliable']
    return arguments


@dataclass
class _Robot:
    """The player's state for one robot."""

    robot: object
    extras: object
    plan: object
    odom_pub: object
    obs_pub: object
    next_item: int = 0
    sent_odometry: int = 0
    sent_sightings: int = 0
    """Clouds sent (the empty one of ``connect`` included)."""

    def __post_init__(self):
        self.poses = []
        self.counts = None
        self.n_odometry = int(np.count_nonzero(self.plan.kind == ODOMETRY))


class LocalizePlayer:
    """Publish every robot's schedule into its localizer and collect the poses."""

    def __init__(self, node, executor, launcher, streams):
        """Create the publishers and pose subscriptions of each robot."""
        self.node, self.executor, self.launcher = node, executor, launcher
        depth = qos.reliable_output(10000)
        self.robots = []
        for robot, extras, plan in streams:
            ns = f'/{robot.name}'
            state = _Robot(robot, extras, plan,
                           node.create_publisher(Odometry, f'{ns}/odometry', depth),
                           node.create_publisher(PointCloud2, f'{ns}/observations', depth))
            node.create_subscription(PoseWithCovarianceStamped, f'{ns}/pose',
                                     lambda msg, s=state: s.poses.append(msg), depth)
            self.robots.append(state)
        by_name = {f'/{s.robot.name}/landmark_localizer': s for s in self.robots}
        node.create_subscription(DiagnosticArray, '/diagnostics',
                                 lambda msg: self._diagnostics(msg, by_name),
                                 qos.DIAGNOSTICS)
        self._odom = Odometry()
        self._odom.header.frame_id, self._odom.child_frame_id = 'odom', 'base_link'
        self.play_wall_s = 0.0

    def _diagnostics(self, msg, by_name):
        for status in msg.status:
            state = by_name.get(status.name)
            if state is not None:
                state.counts = {kv.key: kv.value for kv in status.values}

    def spin_until(self, predicate, timeout_s, what):
        """Spin until ``predicate()``; raise ReplayError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                raise ReplayError(f'timed out after {timeout_s:.0f} s waiting for {what}')
            self.launcher.check()
            self.executor.spin_once(timeout_sec=0.05)

    def connect(self, timeout_s=120.0):
        """Wait until every localizer's inputs and outputs match."""
        def matched():
            return all(s.odom_pub.get_subscription_count() and s.obs_pub.get_subscription_count()
                       for s in self.robots)
        self.spin_until(matched, timeout_s, 'the localizers to connect')
        for state in self.robots:  # the pose outputs too
            self.spin_until(lambda: self.node.count_publishers(
                f'/{state.robot.name}/pose') > 0, timeout_s, f'{state.robot.name}/pose')
        # An empty cloud each, acknowledged: the node's reader has matched this writer
        # (a sample sent before would be repaired later, out of order).
        empty = observation_message(Header(frame_id='base_link'), [], np.zeros((0, 2)))
        for state in self.robots:
            state.obs_pub.publish(empty)
            state.sent_sightings += 1
        for state in self.robots:
            if not state.obs_pub.wait_for_all_acked(Duration(seconds=timeout_s)):
                raise ReplayError(f'{state.robot.name}/observations never acknowledged')

    def _send(self, state, limit):
        """Send up to ``limit`` items of a robot's schedule; return how many."""
        plan, sent = state.plan, 0
        while state.next_item < len(plan) and sent < limit:
            i = state.next_item
            if plan.kind[i] == ODOMETRY:
                if plan.barrier[i] and taken(state) < state.sent_sightings:
                    return sent
                if state.sent_odometry - len(state.poses) >= WINDOW:
                    return sent
                self._publish_odometry(state, plan.stamp_ns[i], plan.index[i])
                state.sent_odometry += 1
            else:
                if len(state.poses) < plan.after_poses[i]:
                    return sent
                r, a, b = state.robot, plan.index[i], plan.end[i]
                state.obs_pub.publish(observation_message(
                    Header(stamp=_time(plan.stamp_ns[i]), frame_id='base_link'),
                    r.ids[a:b], r.z[a:b]))
                state.sent_sightings += 1
            state.next_item += 1
            sent += 1
        return sent

    def _publish_odometry(self, state, stamp, k):
        msg = self._odom
        msg.header.stamp = _time(stamp)
        v, w = state.extras.odom_twist[k]
        msg.twist.twist.linear.x, msg.twist.twist.angular.z = float(v), float(w)
        state.odom_pub.publish(msg)

    def play(self, progress=None):
        """Send every schedule; return when every pose and final diagnostics are in."""
        t0 = last = time.monotonic()
        total = sum(s.n_odometry for s in self.robots)
        done = 0
        while any(len(s.poses) < s.n_odometry for s in self.robots):
            sent = sum(self._send(s, 200) for s in self.robots)
            self.executor.spin_once(timeout_sec=0.0 if sent else 0.02)
            now_done = sum(len(s.poses) for s in self.robots)
            now = time.monotonic()
            if sent or now_done != done:
                last, done = now, now_done
            elif now - last > STALL_S:
                raise ReplayError(f'no progress for {STALL_S:.0f} s ({done} of {total} poses)')
            if now - t0 > 0.5 and int(now * 2) != int((now - 0.05) * 2):
                self.launcher.check()
            if progress is not None:
                progress(done / max(total, 1))
        self.play_wall_s = time.monotonic() - t0
        self.spin_until(lambda: all(
            s.counts is not None and int(s.counts.get('odometry', -1)) == s.n_odometry
            for s in self.robots), 60.0, 'the final diagnostics')

    def tracks(self):
        """Return one ``localize.Track`` per robot from the received poses."""
        return [track(s.robot, s.poses, s.counts) for s in self.robots]


def published_arrays(messages):
    """Return stamps (K,) [ns], poses (K, 3), covariances (K, 3, 3) of pose messages."""
    stamps = np.array([stamp_ns(m.header.stamp) for m in messages], np.int64)
    xP = [pose_from_msg(m, 'map') for m in messages]
    return (stamps, np.array([a for a, _ in xP]).reshape(-1, 3),
            np.array([b for _, b in xP]).reshape(-1, 3, 3))


def track(robot, messages, values):
    """
    Return a robot's ``localize.Track`` from its pose messages inside the ground truth.

    ``values``: the localizer's last diagnostics values (strings; None: none came); its
    counters are the integers among them (``map_stamp_ns`` left out).
    """
    stamps, x, P = published_arrays(messages)
    times = stamps * 1e-9
    truth, inside = interpolate_poses(robot.gt_times, robot.gt_poses, times)
    counts = {k: int(v) for k, v in (values or {}).items()
              if v.lstrip('-').isdigit() and k != 'map_stamp_ns'}
    return Track(robot.number, times[inside], x[inside], P[inside], truth[inside], counts)


def taken(state):
    """Return the sighting messages a robot's localizer counts in (its diagnostics)."""
    return int((state.counts or {}).get('observation_messages_in', -1))


def _start(launcher, dataset, extras, setup):
    """Start one localizer per robot; return the per-robot streams for the player."""
    config_path, work, delay_s, the_map, name = setup
    map_path = write_map(work / f'{name}.json', the_map) if the_map is not None else ''
    streams = []
    for robot in dataset.robots:
        ex = extras[robot.number]
        start = ex.odom_times[0] + delay_s
        pose, _ = interpolate_poses(robot.gt_times, robot.gt_poses, [start])
        params = work / f'{name}_{robot.name}.yaml'
        write_params_file(params, {f'/{robot.name}/landmark_localizer': {
            **LOCALIZER_TRANSPORT, 'initial_pose': [float(v) for v in pose[0]],
            'map_file': str(map_path)}})
        launcher.start_module(f'localizer_{name}_{robot.name}', 'landmark_ros.nodes.localizer',
                              localizer_arguments(robot, config_path, params))
        shown = robot if the_map is not None else _without_sightings(robot)
        # rows without IDs: the node must associate from the offline run's pose
        strict = bool(np.any(shown.ids == UNKNOWN_ID))
        streams.append((shown, ex, schedule(shown, ex, delay_s, strict)))
    return streams


def _without_sightings(robot):
    return replace(robot, times=robot.times[:0], ids=robot.ids[:0], z=robot.z[:0])


def run_map(dataset, extras, setup, context, progress=None):
    """
    Localize every robot through the nodes against one map; return tracks and timing.

    ``setup`` is ``(config_path, work, delay_s, the_map or None, name)``.
    """
    config_path, work, _, _, name = setup
    launcher = Launcher(work / name, domain_id=context[1])
    node = executor = None
    try:
        streams = _start(launcher, dataset, extras, setup)
        node = rclpy.create_node(f'landmark_mrclam_localize_{name}', context=context[0],
                                 start_parameter_services=False)
        executor = SingleThreadedExecutor(context=context[0])
        executor.add_node(node)
        player = LocalizePlayer(node, executor, launcher, streams)
        t0 = time.monotonic()
        player.connect()
        startup_s = time.monotonic() - t0
        player.play(progress)
        cpu = cpu_seconds({n: p.pid for n, p in launcher.processes.items()})
        info = {'startup_s': startup_s, 'play_wall_s': player.play_wall_s,
                'node_cpu_s': round(sum(cpu.values()), 2)}
        return player.tracks(), info
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        codes = launcher.stop()
        bad = {n: c for n, c in codes.items() if c != 0}
        if bad:
            print(f'localizer processes exited with {bad}; logs in {work / name}')


def compare(offline, nodes):
    """
    Return the agreement of the node tracks with the offline ones (one run).

    Keys: ``same_stamps`` (every robot the same odometry stamps), ``same_counts`` (rows
    used and gated, re-filtered batches), ``max_position_diff_m``, ``max_heading_diff_rad``,
    ``max_cov_diff`` (largest absolute difference of a covariance entry).
    """
    same_stamps = same_counts = True
    dpos = dyaw = dcov = 0.0
    for a, b in zip(offline, nodes):
        if len(a.times) != len(b.times) or not np.array_equal(
                seconds_to_stamps_ns(a.times), seconds_to_stamps_ns(b.times)):
            same_stamps = False
            continue
        for key in ('rows_used', 'rows_gated', 'refiltered'):
            same_counts &= a.counts.get(key, 0) == b.counts.get(key, 0)
        if len(a.x):
            dpos = max(dpos, float(np.max(np.hypot(*(a.x[:, :2] - b.x[:, :2]).T))))
            d = np.angle(np.exp(1j * (a.x[:, 2] - b.x[:, 2])))
            dyaw = max(dyaw, float(np.max(np.abs(d))))
            dcov = max(dcov, float(np.max(np.abs(a.P - b.P))))
    return {'same_stamps': same_stamps, 'same_counts': bool(same_counts),
            'max_position_diff_m': dpos, 'max_heading_diff_rad': dyaw,
            'max_cov_diff': dcov}


def run_through_nodes(dataset, extras, config_path, maps, delay_s, domain_id, work,
                      progress_factory=None):
    """
    Run dead reckoning and each map through the nodes; return tracks and info by run.

    ``maps``: name -> (ids, m, P_m). Returns ``{name: (tracks, info)}`` with
    ``dead_reckoning`` first.
    """
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = Context()
    rclpy.init(args=['landmark_mrclam'], context=context, domain_id=domain_id)
    results = {}
    try:
        for name, the_map in [('dead_reckoning', None), *maps.items()]:
            bar = progress_factory(f'{name} (nodes)') if progress_factory else None
            setup = (Path(config_path).resolve(), Path(work), delay_s, the_map, name)
            try:
                results[name] = run_map(dataset, extras, setup, (context, domain_id),
                                        bar.update if bar else None)
            finally:
                if bar:
                    bar.close()
        return results
    finally:
        rclpy.try_shutdown(context=context)


def real_time_factor(duration_s, info):
    """Return the data duration over the play's wall time (nan without a play)."""
    wall = info.get('play_wall_s') or 0.0
    return duration_s / wall if wall > 0 else math.nan
