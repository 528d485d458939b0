"""
landmark_observer: robot pose and range-bearing observations in, landmarks out.

Subscribes ``pose`` (geometry_msgs/PoseWithCovarianceStamped) and ``observations``
(sensor_msgs/PointCloud2 with ``id``, ``range``, ``bearing`` and optional noise
fields); publishes ``landmarks`` (PointCloud2: ``id``, ``x``, ``y``, ``z``,
``cov_xx``, ``cov_xy``, ``cov_yy`` and the dependent part ``cov_dep_*``),
``landmark_markers`` and ``/diagnostics``.
Every observation is matched to the pose at its stamp and placed in the world frame
with ``landmark_ros.core.landmarks.landmark_to_world``.
"""

from collections import deque
from dataclasses import dataclass
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros import node_common, pose_buffer
from landmark_ros.cloud import CloudError, read_columns
from landmark_ros.config import ObserverConfig
from landmark_ros.conversions import InputError, pose_from_msg, stamp_ns
from landmark_ros.diagnostics import Counters
from landmark_ros.markers import landmark_markers
from landmark_ros.observations import landmarks_from_rows, observation_noise
from landmark_ros.ros_params import declare_config, keep_in_sync
from landmark_ros.schemas import landmark_message, OBSERVATION_FIELDS
from landmark_ros.subscriptions import take_waiting
import numpy as np
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray


THROUGHPUT_COUNTERS = frozenset(
    {'poses_in', 'observation_messages_in', 'observations_in', 'landmarks_out'})
"""Counters that are not problems; every other counter names a rejection reason."""


def input_qos(depth):
    """Return the sensor-data QoS profile with the given depth."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=qos_profile_sensor_data.reliability,
                      durability=qos_profile_sensor_data.durability)


def output_qos(depth):
    """Return a reliable, volatile QoS profile with the given depth."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE)


def _observations(columns):
    """Return the ``(range, bearing)`` rows of decoded observation columns."""
    return np.stack([columns['range'], columns['bearing']], axis=1)


@dataclass
class _Pending:
    header: Header
    stamp_ns: int
    arrived_ns: int
    columns: dict


