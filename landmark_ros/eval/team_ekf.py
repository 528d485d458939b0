"""
A reference for the closed loop: one EKF over the whole team, every correlation kept.

The loop of ``eval.slam_loop.TeamLoop`` (the nodes' pipeline) never knows how the
errors of its poses and landmarks are correlated, so it bounds them (split CI). This
estimator knows them: one state holds every robot's pose and every landmark seen, with
the full covariance (the stochastic map of Smith, Self and Cheeseman 1990; EKF SLAM,
Thrun, Burgard and Fox 2005, ch. 10, here for several robots at once as in Roumeliotis
and Bekey 2002). It is centralized and its cost grows with the square of the state, so
it is not what a team of nodes runs; it tells, on the same events and with the same
models, what the information would give if nothing were bounded: the accuracy the loop
gives up and whether the models hold when fully used.

The same models as the loop's localizers (``LocalizerConfig``): the odometry twist held
until the next message, its calibrated systematic error removed (``motion.scale_motion``)
and with the noise of ``localizer.motion`` (per step as
``Localizer`` does it); sightings with the range scale correction
(``update.correct_ranges``), the range and bearing noise, its time-correlated part and
the bias counted as the localizer counts them (``update.row_noise`` with
``steps.count_shared``); a row gated at ``gate_probability`` (2 dof); a sighting of
another robot with ``robot_stddev_floor`` on its position (the marker the camera sees
is not the point the other's pose names). With ``range_scale_state_stddev`` (and
``range_scale_bearing_state_stddev``) each robot's block holds its range scale states
after its pose (``update.observe``; ``place`` is the inverse); the MRCLAM loop's config
sets them only with ``slam_range_scale_state`` (``slam_cli --range-scale-state``). A
row is one reading of one message (range and bearing). A landmark enters the state
at its first row (its mean and covariance from ``core.sensors``' inverse model and the
rows' Jacobians, cross-covariances included). Without IDs the rows are paired by joint
compatibility on the joint state (``TeamEKF._name_rows``). Anchors: the landmarks
of the fuser's ``map_file`` (``LoopConfig.fuser``) start in the state with their
covariance, independent of everything else.

Inputs are those of ``TeamLoop`` (``start``, ``odometry``, ``sightings``,
``robot_sighting``), so ``mrclam.slam.run`` and ``eval.slam_montecarlo`` drive either.
A robot's pose is predicted lazily: the motions since its last update are composed
into one Jacobian and one noise (exact to first order) and applied to the full
covariance only when a row needs that robot.
"""

from collections import Counter
from dataclasses import dataclass
import math
from typing import Dict, List, Optional, Sequence, Tuple

from landmark_ros.core import sensors
from landmark_ros.core.gating import chi2_threshold
from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.eval.slam_loop import LoopConfig, PoseTrack
from landmark_ros.fuser import map_file
from landmark_ros.localizer import motion
from landmark_ros.localizer.steps import count_shared, Estimate
from landmark_ros.localizer.update import (correct_ranges, RANGE_BEARING, row_noise,
                                           sensor_noise)
from landmark_ros.localizer.update import observe as update_observe
import numpy as np
from numpy.typing import NDArray

MIN_RANGE_M = 0.05
"""Rows closer than this [m] are skipped (no bearing to place them with)."""
FIRST_TRACK_ID = 1_000_000
"""Without IDs, the first landmark's track ID (then one up per new landmark)."""
SKIP = -1
"""A row without ID that is neither paired nor new (ambiguous): not used."""


@dataclass
class MapSnapshot:
    """The landmarks' marginals: IDs (L,), means (L, 2) [m], covariances (L, 2, 2)."""

    ids: NDArray[np.int64]
    m: NDArray[np.float64]
    P: NDArray[np.float64]


@dataclass
class _Chain:
    """A robot's motions not yet applied to the full covariance."""

    stamp_ns: int
    pose: NDArray[np.float64]
    F: NDArray[np.float64]
    """Jacobian of the current pose with respect to the pose in the state, (3, 3)."""
    Q: NDArray[np.float64]
    """Covariance of the motions' noise composed to the current pose, (3, 3)."""
    twist: Optional[NDArray[np.float64]] = None
    odom: Optional[NDArray[np.float64]] = None


