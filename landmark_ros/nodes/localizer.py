"""
landmark_localizer: a robot's pose from wheel odometry and landmark sightings.

Subscribes ``odometry`` (nav_msgs/Odometry: the motion from consecutive poses, or from
the twist when the pose is not maintained), ``observations`` (the observer's cloud schema:
``id``, ``range``, ``bearing`` and optional noise fields; a row with one of range or
bearing is a partial observation), ``fused_landmarks`` (the fuser's latched map; or the
``map_file`` parameter) and ``initialpose`` (PoseWithCovarianceStamped, as RViz's 2D
Pose Estimate sends), and with ``other_robots`` each one's ``pose`` and
``robot_observations`` (the observation schema, ``id`` = index into ``other_robots``):
cooperative updates from the other's published pose and covariance (split CI).
Publishes ``pose`` (PoseWithCovarianceStamped in the map frame, one per odometry
message: what ``landmark_observer`` takes), ``odom_to_map`` (the map-to-odom
correction, geometry_msgs/TransformStamped) and ``/diagnostics`` (with ``map_stamp_ns``,
the header stamp of the ``fused_landmarks`` map in use). The node only converts
messages: the work is ``landmark_ros.localizer.localizer.Localizer``.
"""

import sys
from types import SimpleNamespace

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.nodes.start import finish, imported, lazy
from landmark_ros.ros import diagnostics, guard, qos, runner
from landmark_ros.ros.cloud import CloudError, read_columns
from landmark_ros.ros.conversions import InputError, stamp_ns
from landmark_ros.ros.localizer_messages import (initial_pose, observation_rows,
                                                 odometry_motion, pose_message,
                                                 transform_message)
from landmark_ros.ros.lost import counting_gaps, describe
from landmark_ros.ros.params import declare_config, keep_in_sync
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

# Imported when the node is built, after its endpoints (scipy: a second or more).
pipeline = lazy('landmark_ros.localizer.localizer')
map_file = lazy('landmark_ros.fuser.map_file')
schemas = lazy('landmark_ros.ros.schemas')


