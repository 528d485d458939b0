"""
landmark_fuser: the landmark observations of several robots in, one fused map out.

Subscribes every topic of ``input_topics`` (landmark clouds, one source each),
queues their rows and fuses them by landmark ID in batches with
``landmark_ros.fuser.fuser.Fuser``; every topic of ``partial_observation_topics`` (partial
views: range-only and bearing-only, one source each) too. Publishes the confirmed map on
``fused_landmarks`` (transient local: late subscribers get it), the landmarks changed
since the last update on ``fused_landmark_updates``, RViz markers on
``fused_markers`` and ``/diagnostics``; services ``~/reset`` and ``~/save``. With
``map_file`` set the map is loaded at start and saved atomically.
"""

import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from landmark_ros.fuser.fuser import Fuser, LandmarkMessage
from landmark_ros.fuser.publishing import PublicationSchedule
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.ros import diagnostics, guard, qos, runner
from landmark_ros.ros.cloud import CloudError
from landmark_ros.ros.cloud_bytes import read_cloud_bytes
from landmark_ros.ros.conversions import stamp_ns
from landmark_ros.ros.markers import delete_all, delete_markers, landmark_markers
from landmark_ros.ros.params import declare_config, keep_in_sync
from landmark_ros.ros.qos import LATCHED  # noqa: F401 (the map outputs' QoS, re-exported)
from landmark_ros.ros.schemas import (landmark_message, NOT_MERGED, read_landmark_clouds,
                                      read_partial_observations)
from landmark_ros.ros.subscriptions import BurstGroup, take_waiting
import numpy as np
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray


class _LateCounters:
    """The fuser's counters, looked up when a guarded callback fails."""

    def __init__(self, node):
        self._node = node

    def add(self, name, count=1, detail=None):
        """Count into the fuser's counters."""
        self._node.fuser.counters.add(name, count, detail)


