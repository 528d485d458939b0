"""
``Localizer``: a robot's planar pose from wheel odometry and landmark sightings (ROS-free).

The node ``landmark_localizer``, the MRCLAM replay and the tests drive this one object.

Filter
------
An EKF on the pose ``(x, y, theta)`` in the map frame. Each odometry message predicts
(``localizer.motion``: the motion between consecutive messages, from the pose delta or
from the previous message's twist; its covariance from the message or, when that is
zero or absent, the odometry model of Probabilistic Robotics 5.4 with the alphas of the
config). Each batch of sightings updates (``localizer.update``: gate per row, split CI
against the map's correlation, iterated where the linearisation error is large).

Time
----
The filter keeps, for the last ``window_s`` of odometry, one step per odometry message:
its motion, the pose before and after the updates applied at its stamp, and those
updates. A sighting is applied at its own stamp:

- at or after the newest odometry: it waits until odometry reaches its stamp (the pose
  is never extrapolated past the odometry); counted ``waiting_for_odometry``;
- inside the window: the step across its stamp is split along its arc (the motion's
  noise shared in proportion), the update applied there, and every later step re-run
  from that state (their own updates re-applied); counted ``refiltered``;
- older than the window: dropped, ``too_old``.

Odometry events with named counters: ``odometry_out_of_order`` (a stamp not after the
previous: dropped), ``odometry_gap`` (more than ``max_odometry_gap_s`` between messages:
applied, with extra noise ``gap_position_stddev_per_s``), ``odometry_jump`` (faster than
``max_speed_mps`` or ``max_yaw_rate``: the motion is replaced by none with the jump
noise), ``odometry_reset`` (stamp back by more than the window, or an odometry pose back
at the origin from elsewhere: the chain restarts from the current estimate with the jump
noise).

Status
------
``status(stamp_ns)`` gives the average NIS per degree of freedom over the last
``nis_window`` updates, rows used and gated, the time since the last accepted row and the
state: ``lost`` (error) when the largest position standard deviation exceeds
``lost_position_stddev`` or ``lost_gated_rows`` rows in a row were gated; ``stale`` (warn)
after ``lost_after_s`` without an accepted row; else ``ok``.
"""

import bisect
from collections import deque
from dataclasses import replace
import math
from typing import Any, Callable, List, Optional, Tuple

from landmark_ros.core.gating import chi2_threshold
from landmark_ros.localizer import motion
from landmark_ros.localizer.association import label_rows, MapAssociation
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.consider import ConsiderRows, ConsiderSlots, select, update_consider
from landmark_ros.localizer.mixture import alternatives, update_mixture
from landmark_ros.localizer.steps import Batch, count_shared, Estimate, Step as _Step
from landmark_ros.localizer.update import (correct_ranges, RANGE_BEARING, row_noise,
                                           sensor_noise, update, UpdateSettings)
from landmark_ros.pipeline.counters import Counters, Status
from landmark_ros.pipeline.rows import landmark_row_problems
import numpy as np
from numpy.typing import NDArray

UNKNOWN_ID = 0xFFFFFFFF
"""ID of a row without one (the observer's cloud schema)."""

_ZERO3 = np.zeros(3)


def _quiet(_text: str) -> None:
    return None


def _pose(step: _Step) -> Estimate:
    """Return the pose of a step (without the range scale state), copies."""
    return Estimate(step.stamp_ns, step.x[:3].copy(), step.P[:3, :3].copy())


