"""
``landmark_mrclam --slam --through-nodes``: the closed loop through the real nodes.

Processes (``landmark_ros.ros.launcher``, a private ROS domain on the loopback
interface), each with ``--params-file`` the replay's config: per robot a
``landmark_localizer`` (namespace ``robotN``: ``initial_pose`` the truth at its first
odometry stamp, its map from the fuser's ``fused_landmarks``) and a
``landmark_observer`` (its ``pose`` input is the localizer's ``pose`` output); one
``landmark_fuser`` (``/mrclam/slam``, the loop's fusion method, inputs
``/robotN/landmarks`` and, with the observers' ``precision_sources``, each robot's
``landmarks/precision_k``). The player in this process publishes each robot's odometry
(twist only) into its localizer and each sighting message into its localizer and its
observer, and follows the outputs.

Order. The player follows ``slam_plan.plan``, one step (a placed sighting message of
robot ``r``) at a time:

1. wait until ``r``'s localizer published the poses of the step (``Steps.poses``); its
   next odometry is held back until 3;
2. if the player received a map, wait until ``r``'s localizer holds it: its diagnostics
   (``localize_nodes.LOCALIZER_TRANSPORT``: every 10 ms) name the map in use by its header stamp
   (``map_stamp_ns``), the stamp of the player's newest map;
3. the sightings to the localizer (on ``localizer_observations``: the loop hands them to
   it before the fuser takes them, which one shared topic could not order); wait until
   its diagnostics count them in (``observation_messages_in``);
4. the same cloud to the observer (a *stale* step, which the loop's observer placed
   with its newest pose after ``max_wait_s`` of stamps, with the odometry held and the
   observer's ``max_wait_s`` briefly set short: it gives up waiting the same way);
   wait for its ``landmarks`` output (on the topic of its precision level); a mirror
   ``Fuser`` in the player fed with that very cloud says whether the map changes: if
   so, wait for the fuser's next ``fused_landmarks``, else until the fuser's
   diagnostics (every 50 ms) count as many messages in from ``r``'s observer as the
   player received, none queued (it fused the cloud before the next step's comes).

No step relies on DDS ordering two writers (the fuser's map and the player's sightings,
the player's sightings and its odometry, two observers' clouds at the fuser): each waits
for what the node itself reports it took. The robot-to-robot
sightings are not replayed (the node applies one with the other's latest published
pose, the loop with the other's estimate at the stamp, which includes the other's later
updates): the agreement is measured against ``slam_plan.offline_reference`` (the loop
without them), and the figures also beside the full offline ``--slam`` run. The node
publishes the pose of each odometry before the sightings it unblocks (what the
observer takes); ``TeamLoop`` records the estimate after them: the exact comparison is
with the published poses, the loop's own tracks differ at those stamps.

Live order (``live``, ``--live-order``). A robot whose localizer and observer share one
``observations`` topic gets the sightings to the localizer before the odometry that
passes their stamp: the localizer applies them before it publishes that pose, and the
observer places them with a pose that already holds them (their noise fed back once,
docs/slam.md). The player then sends each step's sightings to the localizer
one odometry message earlier; everything else as above. The difference to the offline
loop is what that order costs.
"""

from dataclasses import dataclass
import os
from pathlib import Path
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.mrclam.data import seconds_to_stamps_ns
from landmark_ros.mrclam.localize_nodes import (LOCALIZER_TRANSPORT, published_arrays,
                                                track, WINDOW)
from landmark_ros.mrclam.player import stamp_msg
from landmark_ros.mrclam.replay_plan import (cpu_seconds, observer_arguments,
                                             OBSERVER_TRANSPORT, ReplayError)
from landmark_ros.mrclam.slam_plan import plan, start_pose
from landmark_ros.observer.precision import precision_topics
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.ros import qos
from landmark_ros.ros.conversions import stamp_ns
from landmark_ros.ros.launcher import Launcher, write_params_file
from landmark_ros.ros.schemas import observation_message, read_landmark_clouds, read_landmarks
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

FUSER_NS = '/mrclam/slam'
"""Namespace of the loop's fuser."""