class LandmarkObserver(Node):
    """Turn one robot's range-bearing observations into world-frame landmarks."""

    def __init__(self, **kwargs):
        super().__init__('landmark_observer', **kwargs)
        self.config = declare_config(self, ObserverConfig)
        keep_in_sync(self, lambda: self.config, self._apply_config)
        self.counters = Counters(self.get_logger().warning, self.config.log_throttle_s)
        self.counters.counts.update(dict.fromkeys(THROUGHPUT_COUNTERS, 0))
        self.poses = pose_buffer.PoseBuffer(self.config.pose_buffer_s * 1e9,
                                            self.config.max_pose_gap_s * 1e9)
        self.pending = deque()
        self._landmark_msg = PointCloud2()  # refilled for every publish
        self._latest_markers = {}
        self._reported = {}
        self._apply_config(self.config)

        overrides = QoSOverridingOptions.with_default_policies()
        self.create_subscription(PoseWithCovarianceStamped, 'pose', self.on_pose,
                                 input_qos(self.config.input_depth),
                                 qos_overriding_options=overrides)
        self._observation_sub = self.create_subscription(
            PointCloud2, 'observations', self.on_observations,
            input_qos(self.config.input_depth), qos_overriding_options=overrides)
        self.landmark_pub = self.create_publisher(
            PointCloud2, 'landmarks', output_qos(self.config.output_depth),
            qos_overriding_options=overrides)
        # No QoS event handlers on the auxiliary outputs: each is a waitable that
        # every message pays for in the executor.
        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        self.marker_pub = self.create_publisher(
            MarkerArray, 'landmark_markers', output_qos(self.config.output_depth),
            event_callbacks=quiet)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10,
                                                     event_callbacks=quiet)
        self._tick_timer = None
        self._last_run = {}
        self._reset_timers()

    # Parameters ---------------------------------------------------------------

    def _apply_config(self, config):
        old, self.config = self.config, config
        self.poses.max_gap_ns = int(config.max_pose_gap_s * 1e9)
        self.counters.throttle_s = config.log_throttle_s
        pose = np.array(config.sensor_pose)
        self._sensor_pose = pose if pose.any() else None
        self._R_bias = None
        if config.range_bias_stddev or config.bearing_bias_stddev:
            self._R_bias = np.diag([config.range_bias_stddev ** 2,
                                    config.bearing_bias_stddev ** 2])
        if (old.max_wait_s, old.marker_rate_hz) != (config.max_wait_s, config.marker_rate_hz):
            self._reset_timers()

    def _reset_timers(self):
        # One timer for all housekeeping: every timer in a node costs every message
        # some executor time, so the node keeps a single one.
        if not hasattr(self, '_tick_timer'):
            return
        if self._tick_timer is not None:
            self.destroy_timer(self._tick_timer)
        periods = [self.config.diagnostics_period_s, max(self.config.max_wait_s / 2.0, 0.01)]
        if self.config.marker_rate_hz > 0.0:
            periods.append(1.0 / self.config.marker_rate_hz)
        self._tick_timer = self.create_timer(min(periods), self.tick)

    def _due(self, task, period_s, now):
        last = self._last_run.get(task)
        if last is not None and 0 <= now - last < period_s * 1e9:
            return False
        self._last_run[task] = now
        return True

    def tick(self):
        """Expire waiting observations; publish markers and diagnostics when due."""
        now = self.get_clock().now().nanoseconds
        if self.pending:
            self.drain()
        if self.config.marker_rate_hz > 0.0 and self._due(
                'markers', 1.0 / self.config.marker_rate_hz, now):
            self.publish_markers()
        if self._due('diagnostics', self.config.diagnostics_period_s, now):
            self.publish_diagnostics()

    # Inputs -------------------------------------------------------------------

    def on_pose(self, msg):
        """Check a pose and add it to the buffer; process observations it unblocks."""
        try:
            pose, P_pose = pose_from_msg(msg, self.config.world_frame)
        except InputError as error:
            self.counters.add(error.reason, 1, error.detail)
            return
        stamp = stamp_ns(msg.header.stamp)
        newest = self.poses.newest_ns
        if newest is not None and stamp <= newest:
            if newest - stamp <= self.config.time_jump_s * 1e9:
                self.counters.add('pose_out_of_order', 1,
                                  f'pose stamp {stamp * 1e-9:.3f} s is not newer than '
                                  f'{newest * 1e-9:.3f} s: dropped')
                return
            dropped = sum(len(item.columns['range']) for item in self.pending)
            self.counters.add('time_jump_back', 1,
                              f'pose stamp jumped back from {newest * 1e-9:.3f} s to '
                              f'{stamp * 1e-9:.3f} s: pose history cleared, {dropped} '
                              f'waiting observations dropped')
            self.counters.add('dropped_on_time_jump', dropped)
            self.poses.clear()
            self.pending.clear()
        self.poses.add(stamp, pose, P_pose)
        self.counters.add('poses_in')
        self.drain()

    def on_observations(self, msg):
        """Read observation clouds; process each now or when its pose arrives."""
        ready = []
        for cloud in [msg] + take_waiting(self._observation_sub, PointCloud2,
                                          self.config.max_batch_messages - 1):
            item = self._read(cloud)
            if item is None:
                continue
            if not self.pending:
                found = self.poses.lookup(item.stamp_ns, final=self.config.max_wait_s == 0.0)
                if found.status == pose_buffer.FOUND:
                    ready.append((item, found.pose, found.P_pose))
                    continue
            if len(self.pending) >= self.config.max_pending:
                oldest = self.pending.popleft()
                self.counters.add('backlog_dropped', len(oldest.columns['range']),
                                  f'more than {self.config.max_pending} observation messages '
                                  'waiting for a pose: dropped the oldest')
            item.arrived_ns = self.get_clock().now().nanoseconds
            self.pending.append(item)
        if ready:
            self.process(ready)
        if self.pending:
            self.drain()

    def _read(self, msg):
        """Decode and check one observation cloud; None (and counted) if unusable."""
        self.counters.add('observation_messages_in')
        try:
            columns = read_columns(msg, OBSERVATION_FIELDS)
        except CloudError as error:
            self.counters.add(error.reason, 1, f'observation message dropped: {error}')
            return None
        if self.config.sensor_frame and msg.header.frame_id != self.config.sensor_frame:
            self.counters.add('observation_wrong_frame', 1,
                              f"observations in frame '{msg.header.frame_id}', expected "
                              f"'{self.config.sensor_frame}': message dropped")
            return None
        self.counters.add('observations_in', len(columns['range']))
        return _Pending(msg.header, stamp_ns(msg.header.stamp), None, columns)

    def drain(self):
        """Process waiting observations, in order, as far as their poses are known."""
        now = None
        ready = []
        while self.pending:
            item = self.pending[0]
            found = self.poses.lookup(item.stamp_ns)
            if found.status == pose_buffer.WAIT:
                if now is None:
                    now = self.get_clock().now().nanoseconds
                if now - item.arrived_ns < self.config.max_wait_s * 1e9:
                    break
                found = self.poses.lookup(item.stamp_ns, final=True)
            self.pending.popleft()
            rows = len(item.columns['range'])
            if found.status == pose_buffer.FOUND:
                ready.append((item, found.pose, found.P_pose))
            elif found.status == pose_buffer.TOO_OLD:
                self.counters.add('observation_too_old', rows,
                                  f'observation stamp {item.stamp_ns * 1e-9:.3f} s is older '
                                  'than the pose history: dropped')
            else:
                self.counters.add('no_pose_in_time', rows,
                                  f'no pose for observation stamp {item.stamp_ns * 1e-9:.3f} s '
                                  f'within max_wait_s = {self.config.max_wait_s}: dropped')
        if ready:
            self.process(ready)

    # Processing ---------------------------------------------------------------

    def process(self, ready):
        """
        Place the rows of observation messages in the world; publish one cloud each.

        Parameters
        ----------
        ready : list of (_Pending, ndarray, ndarray)
            Each message with its robot pose (3,) and pose covariance (3, 3); all are
            computed in one call of the core.

        """
        counts = [len(item.columns['range']) for item, _, _ in ready]
        columns = [item.columns for item, _, _ in ready]
        noise = [observation_noise(c, self.config.range_stddev ** 2,
                                   self.config.bearing_stddev ** 2,
                                   self.config.range_stddev_per_m ** 2) for c in columns]
        if len(ready) == 1:
            ids, z, R = columns[0]['id'], _observations(columns[0]), noise[0]
            pose, P_pose = ready[0][1], ready[0][2]
        else:
            ids = np.concatenate([c['id'] for c in columns])
            z = np.concatenate([_observations(c) for c in columns])
            R = noise[0] if all(r.ndim == 2 for r in noise) else np.concatenate(
                [np.broadcast_to(r, (n, 2, 2)) for r, n in zip(noise, counts)])
            pose = np.repeat([p for _, p, _ in ready], counts, axis=0)
            P_pose = np.repeat([P for _, _, P in ready], counts, axis=0)
        kept, m, P_m, P_dep, reasons = landmarks_from_rows(
            ids, z, R, pose, P_pose, self._sensor_pose, self._R_bias)
        for reason, count in reasons.items():
            self.counters.add(reason, count, f'{count} of {len(z)} rows rejected in '
                              f'{len(ready)} observation message(s) at '
                              f'{ready[0][0].stamp_ns * 1e-9:.3f} s')
        ids = ids[kept]
        if len(ready) == 1:
            ends = [len(ids)]
        else:
            ends = np.cumsum(np.bincount(np.repeat(np.arange(len(ready)), counts)[kept],
                                         minlength=len(ready))).tolist()
        markers = self.config.marker_rate_hz > 0.0 and self.marker_pub.get_subscription_count()
        start = 0
        for (item, _, _), end in zip(ready, ends):
            header = item.header  # the received message's own header, reused
            header.frame_id = self.config.world_frame
            self.landmark_pub.publish(landmark_message(
                header, ids[start:end], m[start:end], P_m[start:end], P_dep[start:end],
                out=self._landmark_msg))
            if markers:
                for i in range(start, end):
                    self._latest_markers[int(ids[i])] = (header, m[i], P_m[i])
            start = end
        self.counters.add('landmarks_out', len(ids))

    # Outputs ------------------------------------------------------------------

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
        """Publish the counters and a status level on /diagnostics."""
        counts = dict(self.counters.counts)
        problems = {key: value - self._reported.get(key, 0) for key, value in counts.items()
                    if key not in THROUGHPUT_COUNTERS and value > self._reported.get(key, 0)}
        self._reported = counts
        level, message = DiagnosticStatus.OK, 'ok'
        if problems:
            level = DiagnosticStatus.WARN
            message = 'rejected: ' + ', '.join(f'{k} {v}' for k, v in sorted(problems.items()))
        elif not len(self.poses):
            level, message = DiagnosticStatus.WARN, 'no pose received yet'
        extra = {'pose_buffer_size': len(self.poses), 'pending_messages': len(self.pending)}
        node_common.publish_statuses(self, self.diagnostics_pub, [node_common.status(
            level, self.get_fully_qualified_name(), message, self.get_namespace(), counts,
            extra)])


def main(args=None):
    """Run the node until shutdown."""
    return node_common.run(LandmarkObserver, 'landmark_observer', args)


if __name__ == '__main__':
    sys.exit(main())
