"""
What the localization replay reads beyond ``mrclam.data``, and the odometry calibration.

``RobotN_Odometry.dat`` holds (time [s], forward velocity [m/s], angular velocity
[rad/s]) at about 67 Hz; the robot-to-robot sightings are the measurement rows whose
barcode is a robot's (subjects 1-5), which ``mrclam.data`` drops.

Odometry calibration
--------------------
The alphas of the odometry model (``landmark_ros.localizer.motion``) are fitted on the
odometry against the ground truth, never on a localization result: the odometry of each
robot is cut into windows of ``window_s``; in each, the motion integrated from the
odometry (the previous message's twist held, as the localizer does) is compared with the
true motion (ground truth at both ends, in the frame of the start), and the covariance
the model predicts for the window (propagated step by step from zero, the same
``motion.predict``) is a linear function of the alphas: ``C(a) = sum_i a_i C_i``.

The reference is measured too: the motion-capture poses at the window's ends carry
their own noise (``pose_stddev_*`` of the ``landmark_mrclam`` section, 2 mm and 2
mrad), independent at the two ends (seconds apart, the samples 20 ms apart). The true
motion ``d = (-) g_s (+) g_e`` of the measured poses ``g_s``, ``g_e`` then errs by
``J_d_gs n_s + J_d_ge n_e`` to first order, and a window's error has the covariance
``C(a) + F``, with ``F`` = ``reference_floor``:
``F = J_d_gs Sigma J_d_gs^T + J_d_ge Sigma J_d_ge^T``, ``Sigma`` = diag(sx^2, sy^2,
sth^2) in the world frame, ``J_d_gs = [[-R^T, (d_y, -d_x)^T], [0, -1]]``,
``J_d_ge = [[R^T, 0], [0, 1]]`` (``R`` the rotation of the start heading). With equal
position deviations ``s``: ``F = [[2 s^2 I + sth^2 v v^T, -sth^2 v], [-sth^2 v^T,
2 sth^2]]``, ``v = (d_y, -d_x)``. Left out, ``F`` is taken up by the alphas: over 2 s
the odometry's sideways error (median 1.6 mm on dataset 6) is as small as the
reference's (variance 2 (2 mm)^2), and the model explains sideways error by heading
noise per distance, a2, which then also inflates the heading variance: on the 2 s
windows of dataset 6, a2 is 6.80 without ``F`` and 0.48 with it.

The alphas maximise the Gaussian likelihood of the window errors,
``sum_w log det C_w + e_w^T C_w^-1 e_w`` with ``C_w = C_w(a) + F_w``, over ``a > 0``
(in log space, quasi-Newton with the exact gradient), for the windows of several
lengths together (``windows_s``, default 2, 5, 10 and 20 s: each length cuts the whole
run once, and each length weighs the same, its windows' log-likelihood divided by
their number). Short windows alone weigh the high-frequency part of the odometry error
(the twist's jitter, the reference's noise), which averages out over the tens of
seconds the localizer dead-reckons between landmarks; the long windows hold the drift
that matters there, and counted by number they would be outvoted by the 2 s windows,
ten to one against 20 s. Adjacent windows share an end, so their reference errors
are correlated; the likelihood takes the windows as independent (a composite
likelihood: the estimate is unbiased, only its spread is misstated). The cross-check
fits on all robots but one and reports, on it, the average NEES of the window errors
(3 is right) for each window length; ``robot_halves`` checks whether a model per robot
(each robot's wheels its own sensor) holds from one half of the run to the other.
"""

import copy
from dataclasses import dataclass, replace
import math

from landmark_ros.localizer import motion
from landmark_ros.mrclam.data import interpolate_poses, read_table, ROBOT_SUBJECTS
import numpy as np
from scipy.optimize import minimize


