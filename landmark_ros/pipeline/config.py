"""
Node parameters as frozen, self-validating dataclasses (ROS-free).

Each field carries its parameter description, whether it is read-only at run time
and its valid range; ``landmark_ros.ros.params`` declares them on a node from here,
so the dataclass is the single list of parameters and their defaults.
"""

from dataclasses import dataclass, Field, field, fields, MISSING
import math
from typing import (Any, ClassVar, Dict, Mapping, Optional, Sequence, Tuple, Type, TypeVar,
                    Union)

from landmark_ros.pipeline.limits import MAX_ANGLE, MAX_RANGE


def param(default: Union[float, str, Sequence[Union[float, str]]], description: str,
          read_only: bool = False, low: Optional[float] = None,
          high: Optional[float] = None) -> Any:
    """
    Declare a config field with its parameter metadata.

    Parameters
    ----------
    default : bool, int, float, str or tuple of float
        Default value; its type is the type of the parameter.
    description : str
        What the parameter does, with its unit.
    read_only : bool
        True when a change at run time makes no sense (frames, topics, QoS).
    low, high : float or int, optional
        Inclusive valid range of a number.

    """
    metadata = {'description': description, 'read_only': read_only, 'low': low, 'high': high}
    if isinstance(default, (tuple, list)):
        return field(default_factory=lambda: tuple(default), metadata=metadata)
    return field(default=default, metadata=metadata)


_Config = TypeVar('_Config', bound='ConfigBase')


class ConfigBase:
    """Validation and construction shared by the node configs."""

    # Set by @dataclass on every subclass; declared so that fields() accepts self.
    __dataclass_fields__: ClassVar[Dict[str, 'Field[Any]']]

    def __post_init__(self) -> None:
        for spec in fields(self):
            value = _coerce(spec, getattr(self, spec.name))
            low, high = spec.metadata['low'], spec.metadata['high']
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                if (low is not None and value < low) or (high is not None and value > high):
                    raise ValueError(f'{spec.name} = {value!r} is outside [{low}, {high}]')
            object.__setattr__(self, spec.name, value)
        self.check()

    def check(self) -> None:
        """Check relations between fields; subclasses raise ValueError."""

    @classmethod
    def from_values(cls: Type[_Config], values: Mapping[str, Any]) -> _Config:
        """
        Build from a ``name -> value`` mapping, ignoring names that are not fields.

        Raises
        ------
        ValueError
            If a value has the wrong type or is out of range.

        """
        names = {spec.name for spec in fields(cls)}
        return cls(**{key: value for key, value in values.items() if key in names})


def field_default(spec: 'Field[Any]') -> Any:
    """Return the default value of a dataclass field."""
    return spec.default if spec.default_factory is MISSING else spec.default_factory()


def _coerce(spec, value):
    default = field_default(spec)
    kind = type(default)
    if kind is bool:
        if not isinstance(value, bool):
            raise ValueError(f'{spec.name} must be true or false, got {value!r}')
        return value
    if kind in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f'{spec.name} must be a number, got {value!r}')
        if kind is int and value != int(value):
            raise ValueError(f'{spec.name} must be an integer, got {value!r}')
        if not math.isfinite(value):
            raise ValueError(f'{spec.name} must be finite, got {value!r}')
        return kind(value)
    if kind is str:
        if not isinstance(value, str):
            raise ValueError(f'{spec.name} must be a string, got {value!r}')
        return value
    if isinstance(value, str):
        raise ValueError(f'{spec.name} must be a list, got the string {value!r}')
    items = tuple(value)
    if default and isinstance(default[0], str):
        if not all(isinstance(item, str) for item in items):
            raise ValueError(f'{spec.name} must be a list of strings, got {value!r}')
        return items
    if len(items) != len(default):
        raise ValueError(f'{spec.name} must have {len(default)} entries, got {len(items)}')
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
               for v in items):
        raise ValueError(f'{spec.name} must hold finite numbers, got {value!r}')
    return tuple(float(v) for v in items)


POSE_TYPES = ('pose_with_covariance', 'odometry')
"""Values of ``ObserverConfig.pose_type``: the message type of the robot pose input."""


