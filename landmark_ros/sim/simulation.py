"""
A seeded multi-robot landmark world: paths, poses and range-bearing measurements.

ROS-free (numpy only); ``landmark_ros.nodes.sim`` publishes it. Everything random
is a pure function of ``(seed, what, robot, index)``: the measurement of a robot at
observation index ``j`` is the same whatever else was drawn before, so a run is
reproducible even when a loaded machine makes the node skip or batch steps.

Timing
------
Time ``t`` [s] is simulated time since the start. Poses are stamped at
``k / pose_rate_hz`` and observations at ``j / observation_rate_hz`` plus half a
pose period, so every observation falls between two pose stamps and a consumer
interpolates the pose at its stamp.

Noise model
-----------
Measurements are the true range and bearing plus a per-robot constant bias (drawn
once from N(0, bias_stddev^2)) plus white noise N(0, stddev^2). The reported pose is
the true pose plus an error drawn from the reported covariance ``P_pose``. That
error is held for one observation period, centred on the observation stamp, so the
two poses that bracket an observation carry the same error: interpolating them
gives the true pose at the observation plus exactly one N(0, P_pose) sample,
independent between observations (when ``observation_rate_hz <= pose_rate_hz / 2``;
at higher observation rates two observations can share a pose pair).

Shared map frame (``frame_xy_stddev``, ``frame_yaw_stddev``; 0 by default: off). The
team's map frame is off by a rigid transform drawn once per run
(``Simulation.frame_error``): every reported pose is the true pose moved by it, plus the
white error above, and its reported covariance is the white ``P_pose`` plus the frame
error's first-order covariance at the reported pose (3x3, with translation-heading cross
terms). Every robot's observation of a landmark then carries the same error: the model
split CI assumes (derivation in ``sim.frame_error``).

The world (landmarks, paths, visibility, random streams) is ``sim.world``'s.
"""

from dataclasses import dataclass
import math
from typing import Tuple

from landmark_ros.core import pose2
from landmark_ros.core.sensors import MIN_RANGE
from landmark_ros.pipeline.config import ConfigBase, param
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.sim import frame_error
from landmark_ros.sim.world import (_BIAS, _CLUTTER, _DETECTION, _FRAME, _NOISE, _POSE,
                                    generate_world, load_world, make_paths, rng, visible)
import numpy as np

SENSOR_KINDS = ('rb', 'range', 'bearing')
"""Values of ``SimConfig.sensor_kinds``."""