@dataclass
class RobotExtras:
    """One robot's odometry and robot-to-robot sightings."""

    number: int
    odom_times: np.ndarray
    """Odometry stamps [s], increasing, shape (K,)."""
    odom_twist: np.ndarray
    """Forward speed [m/s] and yaw rate [rad/s], shape (K, 2)."""
    sighting_times: np.ndarray
    """Stamps of the robot-to-robot sightings [s], shape (S,)."""
    sighting_robot: np.ndarray
    """Robot seen (its number), shape (S,)."""
    sighting_z: np.ndarray
    """Range [m] and bearing [rad], shape (S, 2)."""


def load_extras(path, number, barcodes):
    """Read robot ``number``'s odometry and its sightings of other robots."""
    odom = read_table(path / f'Robot{number}_Odometry.dat', 3)
    odom = odom[np.argsort(odom[:, 0], kind='stable')]
    keep = np.concatenate([[True], np.diff(odom[:, 0]) > 0]) if len(odom) else []
    odom = odom[keep]
    meas = read_table(path / f'Robot{number}_Measurement.dat', 4)
    meas = meas[np.argsort(meas[:, 0], kind='stable')]
    subjects = np.array([barcodes.get(int(round(c)), -1) for c in meas[:, 1]], np.int64)
    robot = np.isin(subjects, list(ROBOT_SUBJECTS)) & (subjects != number)
    return RobotExtras(number, odom[:, 0].copy(), odom[:, 1:3].copy(), meas[robot, 0].copy(),
                       subjects[robot], meas[robot][:, 2:4].copy())


def load_all_extras(dataset):
    """Return ``RobotExtras`` per robot of ``dataset``, by robot number."""
    return {r.number: load_extras(dataset.path, r.number, dataset.barcodes)
            for r in dataset.robots}


def with_camera_delay(dataset, extras, seconds):
    """
    Return the dataset and extras with every sighting stamped ``seconds`` earlier.

    The camera stamps its sightings late (``mrclam.camera_delay``): the landmark
    sightings move back by ``Dataset.with_camera_delay`` (those that leave the ground
    truth are dropped and counted), the robot-to-robot sightings (same camera) by the
    same ``seconds`` [s]; the odometry keeps its stamps. 0 returns both unchanged.

    Raises
    ------
    ValueError
        If ``seconds`` is not finite.

    """
    seconds = float(seconds)
    dataset = dataset.with_camera_delay(seconds)
    if seconds == 0.0:
        return dataset, extras
    return dataset, {number: replace(ex, sighting_times=ex.sighting_times - seconds)
                     for number, ex in extras.items()}


def reference_floor(start, end, stddev):
    """
    Return the covariance of the motion between two noisy reference poses.

    The motion ``(-) start (+) end`` of two poses measured with independent zero-mean
    noise of standard deviations ``stddev`` (world frame, per axis) errs, to first
    order, by ``J_d_gs n_s + J_d_ge n_e`` (module docstring): the covariance that the
    reference adds to a window's error, whatever the odometry does.

    Parameters
    ----------
    start, end : ndarray, shape (W, 3)
        Reference poses at the window's ends (x [m], y [m], theta [rad]).
    stddev : sequence of 3 float
        Standard deviations of the reference's noise (x [m], y [m], theta [rad]).

    Returns
    -------
    F : ndarray, shape (W, 3, 3)
        Covariance of the reference's motion in the start's frame (x, y, theta).

    """
    start = np.asarray(start, dtype=np.float64).reshape(-1, 3)
    end = np.asarray(end, dtype=np.float64).reshape(-1, 3)
    Sigma = np.diag(np.square(np.asarray(stddev, dtype=np.float64)))
    c, s = np.cos(start[:, 2]), np.sin(start[:, 2])
    dx, dy = end[:, 0] - start[:, 0], end[:, 1] - start[:, 1]
    J_d_ge = np.zeros((len(start), 3, 3))
    J_d_ge[:, 0, 0], J_d_ge[:, 0, 1], J_d_ge[:, 1, 0], J_d_ge[:, 1, 1] = c, s, -s, c
    J_d_ge[:, 2, 2] = 1.0
    J_d_gs = -J_d_ge
    J_d_gs[:, 0, 2] = -s * dx + c * dy  # d_y of the motion
    J_d_gs[:, 1, 2] = -c * dx - s * dy  # -d_x
    return (np.einsum('wij,jk,wlk->wil', J_d_gs, Sigma, J_d_gs)
            + np.einsum('wij,jk,wlk->wil', J_d_ge, Sigma, J_d_ge))


