"""The localizer's parameters: one frozen, self-validating dataclass (ROS-free)."""

from dataclasses import dataclass
from typing import Tuple

from landmark_ros.pipeline.config import ConfigBase, param

# The choices live here, not in the modules that implement them: the node reads its
# parameters before it imports the filter (scipy, a second or more).
ASSOCIATION_METHODS = ('none', 'nn', 'jcbb')
"""Values of the ``association`` parameter (``none``: rows without ID are skipped)."""

CORRELATIONS = ('independent', 'split_ci', 'consider')
"""Values of ``correlation``: how the map's errors relate to the pose's (``update``)."""
LANDMARK_CORRELATIONS = ('independent', 'unknown')
"""Values of ``landmark_correlation``: how the errors of one update's landmarks relate."""
CORRELATED_NOISE = ('count', 'dependent')
"""Values of ``correlated_noise``: where the time-correlated noise and the bias go."""


@dataclass(frozen=True)
class LocalizerConfig(ConfigBase):
    """Parameters of ``landmark_localizer`` and of ``localizer.Localizer``."""

    map_frame: str = param('map', 'frame of the map, the landmarks and the pose output',
                           read_only=True)
    odom_frame: str = param('odom', 'frame of the odometry (child of the map frame)',
                            read_only=True)
    base_frame: str = param('base_link', 'frame of the robot', read_only=True)
    map_file: str = param('', "landmark map file (the fuser's map_file format) read at start; "
                          "'' takes the map from fused_landmarks only", read_only=True)
    other_robots: Tuple[str, ...] = param(
        [''], 'namespaces of the robots this one may see (empty: none): their pose topics '
        '(NAMESPACE/pose) are read, and a row of robot_observations with id i is a '
        'sighting of other_robots[i]', read_only=True)
    input_depth: int = param(50, 'input queue depth', low=1, high=10000, read_only=True)
    diagnostics_period_s: float = param(1.0, 'diagnostics period [s]', low=0.01, high=1e6)
    odometry_alphas: Tuple[float, float, float, float] = param(
        (0.01, 0.0005, 0.01, 0.0005),
        'odometry motion noise (Probabilistic Robotics 5.4) a1 [rad^2/rad^2], a2 '
        '[rad^2/m^2], a3 [m^2/m^2], a4 [m^2/rad^2], per odometry step; used when the '
        'message covariance is zero')
    odometry_alphas_period_s: float = param(
        0.0, 'odometry step duration the alphas describe [s]: a step of dt has the '
        'model variances times this / dt (odometry error white in time: the same '
        'variance per second at any rate, irregular stamps included); 0: per step '
        'whatever its length (Probabilistic Robotics 5.4; regular odometry at the '
        'calibrated rate)', low=0.0, high=10.0)
    odometry_speed_scale: float = param(
        1.0, 'true distance per odometry distance (wheel radius error)', low=0.01,
        high=100.0)
    odometry_yaw_rate_scale: float = param(
        1.0, 'true turn per odometry turn (wheel base error)', low=0.01, high=100.0)
    odometry_speed_scale_per_yaw_rate: float = param(
        0.0, 'change of the speed scale with the odometry yaw rate [s/rad]: true distance = '
        'odometry distance x max(0, odometry_speed_scale + this x |yaw rate|) (a drive that '
        'slows down in turns, as a controller that keeps the turn rate and gives up speed '
        'does); 0: none', low=-100.0, high=100.0)
    odometry_yaw_per_m: float = param(
        0.0, 'turn per metre of odometry distance [rad/m] added to the odometry turn: a '
        'veer while driving (unequal wheels); 0: none', low=-10.0, high=10.0)
    min_step_variance: float = param(
        1e-10, 'variance floor added to each motion component per odometry step', low=0.0,
        high=1e6)
    range_stddev: float = param(0.05, 'constant part of the range noise [m]', low=0.0,
                                high=1e6)
    range_stddev_per_m: float = param(0.05, 'range noise growing with range [m/m]',
                                      low=0.0, high=1e6)
    range_stddev_per_m2: float = param(
        0.0, 'range noise growing with the square of the range [m/m^2], in quadrature '
        "(the observer's model)", low=0.0, high=1e6)
    range_scale_coeffs: Tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), 'range scale error of the sensor (core.range_scale): the reading is '
        'the true range times 1 + c0 + c1 b + c2 b^2 + range_scale_per_m r (b the bearing '
        '[rad], r the reading [m]); range-bearing rows are divided by it (a noise given '
        'with the rows is propagated; the model noise above describes the corrected range). '
        '(0, 0, 0): no correction')
    range_scale_per_m: float = param(
        0.0, 'range scale error per metre of the reading [1/m] (range_scale_coeffs)',
        low=-1.0, high=1.0)
    range_scale_state_stddev: float = param(
        0.0, 'prior standard deviation of the range scale error of this robot [1] (constant '
        'over the run, its camera calibration; the spread of the scales of the robots): '
        'estimated as a fourth state, range = distance x (1 + s); 0: no state',
        low=0.0, high=0.5)
    range_scale_bearing_state_stddev: float = param(
        0.0, 'prior standard deviation of the change of that range scale error with the '
        "bearing [1/rad] (a lens that reads one side shorter; the spread of the robots' "
        'own values): a fifth state, range = distance x (1 + s + this state x bearing); '
        'needs range_scale_state_stddev; 0: no state', low=0.0, high=1.0)
    bearing_stddev: float = param(0.02, 'bearing noise [rad]', low=0.0, high=1e6)
    range_bias_stddev: float = param(
        0.0, 'range error shared by all sightings of the robot [m] (camera calibration): '
        'the sightings of every landmark within noise_correlation_time_s share it (0: none)',
        low=0.0, high=1e6)
    bearing_bias_stddev: float = param(
        0.0, 'bearing error shared by all sightings of the robot [rad]', low=0.0, high=1e6)
    range_correlated_fraction: float = param(
        0.0, 'share of the range noise variance that is time-correlated (repeats between '
        'sightings; with split_ci it is not trusted as independent)', low=0.0, high=1.0)
    bearing_correlated_fraction: float = param(
        0.0, 'share of the bearing noise variance that is time-correlated', low=0.0,
        high=1.0)
    noise_correlation_time_s: float = param(
        0.0, 'correlation time of the time-correlated noise part [s]: the sightings of a '
        'landmark within it share that part (0: none)', low=0.0, high=1e6)
    correlation: str = param(
        'split_ci', 'map-pose correlation: independent (plain EKF: a landmark error new at '
        'every sighting), split_ci (consistent for any correlation of the map with the pose: '
        "a map built from this robot's poses) or consider (Schmidt-Kalman, the landmarks as "
        "consider states: exact for a map whose errors are independent of the robot's, a "
        'surveyed map or one built from other poses; localizer.consider)')
    landmark_correlation: str = param(
        'independent', 'how the errors of the landmarks of one update relate: independent '
        '(each landmark its own error, as in a surveyed map) or unknown (correlated in any '
        'way, as in a map the team builds from its own poses: covariance intersection '
        'across the rows, update.landmark_bound: never over-confident, conservative); '
        'ignored with consider')
    correlated_noise: str = param(
        'count', 'how the time-correlated noise and the bias enter an update: count (in the '
        'independent noise, the correlated variance times the sightings of the landmark '
        'within noise_correlation_time_s, the bias variance times those of any landmark) or '
        'dependent (with split_ci: beside the map term, of unknown correlation with the '
        'pose, once per sighting; the bias shared by the rows of one update)')
    gate_probability: float = param(0.99, 'chi-square gate per observation row',
                                    low=0.5, high=0.999999)
    iterate_threshold: float = param(
        0.1, 'iterate the update while the linearisation error exceeds this share of the '
        'innovation standard deviation', low=0.0, high=1e6)
    max_iterations: int = param(5, 'Gauss-Newton iterations of the iterated update', low=1,
                                high=50)
    window_s: float = param(1.0, 'late observations are applied at their stamp up to this '
                            'age [s]', low=0.0, high=60.0)
    max_odometry_gap_s: float = param(0.5, 'longer odometry gaps are counted and inflate '
                                      'the motion noise [s]', low=0.0, high=1e6)
    gap_position_stddev_per_s: float = param(
        0.05, 'extra position noise per second of an odometry gap [m/sqrt(s)]', low=0.0, high=1e6)
    max_speed_mps: float = param(3.0, 'a faster odometry step is a jump [m/s]', low=0.0, high=1e6)
    max_yaw_rate: float = param(6.0, 'a faster turn is a jump [rad/s]', low=0.0, high=1e6)
    jump_position_stddev: float = param(0.3, 'position noise added at a jump [m]', low=0.0,
                                        high=1e6)
    jump_heading_stddev: float = param(0.3, 'heading noise added at a jump [rad]', low=0.0,
                                       high=1e6)
    initial_pose: Tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), 'pose at start (x [m], y [m], yaw [rad])')
    initial_stddev: Tuple[float, float, float] = param(
        (0.1, 0.1, 0.05), 'its standard deviations (x [m], y [m], yaw [rad])')
    robot_stddev_floor: float = param(
        0.0, 'added to the position standard deviation of another robot [m] (its marker)',
        low=0.0, high=1e6)
    nis_window: int = param(50, 'updates in the NIS average of the diagnostics', low=1, high=1e6)
    lost_after_s: float = param(30.0, 'no accepted row for this long: warn [s]', low=0.0, high=1e6)
    lost_position_stddev: float = param(
        1.0, 'localization lost when the largest position standard deviation exceeds this '
        '[m]', low=0.0, high=1e6)
    lost_gated_rows: int = param(
        30, 'localization lost after this many consecutive gated rows', low=1, high=1e6)
    association: str = param(
        'jcbb', 'rows without ID: none (skipped), nn (nearest neighbour) or jcbb (joint '
        'compatibility over the message) against the map, from the pose at their stamp')
    association_probability: float = param(
        0.999, 'chi-square gate of the association (2 dof)', low=0.5, high=0.999999)
    association_take_ambiguous: bool = param(
        False, "rows without ID with several candidates take the method's choice "
        '(nearest, or the joint hypothesis) instead of being skipped')
    association_merge_ambiguous: bool = param(
        False, 'rows without ID with several candidates are applied once per candidate '
        'and the results combined with the probabilistic data association weights: a '
        'pairing the pose cannot decide leaves it spread between the candidates; '
        'overrides association_take_ambiguous')

    def check(self) -> None:
        """Check the choices and the list values."""
        if self.correlation not in CORRELATIONS:
            raise ValueError(f'correlation must be one of {CORRELATIONS}, '
                             f'got {self.correlation!r}')
        if self.landmark_correlation not in LANDMARK_CORRELATIONS:
            raise ValueError(f'landmark_correlation must be one of {LANDMARK_CORRELATIONS}, '
                             f'got {self.landmark_correlation!r}')
        if self.correlated_noise not in CORRELATED_NOISE:
            raise ValueError(f'correlated_noise must be one of {CORRELATED_NOISE}, '
                             f'got {self.correlated_noise!r}')
        if self.association not in ASSOCIATION_METHODS:
            raise ValueError(f'association must be one of {ASSOCIATION_METHODS}, '
                             f'got {self.association!r}')
        if any(a < 0.0 for a in self.odometry_alphas):
            raise ValueError(f'odometry_alphas must be >= 0, got {self.odometry_alphas}')
        if self.range_scale_bearing_state_stddev > 0.0 and self.range_scale_state_stddev <= 0.0:
            raise ValueError('range_scale_bearing_state_stddev needs range_scale_state_stddev')
        if any(s <= 0.0 for s in self.initial_stddev):
            raise ValueError(f'initial_stddev must be > 0, got {self.initial_stddev}')
