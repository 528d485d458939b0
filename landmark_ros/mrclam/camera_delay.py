"""
The delay of a MRCLAM camera's stamps, estimated from the ground truth (ROS-free).

A sighting stamped ``t`` was taken at ``t - d``: the image is stamped when it has been
read out and decoded, later than the motion capture saw the robot. The pose the replay
pairs with the sighting (interpolated at ``t``) is then off by the motion in ``d``,
which shows in the bearing error: a robot turning at ``w`` rad/s adds about ``-w d``.
``estimate_camera_delay`` finds ``d`` as the shift of the stamps that makes the bearing
residuals of the sightings (against the ground-truth pose at ``t - d`` and the surveyed
landmarks) smallest, by a robust statistic, in a 1-D search over shifts; the ranges are
not used (their error depends little on the pose's heading). ``Dataset.with_camera_delay``
applies it (``config/mrclam.yaml``: ``camera_delay_s`` of the ``landmark_mrclam``
section); ``landmark_mrclam --calibrate`` prints it.
"""

from dataclasses import asdict, dataclass
import math

from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.mrclam.data import interpolate_poses
from landmark_ros.mrclam.range_calibration import BISQUARE_C, robust_sigma
import numpy as np

DELAY_SEARCH_S = (-0.3, 0.3)
"""Shifts searched [s]: far beyond a camera's latency (a frame is 1/30 s), both signs."""

DELAY_STEP_S = 0.005
"""Grid step of the search [s]; the minimum is refined between grid points (parabola)."""

SIGNIFICANCE = 3.0
"""A shift is applied when it is at least this many standard errors from 0."""


@dataclass
class CameraDelay:
    """The stamp delay estimated from ground truth (``estimate_camera_delay``)."""

    delay_s: float
    """The delay to apply [s]: the shift that minimises the robust loss of the bearing
    residuals when it is significant (``SIGNIFICANCE`` standard errors), else 0."""
    minimum_s: float
    """The shift that minimises the loss [s], significant or not."""
    stderr_s: float
    """Its standard error [s] (``shift_stderr``)."""
    count: int
    """Sightings used (known landmark, inside the ground truth at every shift)."""
    robots: dict
    """Per robot name: the minimum and its standard error from that robot's sightings
    alone [s]."""
    bearing_sd_raw: float
    """Robust standard deviation of the bearing residuals at the raw stamps [rad]."""
    bearing_sd: float
    """The same at the estimated delay [rad]."""

    def to_dict(self):
        """Return plain values for JSON."""
        return asdict(self)


def _sightings(dataset, search):
    """Return, per robot, the sightings usable at every shift of ``search``."""
    out = []
    for robot in dataset.robots:
        if not len(robot.gt_times):
            continue
        known = np.array([i in dataset.landmarks for i in robot.ids.tolist()], dtype=bool)
        inside = ((robot.times - search[1] >= robot.gt_times[0])
                  & (robot.times - search[0] <= robot.gt_times[-1]))
        keep = known & inside
        if not keep.any():
            continue
        truth = np.array([dataset.landmarks[i] for i in robot.ids[keep].tolist()])
        out.append((robot, robot.times[keep], robot.z[keep, 1], truth))
    return out


def bearing_residuals(sightings, delay_s):
    """
    Return the bearing errors of sightings taken ``delay_s`` before their stamps.

    Parameters
    ----------
    sightings : list of (Robot, ndarray (K,), ndarray (K,), ndarray (K, 2))
        Per robot: the robot (its ground truth), the stamps [s], the bearings [rad] and
        the true landmark positions [m].
    delay_s : float
        Shift of the stamps [s]: the pose is interpolated at ``stamp - delay_s``.

    Returns
    -------
    list of ndarray, shape (K,)
        Per robot, measured minus true bearing [rad], wrapped, less the robot's median
        (its bearing bias, which a shift of the stamps does not explain).

    """
    out = []
    for robot, times, bearing, truth in sightings:
        pose, _ = interpolate_poses(robot.gt_times, robot.gt_poses, times - delay_s)
        d = truth - pose[:, :2]
        error = wrap_angle(bearing - (np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2]))
        out.append(error - np.median(error))
    return out


def _bisquare_loss(residuals, scale):
    """Return the mean Tukey bisquare loss of residuals, tuning ``BISQUARE_C * scale``."""
    u = np.minimum(np.abs(residuals) / (BISQUARE_C * scale), 1.0)
    return float(np.mean(1.0 - (1.0 - u * u) ** 3))