def _windows(extras, robot, window_s, delay_s=0.0, scales=(1.0, 1.0), period_s=0.0):
    """Yield (error (3,), per-alpha covariances (4, 3, 3), start, end truth) per window."""
    t = extras.odom_times + delay_s
    gt_t, gt_p = robot.gt_times, robot.gt_poses
    inside = (t >= gt_t[0]) & (t <= gt_t[-1])
    t, twist = t[inside], motion.scale_twists(extras.odom_twist[inside], scales)
    truth, _ = interpolate_poses(gt_t, gt_p, t)
    poses, deltas = motion.integrate_twists(t, twist)
    terms = motion.odometry_noise_terms(deltas)  # step k -> k + 1
    terms = terms * motion.step_noise_scale(np.diff(t), period_s)[:, None, None, None]
    start = 0
    while start < len(t) - 1:
        end = int(np.searchsorted(t, t[start] + window_s))
        if end >= len(t):
            break
        before = poses[start:end]  # pose at the start of each step
        after = poses[start + 1:end + 1]
        c, s = np.cos(before[:, 2]), np.sin(before[:, 2])
        J = np.zeros((end - start, 3, 3))  # d(end pose, world) / d(step motion)
        J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1], J[:, 2, 2] = c, -s, s, c, 1.0
        J[:, 0, 2] = -(poses[end, 1] - after[:, 1])
        J[:, 1, 2] = poses[end, 0] - after[:, 0]
        Ps = np.einsum('kij,kajl,kml->aim', J, terms[start:end], J)
        c0, s0 = math.cos(poses[start, 2]), math.sin(poses[start, 2])
        rot = np.array([[c0, s0, 0.0], [-s0, c0, 0.0], [0.0, 0.0, 1.0]])
        Ps = rot @ Ps @ rot.T
        error = (motion.between(poses[start], poses[end])
                 - motion.between(truth[start], truth[end]))
        error[2] = motion.wrap(error[2])
        yield error, Ps, truth[start], truth[end]
        start = end


@dataclass
class WindowSamples:
    """The windows of ``window_samples``, all lengths pooled."""

    errors: np.ndarray
    """Odometry motion minus reference motion, start frame, shape (W, 3)."""
    covs: np.ndarray
    """Covariance of the odometry motion per unit alpha, shape (W, 4, 3, 3)."""
    floors: np.ndarray
    """Covariance of the reference motion (``reference_floor``), shape (W, 3, 3)."""
    lengths: np.ndarray
    """Window length [s] of each window, shape (W,)."""


def window_samples(dataset, extras, numbers, window_s, delay_s=0.0, scales=(1.0, 1.0),
                   reference_stddev=(0.0, 0.0, 0.0), period_s=0.0):
    """
    Return the windows of the robots ``numbers`` as ``WindowSamples``.

    ``window_s`` [s]: one length or a sequence of lengths, each cutting the whole run.
    ``scales`` (speed, yaw rate[, speed per yaw rate]) correct the odometry's twists
    first (``motion.scale_twists``, ``odometry_scales``). ``reference_stddev`` (x [m],
    y [m], theta [rad]): the noise of the ground truth, for ``reference_floor``.
    ``period_s``: the localizer's ``odometry_alphas_period_s`` (``motion.step_noise_scale``).
    """
    errors, covs, starts, ends, lengths = [], [], [], [], []
    for length in np.atleast_1d(np.asarray(window_s, dtype=np.float64)):
        for robot in dataset.robots:
            if robot.number not in numbers:
                continue
            for error, Ps, a, b in _windows(extras[robot.number], robot, float(length),
                                            delay_s, scales, period_s):
                errors.append(error)
                covs.append(Ps)
                starts.append(a)
                ends.append(b)
                lengths.append(float(length))
    starts, ends = np.array(starts).reshape(-1, 3), np.array(ends).reshape(-1, 3)
    return WindowSamples(np.array(errors).reshape(-1, 3), np.array(covs).reshape(-1, 4, 3, 3),
                         reference_floor(starts, ends, reference_stddev),
                         np.array(lengths, dtype=np.float64))


