"""
landmark_observer: robot pose and range-bearing observations in, landmarks out.

Subscribes ``pose`` (geometry_msgs/PoseWithCovarianceStamped; with ``pose_type:
odometry`` ``odometry``, nav_msgs/Odometry, instead) and ``observations``
(sensor_msgs/PointCloud2 with ``id``, ``range``, ``bearing`` and optional noise
fields); publishes ``landmarks`` (PointCloud2: ``id``, ``x``, ``y``, ``z``,
``cov_xx``, ``cov_xy``, ``cov_yy`` and the dependent part ``cov_dep_*``; with
``precision_sources`` > 1 also ``landmarks/precision_k``, ``observer.precision``),
``partial_observations`` (the partial rows: range-only and bearing-only, see
``observer.partial``), ``landmark_markers`` and ``/diagnostics``.
The node only converts messages: the work is ``landmark_ros.observer.observer.Observer``.
"""

import sys
from types import SimpleNamespace

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.nodes.start import finish, lazy
from landmark_ros.observer.precision import precision_level, precision_topics
from landmark_ros.pipeline.config import ObserverConfig
from landmark_ros.ros import diagnostics, fast_io, guard, qos, runner
from landmark_ros.ros.cloud import CloudError, read_columns
from landmark_ros.ros.conversions import (InputError, pose_from_msg, pose_from_odometry,
                                          stamp_ns)
from landmark_ros.ros.lost import counting_gaps, describe
from landmark_ros.ros.params import declare_config, keep_in_sync
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

# Imported when the node is built, not at module import (scipy: a second or more).
pipeline = lazy('landmark_ros.observer.observer')
markers = lazy('landmark_ros.ros.markers')
schemas = lazy('landmark_ros.ros.schemas')


