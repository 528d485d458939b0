"""
landmark_observer: robot pose and range-bearing observations in, landmarks out.

Subscribes ``pose`` (geometry_msgs/PoseWithCovarianceStamped; with ``pose_type:
odometry`` ``odometry``, nav_msgs/Odometry, instead) and ``observations``
(sensor_msgs/PointCloud2 with ``id``, ``range``, ``bearing`` and optional noise
fields); publishes ``landmarks`` (PointCloud2: ``id``, ``x``, ``y``, ``z``,
``cov_xx``, ``cov_xy``, ``cov_yy`` and the dependent part ``cov_dep_*``),
``partial_observations`` (the partial rows: range-only and bearing-only views, see
``fuser.partial``), ``landmark_markers`` and ``/diagnostics``.
The node only converts messages: the work is ``landmark_ros.observer.observer.Observer``.
"""

import sys

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import ObserverConfig
from landmark_ros.ros import diagnostics, guard, qos, runner
from landmark_ros.ros.cloud import CloudError, read_columns
from landmark_ros.ros.conversions import (InputError, pose_from_msg, pose_from_odometry,
                                          stamp_ns)
from landmark_ros.ros.markers import landmark_markers
from landmark_ros.ros.params import declare_config, keep_in_sync
from landmark_ros.ros.schemas import (landmark_message, OBSERVATION_FIELDS,
                                      partial_observation_message)
from landmark_ros.ros.subscriptions import take_waiting
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray


class LandmarkObserver(Node):
    """Turn one robot's range-bearing observations into world-frame landmarks."""

    def __init__(self, **kwargs):
        super().__init__('landmark_observer', **kwargs)
        config = declare_config(self, ObserverConfig)
        self.observer = Observer(config, self.get_logger().warning)
        keep_in_sync(self, lambda: self.observer.config, self._apply_config)
        self._landmark_msg = PointCloud2()  # refilled for every publish
        self._latest_markers = {}

        overrides = QoSOverridingOptions.with_default_policies()
        if config.pose_type == 'odometry':
            self.create_subscription(Odometry, 'odometry', self._guard(self.on_odometry),
                                     qos.sensor_input(config.input_depth),
                                     qos_overriding_options=overrides)
        else:
            self.create_subscription(PoseWithCovarianceStamped, 'pose',
                                     self._guard(self.on_pose),
                                     qos.sensor_input(config.input_depth),
                                     qos_overriding_options=overrides)
        self._observation_sub = self.create_subscription(
            PointCloud2, 'observations', self._guard(self.on_observations),
            qos.sensor_input(config.input_depth), qos_overriding_options=overrides)
        self.landmark_pub = self.create_publisher(
            PointCloud2, 'landmarks', qos.reliable_output(config.output_depth),
            qos_overriding_options=overrides)
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
        self._tick_timer = None
        self._next_due = {}
        self._reset_timers()

    def _guard(self, callback):
        return guard.guarded(self, self.observer.counters, callback, callback.__name__)

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
        # One timer for all housekeeping: every timer in a node costs every message
        # some executor time, so the node keeps a single one, at the shortest period;
        # each task keeps its own schedule (_due).
        if self._tick_timer is not None:
            self.destroy_timer(self._tick_timer)
        periods = [self.config.diagnostics_period_s, max(self.config.max_wait_s / 2.0, 0.01)]
        if self.config.marker_rate_hz > 0.0:
            periods.append(1.0 / self.config.marker_rate_hz)
        self._tick_ns = int(min(periods) * 1e9)
        self._next_due.pop('markers', None)
        self._tick_timer = self.create_timer(min(periods), self._guard(self.tick))

    def _due(self, task, period_s, now):
        """
        Return whether ``task`` is due at ``now`` [ns]; if so, schedule its next run.

        The next due time advances by the period from the last due time, not from
        ``now``, so a tick that comes a little early or late neither drops a run nor
        shifts the rest: over time the task runs at exactly 1 / ``period_s``. A tick
        within half a tick period of the due time counts as on time. After a stall (or
        a clock jump) of more than a period the schedule restarts from ``now``.
        """
        period = int(period_s * 1e9)
        due = self._next_due.get(task)
        if due is not None and now < due - self._tick_ns // 2:
            if due - now <= period + self._tick_ns:
                return False
            due = now  # the clock jumped back
        due = now if due is None else due
        self._next_due[task] = due + period if now - due < period else now + period
        return True

    def _now_ns(self):
        return self.get_clock().now().nanoseconds

    def tick(self):
        """Expire waiting observations; publish markers and diagnostics when due."""
        now = self._now_ns()
        if self.observer.pending:
            self.publish(self.observer.drain(now))
        if self.config.marker_rate_hz > 0.0 and self._due(
                'markers', 1.0 / self.config.marker_rate_hz, now):
            self.publish_markers()
        if self._due('diagnostics', self.config.diagnostics_period_s, now):
            self.publish_diagnostics()

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

    def on_observations(self, msg):
        """Decode this cloud and those waiting; hand them to the observer; publish."""
        messages = []
        for cloud in [msg] + take_waiting(self._observation_sub, PointCloud2,
                                          self.config.max_batch_messages - 1):
            try:
                columns = read_columns(cloud, OBSERVATION_FIELDS)
            except CloudError as error:
                self.observer.reject('observation_messages_in')
                self.observer.reject(error.reason, 1, f'observation message dropped: {error}')
                continue
            messages.append(ObservationMessage(stamp_ns(cloud.header.stamp), columns,
                                               cloud.header.frame_id, cloud.header))
        self.publish(self.observer.add_observations(messages, self._now_ns()))

    # Outputs ------------------------------------------------------------------

    def publish(self, batches):
        """Publish one landmark cloud per placed observation message."""
        if not batches:
            return
        markers = self.config.marker_rate_hz > 0.0 and self.marker_pub.get_subscription_count()
        for batch in batches:
            header = batch.token  # the received message's own header, reused
            header.frame_id = self.config.world_frame
            self.landmark_pub.publish(landmark_message(
                header, batch.ids, batch.m, batch.P, batch.P_dep, out=self._landmark_msg,
                classes=batch.classes, scan=batch.scan))
            if len(batch.partial_observations):
                msg = partial_observation_message(header, batch.partial_observations.columns())
                self.partial_pub.publish(msg)
                if self.deprecated_partial_pub is not None:
                    self.deprecated_partial_pub.publish(msg)
            if markers:
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
        self.marker_pub.publish(landmark_markers(
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
    sys.exit(main())
