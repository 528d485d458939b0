"""
The observer of one robot: poses and observation columns in, world-frame landmarks out.

ROS-free: the ``landmark_observer`` node, the MRCLAM replay, the Monte Carlo study and
the benchmarks all drive this one object. Time is integer nanoseconds throughout.

Each observation message is matched to the robot pose at its stamp (interpolated between the two
poses that bracket it, see ``pose_buffer``) and its valid rows are placed in the world with
``core.landmarks.landmark_to_world_dependent``: the total covariance and its dependent part (pose
and sensor-bias terms). An observation newer than every pose waits for the next pose, up to
``max_wait_s``, in arrival order.
"""

from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Deque, Dict, List, Optional, Sequence, Tuple

from landmark_ros.core import range_scale
from landmark_ros.core.covariance import COVARIANCE_PROBLEMS, covariance_status
from landmark_ros.observer.partial import (CorrelatedNoise, partial_observations_from_rows,
                                           range_only_corrected, RangeOnlyScale, SensorMount,
                                           split_partial)
from landmark_ros.observer.rows import landmarks_from_rows, NOISE_FIELDS, observation_noise
from landmark_ros.pipeline import limits, pose_buffer
from landmark_ros.pipeline.config import ObserverConfig
from landmark_ros.pipeline.counters import Counters, Status
from landmark_ros.pipeline.partial_rows import no_partial_observations, PartialObservations
from landmark_ros.pipeline.rows import first_problems, UNKNOWN_ID
from landmark_ros.pipeline.scan import Scan
import numpy as np
from numpy.typing import NDArray

THROUGHPUT_COUNTERS = frozenset(
    {'poses_in', 'observation_messages_in', 'observations_in', 'landmarks_out'})
"""Counters that are not problems; every other counter names a rejection reason."""

NOT_PROBLEMS = THROUGHPUT_COUNTERS | {'partial_rows', 'partial_out'}
"""``THROUGHPUT_COUNTERS`` and those of the partial rows (counted once there are any)."""


@dataclass
class ObservationMessage:
    """
    The rows of one observation message, decoded.

    Attributes
    ----------
    stamp_ns : int
        Acquisition time [ns].
    columns : dict of str to ndarray, shape (N,)
        ``range`` [m], ``bearing`` [rad], optional ``id`` (absent: every row is
        unlabelled, ``UNKNOWN_ID``), ``class`` and the noise fields. Without
        ``bearing`` the rows are range-only, without ``range`` bearing-only; a row
        with one of the two NaN is partial (``partial.split_partial``).
    frame_id : str or None
        The message's frame, checked against ``sensor_frame``; None skips the check.
    token : object
        The caller's handle on the message (the node keeps its header), returned with
        the landmarks.

    """

    stamp_ns: int
    columns: Dict[str, NDArray[Any]]
    frame_id: Optional[str] = None
    token: Any = None
    arrived_ns: int = 0

    @property
    def rows(self) -> int:
        """Return how many rows the message has (0 without columns)."""
        return max((len(values) for values in self.columns.values()), default=0)


MessageWithPose = Tuple[ObservationMessage, NDArray[np.float64], NDArray[np.float64]]
"""An observation message with the robot pose, shape (3,), and its covariance, (3, 3)."""


@dataclass(frozen=True)
class LandmarkBatch:
    """
    World-frame landmarks placed from one observation message.

    Attributes
    ----------
    stamp_ns : int
        The observation stamp [ns].
    ids : ndarray of int64, shape (K,)
    m : ndarray, shape (K, 2)
        Positions in ``world_frame`` [m].
    P : ndarray, shape (K, 2, 2)
        Total covariances [m^2].
    P_dep : ndarray, shape (K, 2, 2)
        Their dependent parts (pose and bias terms) [m^2].
    token : object
        The message's ``token``.
    partial_observations : pipeline.partial_rows.PartialObservations
        The message's partial rows (range-only, bearing-only) as views in the world;
        empty when it had none.
    classes : ndarray of int64, shape (K,), optional
        Landmark classes; None when the message had no ``class`` and no row
        without an ID (all 0).
    scan : Scan, optional
        The robot pose terms the fuser's association needs; only when some row has
        no ID (``UNKNOWN_ID``).

    """

    stamp_ns: int
    ids: NDArray[np.int64]
    m: NDArray[np.float64]
    P: NDArray[np.float64]
    P_dep: NDArray[np.float64]
    token: Any = None
    partial_observations: PartialObservations = field(default_factory=no_partial_observations)
    classes: Optional[NDArray[np.int64]] = None
    scan: Optional[Scan] = None