class LandmarkLocalizer(Node):
    """Localize one robot against the team's landmark map."""

    def __init__(self, **kwargs):
        super().__init__('landmark_localizer', **kwargs)
        config = declare_config(self, LocalizerConfig)
        self._previous = None
        self._map_stamp_ns = 0
        depth = config.input_depth
        overrides = qos.input_overrides()
        self.create_subscription(Odometry, 'odometry',
                                 self._guard(self._gaps(self.on_odometry, 'odometry')),
                                 qos.sensor_input(depth), qos_overriding_options=overrides)
        self.create_subscription(PointCloud2, 'observations',
                                 self._guard(self._gaps(self.on_observations, 'observations')),
                                 qos.sensor_input(depth), qos_overriding_options=overrides)
        self.create_subscription(PointCloud2, 'fused_landmarks', self._guard(self.on_map),
                                 qos.LATCHED)
        self.create_subscription(PoseWithCovarianceStamped, 'initialpose',
                                 self._guard(self.on_initial_pose), qos.reliable_input(10))
        self._others = {}
        for index, name in enumerate(n for n in config.other_robots if n):
            self.create_subscription(
                PoseWithCovarianceStamped, f'{name.rstrip("/")}/pose',
                self._guard(lambda msg, i=index: self._others.__setitem__(i, msg)),
                qos.sensor_input(depth))
        if any(config.other_robots):
            self.create_subscription(
                PointCloud2, 'robot_observations',
                self._guard(self._gaps(self.on_robot_observations, 'robot_observations')),
                qos.sensor_input(depth))
        self.pose_pub = self.create_publisher(PoseWithCovarianceStamped, 'pose',
                                              qos.reliable_output(depth))
        self.correction_pub = self.create_publisher(TransformStamped, 'odom_to_map',
                                                    qos.reliable_output(depth))
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                     qos.DIAGNOSTICS)
        self._pose_msg = PoseWithCovarianceStamped()
        # The endpoints first, then the filter (imports: scipy); no callback runs before
        # the constructor returns, and what arrives meanwhile waits in the input queues.
        if not imported(self, lambda: (pipeline.Localizer, schemas.read_landmarks)):
            return      # a stop signal came: the runner ends the node without spinning
        self.localizer = pipeline.Localizer(config, self.get_logger().warning)
        keep_in_sync(self, lambda: self.localizer.config, self.localizer.configure)
        if config.map_file:
            self.load_map_file(config.map_file)
        self.create_timer(config.diagnostics_period_s, self._guard(self.publish_diagnostics))

    def _gaps(self, on_message, topic):
        return counting_gaps(on_message, topic, self.count_publishers, self.on_lost)

    def on_lost(self, topic, count):
        """Count ``count`` messages of ``topic`` that went missing on the way."""
        self.localizer.counters.add('messages_lost', int(count), describe(topic, count))

    def _guard(self, callback):
        # Callbacks created before the localizer exists count into it once it does.
        counters = SimpleNamespace(add=lambda *args: self.localizer.counters.add(*args))
        return guard.guarded(self, counters, callback, callback.__name__)

    @property
    def config(self):
        """Return the parameters in force."""
        return self.localizer.config

    def load_map_file(self, path):
        """Read a landmark map file (the fuser's format) into the localizer."""
        try:
            records = map_file.load(path, self.config.map_frame)['landmarks']
        except (OSError, ValueError) as error:
            self.localizer.counters.add('map_file_unreadable', detail=f'{path}: {error}')
            return
        self.localizer.set_map(np.array([r['id'] for r in records], np.int64),
                               np.array([r['mean'] for r in records]).reshape(-1, 2),
                               np.array([r['covariance'] for r in records]).reshape(-1, 2, 2))

    # Inputs -------------------------------------------------------------------

    def on_odometry(self, msg):
        """Predict to this odometry message; publish the pose and the correction."""
        try:
            pose, twist, Q, has_pose = odometry_motion(msg, self._previous,
                                                       self.config.odom_frame)
        except InputError as error:
            self.localizer.counters.add(error.reason, detail=error.detail)
            return
        stamp = stamp_ns(msg.header.stamp)
        self._previous = (stamp, has_pose)
        estimate = self.localizer.add_odometry(stamp, pose=pose, twist=twist, Q=Q)
        if estimate is None:
            return
        header = Header(stamp=msg.header.stamp, frame_id=self.config.map_frame)
        self.pose_pub.publish(pose_message(header, estimate.x, estimate.P, self._pose_msg))
        self.correction_pub.publish(transform_message(header, self.config.odom_frame,
                                                      self.localizer.odom_to_map()))

    def on_observations(self, msg):
        """Hand the sightings to the localizer (applied at their own stamp)."""
        self.localizer.counters.add('observation_messages_in')
        try:
            columns = read_columns(msg, schemas.OBSERVATION_FIELDS)
        except CloudError as error:
            self.localizer.counters.add(error.reason, detail=f'observations dropped: {error}')
            return
        ids, z, kind, R = observation_rows(columns)
        good = kind >= 0
        self.localizer.counters.add('observation_rows_empty', int((~good).sum()),
                                    detail='rows with neither range nor bearing')
        if good.any():
            self.localizer.add_observations(stamp_ns(msg.header.stamp), ids[good], z[good],
                                            kind[good], None if R is None else R[good])

    def on_robot_observations(self, msg):
        """Apply sightings of other robots with their latest published pose."""
        try:
            ids, z, kind, R = observation_rows(read_columns(msg, schemas.OBSERVATION_FIELDS))
        except CloudError as error:
            self.localizer.counters.add(error.reason, detail=f'robot sightings dropped: {error}')
            return
        stamp = stamp_ns(msg.header.stamp)
        for row, index in enumerate(ids.tolist()):
            other = self._others.get(index)
            if other is None or kind[row] != 0:
                self.localizer.counters.add('robot_rows_unusable', detail='no pose of that '
                                            'robot yet, or not a range-bearing row')
                continue
            try:
                x, P = initial_pose(other, self.config.map_frame)
            except InputError as error:
                self.localizer.counters.add(error.reason, detail=error.detail)
                continue
            self.localizer.add_robot_sighting(
                stamp, z[row], pipeline.Estimate(stamp_ns(other.header.stamp), x, P),
                None if R is None else R[row], other_id=str(index))

    def on_map(self, msg):
        """Replace the map with the fuser's latest."""
        if msg.header.frame_id != self.config.map_frame:
            self.localizer.counters.add('map_wrong_frame',
                                        detail=f"map in '{msg.header.frame_id}'")
            return
        try:
            landmarks = schemas.read_landmarks(msg)
        except CloudError as error:
            self.localizer.counters.add(error.reason, detail=f'map dropped: {error}')
            return
        self.localizer.set_map(landmarks.ids, landmarks.m, landmarks.P)
        self.localizer.counters.add('maps_received')
        self._map_stamp_ns = stamp_ns(msg.header.stamp)

    def on_initial_pose(self, msg):
        """Restart the filter at the given pose."""
        try:
            x, P = initial_pose(msg, self.config.map_frame)
        except InputError as error:
            self.localizer.counters.add(error.reason, detail=error.detail)
            return
        self.localizer.initialize(stamp_ns(msg.header.stamp), x, P)

    # Outputs ------------------------------------------------------------------

    def publish_diagnostics(self):
        """Publish the localizer's status on /diagnostics (with the map's stamp in use)."""
        estimate = self.localizer.estimate()
        status = self.localizer.status(estimate.stamp_ns if estimate else None)
        status.extra['map_stamp_ns'] = self._map_stamp_ns
        diagnostics.publish(self, self.diagnostics_pub, [diagnostics.to_msg(
            status, self.get_fully_qualified_name(), self.get_namespace())])


def main(args=None):
    """Run the node until shutdown."""
    return runner.run(LandmarkLocalizer, 'landmark_localizer', args)


if __name__ == '__main__':
    sys.exit(finish(main()))