@dataclass(frozen=True)
class ObserverConfig(ConfigBase):
    """Parameters of ``landmark_observer``."""

    world_frame: str = param(
        'map', 'Frame of the robot poses in and of the landmarks out.', read_only=True)
    pose_type: str = param(
        'pose_with_covariance', "Robot pose input: 'pose_with_covariance' subscribes 'pose' "
        "(geometry_msgs/PoseWithCovarianceStamped), 'odometry' subscribes 'odometry' "
        '(nav_msgs/Odometry, e.g. from robot_localization; the twist is ignored).',
        read_only=True)
    base_frame: str = param(
        '', "Robot frame an odometry message must name as its child_frame_id; '' accepts "
        'any.', read_only=True)
    sensor_frame: str = param(
        '', "Frame the observation clouds must carry; '' accepts any.", read_only=True)
    sensor_pose: Tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), 'Sensor pose in the robot frame: x [m], y [m], yaw [rad].',
        read_only=True)
    range_stddev: float = param(
        0.1, 'Range noise standard deviation [m] for rows without range_variance.',
        low=0.0, high=1000.0)
    range_stddev_per_m: float = param(
        0.0, 'Range noise growing with the range: standard deviation per metre of range '
        '[m/m], added in quadrature to range_stddev.', low=0.0, high=10.0)
    range_stddev_per_m2: float = param(
        0.0, 'Range noise growing with the square of the range: standard deviation per '
        'squared metre of range [m/m^2], added in quadrature to range_stddev and '
        'range_stddev_per_m r.', low=0.0, high=10.0)
    range_scale_coeffs: Tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), 'Range scale error of the sensor (core.range_scale): the reading '
        'is the true range times 1 + c0 + c1 b + c2 b^2 + range_scale_per_m r (b the '
        'bearing [rad], r the reading [m]); rows with a range and a bearing are divided by '
        'it (their own noise columns propagated). (0, 0, 0): no correction.')
    range_scale_per_m: float = param(
        0.0, 'Range scale error per metre of the reading [1/m] (range_scale_coeffs).',
        low=-1.0, high=1.0)
    range_scale_no_bearing: Tuple[float, float] = param(
        (0.0, 0.0), 'Range scale error of a range-only row (no bearing to correct with): '
        'mean and standard deviation of c0 + c1 b + c2 b^2 over where targets appear in '
        'the field of view; the row is divided by 1 + mean + range_scale_per_m r and its '
        'range variance grows by (stddev r)^2 unless range_scale_bearing_limit is set. '
        '(0, 0): no correction.')
    range_scale_bearing_limit: float = param(
        0.0, 'Half the field of view of a camera whose range scale depends on the bearing '
        '(range_scale_coeffs) [rad]. When set, a range-only row carries that scale as a '
        "model the fuser evaluates at the landmark's predicted bearing, instead of the "
        'spread of range_scale_no_bearing as noise. 0: not used.', low=0.0, high=math.pi)
    bearing_stddev: float = param(
        0.02, 'Bearing noise standard deviation [rad] for rows without bearing_variance.',
        low=0.0, high=math.pi)
    range_bias_stddev: float = param(
        0.0, 'Standard deviation of a range bias shared by all observations [m]; it is '
        'added to the covariance and to its dependent part.', low=0.0, high=1000.0)
    range_scale_bias_stddev: float = param(
        0.0, 'Standard deviation of a relative range error (a scale error, 0.01 = 1 %) '
        'shared by all observations: the shared range error is b + s r, so the dependent '
        'range variance of a row at range r [m] is range_bias_stddev^2 + '
        '(range_scale_bias_stddev r)^2; it is added to the covariance too.',
        low=0.0, high=1.0)
    bearing_bias_stddev: float = param(
        0.0, 'Standard deviation of a bearing bias shared by all observations [rad].',
        low=0.0, high=math.pi)
    noise_correlation_time_s: float = param(
        0.0, 'Correlation time of the slowly varying part of the noise (first-order '
        'Gauss-Markov) [s]; range-only and bearing-only views of a landmark seen again '
        'within it carry less information. 0: the noise is white.', low=0.0, high=3600.0)
    range_correlated_fraction: float = param(
        0.0, 'Share of the range noise variance that is time-correlated (views only).',
        low=0.0, high=0.999)
    bearing_correlated_fraction: float = param(
        0.0, 'Share of the bearing noise variance that is time-correlated (views only).',
        low=0.0, high=0.999)
    pose_buffer_s: float = param(
        10.0, 'How much pose history to keep for matching observation stamps [s].',
        read_only=True, low=0.01, high=3600.0)
    max_pose_gap_s: float = param(
        0.1, 'A stamp this close outside the pose history takes the nearest pose [s].',
        low=0.0, high=60.0)
    max_wait_s: float = param(
        0.5, 'How long an observation newer than every pose waits for its pose [s].',
        low=0.0, high=60.0)
    max_pending: int = param(
        100, 'Observation messages that may wait for a pose; the oldest is dropped beyond.',
        read_only=True, low=1, high=100000)
    max_batch_messages: int = param(
        16, 'Observation messages already waiting in the subscription queue that one '
        'callback takes and processes together (1 takes one at a time).',
        low=1, high=1000)
    time_jump_s: float = param(
        1.0, 'A pose this much older than the newest is a jump back in time (bag loop, '
        'sim reset) and clears the pose history; a smaller step back is dropped [s].',
        low=0.0, high=3600.0)
    input_depth: int = param(
        10, 'Queue depth of the input subscriptions (sensor-data QoS).',
        read_only=True, low=1, high=10000)
    output_depth: int = param(
        100, 'Queue depth of the output publishers (reliable QoS): what a busy '
        'subscriber may fall behind before the oldest are overwritten (the fuser counts '
        'them as messages_lost).',
        read_only=True, low=1, high=10000)
    marker_sigma: float = param(
        2.0, 'Size of the marker ellipses in standard deviations.', low=0.1, high=10.0)
    marker_rate_hz: float = param(
        5.0, 'Most marker arrays per second (only while someone subscribes); 0 disables.',
        low=0.0, high=100.0)
    marker_lifetime_s: float = param(
        2.0, 'How long RViz shows a landmark marker without a new observation [s].',
        low=0.0, high=3600.0)
    diagnostics_period_s: float = param(
        1.0, 'Period of the /diagnostics status [s].', read_only=True, low=0.05, high=60.0)
    log_throttle_s: float = param(
        5.0, 'Shortest interval between two log lines about the same problem [s].',
        low=0.0, high=3600.0)
    precision_sources: int = param(
        1, 'Topics the landmark messages are split over by the size of their dependent '
        'part (observer.precision): a message whose dependent standard deviation s gives '
        'floor(log2(s / precision_base_m)) = k (clipped to 0 .. precision_sources - 1) '
        'goes to landmarks (k = 0) or landmarks/precision_k, so that a fuser taking each '
        'as its own source keeps the precise rows apart from the loose ones. 1: every '
        'message on landmarks.', read_only=True, low=1, high=16)
    precision_base_m: float = param(
        0.02, 'Dependent standard deviation [m] below which a message goes to landmarks '
        'when precision_sources > 1; each next level doubles it.', read_only=True,
        low=1e-6, high=1000.0)
    publish_landmark_constraints: bool = param(
        False, 'Deprecated, removed in the next release: also publish the partial '
        'observations on their former topic landmark_constraints, for fusers still '
        'subscribed to it (constraint_topics).', read_only=True)

    def check(self) -> None:
        """Check relations between fields."""
        if self.max_pose_gap_s > self.pose_buffer_s:
            raise ValueError('max_pose_gap_s must not exceed pose_buffer_s')
        if self.pose_type not in POSE_TYPES:
            raise ValueError(f'pose_type must be one of {POSE_TYPES}, got {self.pose_type!r}')
        x, y, yaw = self.sensor_pose
        if max(abs(x), abs(y)) > MAX_RANGE or abs(yaw) > MAX_ANGLE:
            raise ValueError(f'sensor_pose {list(self.sensor_pose)} is outside |x|, |y| <= '
                             f'{MAX_RANGE:g} m, |yaw| <= {MAX_ANGLE:.4g} rad (pipeline.limits)')


