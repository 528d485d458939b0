"""
A recorded bag through the pipeline, offline, on bag time: what the nodes would publish.

Per robot one ``Observer`` (the ``landmark_observer`` of namespace ``/<robot>``) takes
``/<robot>/pose`` (or ``/<robot>/odometry`` with ``pose_type: odometry``) and
``/<robot>/observations``; one ``Fuser`` (``/landmark_fuser``) takes their landmarks,
source ``/<robot>/landmarks``. Messages go in in bag order (the order a recorder
received them); the nodes' timers run on bag time (as with ``use_sim_time`` and
``ros2 bag play --clock``), each at its configured period from the first message on:
the fuser's batch update (``update_period_s``), its updates and markers
(``updates_rate_hz``) and its map (``publish_rate_hz``, only when changed) on one
publication timer (``fuser.publishing``), the observers' waiting
observations (``max_wait_s``) and every node's ``/diagnostics``. After the last message
the clock runs on long enough for every waiting observation, batch and map to come out.

The output bag holds ``/<robot>/landmarks`` (one cloud per placed observation message,
at the bag time of the input that placed it), ``/fused_landmarks``,
``/fused_landmark_updates``, ``/fused_markers`` and ``/diagnostics`` (one array per
period with the status of every node due).
"""

from dataclasses import dataclass, field, replace
import math
import re
import time
from typing import Callable, Dict, List, Optional

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.bag.params import load_config
from landmark_ros.bag.salvage import salvage_mcap
from landmark_ros.bag.storage import BagError, BagOutput, msgtype, open_bag
from landmark_ros.bag.storage import read_message, storage_of
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.publishing import PublicationSchedule
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.ros import diagnostics
from landmark_ros.ros.cloud import CloudError, read_columns
from landmark_ros.ros.conversions import InputError, pose_from_msg, pose_from_odometry
from landmark_ros.ros.conversions import stamp_ns
from landmark_ros.ros.markers import landmark_markers
from landmark_ros.ros.schemas import (fused_landmark_message, landmark_message,
                                      OBSERVATION_FIELDS, read_landmarks)
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

GROUND_TRUTH_TOPIC = '/ground_truth_landmarks'
OBSERVATIONS_TOPIC = re.compile(r'^/(.+)/observations$')
FUSER_NAME = '/landmark_fuser'
OUTPUT_TOPICS = {
    '/fused_landmarks': (PointCloud2, True),
    '/fused_landmark_updates': (PointCloud2, False),
    '/fused_markers': (MarkerArray, True),
    '/diagnostics': (DiagnosticArray, False),
}
"""Output topics of the fuser and the diagnostics: message class, latched."""


@dataclass
class Task:
    """A node timer on bag time."""

    period_ns: int
    run: Callable[[int], None]
    idle: Callable[[], bool] = lambda: False
    """True when a run now would do nothing: the schedule may skip ahead."""
    due_ns: int = 0


@dataclass
class Result:
    """What ``process_bag`` did."""

    robots: List[str]
    fuser: Fuser
    observers: Dict[str, Observer]
    truth: Optional[dict]
    """``id -> (x, y)`` of the last ``/ground_truth_landmarks`` message, or None."""
    messages_in: int = 0
    counts: Dict[str, int] = field(default_factory=dict)
    messages_expected: int = 0
    """Messages of the input topics the bag's metadata lists."""
    damage: Dict[str, int] = field(default_factory=dict)
    """Skipped records, chunks and messages by reason; ``messages_missing`` is the
    shortfall of messages read against ``messages_expected``. Empty: the bag was whole."""
    """Messages written per output topic."""
    bag_duration_s: float = 0.0
    wall_s: float = 0.0
    cpu_s: float = 0.0

    @property
    def speedup(self):
        """Return bag time per wall-clock time (x real time)."""
        return self.bag_duration_s / self.wall_s if self.wall_s > 0.0 else math.inf


def find_robots(topics):
    """Return the names ``<name>`` of the topics ``/<name>/observations``, sorted."""
    return sorted(match.group(1) for match in map(OBSERVATIONS_TOPIC.match, topics) if match)