def _neg_log_likelihood(log_alphas, errors, covs, floor, weights):
    """Return ``sum_w q_w (log det C_w + e_w^T C_w^-1 e_w)``, its gradient in the log alphas."""
    alphas = np.exp(log_alphas)
    C = np.einsum('i,wijk->wjk', alphas, covs) + floor
    sign, logdet = np.linalg.slogdet(C)
    if np.any(sign <= 0):
        return 1e12, np.zeros_like(log_alphas)
    C_inv = np.linalg.inv(C)
    u = np.einsum('wij,wj->wi', C_inv, errors)
    # d/da_i: tr(C^-1 C_i) - u^T C_i u, u = C^-1 e
    grad = (np.einsum('w,wjk,wikj->i', weights, C_inv, covs)
            - np.einsum('w,wj,wijk,wk->i', weights, u, covs, u))
    value = np.sum(weights * (logdet + np.einsum('wi,wi->w', u, errors)))
    return float(value), alphas * grad


def _floor(samples, floor):
    """Return the reference floor plus ``floor`` [1] on the diagonal, shape (W, 3, 3)."""
    return samples.floors + np.eye(3) * floor


def fit_alphas(samples, floor=1e-8):
    """
    Return the alphas (4,) of the largest likelihood of the window errors.

    ``samples``: ``WindowSamples``; each window's error covariance is ``sum_i a_i
    covs[:, i] + floors`` plus ``floor`` on the diagonal (numerical). Each window
    length weighs the same: a window's log-likelihood counts ``W / (L W_l)`` times
    (``W`` windows of ``L`` lengths, ``W_l`` of its own). Quasi-Newton (L-BFGS-B) on the
    log alphas with the exact gradient, from 1e-3 each, bounded to 1e-12 to 1e4.
    """
    _, index, counts = np.unique(samples.lengths, return_inverse=True, return_counts=True)
    weights = len(samples.lengths) / (len(counts) * counts[index])
    args = (samples.errors, samples.covs, _floor(samples, floor), weights)
    best = minimize(_neg_log_likelihood, np.log(np.full(4, 1e-3)), args=args, jac=True,
                    method='L-BFGS-B', bounds=[(math.log(1e-12), math.log(1e4))] * 4,
                    options={'maxiter': 2000, 'ftol': 1e-13, 'gtol': 1e-8})
    return np.exp(best.x)


def window_nees(alphas, samples, floor=1e-8):
    """Return the average NEES (3 dof) of the windows of ``samples`` under ``alphas``."""
    C = np.einsum('i,wijk->wjk', np.asarray(alphas), samples.covs) + _floor(samples, floor)
    e = samples.errors
    d2 = np.einsum('wi,wi->w', e, np.linalg.solve(C, e[..., None])[..., 0])
    return float(np.mean(d2))


def odometry_delay(dataset, extras, delays=np.arange(0.0, 0.41, 0.025)):
    """
    Return the delay [s] of the true motion after the odometry stamps.

    The yaw rate of the odometry against the ground truth's (central differences over
    0.1 s, every 20 ms of the overlap), all robots pooled; the delay of least squares
    on a grid. On dataset 6 the odometry runs about 0.2 s ahead of the motion (it
    looks like the commanded twist): the replay stamps it ``delay`` later.
    """
    best = []
    for robot in dataset.robots:
        e = extras[robot.number]
        t = np.arange(max(e.odom_times[0], robot.gt_times[0]) + 1.0,
                      min(e.odom_times[-1], robot.gt_times[-1]) - 1.0, 0.02)
        heading = np.unwrap(robot.gt_poses[:, 2])
        rate = (np.interp(t + 0.05, robot.gt_times, heading)
                - np.interp(t - 0.05, robot.gt_times, heading)) / 0.1
        best.append([np.mean((np.interp(t - d, e.odom_times, e.odom_twist[:, 1]) - rate) ** 2)
                     for d in delays])
    return float(delays[int(np.argmin(np.sum(best, axis=0)))])