DEPRECATED_PARAMETERS = frozenset({'constraint_topics', 'publish_landmark_constraints'})
"""Parameters kept for one release under a former name or for a former topic: declared
and documented, left out of the shipped YAML files; they go in the next release."""

DEFAULT_PARTIAL_OBSERVATION_TOPICS = ('partial_observations',)
"""Default of ``FuserConfig.partial_observation_topics``."""


@dataclass(frozen=True)
class FuserConfig(ConfigBase):
    """Parameters of ``landmark_fuser``."""

    world_frame: str = param(
        'map', 'Frame the landmark clouds must be in; the fused map uses it too.',
        read_only=True)
    input_topics: Tuple[str, ...] = param(
        ('landmarks',), 'Landmark topics to fuse, one per robot (each one source).',
        read_only=True)
    partial_observation_topics: Tuple[str, ...] = param(
        DEFAULT_PARTIAL_OBSERVATION_TOPICS, 'Topics of partial observations (range-only, '
        "bearing-only rows), one per robot (each one source); [''] disables.", read_only=True)
    constraint_topics: Tuple[str, ...] = param(
        ('',), 'Deprecated name of partial_observation_topics, removed in the next release: '
        'its topics replace the default partial_observation_topics, with a warning.',
        read_only=True)
    min_triangulation_angle_deg: float = param(
        5.0, 'Smallest angle two bearing rays must cross at before the views of a '
        'landmark may place it [deg].', read_only=True, low=0.0, high=90.0)
    max_curvature_ratio: float = param(
        0.5, 'The views of a landmark place it only once 2.45 standard deviations (its 95 % '
        "region) are at most this fraction of the fit's radius of curvature (Bates and "
        "Watts' relative curvature; else it waits, too_curved); 0 turns the rule off.",
        read_only=True, low=0.0, high=1e6)
    max_views_per_landmark: int = param(
        50, 'Views kept per landmark waiting to be placed; the oldest is dropped beyond.',
        read_only=True, low=2, high=100000)
    fusion: str = param(
        'split_covariance_intersection',
        'independent, covariance_intersection or split_covariance_intersection.',
        read_only=True)
    source_correlation: str = param(
        'unknown', 'Split CI: how the dependent parts (pose error, sensor bias) of different '
        'sources relate. unknown (default): split CI across sources too, as for robots '
        'localized against a shared map; independent: each is its own (robots posed by '
        'motion capture or independent surveys), the product of the source estimates; '
        'range-only and bearing-only rows do not use it.', read_only=True)
    gate_probability: float = param(
        0.999, 'Probability of the chi-square gate on observations of known landmarks.',
        read_only=True, low=0.5, high=0.999999)
    min_observations: int = param(
        2, 'Mutually consistent observations needed before a landmark is published.',
        read_only=True, low=1, high=1000)
    max_consecutive_rejections: int = param(
        5, 'Rejections in a row after which a landmark is rebuilt from them.',
        read_only=True, low=1, high=1000)
    move_false_alarm_rate: float = param(
        2e-5, 'Change detection (Page CUSUM on the innovations of each confirmed landmark, '
        'fuser.change_detection): false alarms per observation of a static landmark its '
        'threshold is set for; an alarm rebuilds the landmark from its post-change rows '
        '(landmark_moved). 0 turns it off.',
        read_only=True, low=0.0, high=0.1)
    move_min_sources: int = param(
        2, 'Change detection: sources (robots) whose rows an alarm needs, each counting up '
        'to 1/move_min_sources of the threshold: a move is seen by every robot, one '
        "robot's persistent sensing error is not. 1: one robot's rows suffice.",
        read_only=True, low=1, high=100)
    noise_correlation_time_s: float = param(
        0.0, "Change detection: correlation time of the slowly varying part of the rows' "
        'noise (first-order Gauss-Markov, fuser.change_reference) [s]; the test takes the '
        'innovations of a filter that models it. 0: the rows are white.', read_only=True,
        low=0.0, high=3600.0)
    range_correlated_fraction: float = param(
        0.0, 'Change detection: share of the range variance of a row (the major axis of its '
        'independent covariance) that is time-correlated.', read_only=True, low=0.0,
        high=0.999)
    bearing_correlated_fraction: float = param(
        0.0, 'Change detection: share of the bearing variance of a row (the minor axis) '
        'that is time-correlated.', read_only=True, low=0.0, high=0.999)
    move_shift_sigma: float = param(
        1.75, 'The move change detection is tuned to, in standard deviations of one '
        'observation (its noncentrality is the square).', read_only=True, low=0.1,
        high=100.0)
    update_period_s: float = param(
        0.02, 'Queued observations are fused in one batch at this period [s].',
        read_only=True, low=0.001, high=10.0)
    publish_rate_hz: float = param(
        5.0, 'Most full maps (fused_landmarks) per second, published only when the map '
        'changed; on one timer with the updates (its rate the faster of the two), every '
        'n-th tick.', read_only=True, low=0.01, high=1000.0)
    updates_rate_hz: float = param(
        10.0, 'Most fused_landmark_updates (the landmarks changed since the last one) and '
        'marker updates per second.', read_only=True, low=0.01, high=1000.0)
    shard_count: int = param(
        1, 'Fusers sharing the team: this one fuses the landmark IDs with ID modulo '
        'shard_count equal to shard_index.', read_only=True, low=1, high=1000)
    shard_index: int = param(
        0, 'Which shard this fuser is (0 to shard_count - 1).', read_only=True, low=0,
        high=999)
    shard_cell_m: float = param(
        20.0, 'With shard_count > 1, a row without an ID goes to the shard of the square '
        'cell (this side) its world position falls in: (floor(x / side) + 31 floor(y / side)) '
        'modulo shard_count [m].', read_only=True, low=0.01, high=1e9)
    max_queue_messages: int = param(
        100, 'Messages one source may have waiting; the oldest is dropped beyond.',
        read_only=True, low=1, high=100000)
    max_batch_messages: int = param(
        16, 'Most messages one callback takes from each input subscription queue and '
        'checks together: those waiting, then, while the last round took more than one, '
        'those that arrived meanwhile, for up to a quarter of update_period_s (1 takes one '
        'at a time).', low=1, high=1000)
    input_depth: int = param(
        100, 'Queue depth of the input subscriptions (reliable QoS).',
        read_only=True, low=1, high=10000)
    source_timeout_s: float = param(
        5.0, 'A source silent this long is reported stale in the diagnostics [s].',
        low=0.1, high=86400.0)
    map_file: str = param(
        '', "JSON file the map is loaded from at start and saved to; '' disables.",
        read_only=True)
    autosave_period_s: float = param(
        30.0, 'Period of saving the map when it changed; 0 saves only on request and at '
        'shutdown [s].', read_only=True, low=0.0, high=86400.0)
    marker_sigma: float = param(
        2.0, 'Size of the marker ellipses in standard deviations.', low=0.1, high=10.0)
    diagnostics_period_s: float = param(
        1.0, 'Period of the /diagnostics status [s].', read_only=True, low=0.05, high=60.0)
    log_throttle_s: float = param(
        5.0, 'Shortest interval between two log lines about the same problem [s].',
        low=0.0, high=3600.0)
    association: str = param(
        'jcbb', 'Data association of rows without an ID: nearest_neighbour, '
        'global_nearest_neighbour or jcbb (joint compatibility, Neira and Tardos 2001).')
    association_gate_probability: float = param(
        0.999, 'Probability of the chi-square gates of the data association.',
        low=0.5, high=0.999999)
    first_new_id: int = param(
        1000000000, 'Smallest ID given to a landmark found without an ID; IDs are never '
        'reused.', read_only=True, low=0, high=4294967294)
    tentative_timeout_s: float = param(
        30.0, 'A track started by a row without an ID and not confirmed within this time '
        '(of observation stamps) is deleted [s].', low=0.0, high=86400.0)
    detection_probability: float = param(
        0.0, 'Probability that a landmark in view gets a row in a message (p_D), for '
        'merging tracks seen in one message: two distinct landmarks are seen together in '
        'about p_D / (2 - p_D) of the messages seeing either. 0: estimated online per '
        'source, over the field of view of its messages (fuser.track_score).',
        low=0.0, high=0.999)
    merge_together_same: float = param(
        0.01, 'Fraction of the messages seeing either of two tracks of one landmark that '
        'give rows to both (a clutter or mis-associated row beside it), for merging.',
        low=1e-6, high=0.5)
    false_track_probability: float = param(
        1e-4, 'alpha of the track score test: probability that a track of clutter rows is '
        'confirmed (confirmation at score ln((1 - beta) / alpha)).', low=1e-12, high=0.49)
    lost_track_probability: float = param(
        0.01, "beta of the track score test: probability that a landmark's tentative track "
        'is deleted (deletion at score ln(beta / (1 - alpha))).', low=1e-9, high=0.49)
    delete_confirmed_tracks: bool = param(
        False, 'Also delete confirmed tracks of landmarks found without an ID when their '
        'track score falls from its peak by ln((1 - beta) / alpha) (fuser.track_screen). '
        'Off by default: misses are taken as independent per message, and on MRCLAM the '
        'camera misses real landmarks in its field of view for seconds on end, which '
        'deletes them.')
    ambiguous_rows: str = param(
        'assign', 'Rows without an ID that the association could pair with several '
        "landmarks: 'assign' uses the chosen pairing, 'skip' drops them.")

    def check(self) -> None:
        """Check relations between fields."""
        from landmark_ros.fusion.methods import FUSION_METHODS, SOURCE_CORRELATIONS
        methods = ('nearest_neighbour', 'global_nearest_neighbour', 'jcbb')
        if self.association not in methods:
            raise ValueError(f'association must be one of {methods}, got {self.association!r}')
        distinct = self.detection_probability / (2.0 - self.detection_probability)
        if self.detection_probability > 0.0 and not self.merge_together_same < distinct:
            raise ValueError(
                f'merge_together_same ({self.merge_together_same}) must be below '
                f'p_D / (2 - p_D) = {distinct:.4g} (detection_probability '
                f'{self.detection_probability})')
        if self.ambiguous_rows not in ('skip', 'assign'):
            raise ValueError(f"ambiguous_rows must be 'skip' or 'assign', got "
                             f'{self.ambiguous_rows!r}')
        if self.fusion not in FUSION_METHODS:
            raise ValueError(f'fusion must be one of {FUSION_METHODS}, got {self.fusion!r}')
        if self.source_correlation not in SOURCE_CORRELATIONS:
            raise ValueError(f'source_correlation must be one of {SOURCE_CORRELATIONS}, '
                             f'got {self.source_correlation!r}')
        if 0.0 < self.move_false_alarm_rate < 1e-12:
            raise ValueError('move_false_alarm_rate must be 0 (off) or at least 1e-12, got '
                             f'{self.move_false_alarm_rate}')
        if not self.input_topics or not all(self.input_topics):
            raise ValueError('input_topics must list at least one topic name')
        if len(set(self.input_topics)) != len(self.input_topics):
            raise ValueError('input_topics must not repeat a topic')
        self._take_deprecated_topics()
        topics = [topic for topic in self.partial_observation_topics if topic]
        if len(set(topics)) != len(topics) or set(topics) & set(self.input_topics):
            raise ValueError('partial_observation_topics must not repeat a topic nor name an '
                             'input topic')
        if self.shard_index >= self.shard_count:
            raise ValueError(f'shard_index must be below shard_count ({self.shard_count}), '
                             f'got {self.shard_index}')

    def _take_deprecated_topics(self) -> None:
        """Let the deprecated ``constraint_topics``, when set, give the partial topics."""
        old = tuple(topic for topic in self.constraint_topics if topic)
        if not old or old == self.partial_observation_topics:
            return
        if self.partial_observation_topics != DEFAULT_PARTIAL_OBSERVATION_TOPICS:
            raise ValueError('constraint_topics is the deprecated name of '
                             'partial_observation_topics: set only partial_observation_topics')
        object.__setattr__(self, 'partial_observation_topics', old)

    def deprecations(self) -> Tuple[str, ...]:
        """
        Return a warning per deprecated parameter that is set (the fuser logs them).

        Returns
        -------
        tuple of str
            Empty when no deprecated parameter is set.

        """
        if not any(self.constraint_topics):
            return ()
        return ('parameter constraint_topics is deprecated and will be removed in the next '
                'release: rename it partial_observation_topics (its topics '
                f'{list(self.partial_observation_topics)} are used)',)


def markdown_table(config_class: Type[ConfigBase]) -> str:
    """
    Return the parameters of a config class as a Markdown table (for the README).

    Parameters
    ----------
    config_class : type
        A ConfigBase dataclass.

    Returns
    -------
    str

    """
    lines = ['| parameter | default | range | description |', '| --- | --- | --- | --- |']
    for spec in fields(config_class):
        meta = spec.metadata
        default = field_default(spec)
        if isinstance(default, tuple):
            default = '[' + ', '.join(repr(v) if isinstance(v, str) else f'{v:g}'
                                      for v in default) + ']'
        elif isinstance(default, str):
            default = repr(default)
        span = '' if meta['low'] is None else f"{meta['low']:g} to {meta['high']:g}"
        note = ' Read-only.' if meta['read_only'] else ''
        lines.append(f"| `{spec.name}` | `{default}` | {span} | {meta['description']}{note} |")
    return '\n'.join(lines)


if __name__ == '__main__':
    import sys
    for name in sys.argv[1:] or ['ObserverConfig', 'FuserConfig']:
        print(f'### {name}\n\n{markdown_table(globals()[name])}\n')