@dataclass(frozen=True)
class SimConfig(ConfigBase):
    """Parameters of ``landmark_sim`` (and of ``Simulation``)."""

    robots: int = param(3, 'Number of robots, named robot1, robot2, ...', read_only=True,
                        low=1, high=100)
    landmarks: int = param(20, 'Number of random landmarks (ignored with world_file).',
                           read_only=True, low=1, high=100000)
    seed: int = param(0, 'Seed of the world, the paths, the biases and the noise.',
                      read_only=True, low=0, high=2 ** 31 - 1)
    odometry_alphas: Tuple[float, float, float, float] = param(
        (0.05, 0.5, 0.05, 0.01), 'wheel odometry noise on robotN/odometry, the odometry '
        'model of Probabilistic Robotics 5.4 per pose step (sim.odometry)')
    world_file: str = param(
        '', "YAML file of landmarks (a list of {id, x, y}); '' generates them.",
        read_only=True)
    world_size: float = param(20.0, 'Side of the square world the landmarks and paths '
                              'are in, centred on the origin [m].', read_only=True,
                              low=1.0, high=100000.0)
    robot_speed: float = param(1.0, 'Mean speed of the robots along their paths [m/s].',
                               read_only=True, low=0.01, high=100.0)
    min_range: float = param(0.5, 'Landmarks closer than this are not measured [m].',
                             read_only=True, low=MIN_RANGE, high=1000.0)
    max_range: float = param(8.0, 'Landmarks farther than this are not measured [m].',
                             read_only=True, low=0.01, high=100000.0)
    fov: float = param(2.0, 'Field of view, centred on the heading [rad].',
                       read_only=True, low=0.0, high=2.0 * math.pi)
    pose_rate_hz: float = param(20.0, 'Rate of the pose messages [Hz of simulated time].',
                                read_only=True, low=0.1, high=1000.0)
    observation_rate_hz: float = param(
        10.0, 'Rate of the observation messages [Hz of simulated time]; at most half the '
        'pose rate keeps the pose errors of observations independent.', read_only=True,
        low=0.1, high=1000.0)
    range_stddev: float = param(0.1, 'Range noise standard deviation [m].', read_only=True,
                                low=0.0, high=1000.0)
    bearing_stddev: float = param(0.02, 'Bearing noise standard deviation [rad].',
                                  read_only=True, low=0.0, high=math.pi)
    range_bias_stddev: float = param(
        0.0, 'Each robot draws a constant range bias once from N(0, this^2) [m].',
        read_only=True, low=0.0, high=1000.0)
    bearing_bias_stddev: float = param(
        0.0, 'Each robot draws a constant bearing bias once from N(0, this^2) [rad].',
        read_only=True, low=0.0, high=math.pi)
    pose_xy_stddev: float = param(
        0.05, 'Standard deviation of the reported position, x and y [m]; the reported '
        'pose is the true pose plus a sample of this covariance.', read_only=True,
        low=0.0, high=1000.0)
    pose_yaw_stddev: float = param(0.01, 'Standard deviation of the reported heading [rad].',
                                   read_only=True, low=0.0, high=math.pi)
    frame_xy_stddev: float = param(
        0.0, 'Standard deviation of the translation of the shared map frame error, drawn '
        'once per run and the same for every robot [m]; 0 (and frame_yaw_stddev 0): no '
        'frame error.', read_only=True, low=0.0, high=1000.0)
    frame_yaw_stddev: float = param(
        0.0, 'Standard deviation of the rotation (about the origin) of the shared map '
        'frame error [rad].', read_only=True, low=0.0, high=0.5)
    detection_probability: float = param(
        1.0, 'Probability that a visible landmark is measured.', read_only=True,
        low=0.0, high=1.0)
    clutter_rate: float = param(
        0.0, 'Mean number of false measurements per observation message (Poisson), '
        'uniform over the field of view and the range interval; their ID is '
        'UNKNOWN_ID.', read_only=True, low=0.0, high=1000.0)
    no_ids: bool = param(
        False, 'Publish every observation without its landmark ID (UNKNOWN_ID).',
        read_only=True)
    sensor_kinds: tuple = param(
        ('rb',), 'Sensor of each robot, in turn (robot i takes entry i modulo the length): '
        "'rb' measures range and bearing, 'range' only the range (UWB, radio; the bearing "
        "column is NaN), 'bearing' only the bearing (camera; the range is NaN).",
        read_only=True)
    duration_s: float = param(0.0, 'Simulated time to run; 0 runs forever [s].',
                              read_only=True, low=0.0, high=1e9)
    time_scale: float = param(1.0, 'Simulated seconds per wall-clock second.',
                              read_only=True, low=0.01, high=100.0)
    frame: str = param('map', 'World frame of the poses and the ground truth.',
                       read_only=True)
    wait_for_subscribers_s: float = param(
        0.0, 'Before starting the simulated clock, wait up to this long for a subscriber '
        'on every observations and pose topic (and those the wait_for_* flags name) '
        '[wall s]; 0 starts at once.',
        read_only=True, low=0.0, high=3600.0)
    wait_for_pose_subscribers: bool = param(
        True, 'wait_for_subscribers_s waits for a subscriber on every pose topic; false when '
        'nothing takes the reported pose (the team without motion capture, whose localizers '
        'publish the poses the observers take).', read_only=True)
    wait_for_odometry_subscribers: bool = param(
        False, 'wait_for_subscribers_s also waits for a subscriber on every odometry topic '
        '(localizers that must see the first odometry message).', read_only=True)
    wait_for_true_pose_subscribers: bool = param(
        False, 'wait_for_subscribers_s also waits for a subscriber on every true_pose topic '
        '(a tool that scores estimates against every true pose).', read_only=True)
    ground_truth_period_s: float = param(
        1.0, 'Ground truth (with the observation counts so far) is republished at most '
        'this often, when the counts changed [wall s].', read_only=True,
        low=0.05, high=3600.0)
    diagnostics_period_s: float = param(1.0, 'Period of the /diagnostics status [wall s].',
                                        read_only=True, low=0.05, high=60.0)

    def check(self):
        """Check relations between fields."""
        if self.min_range >= self.max_range:
            raise ValueError('min_range must be below max_range')
        if not self.frame:
            raise ValueError('frame must not be empty')
        if not self.sensor_kinds or not set(self.sensor_kinds) <= set(SENSOR_KINDS):
            raise ValueError(f'sensor_kinds must be a list of {SENSOR_KINDS}, got '
                             f'{list(self.sensor_kinds)}')

    def sensor_kind(self, robot):
        """Return the sensor kind of a robot (0-based index): 'rb', 'range' or 'bearing'."""
        return self.sensor_kinds[int(robot) % len(self.sensor_kinds)]

    @property
    def pose_period_ns(self):
        """Interval between pose stamps [ns]."""
        return int(round(1e9 / self.pose_rate_hz))

    @property
    def observation_period_ns(self):
        """Interval between observation stamps [ns]."""
        return int(round(1e9 / self.observation_rate_hz))

    @property
    def P_pose(self):
        """Covariance of the reported poses, shape (3, 3)."""
        return np.diag([self.pose_xy_stddev ** 2, self.pose_xy_stddev ** 2,
                        self.pose_yaw_stddev ** 2])

    @property
    def R(self):
        """Covariance of the measurement noise (range, bearing), shape (2, 2)."""
        return np.diag([self.range_stddev ** 2, self.bearing_stddev ** 2])