class TeamEKF:
    """
    Localize a team and map its landmarks in one EKF (module docstring).

    Parameters
    ----------
    config : LoopConfig
        Its ``localizer`` section gives every model; with ``hide_ids`` the rows are
        named by ``_name_rows``; the ``fuser`` section's ``map_file`` (anchors) and
        ``min_observations`` (a confirmed track without IDs).
    names : sequence of str
        Robot names.

    Raises
    ------
    map_file.MapFileError
        If the anchors' map file is not one.

    """

    def __init__(self, config: LoopConfig, names: Sequence[str]) -> None:
        self.config = config
        self.names = list(names)
        cfg = config.localizer
        scale_sd = [v for v in (cfg.range_scale_state_stddev,
                                cfg.range_scale_bearing_state_stddev) if v > 0.0]
        self._k = 3 + len(scale_sd)
        """Components per robot: the pose, then its range scale states (if any)."""
        self.x = np.zeros(self._k * len(names))
        self.P = np.kron(np.eye(len(names)), np.diag([0.0, 0.0, 0.0] + list(np.square(
            scale_sd))))
        self.landmarks: Dict[int, int] = {}
        """Landmark ID -> its first column in the state."""
        self.rows_per_landmark: Counter = Counter()
        self._next_track = FIRST_TRACK_ID
        self.tracks = [PoseTrack() for _ in names]
        self.counts: Counter = Counter()
        self.tallies = [Counter() for _ in names]
        self._chains = [_Chain(0, np.zeros(3), np.eye(3), np.zeros((3, 3))) for _ in names]
        self._seen: List[dict] = [{} for _ in names]
        self._gate = chi2_threshold(2, cfg.gate_probability)
        share = np.array([cfg.range_correlated_fraction, cfg.bearing_correlated_fraction])
        self._parts = (np.sqrt(np.outer(1.0 - share, 1.0 - share)),
                       np.sqrt(np.outer(share, share)))
        self._R_bias = np.diag([cfg.range_bias_stddev ** 2, cfg.bearing_bias_stddev ** 2])
        if config.fuser.map_file:
            document = map_file.load(config.fuser.map_file, config.fuser.world_frame)
            for record in document['landmarks']:
                self._insert(int(record['id']), np.asarray(record['mean'], np.float64),
                             np.asarray(record['covariance'], np.float64))

    # --------------------------------------------------------------------- inputs
    def start(self, robot: int, stamp_ns: int, x: NDArray[np.float64],
              P: NDArray[np.float64]) -> None:
        """Give a robot its starting pose ``x`` (3,), ``P`` (3, 3) at ``stamp_ns``."""
        c = self._pose(robot)
        self.x[c] = x
        self.P[c, :] = 0.0
        self.P[:, c] = 0.0
        self.P[c, c] = P
        self._chains[robot] = _Chain(int(stamp_ns), np.array(x, np.float64), np.eye(3),
                                     np.zeros((3, 3)))

    def odometry(self, robot: int, stamp_ns: int, pose: Optional[NDArray[np.float64]] = None,
                 twist: Optional[NDArray[np.float64]] = None) -> Optional[Estimate]:
        """
        Predict a robot to an odometry message (its ``pose`` (3,) or its ``twist`` (2,)).

        Returns the robot's estimate at ``stamp_ns``; None, the message skipped and
        counted in ``counts['odometry_skipped']``, when the stamp is not later than the
        last one or the message holds no finite pose or twist.
        """
        chain = self._chains[robot]
        stamp_ns = int(stamp_ns)
        given = pose if pose is not None else twist
        if ((stamp_ns <= chain.stamp_ns and chain.odom is not None) or given is None
                or not np.all(np.isfinite(given))):
            self.counts.update(['odometry_skipped'])
            return None
        if pose is not None:
            odom = np.asarray(pose, np.float64)
            if chain.odom is not None:
                self._move(robot, stamp_ns, motion.between(chain.odom, odom))
            chain.odom, chain.stamp_ns = odom, max(stamp_ns, chain.stamp_ns)
        else:
            self._advance(robot, stamp_ns)
            chain.twist = np.asarray(twist, np.float64)
            chain.odom = np.zeros(3)  # the chain has started
        est = self.estimate(robot)
        self.tracks[robot].append(est)
        return est

    def sightings(self, robot: int, stamp_ns: int, ids: NDArray[np.int64],
                  z: NDArray[np.float64]) -> None:
        """Apply one sighting message: rows ``ids`` (N,), ``z`` (N, 2) range [m], bearing."""
        stamp_ns = int(stamp_ns)
        self.counts['messages'] += 1
        ids = np.asarray(ids, np.int64).reshape(-1)
        z = np.asarray(z, np.float64).reshape(-1, 2)
        keep = np.all(np.isfinite(z), axis=1) & (z[:, 0] > MIN_RANGE_M)
        ids, z = ids[keep], z[keep]
        if not len(z):
            return
        self._advance(robot, stamp_ns)
        self._apply(robot)
        if self.config.hide_ids:
            ids = self._name_rows(robot, z)
        z, R = self._noise(robot, stamp_ns, ids.tolist(), z, bias=True)
        for k, landmark_id in enumerate(ids.tolist()):
            if landmark_id < 0:
                continue
            if landmark_id not in self.landmarks:
                self._add_landmark(robot, landmark_id, z[k], R[k])
            else:
                c = self.landmarks[landmark_id]
                if not self._update(robot, np.arange(c, c + 2), z[k], R[k]):
                    continue
            self.rows_per_landmark[landmark_id] += 1

    def robot_sighting(self, robot: int, stamp_ns: int, other: int,
                       z: NDArray[np.float64]) -> bool:
        """Apply a sighting ``z`` (2,) of robot ``other``; return whether it was used."""
        z = np.asarray(z, np.float64).reshape(1, 2)
        if not np.all(np.isfinite(z)) or z[0, 0] <= MIN_RANGE_M:
            return False
        for i in (robot, other):
            self._advance(i, int(stamp_ns))
            self._apply(i)
        z, R = self._noise(robot, int(stamp_ns), [('robot', self.names[other])], z, bias=False)
        floor = self.config.localizer.robot_stddev_floor ** 2 * np.eye(2)
        return self._update(robot, np.arange(self._k * other, self._k * other + 2), z[0], R[0],
                            floor,
                            label='robot_rows')

    # -------------------------------------------------------------------- outputs
    def estimate(self, robot: int) -> Estimate:
        """Return a robot's current pose and its covariance (3, 3)."""
        chain = self._chains[robot]
        c = self._pose(robot)
        P = chain.F @ self.P[c, c] @ chain.F.T + chain.Q
        return Estimate(chain.stamp_ns, chain.pose.copy(), 0.5 * (P + P.T))

    def map_snapshot(self) -> MapSnapshot:
        """Return the landmarks' means and marginal covariances, by ID."""
        ids = np.array(sorted(self.landmarks), np.int64)
        cols = [np.arange(self.landmarks[i], self.landmarks[i] + 2) for i in ids.tolist()]
        m = np.array([self.x[c] for c in cols]).reshape(-1, 2)
        P = np.array([self.P[np.ix_(c, c)] for c in cols]).reshape(-1, 2, 2)
        return MapSnapshot(ids, m, P)

    def joint_map(self) -> Tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Return IDs (L,), means (L, 2) and the joint covariance (2L, 2L), by ID."""
        ids = np.array(sorted(self.landmarks), np.int64)
        cols = np.concatenate([np.arange(self.landmarks[i], self.landmarks[i] + 2)
                               for i in ids.tolist()]) if len(ids) else np.empty(0, int)
        return ids, self.x[cols].reshape(-1, 2), self.P[np.ix_(cols, cols)]

    def map_records(self) -> List[dict]:
        """
        Return the landmarks as map records (mean, marginal covariance).

        Without IDs only those with ``min_observations`` rows of the fuser's config (the
        confirmed tracks); with IDs every landmark.
        """
        snap = self.map_snapshot()
        least = self.config.fuser.min_observations if self.config.hide_ids else 0
        return [{'id': int(i), 'mean': m.tolist(), 'covariance': P.tolist(),
                 'observations': self.rows_per_landmark[int(i)], 'rejections': 0}
                for i, m, P in zip(snap.ids.tolist(), snap.m, snap.P)
                if self.rows_per_landmark[int(i)] >= least]

    def robot_counts(self, robot: int) -> dict:
        """Return a robot's row counts (``rows_used``, ``rows_gated``, ``robot_rows_*``)."""
        return dict(self.tallies[robot])

    def _pose(self, robot):
        """Return the slice of a robot's pose in the state."""
        return slice(self._k * robot, self._k * robot + 3)

    # ---------------------------------------------------------------- prediction
    def _advance(self, robot, stamp_ns):
        """Move a robot's chain to ``stamp_ns`` with its held twist (none: stay)."""
        chain = self._chains[robot]
        dt = (stamp_ns - chain.stamp_ns) * 1e-9
        if dt <= 0.0:
            return
        if chain.twist is None:
            chain.stamp_ns = stamp_ns
            return
        self._move(robot, stamp_ns, motion.delta_from_twist(chain.twist[0], chain.twist[1], dt))

    def _move(self, robot, stamp_ns, delta):
        """Compose the motion ``delta`` (odometry frame, unscaled) into the robot's chain."""
        cfg = self.config.localizer
        chain = self._chains[robot]
        dt = (stamp_ns - chain.stamp_ns) * 1e-9
        if dt <= 0.0:
            return
        delta = motion.scale_motion(delta, dt, cfg.odometry_speed_scale,
                                    cfg.odometry_yaw_rate_scale,
                                    cfg.odometry_speed_scale_per_yaw_rate, cfg.odometry_yaw_per_m)
        Q = (motion.odometry_noise(delta, tuple(cfg.odometry_alphas))
             * motion.step_noise_scale(dt, cfg.odometry_alphas_period_s)
             + np.eye(3) * cfg.min_step_variance)
        if dt > cfg.max_odometry_gap_s:
            extra = cfg.gap_position_stddev_per_s ** 2 * dt
            Q = Q + np.diag([extra, extra, 0.0])
        c, s = math.cos(chain.pose[2]), math.sin(chain.pose[2])
        J_x = np.array([[1.0, 0.0, -s * delta[0] - c * delta[1]],
                        [0.0, 1.0, c * delta[0] - s * delta[1]], [0.0, 0.0, 1.0]])
        chain.pose, chain.Q = motion.predict(chain.pose, chain.Q, delta, Q)
        chain.F = J_x @ chain.F
        chain.stamp_ns = stamp_ns

    def _apply(self, robot):
        """Apply a robot's pending motions to the state and the full covariance."""
        chain = self._chains[robot]
        c = self._pose(robot)
        rows = chain.F @ self.P[c, :]
        P_pose = rows[:, c] @ chain.F.T + chain.Q
        self.P[c, :] = rows
        self.P[:, c] = rows.T
        self.P[c, c] = 0.5 * (P_pose + P_pose.T)
        self.x[c] = chain.pose
        chain.F, chain.Q = np.eye(3), np.zeros((3, 3))

    # -------------------------------------------------------------------- update
    def _noise(self, robot, stamp_ns, keys, z, bias):
        """Return corrected readings (N, 2) and their noise (N, 2, 2), as the localizer."""
        cfg = self.config.localizer
        kind = np.full(len(z), RANGE_BEARING)
        z, _ = correct_ranges(z, kind, None, cfg.range_scale_coeffs, cfg.range_scale_per_m)
        R = sensor_noise(self.config.localizer, z)
        tau_ns = int(cfg.noise_correlation_time_s * 1e9)
        shared = count_shared(self._seen[robot], stamp_ns, keys, tau_ns)
        shared_bias = (count_shared(self._seen[robot], stamp_ns, [None] * len(keys), tau_ns)
                       if bias else None)
        return z, row_noise(R, self._parts, self._R_bias, shared, shared_bias, False)

    def _row_model(self, robot, cols, z):
        """Return a row's innovation (2,), Jacobian (2, k + 2) and its state columns."""
        bc = np.arange(self._k * robot, self._k * (robot + 1))
        block, point = self.x[bc], self.x[cols]
        if np.hypot(*(point - block[:2])) <= MIN_RANGE_M:
            return None
        h, J_z_x, J_z_m = update_observe(block, point[None])
        y = z - h[0]
        y[1] = wrap_angle(y[1])
        return y, np.hstack([J_z_x[0], J_z_m[0]]), np.concatenate([bc, cols])

    def _name_rows(self, robot, z):
        """
        Return track IDs (N,) for rows ``z`` (N, 2) without IDs: JCBB on the joint state.

        A row joins a landmark individually compatible with it (``association_probability``
        of the localizer) in the pairing with the most pairs jointly compatible, then the
        least joint NEES (``_joint_hypothesis``); a row compatible with no landmark starts
        a new one; the others are ``SKIP``. The gates use the sensor noise with its bias
        once (the rows' counts need their IDs).
        """
        cfg = self.config.localizer
        z, _ = correct_ranges(z, np.full(len(z), RANGE_BEARING), None, cfg.range_scale_coeffs,
                              cfg.range_scale_per_m)
        R = row_noise(sensor_noise(self.config.localizer, z), self._parts, self._R_bias, None,
                      np.ones(len(z)), False)
        models, compatible = {}, []
        gate = chi2_threshold(2, cfg.association_probability)
        for k in range(len(z)):
            scored = []
            for key, c in self.landmarks.items():
                model = self._row_model(robot, np.arange(c, c + 2), z[k])
                if model is None:
                    continue
                y, H, idx = model
                d2 = float(y @ np.linalg.solve(H @ self.P[np.ix_(idx, idx)] @ H.T + R[k], y))
                if d2 <= gate:
                    models[(k, key)] = model
                    scored.append((d2, key))
            compatible.append([key for _, key in sorted(scored)])

        def joint_nees(pairs):
            cols = np.unique(np.concatenate([models[p][2] for p in pairs]))
            H = np.zeros((2 * len(pairs), len(cols)))
            for n, pair in enumerate(pairs):
                H[2 * n:2 * n + 2, np.searchsorted(cols, models[pair][2])] = models[pair][1]
            y = np.concatenate([models[p][0] for p in pairs])
            S = H @ self.P[np.ix_(cols, cols)] @ H.T
            for n, (k, _) in enumerate(pairs):
                S[2 * n:2 * n + 2, 2 * n:2 * n + 2] += R[k]
            return float(y @ np.linalg.solve(S, y))

        ids = np.full(len(z), SKIP, np.int64)
        p = cfg.association_probability
        for k, key in _joint_hypothesis(joint_nees, compatible,
                                        lambda n: chi2_threshold(2 * n, p)):
            ids[k] = key
        for k in np.flatnonzero((ids == SKIP) & np.array([not c for c in compatible], bool)):
            ids[k], self._next_track = self._next_track, self._next_track + 1
        return ids

    def _update(self, robot, cols, z, R, P_extra=None, label='rows'):
        """Update with one row of robot ``robot`` seeing the point at ``cols``; return used."""
        model = self._row_model(robot, cols, z)
        if model is None:
            return False
        y, H, idx = model
        PHt = self.P[:, idx] @ H.T
        S = H @ PHt[idx] + R
        if P_extra is not None:
            J_z_m = H[:, -2:]
            S = S + J_z_m @ P_extra @ J_z_m.T
        S_inv = np.linalg.inv(0.5 * (S + S.T))
        if float(y @ S_inv @ y) > self._gate:
            self.tallies[robot][f'{label}_gated'] += 1
            return False
        K = PHt @ S_inv
        dx = K @ y
        self.x += dx
        self.P -= K @ PHt.T
        self.P = 0.5 * (self.P + self.P.T)
        for i, chain in enumerate(self._chains):
            c = self._pose(i)
            self.x[c.start + 2] = wrap_angle(self.x[c.start + 2])
            chain.pose = chain.pose + chain.F @ dx[c]
            chain.pose[2] = wrap_angle(chain.pose[2])
        self.tallies[robot][f'{label}_used'] += 1
        return True

    def _add_landmark(self, robot, landmark_id, z, R):
        """Add a landmark placed by its first row: mean, covariance, cross-covariances."""
        bc = slice(self._k * robot, self._k * (robot + 1))
        m, J_m_x, J_m_z = place(self.x[bc], z)
        cross = J_m_x @ self.P[bc, :]
        P_m = cross[:, bc] @ J_m_x.T + J_m_z @ R @ J_m_z.T
        self._insert(landmark_id, m, P_m, cross)
        self.tallies[robot]['rows_used'] += 1

    def _insert(self, landmark_id, m, P_m, cross=None):
        """Append a landmark ``m`` (2,), ``P_m`` (2, 2), ``cross`` (2, n) with the state."""
        n = len(self.x)
        self.x = np.concatenate([self.x, m])
        P = np.zeros((n + 2, n + 2))
        P[:n, :n] = self.P
        if cross is not None:
            P[n:, :n] = cross
            P[:n, n:] = cross.T
        P[n:, n:] = 0.5 * (P_m + P_m.T)
        self.P = P
        self.landmarks[int(landmark_id)] = n