class Localizer:
    """
    EKF localization of one robot against a landmark map (module docstring).

    Parameters
    ----------
    config : LocalizerConfig
    log : callable, optional
        ``log(text)`` for throttled warnings.

    """

    def __init__(self, config: LocalizerConfig = LocalizerConfig(),
                 log: Callable[[str], Any] = _quiet) -> None:
        self.counters = Counters(log)
        self.configure(config)
        self._steps: List[_Step] = []
        self._stamps: List[int] = []
        self._pending: List[Batch] = []
        self._last_twist: Optional[NDArray[np.float64]] = None
        self._map_index: dict = {}
        self._map_m = np.empty((0, 2))
        self._map_P = np.empty((0, 2, 2))
        self._association: Optional[MapAssociation] = None
        self._nis: deque = deque(maxlen=config.nis_window)
        self._last_update_ns: Optional[int] = None
        self._gated_in_a_row = 0
        self._sightings: dict = {}
        self._consider = ConsiderSlots()

    def configure(self, config: LocalizerConfig) -> None:
        """Take a new config (parameters changed at run time)."""
        self.config = config
        self._association = None  # rebuilt with the new association parameters
        self.settings = UpdateSettings(
            chi2_threshold(1, config.gate_probability), chi2_threshold(2, config.gate_probability),
            config.correlation, config.iterate_threshold, config.max_iterations,
            config.landmark_correlation)
        self._alphas = tuple(config.odometry_alphas)
        self._floor = np.eye(3) * config.min_step_variance
        j = np.square(np.array([config.jump_position_stddev, config.jump_position_stddev,
                                config.jump_heading_stddev]))
        self._jump_Q = np.diag(j)
        share = np.array([config.range_correlated_fraction, config.bearing_correlated_fraction])
        self._correlated = np.sqrt(share[:, None] * share[None, :])
        self._white = np.sqrt((1.0 - share)[:, None] * (1.0 - share)[None, :])
        self._bias_R = np.diag([config.range_bias_stddev ** 2, config.bearing_bias_stddev ** 2])

    # ----------------------------------------------------------------- map and pose
    def set_map(self, ids: NDArray[np.int64], m: NDArray[np.float64],
                P_m: NDArray[np.float64]) -> None:
        """
        Replace the landmark map.

        Landmarks that fail the fuser's live row checks (``rows.landmark_row_problems``:
        finite, a covariance in the accepted range, plausible coordinates) are left out
        and counted as ``map_<reason>``. With ``correlation: consider`` the
        cross-covariances of the landmarks that stay (by ID) are kept, those of the
        landmarks that left dropped (``consider.ConsiderSlots.retain``).

        Parameters
        ----------
        ids : ndarray of int, shape (N,)
            Landmark IDs.
        m : ndarray, shape (N, 2)
            Positions [m].
        P_m : ndarray, shape (N, 2, 2)
            Covariances [m^2].

        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        m = np.asarray(m, dtype=np.float64).reshape(-1, 2)
        P_m = np.asarray(P_m, dtype=np.float64).reshape(-1, 2, 2)
        valid, reasons = landmark_row_problems(ids, m, P_m, np.zeros_like(P_m))
        for reason, count in reasons.items():
            self.counters.add(f'map_{reason}', count, f'{count} map landmarks left out')
        self._map_index = {int(i): k for k, i in enumerate(ids[valid])}
        self._map_m = m[valid].copy()
        self._map_P = P_m[valid].copy()
        self._association = None  # built on the first row without ID
        if self._consider.width:  # the cross-covariances of the landmarks that stay
            columns = self._consider.retain(self._map_index)
            for step in self._steps:
                step.C_prior, step.C = select(step.C_prior, columns), select(step.C, columns)

    @property
    def map_size(self) -> int:
        """Return the number of landmarks in the map."""
        return len(self._map_index)

    def initialize(self, stamp_ns: int, x: NDArray[np.float64],
                   P: NDArray[np.float64]) -> None:
        """
        Restart the filter at pose ``x`` (3,) with covariance ``P`` (3, 3) at a stamp.

        With ``range_scale_state_stddev`` the state takes the range scale error, with
        ``range_scale_bearing_state_stddev`` its change with the bearing (``update``):
        the previous estimates, else 0 with those standard deviations.
        """
        odom = self._steps[-1].odom if self._steps else _ZERO3
        x = np.array(x, dtype=np.float64)[:3]
        x[2] = motion.wrap(x[2])
        P = np.array(P, dtype=np.float64)[:3, :3]
        sd = [v for v in (self.config.range_scale_state_stddev,
                          self.config.range_scale_bearing_state_stddev) if v > 0.0]
        if sd:  # the previous estimates (a restart keeps what was learnt), else the prior
            n = 3 + len(sd)
            last = self._steps[-1] if self._steps and len(self._steps[-1].x) == n else None
            x = np.append(x, last.x[3:] if last else np.zeros(len(sd)))
            P = np.pad(P, ((0, len(sd)), (0, len(sd))))
            P[3:, 3:] = last.P[3:, 3:] if last else np.diag(np.square(sd))
        self._steps = [_Step(int(stamp_ns), _ZERO3, np.zeros((3, 3)), odom, x, P, x, P)]
        self._consider = ConsiderSlots()  # a new pose is independent of the map
        self._stamps = [int(stamp_ns)]
        self._pending = []
        self.counters.add('initialised')

    @property
    def initialized(self) -> bool:
        """Return whether the filter has a pose."""
        return bool(self._steps)

    def estimate(self) -> Optional[Estimate]:
        """Return the newest pose, or None before the first."""
        if not self._steps:
            return None
        return _pose(self._steps[-1])

    def pose_at(self, stamp_ns: int) -> Optional[Estimate]:
        """Return the pose at the newest step at or before ``stamp_ns`` within the window."""
        k = bisect.bisect_right(self._stamps, stamp_ns) - 1
        if k < 0:
            return None
        return _pose(self._steps[k])

    def range_scale(self) -> Optional[Tuple[float, float]]:
        """Return the range scale error estimate and its standard deviation, or None."""
        if not self._steps or len(self._steps[-1].x) < 4:
            return None
        step = self._steps[-1]
        return float(step.x[3]), math.sqrt(step.P[3, 3])

    def odom_to_map(self) -> Optional[NDArray[np.float64]]:
        """Return the pose of the odometry frame in the map frame, shape (3,), or None."""
        if not self._steps:
            return None
        step = self._steps[-1]
        return motion.compose(step.x[:3], motion.inverse(step.odom))

    # -------------------------------------------------------------------- odometry
    def add_odometry(self, stamp_ns: int, pose: Optional[NDArray[np.float64]] = None,
                     twist: Optional[NDArray[np.float64]] = None,
                     Q: Optional[NDArray[np.float64]] = None) -> Optional[Estimate]:
        """
        Predict the pose to an odometry message.

        Parameters
        ----------
        stamp_ns : int
            Stamp of the message [ns].
        pose : ndarray, shape (3,), optional
            Odometry pose (x, y, yaw) in the odometry frame; the motion is the delta from
            the previous message's pose.
        twist : ndarray, shape (2,), optional
            Forward speed [m/s] and yaw rate [rad/s]: used (the previous message's, held
            until this stamp) when there is no pose.
        Q : ndarray, shape (3, 3), optional
            Covariance of the motion since the previous message; None or zero: the
            odometry model of the config.

        Returns
        -------
        Estimate or None
            The pose at ``stamp_ns``; None when the message was dropped or is the first.

        """
        stamp_ns = int(stamp_ns)
        if not self._steps:
            cfg = self.config
            self.initialize(stamp_ns, np.array(cfg.initial_pose),
                            np.diag(np.square(cfg.initial_stddev)))
            self.counters.add('initialised_from_parameter')
        last = self._steps[-1]
        if pose is None and twist is None:
            self.counters.add('odometry_empty', detail='odometry with neither pose nor twist')
            return None
        odom = np.asarray(pose, dtype=np.float64) if pose is not None else None
        first = self.counters['odometry'] == 0
        self.counters.add('odometry')
        dt = (stamp_ns - last.stamp_ns) * 1e-9
        if first or dt <= -self.config.window_s:
            return self._restart_chain(stamp_ns, odom, twist, first)
        if dt <= 0.0:
            self.counters.add('odometry_out_of_order', detail='odometry stamp not after the '
                              'previous: dropped')
            return None
        delta, Q = self._motion(dt, last, odom, twist, Q)
        if twist is not None:
            self._last_twist = np.asarray(twist, dtype=np.float64)
        if odom is None:
            odom = motion.compose(last.odom, delta)
        x, P = motion.predict_with(last.x, last.P, delta, Q)
        C = motion.predict_cross(last.x, last.C, delta)
        self._steps.append(_Step(stamp_ns, delta, Q, odom, x, P, x, P, C_prior=C, C=C))
        self._stamps.append(stamp_ns)
        self._prune()
        self._apply_pending()
        step = self._steps[-1]
        return _pose(step)

    def _restart_chain(self, stamp_ns, odom, twist, first):
        """Start the odometry chain (first message or reset) at the current estimate."""
        last = self._steps[-1]
        if not first:
            self.counters.add('odometry_reset', detail='odometry stamp went back: restarted')
        P = last.P.copy()
        if not first:
            P[:3, :3] += self._jump_Q
        if first and stamp_ns < last.stamp_ns:
            stamp_ns = last.stamp_ns
        odom = odom if odom is not None else _ZERO3
        self._steps = [_Step(stamp_ns, _ZERO3, np.zeros((3, 3)), odom, last.x, P, last.x, P,
                             C_prior=last.C, C=last.C)]
        self._stamps = [stamp_ns]
        self._last_twist = None if twist is None else np.asarray(twist, dtype=np.float64)
        return _pose(self._steps[0])

    def _motion(self, dt, last, odom, twist, Q):
        """Return the motion since ``last`` and its covariance, with the named events."""
        cfg = self.config
        if odom is not None:
            delta = motion.between(last.odom, odom)
            far = math.hypot(last.odom[0], last.odom[1]) > 0.5
            if far and not np.any(odom):
                self.counters.add('odometry_reset', detail='odometry pose back at the origin')
                return _ZERO3, self._jump_Q.copy()
        elif self._last_twist is not None:
            delta = motion.delta_from_twist(self._last_twist[0], self._last_twist[1], dt)
        else:
            delta = _ZERO3
        delta = motion.scale_motion(delta, dt, cfg.odometry_speed_scale,
                                    cfg.odometry_yaw_rate_scale,
                                    cfg.odometry_speed_scale_per_yaw_rate,
                                    cfg.odometry_yaw_per_m)
        trans, rot = math.hypot(delta[0], delta[1]), abs(delta[2])
        if trans > cfg.max_speed_mps * dt or rot > cfg.max_yaw_rate * dt:
            self.counters.add('odometry_jump', detail=f'odometry moved {trans:.2f} m, '
                              f'{rot:.2f} rad in {dt:.3f} s: motion dropped')
            return _ZERO3, self._jump_Q.copy()
        if Q is None or not np.any(Q):
            Q = motion.odometry_noise(delta, self._alphas)
            if cfg.odometry_alphas_period_s > 0.0:  # motion.step_noise_scale, dt > 0
                Q *= cfg.odometry_alphas_period_s / dt
        Q = Q + self._floor
        if dt > cfg.max_odometry_gap_s:
            self.counters.add('odometry_gap', detail=f'{dt:.2f} s without odometry')
            extra = cfg.gap_position_stddev_per_s ** 2 * dt
            Q = Q + np.diag([extra, extra, 0.0])
        return delta, Q

    def _prune(self):
        cut = bisect.bisect_left(self._stamps, self._stamps[-1]
                                 - int(self.config.window_s * 1e9)) - 1
        if cut > 0:
            del self._steps[:cut]
            del self._stamps[:cut]

    # --------------------------------------------------------------- observations
    def add_observations(self, stamp_ns: int, ids: NDArray[np.int64], z: NDArray[np.float64],
                         kind: Optional[NDArray[np.int64]] = None,
                         R: Optional[NDArray[np.float64]] = None) -> int:
        """
        Apply landmark sightings taken at ``stamp_ns`` (now, later, or re-filtered).

        Parameters
        ----------
        stamp_ns : int
            Stamp of the sightings [ns].
        ids : ndarray of int, shape (N,)
            Landmark IDs (``UNKNOWN_ID``: none, counted ``no_id``; associated with the
            map by ``config.association``, ``localizer.association``, else skipped).
        z : ndarray, shape (N, 2)
            Range [m] and bearing [rad]; the missing one of a partial row may be NaN.
        kind : ndarray of int, shape (N,), optional
            ``update.RANGE_BEARING`` (default), ``RANGE`` or ``BEARING`` per row.
        R : ndarray, shape (N, 2, 2), optional
            Sensor noise; default the config's range and bearing model.

        Returns
        -------
        int
            Rows with a landmark of the map, passed on to the filter.

        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
        kind = (np.full(len(ids), RANGE_BEARING, np.int64) if kind is None
                else np.asarray(kind, dtype=np.int64).reshape(-1))
        z, R = self.correct_ranges(z, kind, R)
        unknown = ids == UNKNOWN_ID
        self.counters.add('no_id', int(unknown.sum()), detail='rows without ID')
        merged = {}
        if unknown.any() and self.config.association != 'none':
            ids, merged = self._associate(int(stamp_ns), ids, z, kind, R)
            unknown = ids == UNKNOWN_ID
        index = np.array([self._map_index.get(int(i), -1) for i in ids], np.intp)
        missing = (index < 0) & ~unknown
        if self._map_index:
            self.counters.add('landmark_not_in_map', int(missing.sum()),
                              detail='rows of landmarks that are not in the map skipped')
        else:   # no map yet: a team that builds its map starts so
            self.counters.add('map_empty', int(missing.sum()),
                              detail='rows skipped: no landmark in the map yet')
        keep = index >= 0
        if not keep.any():
            return 0
        k = index[keep]
        others = alternatives(merged, keep, self._map_index, self._map_m, self._map_P)
        self._apply_at(Batch(int(stamp_ns), self._map_m[k], self._map_P[k], z[keep], R[keep],
                             kind[keep], alternatives=others, landmarks=ids[keep],
                             shared=self._shared(int(stamp_ns), ids[keep]),
                             shared_bias=self._shared(int(stamp_ns), [None] * int(keep.sum()))))
        return int(keep.sum())

    def _associate(self, stamp_ns, ids, z, kind, R):
        """Pair the rows without ID with the map (``association.label_rows``)."""
        if self._association is None:
            self._association = MapAssociation(self._map_m, self._map_P,
                                               self.config.association,
                                               self.config.association_probability,
                                               self.config.association_take_ambiguous,
                                               self.config.association_merge_ambiguous)
        est = self.pose_at(stamp_ns) or self.estimate()
        map_ids = np.fromiter(self._map_index, np.int64, len(self._map_index))
        ids, counts, merged = label_rows(self._association, est, map_ids, ids, z, kind, R)
        for name, count in counts.items():
            self.counters.add(name, count, detail=f'rows without ID: {name}')
        return ids, merged

    def add_robot_sighting(self, stamp_ns: int, z: NDArray[np.float64],
                           other: Estimate, R: Optional[NDArray[np.float64]] = None,
                           other_id: Optional[str] = None) -> None:
        """
        Apply a range-bearing sighting of another robot whose estimate is ``other``.

        The other's position and the xy block of its covariance (plus
        ``robot_stddev_floor``) act as a landmark of unknown correlation with this pose:
        the split-CI update, whatever the config's ``correlation``. ``other`` should be
        the other's published estimate at ``stamp_ns`` (counted ``robot_stale`` and
        skipped if it is more than 0.1 s away). ``other_id`` names the other robot: its
        sightings share the time-correlated noise as a landmark's do.
        """
        if abs(other.stamp_ns - stamp_ns) > 100_000_000:
            self.counters.add('robot_stale', detail='other robot pose far from the sighting')
            return
        z = np.asarray(z, dtype=np.float64).reshape(1, 2)
        z, R = self.correct_ranges(z, np.array([RANGE_BEARING]),
                                   None if R is None else np.asarray(R).reshape(1, 2, 2))
        P_m = other.P[:2, :2] + np.eye(2) * self.config.robot_stddev_floor ** 2
        shared = None if other_id is None else self._shared(int(stamp_ns), [('robot', other_id)])
        self._apply_at(Batch(int(stamp_ns), other.x[None, :2], P_m[None], z, R,
                             np.array([RANGE_BEARING]), 'split_ci', 'robot_rows', shared))

    def _shared(self, stamp_ns, ids):
        """Return per row the sightings sharing its correlated noise (``steps.count_shared``)."""
        return count_shared(self._sightings, stamp_ns, ids,
                            int(self.config.noise_correlation_time_s * 1e9))

    def correct_ranges(self, z: NDArray[np.float64], kind: NDArray[np.int64],
                       R: Optional[NDArray[np.float64]] = None
                       ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
        """
        Return readings (N, 2) without the config's range scale error, and their noise.

        ``update.correct_ranges``; ``R`` None: ``sensor_noise`` of the corrected readings.
        """
        cfg = self.config
        z, R = correct_ranges(z, kind, R, cfg.range_scale_coeffs, cfg.range_scale_per_m)
        return z, (self.sensor_noise(z) if R is None else R)

    def sensor_noise(self, z: NDArray[np.float64]) -> NDArray[np.float64]:
        """Return the config's noise of observations ``z`` (N, 2), shape (N, 2, 2)."""
        return sensor_noise(self.config, z)

    def _apply_at(self, batch: Batch) -> None:
        if not self._steps:
            self.counters.add('not_initialised', len(batch.z), detail='no pose yet: dropped')
            return
        if batch.stamp_ns > self._stamps[-1] or self.counters['odometry'] == 0:
            self._pending.append(batch)
            self.counters.add('waiting_for_odometry', len(batch.z))
            return
        if batch.stamp_ns < self._stamps[0]:
            self.counters.add('too_old', len(batch.z), detail='sightings older than the '
                              'window: dropped')
            return
        k = bisect.bisect_right(self._stamps, batch.stamp_ns) - 1
        if self._stamps[k] != batch.stamp_ns:
            self._split(k + 1, batch.stamp_ns)
            k += 1
        self._steps[k].batches.append(batch)
        if k < len(self._steps) - 1:
            self.counters.add('refiltered')
        self._rerun(k)

    def _apply_pending(self):
        if not self._pending:
            return
        newest = self._stamps[-1]
        ready = [b for b in self._pending if b.stamp_ns <= newest]
        if ready:
            self._pending = [b for b in self._pending if b.stamp_ns > newest]
            for batch in sorted(ready, key=lambda b: b.stamp_ns):
                self._apply_at(batch)

    def _split(self, j, stamp_ns):
        """Insert a step at ``stamp_ns`` inside step ``j``'s motion."""
        step = self._steps[j]
        before = self._steps[j - 1]
        f = (stamp_ns - before.stamp_ns) / (step.stamp_ns - before.stamp_ns)
        delta_a = motion.scale_delta(step.delta, f)
        delta_b = motion.between(delta_a, step.delta)
        odom = motion.compose(before.odom, delta_a)
        new = _Step(stamp_ns, delta_a, step.Q * f, odom, _ZERO3, step.Q, _ZERO3, step.Q)
        step.delta, step.Q = delta_b, step.Q * (1.0 - f)
        self._steps.insert(j, new)
        self._stamps.insert(j, stamp_ns)

    def _rerun(self, k):
        """Re-run the filter from step ``k`` (its prediction, then every later step)."""
        for j in range(k, len(self._steps)):
            step = self._steps[j]
            if j > 0:
                prev = self._steps[j - 1]
                step.x_prior, step.P_prior = motion.predict_with(
                    prev.x, prev.P, step.delta, step.Q)
                step.C_prior = motion.predict_cross(prev.x, prev.C, step.delta)
            x, P, C = step.x_prior, step.P_prior, step.C_prior
            for batch in step.batches:
                x, P, C = self._update(x, P, C, batch)
            step.x, step.P, step.C = x, P, C

    def _update(self, x, P, C, batch):
        if batch.alternatives:
            result = update_mixture(x, P, C, batch, self._update_rows)
        else:
            result = self._update_rows(x, P, C, batch)
            if result is None:
                return x, P, C
        if batch.result is None:  # first application: count it
            batch.result = result
            self._count(batch, result)
        return result.x, result.P, result.C

    def _update_rows(self, x, P, C, batch):
        """Return the update of ``batch`` from ``(x, P, C)`` (None if it failed, counted)."""
        try:
            R = self._noise(batch)
            if self.config.correlation == 'consider' and batch.landmarks is not None:
                rows = ConsiderRows(self._consider.slots(batch.landmarks), batch.m, batch.P_m)
                return update_consider(x, P, C, rows, batch.z, R, batch.kind, self.settings)
            settings = self.settings if not batch.correlation else replace(
                self.settings, correlation=batch.correlation)
            result = update(x, P, batch.m, batch.P_m, batch.z, R, batch.kind, settings)
            result.C = C if C is None or result.A is None else result.A @ C
            return result
        except ValueError as error:
            self.counters.add('update_failed', len(batch.z), detail=str(error))
            return None

    def _noise(self, batch):
        """Return the noise of a batch's rows (``update.row_noise``)."""
        cfg = self.config
        return row_noise(batch.R, (self._white, self._correlated), self._bias_R, batch.shared,
                         batch.shared_bias,
                         cfg.correlated_noise == 'dependent' and cfg.correlation == 'split_ci')

    def _count(self, batch, result):
        used, gated = int(result.used.sum()), int(result.gated.sum())
        self.counters.add(f'{batch.label}_used', used)
        self.counters.add(f'{batch.label}_gated', gated)
        if result.iterations > 1:
            self.counters.add('iterated_updates')
        if used:
            self._nis.append((result.nis, result.dof))
            self._last_update_ns = batch.stamp_ns
            self._gated_in_a_row = 0
        else:
            self._gated_in_a_row += gated

    # --------------------------------------------------------------------- status
    def status(self, stamp_ns: Optional[int] = None) -> Status:
        """Return the diagnostics status at ``stamp_ns`` (default: the newest odometry)."""
        cfg = self.config
        est = self.estimate()
        now = stamp_ns if stamp_ns is not None else (est.stamp_ns if est else 0)
        since = (math.inf if self._last_update_ns is None
                 else (now - self._last_update_ns) * 1e-9)
        nis = sum(n for n, _ in self._nis)
        dof = sum(d for _, d in self._nis)
        sigma = (math.sqrt(max(np.linalg.eigvalsh(est.P[:2, :2]))) if est else math.inf)
        if sigma > cfg.lost_position_stddev or self._gated_in_a_row >= cfg.lost_gated_rows:
            level, state = 'error', 'lost'
        elif since > cfg.lost_after_s:
            level, state = 'warn', 'stale'
        else:
            level, state = 'ok', 'ok'
        extra = {'state': state, 'nis_per_dof': nis / dof if dof else math.nan,
                 'time_since_update_s': since, 'position_stddev_m': sigma,
                 'map_landmarks': self.map_size, 'gated_in_a_row': self._gated_in_a_row}
        message = (f'{state}: position sigma {sigma:.3f} m, last update {since:.1f} s ago, '
                   f'NIS/dof {extra["nis_per_dof"]:.2f}')
        return Status(level, message, dict(self.counters.counts), extra)
