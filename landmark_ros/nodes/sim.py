"""
landmark_sim: a simulated team of robots measuring landmarks, for demos and tests.

Simulates ``landmark_ros.sim.simulation.Simulation`` in (scaled) real time. Per robot ``i``
(``robot1``, ``robot2``, ...) it publishes ``robot{i}/pose``
(geometry_msgs/PoseWithCovarianceStamped: the true pose plus a sample of the
reported covariance), ``robot{i}/true_pose`` (geometry_msgs/PoseStamped),
``robot{i}/odometry`` (nav_msgs/Odometry: wheel odometry with the noise model of
``landmark_ros.sim.odometry``, frame ``odom``, at the pose stamps) and
``robot{i}/observations`` (sensor_msgs/PointCloud2, ``id``, ``range``, ``bearing``,
frame ``robot{i}/sensor``: the input of ``landmark_observer``). It also publishes
``ground_truth_landmarks`` (transient local, depth 1: the ``fused_landmarks``
schema with zero covariance, ``observations`` counting the measurements of each
landmark so far; republished when they change) and ``/diagnostics``.

Stamps come from the node clock: simulated time starts at the node clock's time
when the simulation starts and advances ``time_scale`` times as fast as the clock.
Poses are stamped at ``pose_rate_hz``; observations at ``observation_rate_hz``,
each between two pose stamps, and the pose after an observation's stamp is
published as soon as the simulated time reaches it, so observers can interpolate.
"""

import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from landmark_ros.nodes.start import finish, lazy
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.ros import diagnostics, qos, runner
from landmark_ros.ros.conversions import planar_pose_covariance, set_planar_pose
from landmark_ros.ros.params import declare_config
from landmark_ros.sim.odometry import WheelOdometry
from landmark_ros.sim.simulation import SimConfig, Simulation
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.node import Node
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header


# Imported when first used, after the endpoints exist (scipy: seconds on a cold start).
schemas = lazy('landmark_ros.ros.schemas')

STREAM_QOS = qos.replayable_output(100)
"""Poses and observations: reliable and transient local, which best-effort and volatile
(sensor-data) readers accept too; a reader that asks for transient local gets the last 100
messages sent before it matched (the simulation starts once each stream has a subscriber)."""


def robot_name(index):
    """Return the name (and namespace) of robot ``index`` (0-based): ``robot1``, ..."""
    return f'robot{index + 1}'


