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
``motion.predict``) is a linear function of the alphas: ``C(a) = sum_i a_i C_i``. The
alphas maximise the Gaussian likelihood of the window errors,
``sum_w log det C_w(a) + e_w^T C_w(a)^-1 e_w``, over ``a >= 0`` (in log space,
Nelder-Mead). The cross-check fits on some robots and reports, on the others, the
average NEES of the window errors (3 is right) for several window lengths.
"""

from dataclasses import dataclass
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


def _windows(extras, robot, window_s, delay_s=0.0, scales=(1.0, 1.0)):
    """Yield (error (3,), per-alpha covariances (4, 3, 3)) per odometry window."""
    t = extras.odom_times + delay_s
    gt_t, gt_p = robot.gt_times, robot.gt_poses
    inside = (t >= gt_t[0]) & (t <= gt_t[-1])
    t, twist = t[inside], motion.scale_twists(extras.odom_twist[inside], scales)
    truth, _ = interpolate_poses(gt_t, gt_p, t)
    poses, deltas = motion.integrate_twists(t, twist)
    terms = motion.odometry_noise_terms(deltas)  # step k -> k + 1
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
        yield error, Ps
        start = end


def window_samples(dataset, extras, numbers, window_s, delay_s=0.0, scales=(1.0, 1.0)):
    """
    Return the window errors (W, 3) and unit-alpha covariances (W, 4, 3, 3).

    ``scales`` (speed, yaw rate[, speed per yaw rate]) correct the odometry's twists
    first (``motion.scale_twists``, ``odometry_scales``).
    """
    errors, covs = [], []
    for robot in dataset.robots:
        if robot.number not in numbers:
            continue
        for error, Ps in _windows(extras[robot.number], robot, window_s, delay_s, scales):
            errors.append(error)
            covs.append(Ps)
    return np.array(errors).reshape(-1, 3), np.array(covs).reshape(-1, 4, 3, 3)


def _neg_log_likelihood(log_alphas, errors, covs, floor):
    C = np.einsum('i,wijk->wjk', np.exp(log_alphas), covs) + floor
    sign, logdet = np.linalg.slogdet(C)
    if np.any(sign <= 0):
        return 1e12
    d2 = np.einsum('wi,wi->w', errors, np.linalg.solve(C, errors[..., None])[..., 0])
    return float(np.sum(logdet + d2))


def fit_alphas(errors, covs, floor=1e-8):
    """Return the alphas (4,) of the largest likelihood of the window errors."""
    start = np.log(np.full(4, 1e-3))
    best = minimize(_neg_log_likelihood, start, args=(errors, covs, np.eye(3) * floor),
                    method='Nelder-Mead', options={'maxiter': 4000, 'xatol': 1e-4,
                                                   'fatol': 1e-6})
    return np.exp(best.x)


def window_nees(alphas, errors, covs, floor=1e-8):
    """Return the average NEES (3 dof) of window errors under ``alphas``."""
    C = np.einsum('i,wijk->wjk', np.asarray(alphas), covs) + np.eye(3) * floor
    d2 = np.einsum('wi,wi->w', errors, np.linalg.solve(C, errors[..., None])[..., 0])
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


def odometry_scales(dataset, extras, numbers, delay_s, window_s=0.5, min_distance=0.02):
    """
    Return the systematic error of the odometry: true motion per odometry motion.

    Least squares over windows of ``window_s`` of the robots ``numbers`` pooled: the
    true distance (ground truth) against the odometry's distance and its integral of
    speed x |yaw rate| (windows where the odometry moves at least ``min_distance``), the
    true turn against the odometry's through the origin. A systematic error of the wheel
    odometry (wheel radius, wheel base, a drive that slows down in turns; on MRCLAM the
    odometry is the commanded twist: straight at 0.067 m/s the robots make 0.068 m/s,
    turning at 0.4 rad/s and 0.086 m/s they make 0.05 m/s) that the alphas, zero-mean
    noise, cannot describe.

    Returns
    -------
    tuple of 3 float
        ``(speed_scale, yaw_rate_scale, speed_scale_per_yaw_rate [s/rad])``, the
        parameters of ``motion.scale_motion``.

    """
    odo, true = [], []
    for robot in dataset.robots:
        if robot.number in numbers:
            o, t = _motion_pairs(robot, extras, delay_s, window_s)
            odo.append(o)
            true.append(t)
    odo, true = np.concatenate(odo), np.concatenate(true)
    moving = odo[:, 0] >= min_distance
    (speed, per_yaw_rate), *_ = np.linalg.lstsq(odo[moving][:, [0, 2]], true[moving, 0],
                                                rcond=None)
    turn = np.sum(odo[:, 1] * true[:, 1]) / np.sum(odo[:, 1] ** 2)
    return float(speed), float(turn), float(per_yaw_rate)


def calibrate_odometry(dataset, extras, window_s=2.0, check_windows=(1.0, 2.0, 5.0)):
    """
    Fit the alphas on all robots, and cross-check: fit on all but one, test on it.

    Returns
    -------
    dict
        ``alphas`` (all robots), ``window_s`` and ``cross_check``: per held-out robot,
        the alphas fitted without it and the window NEES on it per window length.

    """
    numbers = [r.number for r in dataset.robots]
    delay = odometry_delay(dataset, extras)
    scales = odometry_scales(dataset, extras, numbers, delay)
    errors, covs = window_samples(dataset, extras, numbers, window_s, delay, scales)
    alphas = fit_alphas(errors, covs)
    check = []
    for held in numbers:
        others = [n for n in numbers if n != held]
        held_scales = odometry_scales(dataset, extras, others, delay)
        e, c = window_samples(dataset, extras, others, window_s, delay, held_scales)
        fitted = fit_alphas(e, c)
        nees = {}
        for w in check_windows:
            e_h, c_h = window_samples(dataset, extras, [held], w, delay, held_scales)
            nees[str(w)] = window_nees(fitted, e_h, c_h)
        own = odometry_scales(dataset, extras, [held], delay)
        check.append({'held_out': held, 'alphas': fitted.tolist(), 'scales': held_scales,
                      'own_scales': own, 'window_nees': nees})
    return {'alphas': alphas.tolist(), 'scales': scales, 'window_s': window_s,
            'delay_s': delay, 'windows': len(errors), 'cross_check': check}


def format_odometry_calibration(result):
    """Return the calibration as text with the YAML line to paste."""
    a = result['alphas']
    lines = [f'odometry alphas from {result["windows"]} windows of {result["window_s"]} s '
             f'(all robots, odometry delay {result["delay_s"]:.3f} s, speed and yaw-rate '
             'scales {:.4f}, {:.4f}, speed scale per yaw rate {:.4f} s/rad): '.format(
                 *result['scales'])
             + ', '.join(f'{v:.3g}' for v in a),
             'cross-check (fit without the robot, window NEES on it; 3 is right):']
    for entry in result['cross_check']:
        nees = ', '.join(f'{w} s: {v:.2f}' for w, v in entry['window_nees'].items())
        lines.append(f'  robot {entry["held_out"]}: alphas '
                     + ', '.join(f'{v:.3g}' for v in entry['alphas'])
                     + ', scales {:.4f}, {:.4f}, {:.4f} (its own {:.4f}, {:.4f}, {:.4f})'.format(
                         *entry['scales'], *entry['own_scales']) + f'; NEES {nees}')
    lines.append('landmark_localizer:\n  ros__parameters:\n    odometry_alphas: ['
                 + ', '.join(f'{v:.4g}' for v in a) + ']\n'
                 f'    odometry_speed_scale: {result["scales"][0]:.4f}\n'
                 f'    odometry_yaw_rate_scale: {result["scales"][1]:.4f}\n'
                 f'    odometry_speed_scale_per_yaw_rate: {result["scales"][2]:.4f}\n'
                 'landmark_mrclam:\n  ros__parameters:\n'
                 f'    odometry_delay_s: {result["delay_s"]:.3f}')
    return '\n'.join(lines)


def heading_error(a, b):
    """Return ``wrap(a - b)`` elementwise [rad]."""
    return (np.asarray(a) - b + math.pi) % (2.0 * math.pi) - math.pi