def _search(sightings, scale, grid):
    """Return the shift minimising the bisquare loss: grid minimum, parabola refined."""
    loss = np.array([_bisquare_loss(np.concatenate(bearing_residuals(sightings, d)), scale)
                     for d in grid])
    i = int(np.argmin(loss))
    if 0 < i < len(grid) - 1:
        left, mid, right = loss[i - 1:i + 2]
        curvature = left - 2.0 * mid + right
        if curvature > 0.0:
            step = grid[1] - grid[0]
            return float(grid[i] + 0.5 * step * (left - right) / curvature)
    return float(grid[i])


def shift_stderr(sightings, delay_s, scale, step=1e-3):
    """
    Return the standard error of a shift of the stamps estimated at ``delay_s`` [s].

    Linearised least squares on the inliers (within 3 ``scale`` of 0): with ``g`` the
    derivative of the residuals (robot medians removed) with respect to the shift
    (central difference of ``step``), ``sigma / sqrt(sum g^2)``, ``sigma`` the robust
    standard deviation of the residuals. It counts the residuals as independent: a
    lower bound where they are correlated in time, but infinite where a shift cannot be
    told from a bearing bias (a robot that turns at one constant rate: the shift then
    moves every bearing of the robot alike, and its median takes it all).
    """
    e = np.concatenate(bearing_residuals(sightings, delay_s))
    g = (np.concatenate(bearing_residuals(sightings, delay_s + step))
         - np.concatenate(bearing_residuals(sightings, delay_s - step))) / (2.0 * step)
    inlier = np.abs(e) < 3.0 * scale
    information = float(np.sum(g[inlier] ** 2))
    sigma = robust_sigma(e[inlier])
    return sigma / math.sqrt(information) if information > 0.0 else math.inf


def _minimum(sightings, scale, grid):
    """Return the loss-minimising shift and its standard error [s]."""
    best = _search(sightings, scale, grid)
    return best, shift_stderr(sightings, best, scale)


def estimate_camera_delay(dataset, search=DELAY_SEARCH_S, step=DELAY_STEP_S):
    """
    Estimate how long before its stamp each sighting was taken.

    Procedure: the sightings of known landmarks that lie inside their robot's ground
    truth at every shift of ``search``; for each shift ``d`` of a grid of ``step`` the
    bearing residuals ``bearing_residuals(d)`` (pose interpolated at ``stamp - d``,
    each robot's median removed) and their mean Tukey bisquare loss, with the scale
    the MAD-based standard deviation of the residuals at ``d = 0`` (fixed, so that the
    losses compare; the bisquare gives the far tail, wrong barcodes, a constant loss);
    the minimum of the grid is refined by the parabola through it and its neighbours.
    It is the delay when it lies ``SIGNIFICANCE`` standard errors (``shift_stderr``)
    or more from 0, else the delay is 0: the data do not tell it from a bearing bias.
    The same search on each robot's sightings alone gives the per-robot estimates, a
    check that the delay is one of the camera model and not of a robot.

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        Sightings and ground truth.
    search : (float, float)
        Shifts searched [s].
    step : float
        Grid step [s], positive.

    Returns
    -------
    CameraDelay

    Raises
    ------
    ValueError
        If no sighting is usable, or the search interval or step is invalid.

    """
    low, high = float(search[0]), float(search[1])
    if not (math.isfinite(low) and math.isfinite(high) and low < high and step > 0.0):
        raise ValueError(f'invalid delay search {search} with step {step}')
    sightings = _sightings(dataset, (low, high))
    if not sightings:
        raise ValueError('no sighting of a known landmark inside the ground truth')
    grid = np.arange(low, high + 0.5 * step, step)
    raw = np.concatenate(bearing_residuals(sightings, 0.0))
    scale = max(robust_sigma(raw), 1e-9)
    minimum, stderr = _minimum(sightings, scale, grid)
    delay = minimum if abs(minimum) >= SIGNIFICANCE * stderr else 0.0
    robots = {s[0].name: _minimum([s], scale, grid) for s in sightings}
    best = np.concatenate(bearing_residuals(sightings, delay))
    return CameraDelay(delay, minimum, stderr, len(raw), robots, float(robust_sigma(raw)),
                       float(robust_sigma(best)))


def format_camera_delay(result):
    """Return the printout of a ``CameraDelay``."""
    robots = ', '.join(f'{name} {1e3 * d:+.1f} +- {1e3 * se:.1f}'
                       for name, (d, se) in result.robots.items())
    return (f'camera delay (bearing residuals against the ground truth, {result.count} '
            f'sightings): {1e3 * result.delay_s:+.1f} ms (loss minimum '
            f'{1e3 * result.minimum_s:+.1f} ms, standard error {1e3 * result.stderr_s:.2f} ms; '
            f'applied when beyond {SIGNIFICANCE:g} standard errors); per robot [ms]: {robots}; '
            f'bearing robust sd {result.bearing_sd_raw:.4f} rad at the stamps, '
            f'{result.bearing_sd:.4f} rad shifted')