SLAM_FUSER_TRANSPORT = {
    'update_period_s': 0.005, 'publish_rate_hz': 200.0, 'updates_rate_hz': 200.0,
    'max_queue_messages': 100000, 'input_depth': 1000, 'diagnostics_period_s': 0.05,
    'source_timeout_s': 86400.0, 'autosave_period_s': 0.0,
}
"""Fuser parameters the replay sets on top of the config file (timers and queues only):
a step waits for one fuse and one map publication or one diagnostics message, so short
periods keep it quick."""

STEP_TIMEOUT_S = 120.0
"""A step that makes no progress this long fails."""

STALE_WAIT_S = 0.2
"""The observer's ``max_wait_s`` [wall s] while it places a stale step."""


def _param(name, value):
    if isinstance(value, (list, tuple)):
        value = '[' + ', '.join(f"'{v}'" for v in value) + ']'
    return ['-p', f'{name}:={value}']


def localizer_arguments(robot, config_path, params_path):
    """Return the ROS arguments of a robot's localizer in the loop."""
    ns = f'/{robot.name}'
    arguments = ['-r', f'__ns:={ns}', '-r', 'observations:=localizer_observations',
                 '-r', f'fused_landmarks:={FUSER_NS}/fused_landmarks',
                 '--params-file', str(config_path), '--params-file', str(params_path)]
    for topic in ('odometry', 'localizer_observations'):
        arguments += _param(f'qos_overrides.{ns}/{topic}.subscription.reliability',
                            'reliable')
    return arguments


def fuser_arguments(topics, config_path, fusion):
    """Return the ROS arguments of the loop's fuser."""
    arguments = ['-r', f'__ns:={FUSER_NS}', '--params-file', str(config_path)]
    for name, value in dict(SLAM_FUSER_TRANSPORT, input_topics=list(topics), fusion=fusion,
                            source_correlation='unknown',
                            move_false_alarm_rate=0.0).items():    # slam.loop_config
        arguments += _param(name, value)
    return arguments


@dataclass
class _Robot:
    """The player's endpoints and state for one robot."""

    robot: object
    extras: object
    odom_ns: np.ndarray
    odom_pub: object = None
    loc_pub: object = None
    obs_pub: object = None
    client: object = None
    observer_params: object = None
    sent: int = 0
    hold: int = 0
    loc_sent: int = 0
    """Clouds sent to the localizer (the empty one of ``connect`` included)."""
    map_stamp: int = -1
    """``map_stamp_ns`` of the localizer's newest diagnostics."""
    topics: tuple = ()
    """The robot's landmark topics, one per precision level (``observer.precision``)."""

    def __post_init__(self):
        self.poses, self.counts, self.diagnostics = [], None, 0
        self.outputs = []
        """``(topic, cloud)`` of every landmark message of the observer, in arrival order."""
        self.fused = {}
        """Per topic ``messages_in`` and ``queued_messages`` of the fuser's diagnostics."""

    def fused_in(self):
        """Return the messages the fuser took from this robot, and how many are queued."""
        if len(self.fused) < len(self.topics):
            return -1, -1
        return (sum(a for a, _ in self.fused.values()),
                sum(b for _, b in self.fused.values()))