def place(x: NDArray[np.float64], z: NDArray[np.float64]
          ) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the landmark a reading places and the Jacobians: the inverse of ``update.observe``.

    Parameters
    ----------
    x : ndarray, shape (3,), (4,) or (5,)
        Pose [m, m, rad], optionally the range scale error ``s`` and its change with the
        bearing ``s_b`` [1/rad]: the range reads ``d (1 + s + s_b b)``.
    z : ndarray, shape (2,)
        Range [m] and bearing [rad].

    Returns
    -------
    m : ndarray, shape (2,)
    J_m_x : ndarray, shape (2, len(x))
    J_m_z : ndarray, shape (2, 2)

    """
    r, b = float(z[0]), float(z[1])
    s = float(x[3]) if len(x) > 3 else 0.0
    s_b = float(x[4]) if len(x) > 4 else 0.0
    g = 1.0 + s + s_b * b
    d = r / g
    m = sensors.landmark_from_observation(x[:3], np.array([d, b]))
    J_m_pose, J_m_polar = sensors.landmark_from_observation_jacobians(x[:3], np.array([d, b]))
    J_d = np.array([[1.0 / g, -r * s_b / g ** 2], [0.0, 1.0]])  # (d, b) by (r, b)
    J_m_x = np.zeros((2, len(x)))
    J_m_x[:, :3] = J_m_pose
    if len(x) > 3:
        J_m_x[:, 3] = J_m_polar[:, 0] * (-r / g ** 2)
    if len(x) > 4:
        J_m_x[:, 4] = J_m_polar[:, 0] * (-r * b / g ** 2)
    return m, J_m_x, J_m_polar @ J_d


def _joint_hypothesis(innovations, compatible, threshold_of):
    """
    Return the rows' pairing with the most pairs, then the least joint NEES (JCBB).

    ``compatible[k]`` lists row k's candidate landmarks; ``innovations(pairs)`` returns
    the joint NEES of a list of ``(row, landmark)`` pairs; ``threshold_of(n)`` the
    joint gate for n pairs. Exhaustive over the candidates (a message holds a few rows);
    Neira and Tardos 2001.
    """
    best = ([], 0.0)

    def search(row, pairs, used, d2):
        nonlocal best
        if len(pairs) + (len(compatible) - row) < len(best[0]):
            return
        if row == len(compatible):
            if len(pairs) > len(best[0]) or (len(pairs) == len(best[0]) and d2 < best[1]):
                best = (list(pairs), d2)
            return
        for j in compatible[row]:
            if j in used:
                continue
            trial = pairs + [(row, j)]
            joint = innovations(trial)
            if joint <= threshold_of(len(trial)):
                search(row + 1, trial, used | {j}, joint)
        search(row + 1, pairs, used, d2)

    search(0, [], frozenset(), 0.0)
    return best[0]