def _check_topic(topics, topic, message_class):
    expected = msgtype(message_class)
    if topic not in topics:
        raise BagError(f'the bag has no topic {topic} ({expected})')
    found = topics[topic].msgtype
    if found != expected:
        raise BagError(f'topic {topic} has message type {found or "(mixed)"}, '
                       f'expected {expected}')


class BagPipeline:
    """
    The observers and the fuser of a team, driven by bag messages on bag time.

    Parameters
    ----------
    robots : sequence of str
        Robot names (namespaces without the leading slash).
    document : dict or None
        A ROS parameter file (``params.read_document``); None gives the defaults.
    out : BagOutput
        Where the outputs go; topics are registered here.

    Raises
    ------
    ValueError
        If a parameter value is invalid.

    """

    def __init__(self, robots, document, out):
        self.robots = list(robots)
        self.out = out
        self.observers = {
            robot: Observer(load_config(ObserverConfig, document,
                                        f'/{robot}/landmark_observer'))
            for robot in self.robots}
        fuser_config = load_config(FuserConfig, document, FUSER_NAME)
        # The sources are the robots of the bag, whatever input_topics the file lists.
        topics = tuple(f'/{robot}/landmarks' for robot in self.robots)
        self.fuser = Fuser(replace(fuser_config, input_topics=topics), topics)
        for topic in topics:
            out.add_topic(topic, PointCloud2)
        for topic, (message_class, latched) in OUTPUT_TOPICS.items():
            out.add_topic(topic, message_class, latched, depth=1 if latched else 10)
        self.truth = None
        self._markers_stale = True
        self.schedule = PublicationSchedule(self.fuser.config.publish_rate_hz,
                                            self.fuser.config.updates_rate_hz)
        self.tasks = self._tasks()
        self._statuses = []
        self._statuses_ns = 0

    def input_topics(self):
        """Return ``topic -> (message class, handler)`` of every input the pipeline reads."""
        handlers = {}
        for robot, observer in self.observers.items():
            if observer.config.pose_type == 'odometry':
                handlers[f'/{robot}/odometry'] = (Odometry,
                                                  self._pose_handler(robot, odometry=True))
            else:
                handlers[f'/{robot}/pose'] = (PoseWithCovarianceStamped,
                                              self._pose_handler(robot))
            handlers[f'/{robot}/observations'] = (PointCloud2, self._observation_handler(robot))
        return handlers

    # Timers -----------------------------------------------------------------------------

    def _tasks(self):
        fuser = self.fuser.config
        tasks = [
            Task(_ns(fuser.update_period_s), lambda now: self.fuser.fuse_queued(),
                 lambda: not self.fuser.queued_messages()),
            Task(_ns(self.schedule.period_s), self.publish_outputs),
            Task(_ns(fuser.diagnostics_period_s), self.fuser_diagnostics),
        ]
        for robot, observer in self.observers.items():
            tasks.append(Task(_ns(max(observer.config.max_wait_s / 2.0, 0.01)),
                              lambda now, robot=robot: self.drain(robot, now),
                              lambda observer=observer: not observer.pending))
            tasks.append(Task(_ns(observer.config.diagnostics_period_s),
                              lambda now, robot=robot: self.observer_diagnostics(robot, now)))
        return tasks

    def start(self, now_ns):
        """Start the timers at bag time ``now_ns``."""
        for task in self.tasks:
            task.due_ns = now_ns + task.period_ns

    def advance(self, now_ns):
        """Run every timer due up to bag time ``now_ns``, in time order."""
        while True:
            task = min(self.tasks, key=lambda t: t.due_ns)
            if self._statuses and task.due_ns > self._statuses_ns:
                self._flush_diagnostics()
            if task.due_ns > now_ns:
                break
            if task.idle():
                # Nothing to do until an input comes: skip to the first due time > now.
                task.due_ns += ((now_ns - task.due_ns) // task.period_ns + 1) * task.period_ns
                continue
            task.run(task.due_ns)
            task.due_ns += task.period_ns

    def settle_s(self):
        """Return how long the clock runs after the last message [s]."""
        fuser = self.fuser.config
        wait = max([o.config.max_wait_s for o in self.observers.values()] + [0.0])
        return (wait + fuser.update_period_s + self.schedule.map_period_s
                + self.schedule.updates_period_s + 0.01)

    # Inputs ------------------------------------------------------------------------------

    def _pose_handler(self, robot, odometry=False):
        observer = self.observers[robot]

        def convert(msg):
            config = observer.config
            if odometry:
                return pose_from_odometry(msg, config.world_frame, config.base_frame)
            return pose_from_msg(msg, config.world_frame)

        def handle(msg, now_ns):
            try:
                pose, P_pose = convert(msg)
            except InputError as error:
                observer.reject(error.reason, 1, error.detail)
                return
            self.publish_landmarks(robot, observer.add_pose(stamp_ns(msg.header.stamp), pose,
                                                            P_pose, now_ns), now_ns)
        return handle

    def _observation_handler(self, robot):
        observer = self.observers[robot]

        def handle(msg, now_ns):
            try:
                columns = read_columns(msg, OBSERVATION_FIELDS)
            except CloudError as error:
                observer.reject('observation_messages_in')
                observer.reject(error.reason, 1, f'observation message dropped: {error}')
                return
            message = ObservationMessage(stamp_ns(msg.header.stamp), columns,
                                         msg.header.frame_id, msg.header)
            self.publish_landmarks(robot, observer.add_observations([message], now_ns), now_ns)
        return handle

    def ground_truth(self, msg, now_ns):
        """Keep the true landmark positions of a ``/ground_truth_landmarks`` cloud."""
        try:
            rows = read_landmarks(msg)
        except CloudError as error:
            raise BagError(f'{GROUND_TRUTH_TOPIC}: not a landmarks cloud ({error})') from error
        self.truth = {int(i): (float(x), float(y)) for i, (x, y) in zip(rows.ids, rows.m)}

    # Outputs -----------------------------------------------------------------------------

    def drain(self, robot, now_ns):
        """Expire the waiting observations of one robot (its observer's tick)."""
        self.publish_landmarks(robot, self.observers[robot].drain(now_ns), now_ns)

    def publish_landmarks(self, robot, batches, now_ns):
        """Write one landmarks cloud per batch and hand its rows to the fuser."""
        world_frame = self.observers[robot].config.world_frame
        topic = f'/{robot}/landmarks'
        for batch in batches:
            header = batch.token
            header.frame_id = world_frame
            self.out.write(topic, now_ns, landmark_message(
                header, batch.ids, batch.m, batch.P, batch.P_dep, classes=batch.classes,
                scan=batch.scan))
            self.fuser.add_landmarks(topic, LandmarkMessage(
                batch.stamp_ns, batch.ids, batch.m, batch.P, batch.P_dep, world_frame,
                batch.classes, batch.scan), now_ns)

    def _header(self, now_ns):
        header = Header(frame_id=self.fuser.config.world_frame)
        header.stamp.sec, header.stamp.nanosec = divmod(int(now_ns), 1_000_000_000)
        return header

    def publish_outputs(self, now_ns):
        """Write what is due at this tick of the fuser's publication timer, as the node does."""
        updates, full_map = self.schedule.tick()
        if updates:
            self.publish_updates(now_ns)
        if full_map:
            self.publish_map(now_ns)

    def publish_map(self, now_ns):
        """Write the full map if it changed (at most ``publish_rate_hz``)."""
        if not self.fuser.map_changed:
            return
        ids, m, P, P_dep, observations = self.fuser.snapshot()
        self.out.write('/fused_landmarks', now_ns, fused_landmark_message(
            self._header(now_ns), ids, m, P, P_dep, observations))

    def publish_updates(self, now_ns):
        """Write the landmarks changed since last time and their markers (all at first)."""
        ids, m, P, P_dep, observations = self.fuser.take_updates()
        header = self._header(now_ns)
        if len(ids):
            self.out.write('/fused_landmark_updates', now_ns,
                           fused_landmark_message(header, ids, m, P, P_dep, observations))
        if self._markers_stale:
            ids, m, P, _, _ = self.fuser.map.snapshot()
            self._markers_stale = False
        if len(ids):
            self.out.write('/fused_markers', now_ns, landmark_markers(
                header, ids, m, P, self.fuser.config.marker_sigma, rgb=(1.0, 0.5, 0.0)))

    def fuser_diagnostics(self, now_ns):
        """Queue the fuser's statuses for the ``/diagnostics`` array of this time."""
        self._statuses += [diagnostics.to_msg(status, FUSER_NAME, '/')
                           for status in self.fuser.statuses(now_ns)]
        self._statuses_ns = now_ns

    def observer_diagnostics(self, robot, now_ns):
        """Queue one observer's status for the ``/diagnostics`` array of this time."""
        self._statuses.append(diagnostics.to_msg(self.observers[robot].status(),
                                                 f'/{robot}/landmark_observer', f'/{robot}'))
        self._statuses_ns = now_ns

    def _flush_diagnostics(self):
        """Write the statuses due at one bag time as one array."""
        array = DiagnosticArray(header=self._header(self._statuses_ns), status=self._statuses)
        self.out.write('/diagnostics', self._statuses_ns, array)
        self._statuses = []


class _Damage:
    """What a damaged bag cost: skipped records and chunks by reason."""

    def __init__(self):
        self.counts = {}
        self.salvaged = False
        """Whether ``salvage`` read (part of) the bag: its reasons are counted."""

    def add(self, reason, count=1):
        self.counts[reason] = self.counts.get(reason, 0) + count


def _read_reason(error):
    """Return the named reason of an exception raised while reading bag records."""
    name = type(error).__name__
    if 'zstd' in name.lower() or 'zstd' in str(error).lower() or 'lz4' in str(error).lower():
        return 'chunk_undecompressable'
    if 'corrupt' in name.lower() or 'database' in str(error).lower():
        return 'storage_corrupt'
    return 'record_unreadable'


def _messages(reader, connections, damage, resumes=64):
    """
    Yield the reader's messages; past an unreadable record, what can still be read.

    A read error is counted in ``damage`` by reason (``_read_reason``). An MCAP bag is
    then read on by ``salvage.salvage_mcap`` (record by record, from after the last
    message read, each skipped record or chunk counted by its own reason); another
    storage resumes after the last message read (bag time + 1 ns), until a resume gives
    nothing new or after ``resumes`` of them. The caller compares what was read with
    the bag's metadata.
    """
    start = None
    while True:
        progressed = False
        try:
            for item in reader.messages(connections=connections, start=start):
                progressed = True
                start = item[1] + 1
                yield item
            return
        except Exception as error:  # noqa: B902 - storage back ends raise many kinds
            files = _mcap_files(reader)
            if files:
                yield from _salvaged(files, connections, damage, start)
                return
            damage.add(_read_reason(error))
            resumes -= 1
            if not progressed or resumes <= 0:
                return


def _mcap_files(reader):
    """Return the MCAP files of an open reader ([] for another storage)."""
    storage = getattr(reader, 'storage', reader)       # a file, or a bag directory
    storages = getattr(storage, 'storages', None) or [storage]
    return [part.path for part in storages
            if type(part).__name__.lower().startswith('mcap') and hasattr(part, 'path')]


def _salvaged(files, connections, damage, start):
    """Yield ``(connection, time_ns, raw)`` of what ``salvage_mcap`` reads of ``files``."""
    damage.salvaged = True
    by_topic = {}
    for connection in connections:
        by_topic.setdefault(connection.topic, connection)
    for path in files:
        for topic, time_ns, raw in salvage_mcap(path, damage.add, start):
            if topic in by_topic:
                yield by_topic[topic], time_ns, raw


def _ns(seconds):
    return max(1, int(round(seconds * 1e9)))


def process_bag(input_path, output_path, document=None, robots=None, progress=None,
                storage=None):
    """
    Run a recorded bag through the observers and the fuser; write what they publish.

    Parameters
    ----------
    input_path : str or Path
        A rosbag2 (directory, ``.mcap`` or ``.db3``) with ``/<robot>/pose`` (or
        ``/<robot>/odometry``) and ``/<robot>/observations`` per robot, optionally
        ``/ground_truth_landmarks``.
    output_path : str or Path
        The output bag directory to create; written atomically.
    document : dict, optional
        A ROS parameter file (``params.read_document``): sections ``landmark_observer``
        (per robot: ``/<robot>/landmark_observer``) and ``landmark_fuser``.
    robots : sequence of str, optional
        Robot names; by default every ``<name>`` with a topic ``/<name>/observations``.
    progress : callable, optional
        ``progress(messages_done, messages_total)``, called now and then.
    storage : str, optional
        Storage of the output, ``mcap`` or ``sqlite3``; by default the input's.

    Returns
    -------
    Result
        With ``damage``: a bag damaged past its opening (a corrupt record, chunk or
        message) is processed as far as it can be read, the rest counted by reason
        (those of ``salvage`` for MCAP, ``storage_corrupt`` or ``record_unreadable``
        for sqlite3, ``message_undecodable``, ``ground_truth_unreadable``,
        ``messages_missing``: the shortfall against the bag's metadata). The output
        holds what was read.

    Raises
    ------
    BagError
        If the bag cannot be opened (missing, cut before its index, not a bag), lacks
        a topic the robots need, holds one of another message type, or has no robot at all; no
        output is left behind.
    ValueError
        If a parameter value is invalid.

    """
    started, cpu_started = time.monotonic(), time.process_time()
    reader = open_bag(input_path)
    try:
        topics = reader.topics
        names = list(robots) if robots else find_robots(topics)
        if not names:
            raise BagError(f'{input_path}: no topic /<robot>/observations: no robot to run')
        with BagOutput(output_path, storage or storage_of(input_path)) as out:
            pipeline = BagPipeline(names, document, out)
            inputs = pipeline.input_topics()
            for topic, (message_class, _) in inputs.items():
                _check_topic(topics, topic, message_class)
            if GROUND_TRUTH_TOPIC in topics:
                _check_topic(topics, GROUND_TRUTH_TOPIC, PointCloud2)
                inputs[GROUND_TRUTH_TOPIC] = (PointCloud2, pipeline.ground_truth)
            connections = [c for c in reader.connections if c.topic in inputs]
            total = sum(c.msgcount for c in connections)
            done = 0
            first = last = None
            damage = _Damage()
            for connection, time_ns, raw in _messages(reader, connections, damage):
                done += 1
                message_class, handle = inputs[connection.topic]
                try:
                    message = read_message(raw, message_class, connection.topic)
                except BagError:
                    damage.add('message_undecodable')
                    continue
                if first is None:
                    first = time_ns
                    pipeline.start(time_ns)
                last = time_ns
                pipeline.advance(time_ns)
                try:
                    handle(message, time_ns)
                except BagError:        # a ground truth cloud that cannot be read
                    damage.add('ground_truth_unreadable')
                if progress is not None and not done % 256:
                    progress(done, total)
            if done < total:
                damage.add('messages_missing', total - done)
                if not damage.salvaged:     # read quietly short: find out why
                    for _ in _salvaged(_mcap_files(reader), connections, damage, None):
                        pass
            if first is not None:
                pipeline.advance(last + _ns(pipeline.settle_s()))
            if progress is not None:
                progress(done, total)
    finally:
        reader.close()
    duration = 0.0 if first is None else (last - first) * 1e-9
    return Result(names, pipeline.fuser, pipeline.observers, pipeline.truth, done,
                  dict(out.counts), total, dict(damage.counts), duration,
                  time.monotonic() - started, time.process_time() - cpu_started)