def _motion_pairs(robot, extras, delay_s, window_s):
    """
    Return per window the odometry's and the true motion.

    Returns
    -------
    odo : ndarray, shape (W, 3)
        Odometry distance [m], turn [rad] and the integral of speed x |yaw rate| [rad m].
    true : ndarray, shape (W, 2)
        True distance [m] and turn [rad].

    """
    e = extras[robot.number]
    t = np.arange(max(e.odom_times[0] + delay_s, robot.gt_times[0]),
                  min(e.odom_times[-1] + delay_s, robot.gt_times[-1]), window_s)
    heading = np.unwrap(robot.gt_poses[:, 2])
    xy = np.stack([np.interp(t, robot.gt_times, robot.gt_poses[:, c]) for c in (0, 1)], 1)
    true = np.stack([np.hypot(*np.diff(xy, axis=0).T),
                     np.diff(np.interp(t, robot.gt_times, heading))], 1)
    # the odometry integrated as the localizer does: each twist held until the next stamp
    ot = e.odom_times + delay_s
    dt = np.diff(ot)
    v, w = e.odom_twist[:-1, 0], e.odom_twist[:-1, 1]
    rates = np.stack([np.abs(v), w, np.abs(v * w)], 1) * dt[:, None]
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(rates, axis=0)])
    odo = np.diff(np.stack([np.interp(t, ot, cum[:, c]) for c in range(3)], 1), axis=0)
    return odo, true


def odometry_scales(dataset, extras, numbers, delay_s, window_s=0.5, min_distance=0.02,
                    turn_window_s=2.0):
    """
    Return the systematic error of the odometry: true motion per odometry motion.

    Least squares over windows of ``window_s`` of the robots ``numbers`` pooled: the
    true distance (ground truth) against the odometry's distance and its integral of
    speed x |yaw rate| (windows where the odometry moves at least ``min_distance``).
    Over windows of ``turn_window_s``: the true turn against the odometry's turn and
    distance (a veer while driving); shorter windows bias the turn's factor towards 0,
    as the odometry's timing jitter is noise in the regressor. A systematic error of the wheel
    odometry (wheel radius, wheel base, a drive that slows down in turns; on MRCLAM the
    odometry is the commanded twist: straight at 0.067 m/s the robots make 0.068 m/s,
    turning at 0.4 rad/s and 0.086 m/s they make 0.05 m/s) that the alphas, zero-mean
    noise, cannot describe.

    Returns
    -------
    tuple of 4 float
        ``(speed_scale, yaw_rate_scale, speed_scale_per_yaw_rate [s/rad], yaw_per_m
        [rad/m])``, the parameters of ``motion.scale_motion``.

    """
    robots = [r for r in dataset.robots if r.number in numbers]
    odo, true = (np.concatenate(a) for a in zip(
        *(_motion_pairs(r, extras, delay_s, window_s) for r in robots)))
    moving = odo[:, 0] >= min_distance
    (speed, per_yaw_rate), *_ = np.linalg.lstsq(odo[moving][:, [0, 2]], true[moving, 0],
                                                rcond=None)
    odo, true = (np.concatenate(a) for a in zip(
        *(_motion_pairs(r, extras, delay_s, turn_window_s) for r in robots)))
    (turn, veer), *_ = np.linalg.lstsq(odo[:, [1, 0]], true[:, 1], rcond=None)
    return float(speed), float(turn), float(per_yaw_rate), float(veer)