class LandmarkSim(Node):
    """Publish the simulated poses, observations and ground truth of a robot team."""

    def __init__(self, **kwargs):
        super().__init__('landmark_sim', **kwargs)
        self.config = config = declare_config(self, SimConfig)
        self.names = [robot_name(i) for i in range(config.robots)]
        self.pose_pubs = [self.create_publisher(PoseWithCovarianceStamped, f'{n}/pose',
                                                STREAM_QOS) for n in self.names]
        self.true_pose_pubs = [self.create_publisher(PoseStamped, f'{n}/true_pose',
                                                     STREAM_QOS) for n in self.names]
        self.odometry_pubs = [self.create_publisher(Odometry, f'{n}/odometry', STREAM_QOS)
                              for n in self.names]
        generator = np.random.default_rng([config.seed, 7919])
        self.wheels = [WheelOdometry(config.odometry_alphas, generator) for _ in self.names]
        self.observation_pubs = [self.create_publisher(PointCloud2, f'{n}/observations',
                                                       STREAM_QOS) for n in self.names]
        self.truth_pub = self.create_publisher(PointCloud2, 'ground_truth_landmarks', qos.LATCHED)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.sim = Simulation(config)

        self._pose_covariance = planar_pose_covariance(self.sim.P_pose)
        self._duration_ns = int(round(config.duration_s * 1e9))
        self._created_ns = self.get_clock().now().nanoseconds
        self._start_ns = None  # node clock at simulated time 0
        self._sim_ns = 0  # simulated time published up to
        self._next_pose = 0
        self._next_observation = 0
        self.finished = False
        self.counts = np.zeros(len(self.sim.world.ids), np.int64)
        self.robot_counts = np.zeros(config.robots, np.int64)
        self.messages = {'poses_out': 0, 'observation_messages_out': 0}
        self._truth_dirty = True
        self._last_truth_ns = None

        self.publish_truth()
        period = 0.5 * min(self.sim.pose_period_ns, self.sim.observation_period_ns) * 1e-9
        self._step_timer = self.create_timer(
            min(max(period / config.time_scale, 0.001), 0.05), self.step)
        self.create_timer(config.diagnostics_period_s, self.publish_diagnostics)
        world = (f'world {config.world_file}' if config.world_file
                 else f'{config.landmarks} random landmarks (seed {config.seed})')
        self.get_logger().info(
            f'{config.robots} robots, {world}; '
            + (f'{config.duration_s:g} s' if config.duration_s else 'no time limit')
            + f' at time scale {config.time_scale:g}')

    # Simulation -------------------------------------------------------------------

    @property
    def started(self):
        """Whether the simulated clock runs."""
        return self._start_ns is not None

    @property
    def sim_time_s(self):
        """Return the simulated time published up to [s]."""
        return self._sim_ns * 1e-9

    def _ready(self, now_ns):
        wait = self.config.wait_for_subscribers_s
        if wait <= 0.0 or (now_ns - self._created_ns) * 1e-9 >= wait:
            return True
        cfg = self.config
        poses = self.pose_pubs if cfg.wait_for_pose_subscribers else []
        odometry = self.odometry_pubs if cfg.wait_for_odometry_subscribers else []
        truth = self.true_pose_pubs if cfg.wait_for_true_pose_subscribers else []
        return all(pub.get_subscription_count() > 0
                   for pub in poses + self.observation_pubs + odometry + truth)

    def step(self):
        """Publish every pose and observation whose stamp the simulated time reached."""
        now = self.get_clock().now().nanoseconds
        if not self.started:
            if not self._ready(now):
                return
            self._start_ns = now
            self.get_logger().info(
                f'simulation started after {(now - self._created_ns) * 1e-9:.2f} s')
        target = max(int((now - self._start_ns) * self.config.time_scale), 0)
        if self._duration_ns:
            target = min(target, self._duration_ns)
        pose_end = self.sim.poses_until(target)
        observation_end = self.sim.observations_until(target)
        # In stamp order, so that the pose after each observation follows it.
        while self._next_pose < pose_end or self._next_observation < observation_end:
            pose_stamp = self.sim.pose_stamp_ns(self._next_pose)
            if self._next_observation < observation_end and (
                    self._next_pose >= pose_end
                    or self.sim.observation_stamp_ns(self._next_observation) < pose_stamp):
                self.publish_observations(self._next_observation)
                self._next_observation += 1
            else:
                self.publish_poses(self._next_pose)
                self._next_pose += 1
        self._sim_ns = max(self._sim_ns, target)
        if self._truth_dirty and (self._last_truth_ns is None or now - self._last_truth_ns
                                  >= self.config.ground_truth_period_s * 1e9):
            self.publish_truth()
        if self._duration_ns and target >= self._duration_ns and not self.finished:
            self.finished = True
            self._step_timer.cancel()
            self.publish_truth()
            self.publish_diagnostics()
            self.get_logger().info(
                f'simulation finished at {self.sim_time_s:.2f} s: '
                f'{int(self.robot_counts.sum())} observations of '
                f'{int((self.counts > 0).sum())} landmarks')

    def _header(self, sim_ns, frame_id):
        return Header(stamp=Time(nanoseconds=self._start_ns + sim_ns).to_msg(),
                      frame_id=frame_id)

    def publish_poses(self, k):
        """Publish pose ``k`` of every robot: reported and true."""
        for robot, (pose_pub, true_pub) in enumerate(zip(self.pose_pubs,
                                                         self.true_pose_pubs)):
            stamp, true, pose, P_pose = self.sim.reported_pose(robot, k)
            header = self._header(stamp, self.config.frame)
            msg = PoseWithCovarianceStamped(header=header)
            set_planar_pose(msg.pose.pose, pose)
            # With a shared frame error the covariance depends on the pose.
            msg.pose.covariance = (self._pose_covariance if self.sim.frame_error is None
                                   else planar_pose_covariance(P_pose))
            pose_pub.publish(msg)
            true_msg = PoseStamped(header=header)
            set_planar_pose(true_msg.pose, true)
            true_pub.publish(true_msg)
            odometry = Odometry(header=self._header(stamp, 'odom'), child_frame_id='base_link')
            set_planar_pose(odometry.pose.pose, self.wheels[robot].step(true))
            self.odometry_pubs[robot].publish(odometry)
        self.messages['poses_out'] += len(self.pose_pubs)

    def publish_observations(self, j):
        """Publish observation ``j`` of every robot (an empty cloud when it sees nothing)."""
        for robot, pub in enumerate(self.observation_pubs):
            measurement = self.sim.measure(robot, j)
            header = self._header(measurement.stamp_ns, f'{self.names[robot]}/sensor')
            ids = measurement.ids
            pub.publish(schemas.observation_message(
                header, np.full(len(ids), UNKNOWN_ID) if self.sim.config.no_ids else ids,
                measurement.z))
            ids = ids[ids != UNKNOWN_ID]  # clutter is no landmark
            if len(ids):
                self.counts[np.searchsorted(self.sim.world.ids, ids)] += 1
                self.robot_counts[robot] += len(ids)
                self._truth_dirty = True
        self.messages['observation_messages_out'] += len(self.observation_pubs)

    # Outputs --------------------------------------------------------------------------

    def publish_truth(self):
        """Publish the true landmarks with the number of measurements of each so far."""
        world = self.sim.world
        count = len(world.ids)
        stamp_ns = (self._start_ns + self._sim_ns) if self.started else self._created_ns
        header = Header(stamp=Time(nanoseconds=stamp_ns).to_msg(), frame_id=self.config.frame)
        self.truth_pub.publish(schemas.fused_landmark_message(
            header, world.ids, world.positions, np.zeros((count, 2, 2)), None, self.counts))
        self._truth_dirty = False
        self._last_truth_ns = self.get_clock().now().nanoseconds

    def publish_diagnostics(self):
        """Publish the simulated time, the progress and the counts on /diagnostics."""
        if self.finished:
            level, message = DiagnosticStatus.OK, 'finished'
        elif self.started:
            level, message = DiagnosticStatus.OK, 'running'
        else:
            level, message = DiagnosticStatus.WARN, 'waiting for subscribers'
        counts = dict(self.messages)
        counts['observations_out'] = int(self.robot_counts.sum())
        for name, value in zip(self.names, self.robot_counts.tolist()):
            counts[f'{name}_observations'] = value
        extra = {
            'sim_time_s': f'{self.sim_time_s:.3f}',
            'duration_s': f'{self.config.duration_s:g}',
            'time_scale': f'{self.config.time_scale:g}',
            'start_stamp_ns': str(self._start_ns) if self.started else '',
            'finished': str(self.finished).lower(),
            'landmarks': len(self.sim.world.ids),
            'landmarks_seen': int((self.counts > 0).sum()),
        }
        diagnostics.publish(self, self.diagnostics_pub, [diagnostics.status(
            level, self.get_fully_qualified_name(), message, 'simulation', counts, extra)])


def main(args=None):
    """Run the simulator until shutdown."""
    return runner.run(LandmarkSim, 'landmark_sim', args, (OSError,),
                      'invalid parameters or world file')


if __name__ == '__main__':
    sys.exit(finish(main()))