class Observer:
    """
    Turn one robot's poses and range-bearing observations into world-frame landmarks.

    Parameters
    ----------
    config : ObserverConfig
        The parameters (noise model, sensor pose, time policy).
    log : callable, optional
        ``log(text)`` for throttled warnings about rejected input.

    Notes
    -----
    Every rejection is counted in ``counters`` under a named reason; the valid rows
    of a message are still used. Source of the maths: the chapter's pose composition
    and inverse observation model with first-order covariance propagation.

    """

    def __init__(self, config: ObserverConfig,
                 log: Optional[Callable[[str], None]] = None) -> None:
        self.config = config
        self.counters = Counters(log or (lambda text: None), config.log_throttle_s)
        self.counters.counts.update(dict.fromkeys(THROUGHPUT_COUNTERS, 0))
        self.poses = pose_buffer.PoseBuffer(config.pose_buffer_s * 1e9,
                                            config.max_pose_gap_s * 1e9)
        self.pending: Deque[ObservationMessage] = deque()
        self._superseded_ns: Optional[Tuple[Optional[int], int]] = None
        self._reported: Dict[str, int] = {}
        self._view_group = 0
        self._correlated: Optional[CorrelatedNoise] = None
        self.reconfigure(config)

    def reconfigure(self, config: ObserverConfig) -> None:
        """Apply new parameters (those that may change at run time)."""
        self.config = config
        self.poses.max_gap_ns = int(config.max_pose_gap_s * 1e9)
        self.counters.throttle_s = config.log_throttle_s
        pose = np.array(config.sensor_pose, dtype=np.float64)
        self._sensor_pose = pose if pose.any() else None
        self._R_bias, self._scale_var = None, config.range_scale_bias_stddev ** 2
        self._lens = RangeOnlyScale(config.range_scale_coeffs, config.range_scale_per_m,
                                    config.range_scale_no_bearing,
                                    config.range_scale_bearing_limit)
        if config.range_bias_stddev or config.bearing_bias_stddev or self._scale_var:
            self._R_bias = np.diag([config.range_bias_stddev ** 2,
                                    config.bearing_bias_stddev ** 2])
        correlated = CorrelatedNoise(config.range_correlated_fraction,
                                     config.bearing_correlated_fraction,
                                     config.noise_correlation_time_s)
        if self._correlated is not None:  # keep when each landmark was last seen
            correlated.last_ns = self._correlated.last_ns
        self._correlated = correlated

    def reject(self, reason: str, count: int = 1, detail: Optional[str] = None) -> None:
        """Count (and log, throttled) input rejected before it reached the observer."""
        self.counters.add(reason, count, detail)

    # Poses ----------------------------------------------------------------------

    def add_pose(self, stamp_ns: int, pose: NDArray[np.float64], P_pose: NDArray[np.float64],
                 now_ns: int = 0) -> List[LandmarkBatch]:
        """
        Add a robot pose; return the landmarks of the observations it unblocks.

        Parameters
        ----------
        stamp_ns : int
            Stamp of the pose [ns]; zero is never a valid stamp.
        pose : ndarray, shape (3,)
            (x [m], y [m], theta [rad]) in ``world_frame``.
        P_pose : ndarray, shape (3, 3)
            Its covariance.
        now_ns : int
            The caller's clock [ns], for the waiting observations.

        Returns
        -------
        list of LandmarkBatch
            One per observation message placed, in arrival order.

        """
        pose = np.asarray(pose, dtype=np.float64)
        P_pose = np.asarray(P_pose, dtype=np.float64)
        if not np.all(np.isfinite(pose)):
            self.counters.add('pose_nonfinite', 1, f'pose {pose.tolist()}: dropped')
            return []
        status = int(covariance_status(P_pose))
        if status:
            self.counters.add(f'pose_{COVARIANCE_PROBLEMS[status]}', 1,
                              f'(x, y, yaw) covariance {P_pose.tolist()}: dropped')
            return []
        reason, detail = limits.pose_problem(pose, P_pose)
        if reason:
            self.counters.add(reason, 1, f'{detail}: dropped')
            return []
        if stamp_ns <= 0:
            self.counters.add('pose_stamp_zero', 1, 'pose with a zero stamp: dropped')
            return []
        newest = self.poses.newest_ns
        if newest is not None and stamp_ns <= newest:
            if stamp_ns == newest:
                self._repeated_pose(stamp_ns, pose, P_pose)
                return []
            if newest - stamp_ns <= self.config.time_jump_s * 1e9:
                self.counters.add('pose_out_of_order', 1,
                                  f'pose stamp {stamp_ns * 1e-9:.3f} s is older than '
                                  f'{newest * 1e-9:.3f} s: dropped')
                return []
            dropped = sum(item.rows for item in self.pending)
            self.counters.add('time_jump_back', 1,
                              f'pose stamp jumped back from {newest * 1e-9:.3f} s to '
                              f'{stamp_ns * 1e-9:.3f} s: pose history cleared, {dropped} '
                              'waiting observations dropped')
            self.counters.add('dropped_on_time_jump', dropped)
            self.poses.clear()
            self.pending.clear()
            self._superseded_ns = None
        self.poses.add(stamp_ns, pose, P_pose)
        self.counters.add('poses_in')
        return self.drain(now_ns)

    def _repeated_pose(self, stamp_ns: int, pose: NDArray[np.float64],
                       P_pose: NDArray[np.float64]) -> None:
        lookup = self.poses.lookup(stamp_ns)
        same = (lookup.status == pose_buffer.FOUND and lookup.pose is not None
                and lookup.P_pose is not None and np.array_equal(lookup.pose, pose)
                and np.array_equal(lookup.P_pose, P_pose))
        if same:
            self.counters.add('pose_duplicate')
            return
        # Same stamp, other content: the driver's clock is frozen. Which pose the robot
        # had at this stamp is unknown: observations that would use it are rejected.
        stamps = self.poses.stamps_ns
        before = stamps[-2] if len(stamps) > 1 else None
        self._superseded_ns = (before, stamp_ns)
        self.counters.add('pose_stamp_repeated', 1,
                          f'pose stamp {stamp_ns * 1e-9:.3f} s repeated with another pose '
                          '(frozen clock?): dropped; observations that need it are rejected')

    # Observations ------------------------------------------------------------------

    def add_observations(self, messages: Sequence[ObservationMessage],
                         now_ns: int = 0) -> List[LandmarkBatch]:
        """
        Check observation messages; place each now or when its pose arrives.

        Parameters
        ----------
        messages : sequence of ObservationMessage
            In arrival order; all placed with one call of the core when their poses
            are known.
        now_ns : int
            The caller's clock [ns]: when the messages arrived.

        Returns
        -------
        list of LandmarkBatch
            One per message placed (now or unblocked), in arrival order; a message
            whose rows were all rejected gives an empty batch.

        """
        ready = []
        for message in messages:
            if not self._accept(message):
                continue
            message.arrived_ns = now_ns
            if not self.pending:
                found = self.poses.lookup(message.stamp_ns,
                                          final=self.config.max_wait_s == 0.0)
                if found.status == pose_buffer.FOUND:
                    ready.append(_with_pose(message, found))
                    continue
            if len(self.pending) >= self.config.max_pending:
                oldest = self.pending.popleft()
                self.counters.add('backlog_dropped', oldest.rows,
                                  f'more than {self.config.max_pending} observation messages '
                                  'waiting for a pose: dropped the oldest')
            self.pending.append(message)
        batches = self.place(ready) if ready else []
        if self.pending:
            batches += self.drain(now_ns)
        return batches

    def _accept(self, message: ObservationMessage) -> bool:
        """Count a message in; check its frame and stamp."""
        self.counters.add('observation_messages_in')
        sensor_frame = self.config.sensor_frame
        if sensor_frame and message.frame_id is not None and message.frame_id != sensor_frame:
            self.counters.add('observation_wrong_frame', 1,
                              f"observations in frame '{message.frame_id}', expected "
                              f"'{sensor_frame}': message dropped")
            return False
        self.counters.add('observations_in', message.rows)
        if 'range' not in message.columns and 'bearing' not in message.columns:
            self.counters.add('missing_field', max(message.rows, 1),
                              "observation message with neither 'range' nor 'bearing': "
                              'dropped')
            return False
        if message.stamp_ns <= 0:
            self.counters.add('observation_stamp_zero', message.rows,
                              'observation message with a zero stamp: dropped')
            return False
        if self._superseded_ns is not None:
            before, repeated = self._superseded_ns
            if (before is None or message.stamp_ns > before) and message.stamp_ns <= repeated:
                self.counters.add('observation_pose_ambiguous', message.rows,
                                  f'observation stamp {message.stamp_ns * 1e-9:.3f} s needs the '
                                  f'pose at {repeated * 1e-9:.3f} s, which came twice with '
                                  'different values: dropped')
                return False
        return True

    def drain(self, now_ns: int = 0) -> List[LandmarkBatch]:
        """
        Place waiting observations, in order, as far as their poses are known.

        Parameters
        ----------
        now_ns : int
            The caller's clock [ns]; a message waiting ``max_wait_s`` takes what the
            buffer has (the newest pose within ``max_pose_gap_s``) or is dropped.

        Returns
        -------
        list of LandmarkBatch

        """
        ready = []
        while self.pending:
            item = self.pending[0]
            found = self.poses.lookup(item.stamp_ns)
            if found.status == pose_buffer.WAIT:
                if now_ns - item.arrived_ns < self.config.max_wait_s * 1e9:
                    break
                found = self.poses.lookup(item.stamp_ns, final=True)
            self.pending.popleft()
            if found.status == pose_buffer.FOUND:
                ready.append(_with_pose(item, found))
            elif found.status == pose_buffer.TOO_OLD:
                self.counters.add('observation_too_old', item.rows,
                                  f'observation stamp {item.stamp_ns * 1e-9:.3f} s is older '
                                  'than the pose history: dropped')
            else:
                self.counters.add('no_pose_in_time', item.rows,
                                  f'no pose for observation stamp {item.stamp_ns * 1e-9:.3f} s '
                                  f'within max_wait_s = {self.config.max_wait_s}: dropped')
        return self.place(ready) if ready else []

    # Placing -------------------------------------------------------------------------

    def noise(self, columns: Dict[str, NDArray[Any]]) -> NDArray[np.float64]:
        """Return the noise covariance ``R``, shape (2, 2) or (N, 2, 2), of one message."""
        cfg = self.config
        return observation_noise(columns, cfg.range_stddev ** 2, cfg.bearing_stddev ** 2,
                                 cfg.range_stddev_per_m ** 2, cfg.range_stddev_per_m2 ** 2)

    def place(self, ready: Sequence[MessageWithPose]) -> List[LandmarkBatch]:
        """
        Place the rows of observation messages in the world with one core call.

        Parameters
        ----------
        ready : sequence of (ObservationMessage, ndarray (3,), ndarray (3, 3))
            Each message with its robot pose and pose covariance.

        Returns
        -------
        list of LandmarkBatch
            One per message, in order.

        """
        ready = [(_with_columns(item, self._corrected(self._plausible(_with_ids(
            item.columns)))), pose, P_pose) for item, pose, P_pose in ready]
        ready, found_partial = self._partial(ready)
        counts = [item.rows for item, _, _ in ready]
        columns = [item.columns for item, _, _ in ready]
        noise = [self.noise(c) for c in columns]
        if len(ready) == 1:
            ids = np.asarray(columns[0]['id'])
            z = _range_bearing(columns[0])
            R = noise[0]
            pose, P_pose = ready[0][1], ready[0][2]
        else:
            ids = np.concatenate([c['id'] for c in columns])
            z = np.concatenate([_range_bearing(c) for c in columns])
            R = noise[0] if all(r.ndim == 2 for r in noise) and all(
                np.array_equal(r, noise[0]) for r in noise) else np.concatenate(
                [np.broadcast_to(r, (n, 2, 2)) for r, n in zip(noise, counts)])
            pose = np.repeat([p for _, p, _ in ready], counts, axis=0)
            P_pose = np.repeat([P for _, _, P in ready], counts, axis=0)
        kept, m, P_m, P_dep, reasons = landmarks_from_rows(
            ids, z, R, pose, P_pose, self._sensor_pose, self._R_bias, self._scale_var)
        for reason, count in reasons.items():
            self.counters.add(reason, count, f'{count} of {len(z)} rows rejected in '
                              f'{len(ready)} observation message(s) at '
                              f'{ready[0][0].stamp_ns * 1e-9:.3f} s')
        ids = np.asarray(ids)[kept].astype(np.int64)
        if len(ready) == 1:
            ends = [len(ids)]
        else:
            ends = np.cumsum(np.bincount(np.repeat(np.arange(len(ready)), counts)[kept],
                                         minlength=len(ready))).tolist()
        batches = []
        start = row = 0
        for (item, pose_k, P_pose_k), c, count, end in zip(ready, columns, counts, ends):
            batch = LandmarkBatch(item.stamp_ns, ids[start:end], m[start:end],
                                  P_m[start:end], P_dep[start:end], item.token,
                                  found_partial.get(id(item), no_partial_observations()))
            unlabelled = np.count_nonzero(batch.ids == UNKNOWN_ID) > 0
            if unlabelled or 'class' in c:
                classes = np.zeros(end - start, np.int64)
                if 'class' in c:
                    classes = np.asarray(c['class'], np.int64)[kept[row:row + count]]
                batch = replace(batch, classes=classes, scan=self._scan(
                    pose_k, P_pose_k) if unlabelled else None)
            batches.append(batch)
            start, row = end, row + count
        self.counters.add('landmarks_out', len(ids))
        return batches

    def _plausible(self, columns: Dict[str, NDArray[Any]]) -> Dict[str, NDArray[Any]]:
        """Return the rows of a message within ``limits``; count the others by reason."""
        count = len(columns['id'])
        valid, reasons = first_problems(count, limits.observation_problems(columns, count))
        if not reasons:
            return columns
        for reason, rejected in reasons.items():
            self.counters.add(reason, rejected, f'{rejected} of {count} observation rows '
                              'outside the plausible ranges (pipeline.limits)')
        return {name: np.asarray(values)[valid] for name, values in columns.items()}

    def _corrected(self, columns: Dict[str, NDArray[Any]]) -> Dict[str, NDArray[Any]]:
        """
        Return the rows with the range scale error removed (``core.range_scale``).

        Rows with a finite range and bearing are corrected with ``range_scale_coeffs``
        and ``range_scale_per_m``; partial rows (no bearing to correct with) and rows
        outside the model (scale below ``range_scale.MIN_SCALE``) are left as they are.
        The noise model of the config describes the corrected range; a message with
        its own noise columns has them propagated (``J R J^T``).
        """
        cfg = self.config
        if (range_scale.is_identity(cfg.range_scale_coeffs, cfg.range_scale_per_m)
                or 'range' not in columns or 'bearing' not in columns):
            return columns
        z = np.stack([np.asarray(columns['range'], np.float64),
                      np.asarray(columns['bearing'], np.float64)], axis=1)
        rows = np.all(np.isfinite(z), axis=1)
        rows[rows] = range_scale.scale(z[rows], cfg.range_scale_coeffs,
                                       cfg.range_scale_per_m) >= range_scale.MIN_SCALE
        if not rows.any():
            return columns
        columns = dict(columns)
        own_noise = any(name in columns for name in NOISE_FIELDS)
        R = self.noise(columns) if own_noise else np.zeros((2, 2))
        z[rows], R_c = range_scale.correct_with_noise(z[rows], R if R.ndim == 2 else R[rows],
                                                      cfg.range_scale_coeffs,
                                                      cfg.range_scale_per_m)
        columns['range'] = z[:, 0]
        if own_noise:
            R = np.array(np.broadcast_to(R, (len(z), 2, 2)))
            R[rows] = R_c
            columns['range_variance'] = R[:, 0, 0]
            columns['bearing_variance'] = R[:, 1, 1]
            columns['range_bearing_covariance'] = R[:, 0, 1]
        return columns

    def _partial(self, ready: Sequence[MessageWithPose]
                 ) -> Tuple[List[MessageWithPose], Dict[int, PartialObservations]]:
        """Take the partial rows out of messages; return the rest and their observations."""
        out, found_by_item = [], {}
        for item, pose, P_pose in ready:
            self._view_group = (self._view_group + 1) % (1 << 32)
            columns, partial = split_partial(item.columns)
            if np.count_nonzero(partial):
                rows = {name: np.asarray(values)[partial] for name, values in columns.items()}
                rows, R = range_only_corrected(rows, self.noise(rows), self._lens)
                mount = SensorMount(self._sensor_pose, self._R_bias, self._scale_var)
                found, reasons = partial_observations_from_rows(
                    rows, R, pose, P_pose, mount, self._view_group, item.stamp_ns,
                    self._correlated)
                self.counters.add('partial_rows', int(partial.sum()))
                for reason, count in reasons.items():
                    self.counters.add(reason, count, f'{count} of {int(partial.sum())} '
                                      'partial rows rejected')
                self.counters.add('partial_out', len(found))
                columns = {name: np.asarray(values)[~partial]
                           for name, values in columns.items()}
                item = replace(item, columns=columns)
                found_by_item[id(item)] = found
            elif columns is not item.columns:
                item = replace(item, columns=columns)
            out.append((item, pose, P_pose))
        return out, found_by_item

    def _scan(self, pose: NDArray[np.float64], P_pose: NDArray[np.float64]) -> Scan:
        """Return the pose (and bias) terms of a message's joint covariance, its heading."""
        pose, P_pose = np.asarray(pose, np.float64), np.array(P_pose, np.float64)
        sensor = np.zeros(3) if self._sensor_pose is None else self._sensor_pose
        c, s = np.cos(pose[2]), np.sin(pose[2])
        sensor_xy = pose[:2] + np.array([c * sensor[0] - s * sensor[1],
                                         s * sensor[0] + c * sensor[1]])
        heading = float(pose[2] + sensor[2])
        if self._R_bias is None:
            return Scan(pose[:2].copy(), P_pose, heading=heading)
        return Scan(pose[:2].copy(), P_pose, self._R_bias, sensor_xy, heading, self._scale_var)

    # Status --------------------------------------------------------------------------

    def status(self) -> Status:
        """
        Return the diagnostics status: problems since the last call, and the counters.

        Returns
        -------
        Status
            ``warn`` when rows or messages were rejected since the last status, or no
            pose arrived yet; ``ok`` otherwise.

        """
        counts = dict(self.counters.counts)
        problems = {key: value - self._reported.get(key, 0) for key, value in counts.items()
                    if key not in NOT_PROBLEMS and value > self._reported.get(key, 0)}
        self._reported = counts
        level, message = 'ok', 'ok'
        if problems:
            level = 'warn'
            message = 'rejected: ' + ', '.join(f'{k} {v}' for k, v in sorted(problems.items()))
        elif not len(self.poses):
            level, message = 'warn', 'no pose received yet'
        extra = {'pose_buffer_size': len(self.poses), 'pending_messages': len(self.pending)}
        return Status(level, message, counts, extra)