def calibrate_odometry(dataset, extras, windows_s=(2.0, 5.0, 10.0, 20.0),
                       check_windows=(2.0, 5.0, 10.0, 20.0), period_s=0.0):
    """
    Fit the alphas on all robots, and cross-check: fit on all but one, test on it.

    The windows of every length of ``windows_s`` [s] together, the reference's noise
    ``dataset.pose_stddev`` (``reference_floor``), the steps scaled as the localizer
    does with ``odometry_alphas_period_s`` = ``period_s`` (``motion.step_noise_scale``).

    Returns
    -------
    dict
        ``alphas`` (all robots), ``period_s``, ``windows_s``, ``reference_stddev``,
        ``windows`` (their number), ``window_nees`` (all robots, per window length) and
        ``cross_check``: per held-out robot, the alphas fitted without it and the window
        NEES on it per window length; ``halves``: ``robot_halves``, per robot and fold.

    """
    numbers = [r.number for r in dataset.robots]
    stddev = tuple(float(v) for v in dataset.pose_stddev)
    delay = odometry_delay(dataset, extras)

    def samples(robots, lengths, scales):
        return window_samples(dataset, extras, robots, lengths, delay, scales, stddev,
                              period_s)

    scales = odometry_scales(dataset, extras, numbers, delay)
    pooled = samples(numbers, windows_s, scales)
    alphas = fit_alphas(pooled)
    own_nees = {str(w): window_nees(alphas, samples(numbers, w, scales))
                for w in check_windows}
    check = []
    for held in numbers:
        others = [n for n in numbers if n != held]
        held_scales = odometry_scales(dataset, extras, others, delay)
        fitted = fit_alphas(samples(others, windows_s, held_scales))
        nees = {str(w): window_nees(fitted, samples([held], w, held_scales))
                for w in check_windows}
        own = odometry_scales(dataset, extras, [held], delay)
        check.append({'held_out': held, 'alphas': fitted.tolist(), 'scales': held_scales,
                      'own_scales': own, 'window_nees': nees})
    return {'alphas': alphas.tolist(), 'period_s': period_s, 'scales': scales,
            'windows_s': list(windows_s), 'reference_stddev': list(stddev), 'delay_s': delay,
            'windows': len(pooled.errors), 'window_nees': own_nees, 'cross_check': check,
            'halves': robot_halves(dataset, extras, delay, windows_s, stddev, period_s)}


def _half(dataset, second, middle):
    """Return ``dataset`` with each robot's ground truth cut before or from ``middle``."""
    robots = []
    for robot in dataset.robots:
        keep = robot.gt_times >= middle if second else robot.gt_times < middle
        cut = copy.copy(robot)
        cut.gt_times, cut.gt_poses = robot.gt_times[keep], robot.gt_poses[keep]
        robots.append(cut)
    out = copy.copy(dataset)
    out.robots = robots
    return out


def robot_halves(dataset, extras, delay_s, windows_s=(2.0, 5.0, 10.0, 20.0),
                 stddev=(0.0, 0.0, 0.0), period_s=0.0):
    """
    Check a per-robot odometry model across the halves of the run, both folds.

    The run is cut at the middle of its ground truth (earliest start to latest end). On
    one half the scales and alphas are fitted per robot (that robot's windows) and
    pooled (all robots), as ``calibrate_odometry`` does; each robot's windows of the
    other half are scored under both: window NEES (3 is right) per window length. A
    per-robot model is worth its parameters only where its NEES on the other half is
    nearer 3 than the pooled model's, for every robot and both folds.

    Returns
    -------
    list of dict
        Per fold and robot: ``fitted_on`` (``first`` or ``second``), ``robot``,
        ``alphas`` and ``scales`` (its own fit), ``nees_own`` and ``nees_pooled`` (per
        window length [s] as a string).

    """
    numbers = [r.number for r in dataset.robots]
    middle = 0.5 * (min(r.gt_times[0] for r in dataset.robots)
                    + max(r.gt_times[-1] for r in dataset.robots))
    halves = [_half(dataset, False, middle), _half(dataset, True, middle)]
    out = []

    def samples(data, robots, lengths, scales):
        return window_samples(data, extras, robots, lengths, delay_s, scales, stddev,
                              period_s)

    for k, name in enumerate(('first', 'second')):
        fit_on, score_on = halves[k], halves[1 - k]
        scales = odometry_scales(fit_on, extras, numbers, delay_s)
        alphas = fit_alphas(samples(fit_on, numbers, windows_s, scales))
        for n in numbers:
            own_scales = odometry_scales(fit_on, extras, [n], delay_s)
            own = fit_alphas(samples(fit_on, [n], windows_s, own_scales))
            nees = [{str(w): window_nees(a, samples(score_on, [n], w, sc)) for w in windows_s}
                    for a, sc in ((own, own_scales), (alphas, scales))]
            out.append({'fitted_on': name, 'robot': n, 'alphas': own.tolist(),
                        'scales': own_scales, 'nees_own': nees[0], 'nees_pooled': nees[1]})
    return out