class LandmarkFuser(Node):
    """Fuse the landmark observations of a team of robots by landmark ID."""

    def __init__(self, **kwargs):
        super().__init__('landmark_fuser', **kwargs)
        config = declare_config(self, FuserConfig)
        self._subscriptions_by_topic = {}
        # qos_overrides.<topic>.subscription.* parameters, per input topic. rclpy applies
        # them to the profile it is given: each subscription gets its own.
        overrides = QoSOverridingOptions.with_default_policies()
        # One callback takes the clouds waiting on every input; the group then spares
        # the executor the empty dispatches of the inputs it emptied.
        self._inputs = BurstGroup(self)
        for topic in config.input_topics:
            # Raw: the clouds are read from their bytes (``cloud_bytes``), not built
            # as Python messages first.
            self._subscriptions_by_topic[topic] = self.create_subscription(
                PointCloud2, topic, self._guard(lambda msg, topic=topic: self.on_landmarks(
                    msg, topic), 'landmarks callback'),
                qos.reliable_input(config.input_depth), qos_overriding_options=overrides,
                raw=True, event_callbacks=self._no_events(), callback_group=self._inputs)
        self._source_of = {topic: subscription.topic_name
                           for topic, subscription in self._subscriptions_by_topic.items()}
        self._partial_subs = {}
        for topic in (topic for topic in config.partial_observation_topics if topic):
            self._partial_subs[topic] = self.create_subscription(
                PointCloud2, topic, self._guard(
                    lambda msg, topic=topic: self.on_partial_observations(msg, topic),
                    'partial observations callback'),
                qos.reliable_input(config.input_depth), qos_overriding_options=overrides,
                event_callbacks=self._no_events())
        self._partial_source_of = {topic: subscription.topic_name
                                   for topic, subscription in self._partial_subs.items()}
        self.fuser = Fuser(config, list(self._source_of.values()), self.get_logger(),
                           list(self._partial_source_of.values()))
        keep_in_sync(self, lambda: self.fuser.config, self._apply_config)
        self._markers_stale = True
        self.fuser.load()
        self._markers_stale = self.fuser.map_changed or self._markers_stale
        self.map_pub = self.create_publisher(PointCloud2, 'fused_landmarks', qos.LATCHED)
        self.updates_pub = self.create_publisher(PointCloud2, 'fused_landmark_updates',
                                                 qos.reliable_output(10))
        self.marker_pub = self.create_publisher(MarkerArray, 'fused_markers', qos.LATCHED)
        self._marker_subscribers = 0
        self._incompatible = set()      # publishers counted as incompatible_qos (GIDs)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                     qos.DIAGNOSTICS)
        self.create_service(Trigger, '~/reset', self._guard(self.on_reset))
        self.create_service(Trigger, '~/save', self._guard(self.on_save))
        self.create_timer(config.update_period_s, self._guard(self.fuse_queued))
        self._schedule = PublicationSchedule(config.publish_rate_hz, config.updates_rate_hz)
        self.create_timer(self._schedule.period_s, self._guard(self.publish_outputs))
        self.create_timer(config.diagnostics_period_s, self._guard(self.publish_diagnostics))
        if config.map_file and config.autosave_period_s > 0.0:
            self.create_timer(config.autosave_period_s, self._guard(self.autosave))

    @staticmethod
    def _no_events():
        # No QoS event handlers on the inputs: each is one more entity in every wait
        # of the executor (with 50 input topics rclpy's two defaults made a wait cost
        # 542 instead of 157 us). Incompatible publishers are found by
        # ``_check_publishers`` instead.
        return SubscriptionEventCallbacks(use_default_callbacks=False)

    def _check_publishers(self):
        """
        Count each publisher whose QoS cannot reach an input (``incompatible_qos``), once.

        Run with the diagnostics: the publishers of every input topic
        (``get_publishers_info_by_topic``) against the subscription's QoS
        (``qos.incompatible_policy``).
        """
        inputs = [(self._source_of[topic], subscription)
                  for topic, subscription in self._subscriptions_by_topic.items()]
        inputs += [(self._partial_source_of[topic], subscription)
                   for topic, subscription in self._partial_subs.items()]
        for source, subscription in inputs:
            for info in self.get_publishers_info_by_topic(subscription.topic_name):
                gid = bytes(info.endpoint_gid)
                if gid in self._incompatible:
                    continue
                policy = qos.incompatible_policy(subscription.qos_profile, info.qos_profile)
                if policy is not None:
                    self._incompatible.add(gid)
                    name = f'{info.node_namespace.rstrip("/")}/{info.node_name}'
                    self.fuser.reject(source, 'incompatible_qos', 1,
                                      f'publisher {name} offers incompatible QoS '
                                      f'({policy}): its messages are not received')

    def _guard(self, callback, what=None):
        # Callbacks created before the fuser exists count into it once it does.
        counters = _LateCounters(self)
        return guard.guarded(self, counters, callback, what or callback.__name__)

    @property
    def config(self):
        """Return the parameters in force (the fuser's)."""
        return self.fuser.config

    @property
    def sources(self):
        """Return the fuser's sources by ``input_topics`` entry (names: resolved topics)."""
        return {topic: self.fuser.sources[name] for topic, name in self._source_of.items()}

    def _apply_config(self, config):
        self.fuser.reconfigure(config)
        self._markers_stale = True

    # Input ---------------------------------------------------------------------

    def on_landmarks(self, msg, topic):
        """
        Decode landmark clouds (this one, those waiting) and queue their rows.

        The clouds already waiting on the other input topics are taken too: with many
        robots, one callback then serves a burst of all of them (one executor dispatch,
        one row check, ``Fuser.add_landmark_bursts``), not one cloud each. While a
        round takes more than one cloud (the inputs are busy), the callback takes
        another round of what arrived meanwhile, up to ``max_batch_messages`` per
        input in all and for at most a quarter of ``update_period_s``: a round that
        finds nothing costs about 1 us per input, an executor wait about 4 us per
        entity of the node (rclpy builds its wait set entity by entity).
        """
        clock = self.get_clock()
        now = clock.now().nanoseconds
        limit = self.config.max_batch_messages
        bursts = [(topic, [msg] + take_waiting(
            self._subscriptions_by_topic[topic], PointCloud2, limit - 1, raw=True))]
        for other, subscription in self._subscriptions_by_topic.items():
            if other != topic:
                waiting = self._inputs.take(subscription, PointCloud2, limit, raw=True)
                if waiting:
                    bursts.append((other, waiting))
        taken = {name: len(clouds) for name, clouds in bursts}
        # Wall time (not the node's clock, which may be a paused simulation's).
        deadline = time.monotonic() + 0.25 * self.config.update_period_s
        while True:
            self.fuser.add_landmark_bursts(self._decode_landmarks(bursts), now)
            if sum(len(clouds) for _, clouds in bursts) < 2:
                break
            if time.monotonic() >= deadline:
                break
            now = clock.now().nanoseconds
            bursts = []
            for name, subscription in self._subscriptions_by_topic.items():
                room = limit - taken.get(name, 0)
                if room > 0:
                    waiting = self._inputs.take(subscription, PointCloud2, room, raw=True)
                    if waiting:
                        bursts.append((name, waiting))
                        taken[name] = taken.get(name, 0) + len(waiting)
            if not bursts:
                break

    def _decode_landmarks(self, bursts):
        """
        Return ``(source, messages)`` of ``(topic, clouds)`` (serialized or messages).

        The clouds of every topic are read together (``read_landmark_clouds``); one
        that cannot be read is counted against its source and dropped.
        """
        parsed = []
        for topic, clouds in bursts:
            source = self._source_of[topic]
            for cloud in clouds:
                try:
                    if isinstance(cloud, (bytes, bytearray, memoryview)):
                        cloud = read_cloud_bytes(cloud)
                    parsed.append((source, cloud))
                except CloudError as error:
                    self._drop_cloud(source, error)
        out = {}
        reads = read_landmark_clouds([cloud for _, cloud in parsed])
        for (source, cloud), read in zip(parsed, reads):
            if isinstance(read, CloudError):
                self._drop_cloud(source, read)
                continue
            rows, extras = read
            out.setdefault(source, []).append(LandmarkMessage(
                stamp_ns(cloud.header.stamp), rows.ids, rows.m, rows.P, rows.P_dep,
                cloud.header.frame_id, extras.classes, extras.scan))
        return list(out.items())

    def _drop_cloud(self, source, error):
        self.fuser.reject(source, 'messages_in')
        self.fuser.reject(source, error.reason, 1, f'message dropped: {error}')

    def on_partial_observations(self, msg, topic):
        """Decode partial observation clouds (this one and those waiting) and queue their views."""
        source = self._partial_source_of[topic]
        now = self.get_clock().now().nanoseconds
        for cloud in [msg] + take_waiting(self._partial_subs[topic], PointCloud2,
                                          self.config.max_batch_messages - 1):
            try:
                columns = read_partial_observations(cloud)
            except CloudError as error:
                self.fuser.reject(source, 'messages_in')
                self.fuser.reject(source, error.reason, 1, f'message dropped: {error}')
                continue
            self.fuser.add_partial_observations(source, stamp_ns(cloud.header.stamp), columns,
                                                cloud.header.frame_id, now)

    def fuse_queued(self):
        """Fuse every queued row, in arrival order, in one batch."""
        self.fuser.fuse_queued()

    # Output --------------------------------------------------------------------

    def _header(self):
        return Header(stamp=self.get_clock().now().to_msg(), frame_id=self.config.world_frame)

    def publish_outputs(self):
        """
        Publish what is due at this tick of the publication timer (``PublicationSchedule``).

        The updates first, then the full map: both from one fold of the map.
        """
        updates, full_map = self._schedule.tick()
        if updates:
            self.publish_updates()
        if full_map:
            self.publish_map()

    def publish_map(self):
        """Publish the full map if it changed (at most ``publish_rate_hz``)."""
        if not self.fuser.map_changed:
            return
        ids, m, P, P_dep, observations = self.fuser.snapshot()
        self.map_pub.publish(landmark_message(self._header(), ids, m, P, P_dep, observations,
                                              classes=self.fuser.classes_of(ids)))

    def publish_updates(self):
        """
        Publish the landmarks changed since last time, and their markers.

        Markers go out for the changed landmarks only (ADD replaces a marker by ID),
        and in full when a subscriber joined, after a reset or a load, or when the
        marker size changed. Landmarks merged into others are announced with the
        updates (``merged_into``) and their markers deleted.
        """
        removed = self.fuser.take_removed()
        ids, m, P, P_dep, observations = self.fuser.take_updates()
        header = self._header()
        classes, merged_into = self.fuser.classes_of(ids), None
        if removed:
            gone, into = self.fuser.removal_rows(removed)
            merged_into = np.concatenate([np.full(len(ids), NOT_MERGED, np.int64), into])
            classes = np.concatenate([classes, self.fuser.classes_of(into)])
            ids, m, P, P_dep, observations = (np.concatenate([a, b]) for a, b in zip(
                (ids, m, P, P_dep, observations), gone))
        if len(ids):
            self.updates_pub.publish(landmark_message(header, ids, m, P, P_dep, observations,
                                                      classes=classes,
                                                      merged_into=merged_into))
        subscribers = self.marker_pub.get_subscription_count()
        joined, self._marker_subscribers = subscribers > self._marker_subscribers, subscribers
        if not subscribers:
            return
        # One message (the marker topic keeps one on a latched writer): deletions first.
        deleted = delete_markers(header, [drop for drop, _ in removed]).markers
        if merged_into is not None:
            changed = merged_into == NOT_MERGED
            ids, m, P = ids[changed], m[changed], P[changed]
        if joined or self._markers_stale:
            ids, m, P, _, _ = self.fuser.map.snapshot()
            self._markers_stale = False
        elif not len(ids) and not deleted:
            return
        array = landmark_markers(header, ids, m, P, self.config.marker_sigma,
                                 rgb=(1.0, 0.5, 0.0))
        array.markers = deleted + list(array.markers)
        self.marker_pub.publish(array)

    def publish_diagnostics(self):
        """Publish the fuser's status and one status per source on /diagnostics."""
        self._check_publishers()
        name = self.get_fully_qualified_name()
        diagnostics.publish(self, self.diagnostics_pub, [
            diagnostics.to_msg(status, name, self.get_namespace())
            for status in self.fuser.statuses(self.get_clock().now().nanoseconds)])

    # Services and persistence ----------------------------------------------------

    def on_reset(self, request, response):
        """Clear the map, the queues and the markers."""
        count = self.fuser.reset()
        header = self._header()
        self.map_pub.publish(landmark_message(header, [], np.empty((0, 2)),
                                              np.empty((0, 2, 2)), observations=[]))
        self.marker_pub.publish(delete_all(header))
        self._markers_stale = True
        self.get_logger().info(f'map reset: {count} landmarks cleared')
        response.success, response.message = True, f'cleared {count} landmarks'
        return response

    def on_save(self, request, response):
        """Save the map to ``map_file`` now."""
        if not self.config.map_file:
            response.success, response.message = False, 'map_file is not set'
            return response
        response.success = self.fuser.save()
        response.message = (f'saved {len(self.fuser.map)} landmarks to {self.config.map_file}'
                            if response.success else 'save failed: see the log')
        return response

    def autosave(self):
        """Save the map if it changed since the last save."""
        if self.fuser.unsaved:
            self.fuser.save()

    def destroy_node(self):
        """Save the map (when a map file is set) before going away."""
        if self.config.map_file and self.fuser.unsaved:
            self.fuser.save()
        return super().destroy_node()


def main(args=None):
    """Run the node until shutdown; the map is saved on the way out."""
    return runner.run(LandmarkFuser, 'landmark_fuser', args)


if __name__ == '__main__':
    sys.exit(main())