class SlamPlayer:
    """Play the loop's steps into the nodes (module docstring) and collect the outputs."""

    def __init__(self, node, executor, launcher, setup):
        """
        Create the endpoints; ``setup`` is ``(dataset, extras, delay_s, loop_config, live)``.

        ``live``: each localizer takes a step's sightings one odometry message earlier
        (``take``), before the odometry that passes their stamp, as with one shared
        ``observations`` topic: the pose it publishes there already holds them.
        """
        dataset, extras, delay_s, loop_config, live = setup
        self.node, self.executor, self.launcher = node, executor, launcher
        self.steps = plan(dataset, extras, delay_s, loop_config.observer)
        self.live = bool(live)
        self.hide_ids = bool(loop_config.hide_ids)
        self.take = self.steps.poses - 1 if live else self.steps.poses
        """Poses each step's localizer has published when it takes the sightings, (S,)."""
        depth = qos.reliable_output(10000)
        self.robots = []
        for robot in dataset.robots:
            ex, ns = extras[robot.number], f'/{robot.name}'
            s = _Robot(robot, ex, seconds_to_stamps_ns(ex.odom_times + delay_s),
                       topics=tuple(precision_topics(
                           f'{ns}/landmarks', loop_config.observer.precision_sources)))
            s.odom_pub = node.create_publisher(Odometry, f'{ns}/odometry', depth)
            s.loc_pub = node.create_publisher(PointCloud2, f'{ns}/localizer_observations',
                                              depth)
            s.obs_pub = node.create_publisher(PointCloud2, f'{ns}/observations', depth)
            s.client = node.create_client(GetParameters,
                                          f'{ns}/landmark_localizer/get_parameters')
            s.observer_params = node.create_client(
                SetParameters, f'{ns}/landmark_observer/set_parameters')
            node.create_subscription(PoseWithCovarianceStamped, f'{ns}/pose',
                                     lambda m, s=s: s.poses.append(m), depth)
            for topic in s.topics:
                node.create_subscription(PointCloud2, topic, lambda m, s=s, t=topic:
                                         s.outputs.append((t, m)), depth)
            self.robots.append(s)
        self.maps = []
        node.create_subscription(PointCloud2, f'{FUSER_NS}/fused_landmarks',
                                 self.maps.append, qos.LATCHED)
        self.fuser_client = node.create_client(
            GetParameters, f'{FUSER_NS}/landmark_fuser/get_parameters')
        by_name = {f'/{s.robot.name}/landmark_localizer': s for s in self.robots}
        by_name.update({f'{FUSER_NS}/landmark_fuser: {topic}': (s, topic)
                        for s in self.robots for topic in s.topics})
        node.create_subscription(DiagnosticArray, '/diagnostics',
                                 lambda msg: self._diagnostics(msg, by_name), qos.DIAGNOSTICS)
        self.sources = [topic for s in self.robots for topic in s.topics]
        self.mirror = Fuser(loop_config.fuser, self.sources)
        self.mirror.load()
        self._odom = Odometry()
        self._odom.header.frame_id, self._odom.child_frame_id = 'odom', 'base_link'
        self.info = {'order': 'live' if live else 'offline', 'steps': len(self.steps),
                     'map_waits': 0, 'fuser_waits': 0,
                     'maps_expected': 0, 'maps_unexpected': 0, 'stale_steps': 0,
                     'dropped_messages': self.steps.dropped, 'play_wall_s': 0.0,
                     'wait_s': {}}

    def _diagnostics(self, msg, by_name):
        for status in msg.status:
            state = by_name.get(status.name)
            if state is None:
                continue
            values = {kv.key: kv.value for kv in status.values}
            if status.name.startswith(FUSER_NS):
                state, topic = state
                state.fused[topic] = (int(values.get('messages_in', 0)),
                                      int(values['queued_messages']))
                continue
            state.counts = values
            state.map_stamp = int(values.get('map_stamp_ns', -1))
            state.diagnostics += 1

    # ------------------------------------------------------------------ waiting
    def _pump(self):
        """Send every robot's odometry up to its hold and window; spin once."""
        sent = 0
        for s in self.robots:
            while (s.sent < min(s.hold, len(s.odom_ns))
                   and s.sent - len(s.poses) < WINDOW):
                msg = self._odom
                msg.header.stamp = stamp_msg(s.odom_ns[s.sent])
                v, w = s.extras.odom_twist[s.sent]
                msg.twist.twist.linear.x, msg.twist.twist.angular.z = float(v), float(w)
                s.odom_pub.publish(msg)
                s.sent += 1
                sent += 1
        self.executor.spin_once(timeout_sec=0.0 if sent else 0.01)

    def wait(self, predicate, what, timeout_s=STEP_TIMEOUT_S, phase=None):
        """
        Pump until ``predicate()``; raise ReplayError after ``timeout_s``.

        The time spent adds to ``info['wait_s'][phase]`` (``phase``: default ``what``).
        """
        deadline = checked = start = time.monotonic()
        deadline += timeout_s
        try:
            self._wait(predicate, what, deadline, checked)
        finally:
            key = phase or what
            waits = self.info['wait_s']
            waits[key] = waits.get(key, 0.0) + time.monotonic() - start

    def _wait(self, predicate, what, deadline, checked):
        timeout_s = deadline - checked
        while not predicate():
            now = time.monotonic()
            if now > deadline:
                raise ReplayError(f'timed out after {timeout_s:.0f} s waiting for {what}')
            if now - checked > 0.5:
                self.launcher.check()
                checked = now
            self._pump()

    def _map_stamp(self):
        """Return the header stamp of the newest fused map received [ns]."""
        return stamp_ns(self.maps[-1].header.stamp)

    # ------------------------------------------------------------------ connect
    def connect(self, timeout_s=120.0):
        """Wait until every link of the loop is matched; open the player's clouds."""
        graph = self.node

        def matched():
            for s in self.robots:
                ns = f'/{s.robot.name}'
                if not (s.odom_pub.get_subscription_count() and s.client.service_is_ready()
                        and s.observer_params.service_is_ready()
                        and s.loc_pub.get_subscription_count()
                        and s.obs_pub.get_subscription_count()
                        and graph.count_subscribers(f'{ns}/pose') >= 2
                        and graph.count_publishers(f'{ns}/pose') >= 1
                        and all(graph.count_subscribers(t) >= 2 and graph.count_publishers(t)
                                for t in s.topics)):
                    return False
            return (self.fuser_client.service_is_ready() and graph.count_subscribers(
                f'{FUSER_NS}/fused_landmarks') >= len(self.robots) + 1)
        self.wait(matched, 'the nodes to connect', timeout_s)
        for s in self.robots:
            topic = f'/{s.robot.name}/localizer_observations'
            for info in graph.get_subscriptions_info_by_topic(topic):
                if info.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
                    raise ReplayError(f'{topic} is not reliable at the localizer')
        empty = observation_message(Header(frame_id='base_link'), [], np.zeros((0, 2)))
        for s in self.robots:
            s.loc_pub.publish(empty)
            s.loc_sent += 1
            s.obs_pub.publish(empty)
        for s in self.robots:
            for pub in (s.loc_pub, s.obs_pub):
                if not pub.wait_for_all_acked(Duration(seconds=timeout_s)):
                    raise ReplayError(f'{pub.topic_name} never acknowledged')

    # --------------------------------------------------------------------- play
    def play(self, progress=None):
        """Play every step, then the remaining odometry; wait for the final diagnostics."""
        t0 = time.monotonic()
        steps = self.steps
        self.next_of, first = [None] * len(steps), {}
        for i in range(len(steps) - 1, -1, -1):
            r = int(steps.robot[i])
            self.next_of[i], first[r] = first.get(r), i
        self.taken = np.zeros(len(steps), bool)
        for r, s in enumerate(self.robots):
            s.hold = int(self.take[first[r]]) if r in first else len(s.odom_ns)
        for i in range(len(steps)):
            self._step(i)
            if progress is not None:
                progress((i + 1) / max(len(steps), 1))
        for s in self.robots:
            self.wait(lambda s=s: len(s.poses) >= len(s.odom_ns), f'{s.robot.name} poses')
        self.info['play_wall_s'] = time.monotonic() - t0
        # Two diagnostics after the last pose: the second was published after it.
        base = [s.diagnostics for s in self.robots]
        self.wait(lambda: all(s.diagnostics >= b + 2 and int(s.counts.get('odometry', -1))
                              == len(s.odom_ns) for s, b in zip(self.robots, base)),
                  'the final diagnostics', 60.0)

    def _to_localizer(self, i):
        """
        Send step ``i``'s sightings to its localizer holding the newest map; wait till taken.

        In the live order the robot's next steps that its localizer takes at the same
        pose go too (all before that odometry, whose pose the observer needs).
        """
        steps = self.steps
        s = self.robots[int(steps.robot[i])]
        name = s.robot.name
        group, j = [i], self.next_of[i]
        while self.live and j is not None and self.take[j] == self.take[i]:
            group.append(j)
            j = self.next_of[j]
        self.wait(lambda: len(s.poses) >= self.take[i], f'{name} pose {self.take[i]}',
                  phase='poses')
        if self.maps and s.map_stamp != self._map_stamp():
            self.info['map_waits'] += 1
            self.wait(lambda: s.map_stamp == self._map_stamp(),
                      f'{name} localizer to hold the map', phase='map_held')
        for k in group:
            s.loc_pub.publish(self._cloud(k))
            s.loc_sent += 1
        self.wait(lambda: int((s.counts or {}).get('observation_messages_in', -1)) >= s.loc_sent,
                  f'{name} localizer to take the sightings', phase='sightings_taken')
        self.taken[group] = True
        return len(s.odom_ns) if j is None else int(self.take[j])

    def _cloud(self, i):
        steps, robot = self.steps, self.robots[int(self.steps.robot[i])].robot
        a, b = int(steps.start[i]), int(steps.end[i])
        ids = np.full(b - a, UNKNOWN_ID, np.int64) if self.hide_ids else robot.ids[a:b]
        return observation_message(Header(stamp=stamp_msg(steps.stamp_ns[i]),
                                          frame_id='base_link'), ids, robot.z[a:b])

    def _step(self, i):
        """Play step ``i``: localizer, observer, fuser (module docstring)."""
        s = self.robots[int(self.steps.robot[i])]
        name = s.robot.name
        if not self.taken[i]:
            s.hold = self._to_localizer(i)
        before_outputs, before_maps = len(s.outputs), len(self.maps)
        if self.steps.stale[i]:
            self._stale(s, i)
        else:
            s.obs_pub.publish(self._cloud(i))
            self.wait(lambda: len(s.outputs) > before_outputs, f'{name} landmarks',
                      phase='landmarks')
        topic, cloud = s.outputs[before_outputs]
        if self._mirror(cloud, topic):
            self.info['maps_expected'] += 1
            self.wait(lambda: len(self.maps) > before_maps, 'the fused map', phase='map')
            return
        # No new map: the fuser fuses the cloud all the same before the next step's.
        fused, queued = s.fused_in()
        if fused < len(s.outputs) or queued:
            self.info['fuser_waits'] += 1
            self.wait(lambda: s.fused_in()[0] >= len(s.outputs) and not s.fused_in()[1],
                      f'the fuser to fuse {name} landmarks', phase='fused')
        if len(self.maps) > before_maps:
            self.info['maps_unexpected'] += 1

    def _stale(self, s, i):
        """
        Let the observer place a stale step with its newest pose (``Steps.stale``).

        The robot's odometry is held at the step's pose; the observer's ``max_wait_s``
        is set to ``STALE_WAIT_S`` for the step, so its drain timer gives up waiting
        (final lookup: the newest pose), then set back.
        """
        hold, s.hold = s.hold, int(self.steps.poses[i])
        self.wait(lambda: len(s.poses) >= s.hold, f'{s.robot.name} pose {s.hold}', phase='poses')
        before = len(s.outputs)
        self._observer_wait(s, STALE_WAIT_S)
        s.obs_pub.publish(self._cloud(i))
        self.wait(lambda: len(s.outputs) > before, f'{s.robot.name} landmarks (stale)',
                  phase='stale')
        self._observer_wait(s, OBSERVER_TRANSPORT['max_wait_s'])
        s.hold = hold
        self.info['stale_steps'] += 1

    def _observer_wait(self, s, seconds):
        """Set the observer's ``max_wait_s`` and wait for its answer."""
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(seconds))
        future = s.observer_params.call_async(SetParameters.Request(
            parameters=[Parameter(name='max_wait_s', value=value)]))
        self.wait(future.done, f'{s.robot.name} observer max_wait_s', phase='stale')
        if not all(r.successful for r in future.result().results):
            raise ReplayError(f'{s.robot.name} observer refused max_wait_s = {seconds}')

    def _mirror(self, msg, source):
        """Fuse the observer's output in the mirror fuser; return whether the map changed."""
        read = read_landmark_clouds([msg])[0]
        if isinstance(read, Exception):
            raise ReplayError(f'{source}: unreadable landmarks cloud: {read}')
        rows, extras = read
        if not len(rows.ids):
            return False
        self.mirror.add_landmarks(source, LandmarkMessage(
            stamp_ns(msg.header.stamp), rows.ids, rows.m, rows.P, rows.P_dep,
            msg.header.frame_id, extras.classes, extras.scan))
        self.mirror.fuse_queued()
        changed = self.mirror.map_changed
        if changed:
            self.mirror.snapshot()
        return changed

    # ------------------------------------------------------------------ results
    def tracks(self):
        """Return one ``localize.Track`` per robot from the published poses."""
        return [track(s.robot, s.poses, s.counts) for s in self.robots]