def format_odometry_calibration(result):
    """Return the calibration as text with the YAML line to paste."""
    a = result['alphas']
    lengths = ', '.join(f'{w:g}' for w in result['windows_s'])
    lines = [f'odometry alphas from {result["windows"]} windows of {lengths} s '
             f'(all robots, reference noise '
             + ', '.join(f'{v:g}' for v in result['reference_stddev'])
             + f', odometry delay {result["delay_s"]:.3f} s, speed and yaw-rate '
             'scales {:.4f}, {:.4f}, speed scale per yaw rate {:.4f} s/rad, veer {:.4f} '
             'rad/m, alphas per {}): '.format(*result['scales'], _period(result))
             + ', '.join(f'{v:.4g}' for v in a),
             'window NEES, all robots (3 is right): '
             + ', '.join(f'{w} s: {v:.2f}' for w, v in result['window_nees'].items()),
             'cross-check (fit without the robot, window NEES on it; 3 is right):']
    for entry in result['cross_check']:
        nees = ', '.join(f'{w} s: {v:.2f}' for w, v in entry['window_nees'].items())
        lines.append(f'  robot {entry["held_out"]}: alphas '
                     + ', '.join(f'{v:.3g}' for v in entry['alphas'])
                     + ', scales {:.4f}, {:.4f}, {:.4f}, {:.4f} (its own {:.4f}, {:.4f}, '
                     '{:.4f}, {:.4f})'.format(*entry['scales'], *entry['own_scales'])
                     + f'; NEES {nees}')
    lines.append('per robot across halves (own scales and alphas from one half, window '
                 'NEES on the other; pooled: all robots fitted on that half; 3 is right):')
    for entry in result.get('halves', ()):
        lines.append(f'  fitted on the {entry["fitted_on"]:6s} robot {entry["robot"]}: alphas '
                     + ', '.join(f'{v:.3g}' for v in entry['alphas'])
                     + '; NEES own ' + ', '.join(f'{v:.2f}' for v in entry['nees_own'].values())
                     + ', pooled '
                     + ', '.join(f'{v:.2f}' for v in entry['nees_pooled'].values()))
    lines.append('landmark_localizer:\n  ros__parameters:\n    odometry_alphas: ['
                 + ', '.join(f'{v:.4g}' for v in a) + ']\n'
                 f'    odometry_alphas_period_s: {result.get("period_s", 0.0):g}\n'
                 f'    odometry_speed_scale: {result["scales"][0]:.4f}\n'
                 f'    odometry_yaw_rate_scale: {result["scales"][1]:.4f}\n'
                 f'    odometry_speed_scale_per_yaw_rate: {result["scales"][2]:.4f}\n'
                 f'    odometry_yaw_per_m: {result["scales"][3]:.4f}\n'
                 'landmark_mrclam:\n  ros__parameters:\n'
                 f'    odometry_delay_s: {result["delay_s"]:.3f}')
    return '\n'.join(lines)


def _period(result):
    period = result.get('period_s', 0.0)
    return f'{period:g} s of odometry' if period > 0.0 else 'odometry step'


def heading_error(a, b):
    """Return ``wrap(a - b)`` elementwise [rad]."""
    return (np.asarray(a) - b + math.pi) % (2.0 * math.pi) - math.pi
