"""
landmark_fuser: the landmark observations of several robots in, one fused map out.

Subscribes every topic of ``input_topics`` (landmark clouds, one source each),
queues their rows and fuses them by landmark ID in batches with
``landmark_ros.core.landmark_map.LandmarkMap``. Publishes the confirmed map on
``fused_landmarks`` (transient local: late subscribers get it), RViz markers on
``fused_markers`` and ``/diagnostics``; services ``~/reset`` and ``~/save``. With
``map_file`` set the map is loaded at start and saved atomically.
"""

from collections import Counter, deque
from dataclasses import dataclass, field
import itertools
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from landmark_ros import map_file
from landmark_ros import node_common
from landmark_ros.cloud import CloudError
from landmark_ros.config import FuserConfig
from landmark_ros.conversions import stamp_ns
from landmark_ros.core.landmark_map import LandmarkMap
from landmark_ros.diagnostics import Counters
from landmark_ros.markers import delete_all, landmark_markers
from landmark_ros.observations import landmark_row_problems
from landmark_ros.ros_params import declare_config, keep_in_sync
from landmark_ros.schemas import landmark_message, read_landmarks
from landmark_ros.subscriptions import take_waiting
import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray


NOT_PROBLEMS = frozenset({'landmarks_confirmed', 'saves'})
"""Fuser counters that do not make its status a warning (a re-initialisation does)."""

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""QoS of the map outputs: a late subscriber gets the current map."""


@dataclass
class _Source:
    topic: str
    subscription: object = None
    queue: deque = field(default_factory=deque)
    counts: Counter = field(default_factory=Counter)
    last_message_ns: int = None


class LandmarkFuser(Node):
    """Fuse the landmark observations of a team of robots by landmark ID."""

    def __init__(self, **kwargs):
        super().__init__('landmark_fuser', **kwargs)
        self.config = declare_config(self, FuserConfig)
        keep_in_sync(self, lambda: self.config, self._apply_config)
        self.counters = Counters(self.get_logger().warning, self.config.log_throttle_s)
        self.map = LandmarkMap(self.config.fusion, self.config.gate_probability,
                               self.config.min_observations,
                               self.config.max_consecutive_rejections)
        self._sequence = itertools.count()
        self._map_changed = False
        self._markers_stale = True
        self._unsaved = False
        self._reported = {}
        self.load_map()

        self.sources = {}
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.config.input_depth,
                         reliability=ReliabilityPolicy.RELIABLE)
        for topic in self.config.input_topics:
            subscription = self.create_subscription(
                PointCloud2, topic, lambda msg, topic=topic: self.on_landmarks(msg, topic), qos)
            self.sources[topic] = _Source(subscription.topic_name, subscription)
        resolved = [source.topic for source in self.sources.values()]
        if len(set(resolved)) != len(resolved):
            raise ValueError(f'input_topics name one topic twice once resolved: {resolved}')
        self.map_pub = self.create_publisher(PointCloud2, 'fused_landmarks', LATCHED)
        self.marker_pub = self.create_publisher(MarkerArray, 'fused_markers', LATCHED)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/reset', self.on_reset)
        self.create_service(Trigger, '~/save', self.on_save)
        self.create_timer(self.config.update_period_s, self.fuse_queued)
        self.create_timer(1.0 / self.config.publish_rate_hz, self.publish_map)
        self.create_timer(self.config.diagnostics_period_s, self.publish_diagnostics)
        if self.config.map_file and self.config.autosave_period_s > 0.0:
            self.create_timer(self.config.autosave_period_s, self.autosave)

    def _apply_config(self, config):
        self.config = config
        self.counters.throttle_s = config.log_throttle_s
        self._markers_stale = True

    def _count(self, source, reason, count, detail=None):
        source.counts[reason] += count
        self.counters.add(reason, count, None if detail is None else f'{source.topic}: {detail}')

    # Input ---------------------------------------------------------------------

    def on_landmarks(self, msg, topic):
        """Check landmark clouds (this one and those waiting) and queue their valid rows."""
        source = self.sources[topic]
        source.last_message_ns = self.get_clock().now().nanoseconds
        for cloud in [msg] + take_waiting(source.subscription, PointCloud2,
                                          self.config.max_batch_messages - 1):
            self._queue(source, cloud)

    def _queue(self, source, msg):
        source.counts['messages_in'] += 1
        try:
            rows = read_landmarks(msg)
        except CloudError as error:
            self._count(source, error.reason, 1, f'message dropped: {error}')
            return
        if msg.header.frame_id != self.config.world_frame:
            self._count(source, 'wrong_frame', 1,
                        f"landmarks in frame '{msg.header.frame_id}', expected "
                        f"'{self.config.world_frame}': message dropped")
            return
        source.counts['observations_in'] += len(rows.ids)
        valid, reasons = landmark_row_problems(rows.ids, rows.m, rows.P, rows.P_dep)
        for reason, count in reasons.items():
            self._count(source, reason, count, f'{count} of {len(valid)} rows rejected')
        if not valid.any():
            return
        if len(source.queue) >= self.config.max_queue_messages:
            dropped = source.queue.popleft()
            self._count(source, 'queue_overflow', len(dropped[1]),
                        f'more than {self.config.max_queue_messages} messages waiting: '
                        'dropped the oldest')
        if not valid.all():
            rows = type(rows)(*(column[valid] for column in rows))
        source.queue.append((next(self._sequence), rows.ids, rows.m, rows.P, rows.P_dep,
                             stamp_ns(msg.header.stamp) * 1e-9))

    def fuse_queued(self):
        """Fuse every queued row, in arrival order, in one batch."""
        items = []
        for source in self.sources.values():
            items += [(item, source.topic) for item in source.queue]
            source.queue.clear()
        if not items:
            return
        items.sort(key=lambda entry: entry[0][0])
        lengths = [len(item[1]) for item, _ in items]
        result = self.map.update(
            np.concatenate([item[1] for item, _ in items]),
            np.concatenate([item[2] for item, _ in items]),
            np.concatenate([item[3] for item, _ in items]),
            np.concatenate([item[4] for item, _ in items]),
            np.repeat([topic for _, topic in items], lengths),
            np.repeat([item[5] for item, _ in items], lengths))
        by_topic = {source.topic: source for source in self.sources.values()}
        for topic, count in result.accepted.items():
            by_topic[topic].counts['fused'] += count
        for topic, count in result.rejected.items():
            self._count(by_topic[topic], 'gated_out', count,
                        'observations outside the chi-square gate of their landmark')
        if result.confirmed:
            self.counters.add('landmarks_confirmed', len(result.confirmed))
        if result.reinitialised:
            self.counters.add('landmarks_reinitialised', len(result.reinitialised),
                              f'landmarks {result.reinitialised} rejected '
                              f'{self.config.max_consecutive_rejections} times in a row were '
                              'rebuilt from their recent observations (moved?)')
        if result.changed:
            self._map_changed = self._markers_stale = self._unsaved = True

    # Output --------------------------------------------------------------------

    def _header(self):
        return Header(stamp=self.get_clock().now().to_msg(), frame_id=self.config.world_frame)

    def publish_map(self):
        """Publish the map if it changed, and the markers if someone wants them."""
        if not (self._map_changed or (self._markers_stale
                                      and self.marker_pub.get_subscription_count())):
            return
        ids, m, P, P_dep, observations = self.map.snapshot()
        header = self._header()
        if self._map_changed:
            self.map_pub.publish(landmark_message(header, ids, m, P, P_dep, observations))
            self._map_changed = False
        if self.marker_pub.get_subscription_count():
            self.marker_pub.publish(landmark_markers(header, ids, m, P, self.config.marker_sigma,
                                                     rgb=(1.0, 0.5, 0.0)))
            self._markers_stale = False

    def publish_diagnostics(self):
        """Publish the fuser's status and one status per source on /diagnostics."""
        now = self.get_clock().now().nanoseconds
        name = self.get_fully_qualified_name()
        statuses = []
        stale = []
        for source in self.sources.values():
            age = None if source.last_message_ns is None else (
                now - source.last_message_ns) * 1e-9
            is_stale = age is None or age > self.config.source_timeout_s
            if is_stale:
                stale.append(source.topic)
            extra = {'age_s': 'never' if age is None else f'{age:.3f}',
                     'stale': str(is_stale).lower(), 'queued_messages': len(source.queue)}
            statuses.append(node_common.status(
                DiagnosticStatus.WARN if is_stale else DiagnosticStatus.OK,
                f'{name}: {source.topic}', 'stale' if is_stale else 'ok', source.topic,
                source.counts, extra))
        counts = dict(self.counters.counts)
        problems = sorted(key for key, value in counts.items()
                          if key not in NOT_PROBLEMS and value > self._reported.get(key, 0))
        self._reported = counts
        message = f'{len(self.map)} landmarks'
        if stale:
            message += f"; stale: {', '.join(stale)}"
        if problems:
            message += f"; rejected: {', '.join(problems)}"
        extra = {'landmarks': len(self.map), 'fusion': self.config.fusion,
                 'map_file': self.config.map_file or '(none)'}
        statuses.insert(0, node_common.status(
            DiagnosticStatus.WARN if (stale or problems) else DiagnosticStatus.OK,
            name, message, self.get_namespace(), counts, extra))
        node_common.publish_statuses(self, self.diagnostics_pub, statuses)

    # Services and persistence ----------------------------------------------------

    def on_reset(self, request, response):
        """Clear the map, the queues and the markers."""
        count = len(self.map)
        self.map.reset()
        for source in self.sources.values():
            source.queue.clear()
        header = self._header()
        self.map_pub.publish(landmark_message(header, [], np.empty((0, 2)),
                                              np.empty((0, 2, 2)), observations=[]))
        self.marker_pub.publish(delete_all(header))
        self._map_changed = self._markers_stale = False
        self._unsaved = True
        self.get_logger().info(f'map reset: {count} landmarks cleared')
        response.success, response.message = True, f'cleared {count} landmarks'
        return response

    def on_save(self, request, response):
        """Save the map to ``map_file`` now."""
        if not self.config.map_file:
            response.success, response.message = False, 'map_file is not set'
            return response
        response.success = self.save_map()
        response.message = (f'saved {len(self.map)} landmarks to {self.config.map_file}'
                            if response.success else 'save failed: see the log')
        return response

    def autosave(self):
        """Save the map if it changed since the last save."""
        if self._unsaved:
            self.save_map()

    def save_map(self):
        """Write the map file atomically; return whether it worked."""
        try:
            map_file.save(self.config.map_file, self.map.to_records(),
                          self.config.world_frame, self.config.fusion)
        except OSError as error:
            self.counters.add('save_failed', 1, f'cannot save {self.config.map_file}: {error}')
            return False
        self._unsaved = False
        self.counters.add('saves', 1)
        return True

    def load_map(self):
        """Load ``map_file`` if set; move an unusable file aside and start empty."""
        path = self.config.map_file
        if not path:
            return
        for stale in map_file.remove_stale_temporaries(path):
            self.get_logger().info(f'removed {stale}, left by an interrupted save')
        try:
            document = map_file.load(path, self.config.world_frame)
            self.map.load_records(document['landmarks'])
        except FileNotFoundError:
            self.get_logger().info(f'no map file {path} yet: starting with an empty map')
            return
        except (OSError, ValueError) as error:
            try:
                moved = map_file.move_aside(path)
            except OSError as move_error:
                moved = f'(could not be moved: {move_error})'
            self.counters.add('map_file_rejected', 1)
            self.get_logger().error(
                f'map file {path} is unusable ({error}); moved it to {moved} and starting '
                'with an empty map')
            return
        if document.get('fusion') != self.config.fusion:
            self.get_logger().warning(
                f"map file {path} was made with fusion {document.get('fusion')!r}, this "
                f'fuser uses {self.config.fusion!r}')
        self._map_changed = self._markers_stale = True
        self.get_logger().info(f'loaded {len(self.map)} landmarks from {path}')

    def destroy_node(self):
        """Save the map (when a map file is set) before going away."""
        if self.config.map_file and self._unsaved:
            self.save_map()
        return super().destroy_node()


def main(args=None):
    """Run the node until shutdown; the map is saved on the way out."""
    return node_common.run(LandmarkFuser, 'landmark_fuser', args)


if __name__ == '__main__':
    sys.exit(main())