class LandmarkObserver(Node):
    """Turn one robot's range-bearing observations into world-frame landmarks."""

    def __init__(self, **kwargs):
        super().__init__('landmark_observer', **kwargs)
        config = declare_config(self, ObserverConfig)
        self._fast = fast_io.declare_switch(self)
        # The pipeline first (a second of imports), then the endpoints: its inputs are
        # best-effort sensor data with a short queue, whose publishers start sending as
        # soon as they see a subscriber; the node takes them from its first message.
        self.observer = pipeline.Observer(config, self.get_logger().warning)
        overrides = qos.input_overrides()
        pose_type, pose_topic, on_pose = (
            (Odometry, 'odometry', self.on_odometry) if config.pose_type == 'odometry'
            else (PoseWithCovarianceStamped, 'pose', self.on_pose))
        self.pose_subscription = self.create_subscription(
            pose_type, pose_topic,
            self._guard(counting_gaps(on_pose, pose_topic, self.count_publishers, self.on_lost)),
            qos.sensor_input(config.input_depth), qos_overriding_options=overrides)
        self.observation_inputs = fast_io.Inputs(self, fast_io.InputSpec(
            PointCloud2, ['observations'], qos.sensor_input(config.input_depth),
            lambda: self.config.max_batch_messages, qos_overriding_options=overrides,
            on_lost=self.on_lost), self.on_observations, self._guard, self._fast)
        # One landmark topic per precision level (observer.precision): landmarks first.
        self.landmark_pubs = [self.create_publisher(
            PointCloud2, topic, qos.reliable_output(config.output_depth),
            qos_overriding_options=overrides)
            for topic in precision_topics('landmarks', config.precision_sources)]
        self.landmark_pub = self.landmark_pubs[0]
        self.partial_pub = self.create_publisher(
            PointCloud2, 'partial_observations', qos.reliable_output(config.output_depth),
            qos_overriding_options=overrides)
        self.deprecated_partial_pub = None  # landmark_constraints, for one more release
        if config.publish_landmark_constraints:
            self.get_logger().warning('publish_landmark_constraints is deprecated: fusers '
                                      'take partial_observations (partial_observation_topics)')
            self.deprecated_partial_pub = self.create_publisher(
                PointCloud2, 'landmark_constraints', qos.reliable_output(config.output_depth))
        # No QoS event handlers on the auxiliary outputs: each is a waitable that
        # every message pays for in the executor.
        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        self.marker_pub = self.create_publisher(
            MarkerArray, 'landmark_markers', qos.reliable_output(config.output_depth),
            event_callbacks=quiet)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                     qos.DIAGNOSTICS, event_callbacks=quiet)
        keep_in_sync(self, lambda: self.observer.config, self._apply_config)
        self._landmark_msg = PointCloud2()  # refilled for every publish
        self._latest_markers = {}
        self._periodic = None
        self._reset_timers()

    def on_lost(self, topic, count):
        """Count ``count`` messages of ``topic`` that went missing on the way."""
        self.observer.counters.add('messages_lost', int(count), describe(topic, count))

    def _guard(self, callback):
        # Callbacks created before the observer exists count into it once it does.
        counters = SimpleNamespace(add=lambda *args: self.observer.counters.add(*args))
        return guard.guarded(self, counters, callback, callback.__name__)

    @property
    def config(self):
        """Return the parameters in force (the observer's)."""
        return self.observer.config

    @property
    def counters(self):
        """Return the observer's counters."""
        return self.observer.counters

    def _apply_config(self, config):
        old = self.observer.config
        self.observer.reconfigure(config)
        if (old.max_wait_s, old.marker_rate_hz) != (config.max_wait_s, config.marker_rate_hz):
            self._reset_timers()

    def _reset_timers(self):
        # Periodic: one timer for all housekeeping with fast_io (every timer in a node
        # costs every message some executor time), one each without.
        if self._periodic is not None:
            self._periodic.destroy()
        tasks = [('drain', max(self.config.max_wait_s / 2.0, 0.01), self.drain),
                 ('diagnostics', self.config.diagnostics_period_s, self.publish_diagnostics)]
        if self.config.marker_rate_hz > 0.0:
            tasks.append(('markers', 1.0 / self.config.marker_rate_hz, self.publish_markers))
        self._periodic = fast_io.Periodic(self, tasks, self._guard, self._fast)

    def _now_ns(self):
        return self.get_clock().now().nanoseconds

    def drain(self):
        """Place the observations that waited ``max_wait_s`` for a pose."""
        if self.observer.pending:
            self.publish(self.observer.drain(self._now_ns()))

    # Inputs -------------------------------------------------------------------

    def on_odometry(self, msg):
        """Convert the pose part of an odometry message and hand it to the observer."""
        try:
            pose, P_pose = pose_from_odometry(msg, self.config.world_frame,
                                              self.config.base_frame)
        except InputError as error:
            self.observer.reject(error.reason, 1, error.detail)
            return
        self.publish(self.observer.add_pose(stamp_ns(msg.header.stamp), pose, P_pose,
                                            self._now_ns()))

    def on_pose(self, msg):
        """Convert a pose message and hand it to the observer; publish what it unblocks."""
        try:
            pose, P_pose = pose_from_msg(msg, self.config.world_frame)
        except InputError as error:
            self.observer.reject(error.reason, 1, error.detail)
            return
        self.publish(self.observer.add_pose(stamp_ns(msg.header.stamp), pose, P_pose,
                                            self._now_ns()))

    def on_observations(self, bursts):
        """Decode observation clouds (``[(topic, clouds)]``); hand them on; publish."""
        messages = []
        for cloud in (cloud for _, clouds in bursts for cloud in clouds):
            try:
                columns = read_columns(cloud, schemas.OBSERVATION_FIELDS)
            except CloudError as error:
                self.observer.reject('observation_messages_in')
                self.observer.reject(error.reason, 1, f'observation message dropped: {error}')
                continue
            messages.append(pipeline.ObservationMessage(
                stamp_ns(cloud.header.stamp), columns, cloud.header.frame_id, cloud.header))
        self.publish(self.observer.add_observations(messages, self._now_ns()))

    # Outputs ------------------------------------------------------------------

    def publish(self, batches):
        """
        Publish one landmark cloud per placed observation message.

        On ``landmarks``, or with ``precision_sources`` > 1 on the topic of the message's
        precision level (``observer.precision.precision_level``).
        """
        if not batches:
            return
        keep = self.config.marker_rate_hz > 0.0 and self.marker_pub.get_subscription_count()
        for batch in batches:
            header = batch.token  # the received message's own header, reused
            header.frame_id = self.config.world_frame
            level = precision_level(batch.P_dep, len(self.landmark_pubs),
                                    self.config.precision_base_m)
            self.landmark_pubs[level].publish(schemas.landmark_message(
                header, batch.ids, batch.m, batch.P, batch.P_dep, out=self._landmark_msg,
                classes=batch.classes, scan=batch.scan))
            if len(batch.partial_observations):
                msg = schemas.partial_observation_message(
                    header, batch.partial_observations.columns())
                self.partial_pub.publish(msg)
                if self.deprecated_partial_pub is not None:
                    self.deprecated_partial_pub.publish(msg)
            if keep:
                for i, landmark_id in enumerate(batch.ids.tolist()):
                    self._latest_markers[landmark_id] = (header, batch.m[i], batch.P[i])

    def publish_markers(self):
        """Publish an ellipse and a label for each landmark observed since last time."""
        if not self._latest_markers:
            return
        latest, self._latest_markers = self._latest_markers, {}
        ids = list(latest)
        header = max((entry[0] for entry in latest.values()),
                     key=lambda h: stamp_ns(h.stamp))
        self.marker_pub.publish(markers.landmark_markers(
            header, ids, np.array([latest[i][1] for i in ids]),
            np.array([latest[i][2] for i in ids]), self.config.marker_sigma,
            self.config.marker_lifetime_s))

    def publish_diagnostics(self):
        """Publish the observer's status on /diagnostics."""
        status = self.observer.status()
        diagnostics.publish(self, self.diagnostics_pub, [diagnostics.to_msg(
            status, self.get_fully_qualified_name(), self.get_namespace())])


def main(args=None):
    """Run the node until shutdown."""
    return runner.run(LandmarkObserver, 'landmark_observer', args)


if __name__ == '__main__':
    sys.exit(finish(main()))