def _with_pose(message: ObservationMessage, found: pose_buffer.Lookup) -> MessageWithPose:
    """Return the message with the pose of a ``FOUND`` lookup (which sets both fields)."""
    assert found.pose is not None and found.P_pose is not None, found.status
    return message, found.pose, found.P_pose


def _with_ids(columns: Dict[str, NDArray[Any]]) -> Dict[str, NDArray[Any]]:
    """Return the columns with an ``id`` column (``UNKNOWN_ID`` when the message has none)."""
    if 'id' in columns:
        return columns
    count = len(next(iter(columns.values())))
    return {**columns, 'id': np.full(count, UNKNOWN_ID, np.int64)}


def _with_columns(message: ObservationMessage,
                  columns: Dict[str, NDArray[Any]]) -> ObservationMessage:
    """Return the message with ``columns`` (itself when they are its own)."""
    return message if columns is message.columns else replace(message, columns=columns)


def _range_bearing(columns: Dict[str, NDArray[Any]]) -> NDArray[np.float64]:
    """Return ``z``, shape (N, 2): range and bearing (``np.stack`` costs several times more)."""
    r, b = columns['range'], columns['bearing']
    z = np.empty((len(r), 2), np.result_type(r, b))
    z[:, 0], z[:, 1] = r, b
    return z