def start_nodes(launcher, dataset, extras, setup):
    """
    Start the localizers, observers and the fuser.

    ``setup`` is ``(config_path, work, delay_s, loop_config)``; the localizers take the
    loop's range scale states, range bias and map correlation (``slam.loop_config``)
    over the file's, the observers its precision sources, the fuser each robot's
    precision topics.
    """
    config_path, work, delay_s, loop_config = setup
    fusion, loc = loop_config.fuser.fusion, loop_config.localizer
    observer = loop_config.observer
    precision = (_param('precision_sources', observer.precision_sources)
                 + _param('precision_base_m', observer.precision_base_m))
    for robot in dataset.robots:
        params = work / f'localizer_{robot.name}.yaml'
        write_params_file(params, {f'/{robot.name}/landmark_localizer': {
            **LOCALIZER_TRANSPORT, 'map_file': '',
            'range_scale_state_stddev': float(loc.range_scale_state_stddev),
            'range_scale_bearing_state_stddev': float(loc.range_scale_bearing_state_stddev),
            'range_bias_stddev': float(loc.range_bias_stddev), 'correlation': loc.correlation,
            'initial_pose': [float(v) for v in start_pose(robot, extras, delay_s)]}})
        launcher.start_module(f'localizer_{robot.name}', 'landmark_ros.nodes.localizer',
                              localizer_arguments(robot, config_path, params))
        launcher.start_module(f'observer_{robot.name}', 'landmark_ros.nodes.observer',
                              observer_arguments(robot, config_path) + precision)
    topics = [t for r in dataset.robots
              for t in precision_topics(f'/{r.name}/landmarks', observer.precision_sources)]
    launcher.start_module('fuser', 'landmark_ros.nodes.fuser',
                          fuser_arguments(topics, config_path, fusion))