# Measurements -----------------------------------------------------------------------

@dataclass(frozen=True)
class Measurement:
    """The observations of one robot at one observation stamp."""

    stamp_ns: int
    """Simulated time [ns]."""
    true_pose: np.ndarray
    """Shape (3,)."""
    ids: np.ndarray
    """Landmark IDs, int64, shape (N,)."""
    z: np.ndarray
    """Measured ``(range [m], bearing [rad])``, shape (N, 2); the column a range-only
    or bearing-only robot does not measure is NaN."""
    z_true: np.ndarray
    """Noise- and bias-free values, shape (N, 2)."""


class Simulation:
    """
    The world, the paths and every robot's poses and measurements.

    Parameters
    ----------
    config : SimConfig
        Parameters.
    world : World, optional
        Landmarks; by default loaded from ``config.world_file`` or generated.

    """

    def __init__(self, config, world=None):
        self.config = config
        if world is None:
            world = (load_world(config.world_file, config.world_size) if config.world_file
                     else generate_world(config.landmarks, config.world_size, config.seed))
        self.world = world
        self.paths = make_paths(config.robots, world.bounds, config.robot_speed, config.seed)
        self.bias = np.array([
            rng(config.seed, _BIAS, i).standard_normal(2)
            * (config.range_bias_stddev, config.bearing_bias_stddev)
            for i in range(config.robots)]).reshape(-1, 2)
        """Per-robot ``(range [m], bearing [rad])`` bias, shape (robots, 2)."""
        self.P_pose = config.P_pose
        """Covariance of the white part of the pose errors, shape (3, 3)."""
        self.frame_error = None
        """The shared map frame error (``frame_error.FrameError``), None when off."""
        if config.frame_xy_stddev or config.frame_yaw_stddev:
            self.frame_error = frame_error.draw(rng(config.seed, _FRAME),
                                                config.frame_xy_stddev, config.frame_yaw_stddev)
        self._L_pose = np.sqrt(np.diag(self.P_pose))  # diagonal: its Cholesky factor
        self.pose_period_ns = config.pose_period_ns
        self.observation_period_ns = config.observation_period_ns
        self.observation_offset_ns = self.pose_period_ns // 2

    @property
    def robots(self):
        """Return the number of robots."""
        return self.config.robots

    # Time ---------------------------------------------------------------------------

    def pose_stamp_ns(self, k):
        """Return the simulated time of pose ``k`` [ns]."""
        return int(k) * self.pose_period_ns

    def observation_stamp_ns(self, j):
        """Return the simulated time of observation ``j`` [ns], between two pose stamps."""
        return int(j) * self.observation_period_ns + self.observation_offset_ns

    def poses_until(self, t_ns):
        """Return how many pose stamps are at or before ``t_ns``."""
        return 0 if t_ns < 0 else int(t_ns // self.pose_period_ns) + 1

    def observations_until(self, t_ns):
        """Return how many observation stamps are at or before ``t_ns``."""
        t_ns -= self.observation_offset_ns
        return 0 if t_ns < 0 else int(t_ns // self.observation_period_ns) + 1

    def _segment(self, t_ns):
        # The observation period centred on each observation stamp.
        half = self.observation_period_ns // 2
        return (int(t_ns) - self.observation_offset_ns + half) // self.observation_period_ns

    # Poses ----------------------------------------------------------------------------

    def true_pose(self, robot, t):
        """
        Return the true pose of a robot.

        Parameters
        ----------
        robot : int
            Index, 0-based (``robot1`` is 0).
        t : float or array_like, shape (N,)
            Simulated time [s].

        Returns
        -------
        ndarray, shape (3,) or (N, 3)

        """
        return self.paths[robot].pose(t)

    def pose_error(self, robot, t_ns):
        """
        Return the error of the reported pose at ``t_ns``, drawn from ``P_pose``.

        Constant over the observation period centred on each observation stamp (see
        the module notes), shape (3,).
        """
        sample = rng(self.config.seed, _POSE, robot, self._segment(t_ns)).standard_normal(3)
        return self._L_pose * sample

    def reported_pose(self, robot, k):
        """
        Return the reported pose ``k`` of a robot and its covariance.

        Parameters
        ----------
        robot : int
            Index, 0-based.
        k : int
            Pose index; its stamp is ``pose_stamp_ns(k)``.

        Returns
        -------
        stamp_ns : int
        true_pose : ndarray, shape (3,)
        pose : ndarray, shape (3,)
            ``true_pose`` plus a sample of ``P_pose`` (heading wrapped); with a frame
            error, ``true_pose`` moved by ``frame_error`` plus that sample.
        P_pose : ndarray, shape (3, 3)
            The white ``P_pose``, plus the frame error's covariance at ``pose``.

        """
        stamp = self.pose_stamp_ns(k)
        true = self.true_pose(robot, stamp * 1e-9)
        pose = true if self.frame_error is None else self.frame_error.apply(true)
        pose = pose + self.pose_error(robot, stamp)
        pose[2] = pose2.wrap_angle(float(pose[2]))
        if self.frame_error is None:
            return stamp, true, pose, self.P_pose.copy()
        return stamp, true, pose, self.P_pose + self.frame_error.covariance(pose)

    # Measurements ---------------------------------------------------------------------

    def measure(self, robot, j):
        """
        Return the measurements of a robot at observation ``j``.

        Landmarks within ``[min_range, max_range]`` and the field of view of the true
        pose are measured: true range and bearing plus the robot's bias plus white
        noise (bearing wrapped to ``[-pi, pi)``), in ID order; each is kept with
        probability ``detection_probability``, and a Poisson number (mean
        ``clutter_rate``) of false measurements with ID ``UNKNOWN_ID`` follow, uniform
        over the range interval and the field of view (the defaults draw nothing).
        A robot whose ``sensor_kind`` is ``range`` (``bearing``) gets NaN bearings
        (ranges); the draws are the same whatever the kind.

        Parameters
        ----------
        robot : int
            Index, 0-based.
        j : int
            Observation index; its stamp is ``observation_stamp_ns(j)``.

        Returns
        -------
        Measurement

        """
        config = self.config
        stamp = self.observation_stamp_ns(j)
        true = self.true_pose(robot, stamp * 1e-9)
        mask, z_all = visible(true, self.world.positions, config.min_range,
                              config.max_range, config.fov)
        z_true = z_all[mask]
        noise = rng(config.seed, _NOISE, robot, j).standard_normal((len(z_true), 2))
        z = z_true + self.bias[robot] + noise * (config.range_stddev, config.bearing_stddev)
        z[:, 1] = pose2.wrap_angle(z[:, 1])
        # A bias or noise draw can push a close landmark's range below the minimum.
        z[:, 0] = np.maximum(z[:, 0], MIN_RANGE)
        ids = self.world.ids[mask]
        if config.detection_probability < 1.0:
            kept = rng(config.seed, _DETECTION, robot, j).random(len(z)) < (
                config.detection_probability)
            ids, z, z_true = ids[kept], z[kept], z_true[kept]
        if config.clutter_rate > 0.0:
            draw = rng(config.seed, _CLUTTER, robot, j)
            count = draw.poisson(config.clutter_rate)
            clutter = np.column_stack([
                draw.uniform(max(config.min_range, MIN_RANGE), config.max_range, count),
                draw.uniform(-0.5 * config.fov, 0.5 * config.fov, count)])
            ids = np.concatenate([ids, np.full(count, UNKNOWN_ID, np.int64)])
            z, z_true = np.concatenate([z, clutter]), np.concatenate([z_true, clutter])
        kind = config.sensor_kind(robot)
        if kind != 'rb':
            z[:, 1 if kind == 'range' else 0] = np.nan
        return Measurement(stamp, true, ids, z, z_true)

    def visible_ids(self, robot, t):
        """Return the IDs a robot measures at time ``t`` [s] (without noise)."""
        mask, _ = visible(self.true_pose(robot, t), self.world.positions,
                          self.config.min_range, self.config.max_range, self.config.fov)
        return self.world.ids[mask]
