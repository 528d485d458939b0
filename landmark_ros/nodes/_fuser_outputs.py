"""The fuser node's map outputs: the full map, its updates and the RViz markers."""

from landmark_ros.nodes.start import lazy
from landmark_ros.ros import qos
import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

# Imported when first used, not at module import (scipy: a second or more).
markers = lazy('landmark_ros.ros.markers')
publishing = lazy('landmark_ros.fuser.publishing')    # the map, scipy: after the publishers
schemas = lazy('landmark_ros.ros.schemas')


class MapOutputs:
    """
    Publish a ``fuser.fuser.Fuser``'s map on the fuser node's output topics.

    ``fused_landmarks`` (the confirmed map, transient local), ``fused_landmark_updates``
    (what changed) and ``fused_markers``, on the schedule of ``PublicationSchedule``
    (one timer at the faster of ``updates_rate_hz`` and ``publish_rate_hz``).
    ``markers_stale``: the next markers go out in full (set after a reset, a load or
    a change of the marker size).
    """

    def __init__(self, node, config):
        self._node = node
        self.map_pub = node.create_publisher(PointCloud2, 'fused_landmarks', qos.LATCHED)
        self.updates_pub = node.create_publisher(PointCloud2, 'fused_landmark_updates',
                                                 qos.reliable_output(10))
        self.marker_pub = node.create_publisher(MarkerArray, 'fused_markers', qos.LATCHED)
        self._schedule = publishing.PublicationSchedule(config.publish_rate_hz,
                                                        config.updates_rate_hz)
        self.period_s = self._schedule.period_s
        self.markers_stale = True
        self._marker_subscribers = 0

    def _header(self, fuser):
        return Header(stamp=self._node.get_clock().now().to_msg(),
                      frame_id=fuser.config.world_frame)

    def publish(self, fuser):
        """
        Publish what is due at this tick of the publication timer.

        The updates first, then the full map: both from one fold of the map.
        """
        updates, full_map = self._schedule.tick()
        if updates:
            self.publish_updates(fuser)
        if full_map:
            self.publish_map(fuser)

    def publish_map(self, fuser):
        """Publish the full map if it changed (at most ``publish_rate_hz``)."""
        if not fuser.map_changed:
            return
        ids, m, P, P_dep, observations = fuser.snapshot()
        self.map_pub.publish(schemas.fused_landmark_message(
            self._header(fuser), ids, m, P, P_dep, observations,
            classes=fuser.classes_of(ids)))

    def publish_updates(self, fuser):
        """
        Publish the landmarks changed since last time, and their markers.

        Landmarks merged into others are announced with the updates (``merged_into``)
        and their markers deleted.
        """
        removed = fuser.take_removed()
        ids, m, P, P_dep, observations = fuser.take_updates()
        header = self._header(fuser)
        classes, merged_into = fuser.classes_of(ids), None
        if removed:
            gone, into = fuser.removal_rows(removed)
            merged_into = np.concatenate([np.full(len(ids), schemas.NOT_MERGED, np.int64), into])
            classes = np.concatenate([classes, fuser.classes_of(into)])
            ids, m, P, P_dep, observations = (np.concatenate([a, b]) for a, b in zip(
                (ids, m, P, P_dep, observations), gone))
        if len(ids):
            self.updates_pub.publish(schemas.fused_landmark_message(
                header, ids, m, P, P_dep, observations, classes=classes,
                merged_into=merged_into))
        if merged_into is not None:
            changed = merged_into == schemas.NOT_MERGED
            ids, m, P = ids[changed], m[changed], P[changed]
        self._publish_markers(fuser, header, (ids, m, P), [drop for drop, _ in removed])

    def _publish_markers(self, fuser, header, changed, deleted_ids):
        """
        Publish the markers of the ``changed`` landmarks ``(ids, m, P)``; delete the others.

        Markers go out for the changed landmarks only (ADD replaces a marker by ID),
        and in full when a subscriber joined or ``markers_stale``; in one message (the
        marker topic keeps one on a latched writer), deletions first.
        """
        subscribers = self.marker_pub.get_subscription_count()
        joined, self._marker_subscribers = subscribers > self._marker_subscribers, subscribers
        if not subscribers:
            return
        deleted = markers.delete_markers(header, deleted_ids).markers
        ids, m, P = changed
        if joined or self.markers_stale:
            ids, m, P, _, _ = fuser.map.snapshot()
            self.markers_stale = False
        elif not len(ids) and not deleted:
            return
        array = markers.landmark_markers(header, ids, m, P, fuser.config.marker_sigma,
                                         rgb=(1.0, 0.5, 0.0))
        array.markers = deleted + list(array.markers)
        self.marker_pub.publish(array)

    def clear(self, fuser):
        """Publish an empty map and delete every marker (after a reset)."""
        header = self._header(fuser)
        self.map_pub.publish(schemas.fused_landmark_message(
            header, [], np.empty((0, 2)), np.empty((0, 2, 2)), None, []))
        self.marker_pub.publish(markers.delete_all(header))
        self.markers_stale = True