def run_through_nodes(dataset, extras, loop_config, paths, delay_s, domain_id,
                      live=False):
    """
    Run the loop (no anchors) through the nodes; return what it left.

    With ``loop_config.hide_ids`` the clouds go without IDs (every row ``UNKNOWN_ID``):
    each localizer names the rows against the map it holds, the fuser associates them
    (``LoopConfig.association`` must be ``localizer``: no topic carries the fuser's
    pairing back to a localizer).

    ``paths`` is ``(config_path, work)``; ``live``: the localizers take the sightings
    before the odometry that passes their stamp (``SlamPlayer``). Returns a dict: ``tracks`` (one
    ``localize.Track`` per robot, the published poses), ``published`` (per robot
    ``stamps_ns``, ``x``, ``P`` of every pose), ``map`` (the last ``fused_landmarks``:
    ``ids``, ``m``, ``P``, ``observations``), ``info`` (timing, waits, CPU time of the nodes).
    """
    config_path, work = Path(paths[0]).resolve(), Path(paths[1])
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = Context()
    rclpy.init(args=['landmark_mrclam'], context=context, domain_id=domain_id)
    launcher = Launcher(work, domain_id=domain_id)
    node = executor = None
    try:
        start_nodes(launcher, dataset, extras, (config_path, work, delay_s, loop_config))
        node = rclpy.create_node('landmark_mrclam_slam', context=context,
                                 start_parameter_services=False)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        player = SlamPlayer(node, executor, launcher,
                            (dataset, extras, delay_s, loop_config, live))
        t0 = time.monotonic()
        player.connect()
        player.info['startup_s'] = time.monotonic() - t0
        player.play()
        cpu = cpu_seconds({n: p.pid for n, p in launcher.processes.items()})
        player.info['node_cpu_s'] = round(sum(cpu.values()), 2)
        last = read_landmarks(player.maps[-1]) if player.maps else None
        the_map = ({'ids': last.ids, 'm': last.m, 'P': last.P,
                    'observations': last.observations} if last is not None else
                   {'ids': np.zeros(0, np.int64), 'm': np.zeros((0, 2)),
                    'P': np.zeros((0, 2, 2)), 'observations': np.zeros(0, np.int64)})
        published = [dict(zip(('stamps_ns', 'x', 'P'), published_arrays(s.poses)))
                     for s in player.robots]
        return {'tracks': player.tracks(), 'published': published, 'map': the_map,
                'info': player.info}
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        codes = launcher.stop()
        bad = {n: c for n, c in codes.items() if c != 0}
        if bad:
            print(f'processes exited with {bad}; logs in {work}')
