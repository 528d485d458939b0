"""
The camera model of a MRCLAM dataset, estimated from its ground truth (ROS-free).

``calibrate`` documents the procedure: range and bearing errors of every landmark
sighting against the ground truth, per-robot median errors for the bias (the dependent
part of the observer's covariance), and the Gaussian that holds the central 99 % of the
residuals for the independent noise, with a range-dependent range noise
``sigma_r(r)^2 = a^2 + (k r)^2 + (c r^2)^2``, all of the ranges corrected for the
camera's range scale error first (``range_calibration``), and all of the sightings moved
back by the camera's stamp delay before anything else (``camera_delay``).
``landmark_mrclam --calibrate`` prints it with ``format_calibration`` and suggests the
``config/mrclam.yaml`` values.
"""

from dataclasses import asdict, dataclass
import math

from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.mrclam.camera_delay import (CameraDelay, estimate_camera_delay,
                                              format_camera_delay)
from landmark_ros.mrclam.range_calibration import (bearing_scale_spread, fit_range_noise,
                                                   range_noise_bins, remove_range_scale,
                                                   robust_sigma, SHORT_TAIL_M)
import numpy as np
from scipy import special
from scipy.optimize import minimize_scalar

CENTRAL_MASS = 0.99
"""Share of the residuals a Gaussian noise model must contain (``calibrate``)."""


def central_sigma(values, mass=CENTRAL_MASS):
    """
    Return the standard deviation of the Gaussian whose central ``mass`` matches.

    ``quantile(|e - median(e)|, mass) / z`` with ``z`` the two-sided Gaussian quantile
    of ``mass`` (2.576 for 0.99): the Gaussian that holds the same share of the errors.
    """
    values = np.asarray(values, dtype=np.float64)
    if not len(values):
        return float('nan')
    z = math.sqrt(2.0) * float(special.erfinv(mass))
    return float(np.quantile(np.abs(values - np.median(values)), mass) / z)


OBSERVER_FIELDS = ('range_stddev', 'range_stddev_per_m', 'range_stddev_per_m2', 'bearing_stddev',
                   'range_bias_stddev',
                   'bearing_bias_stddev', 'noise_correlation_time_s',
                   'range_correlated_fraction', 'bearing_correlated_fraction',
                   'range_scale_per_m', 'range_scale_bearing_limit')
"""The observer parameters ``calibrate`` estimates (``Calibration.observer_values``)."""

LOCALIZER_FIELDS = ('range_stddev', 'range_stddev_per_m', 'range_stddev_per_m2',
                    'bearing_stddev', 'range_bias_stddev',
                    'bearing_bias_stddev', 'noise_correlation_time_s',
                    'range_correlated_fraction', 'bearing_correlated_fraction',
                    'range_scale_per_m')
"""Localizer parameters taken as they are (``Calibration.localizer_values``)."""


@dataclass
class Calibration:
    """Sensor model estimated from ground truth (``calibrate``)."""

    count: int
    overall: dict
    """Raw errors: per quantity (range, bearing) n, mean, std, median, robust_sd, tail."""
    robots: list
    """Per robot: name, n, range and bearing median error, and the median range error
    per bin of true range (``range_by_range``: ``low``, ``high`` [m], ``n``, ``median``
    [m], None without sightings; an offset is flat, a scale error grows with the range)."""
    pairs: int
    """Robot-landmark pairs with enough sightings for the bias and residuals."""
    range_bins: list
    """Per range bin: low, high, median range, n, robust sd of residuals, model sd."""
    range_stddev: float
    range_stddev_per_m: float
    bearing_stddev: float
    range_bias_stddev: float
    bearing_bias_stddev: float
    pair_range_bias_rms: float
    pair_bearing_bias_rms: float
    residual_tails: dict
    """Fraction of residuals beyond 3 model standard deviations, per quantity."""
    range_correlated_fraction: float = 0.0
    bearing_correlated_fraction: float = 0.0
    noise_correlation_time_s: float = 0.0
    correlation: dict = None
    """``correlation_model``: the binned correlations the time constant was fitted to."""
    range_scale_coeffs: tuple = (0.0, 0.0, 0.0)
    range_scale_per_m: float = 0.0
    range_scale_no_bearing: tuple = (0.0, 0.0)
    """Mean and standard deviation of ``c0 + c1 b + c2 b^2`` over the sightings."""
    scale: dict = None
    """``_scale_report``: relative error per bearing bin, and the short tail, raw and
    corrected."""
    range_scale_state_stddev: float = 0.0
    """Root mean square of the robots' median relative range errors after the correction
    (the scale error each robot keeps), less the variance of a median (step 5)."""
    range_stddev_per_m2: float = 0.0
    """Range noise per squared metre of range [m/m^2] (step 4)."""
    camera_delay_s: float = 0.0
    """Stamp delay of the sightings [s] (step 0), removed before every other step."""
    camera_delay: dict = None
    """``camera_delay.CameraDelay.to_dict`` of step 0 (None when not estimated)."""
    range_scale_bearing_state_stddev: float = 0.0
    """Root mean square of the robots' own change of the range scale with the bearing
    [1/rad] (``range_calibration.bearing_scale_spread``, step 5)."""
    range_scale_bearing_per_robot: dict = None
    """That change per robot name [1/rad]."""
    range_scale_bearing_limit: float = 0.0
    """Half the camera's field of view: the largest bearing of a sighting [rad]."""

    def to_dict(self):
        """Return plain values for JSON."""
        return asdict(self)

    def observer_values(self, scale_bias=False):
        """
        Return the ``ObserverConfig`` fields this calibration sets, by name.

        With ``scale_bias`` the robot's shared range error is a scale error ``s r``:
        ``range_scale_bias_stddev`` is ``range_scale_state_stddev`` (the RMS of the
        robots' median relative errors) and ``range_bias_stddev`` is 0 (the same error,
        not to be counted twice); without, an offset only (step 5).
        """
        values = {name: float(getattr(self, name)) for name in OBSERVER_FIELDS}
        values['range_scale_coeffs'] = tuple(float(c) for c in self.range_scale_coeffs)
        values['range_scale_no_bearing'] = tuple(float(c) for c in self.range_scale_no_bearing)
        values['range_scale_bias_stddev'] = 0.0
        if scale_bias:
            values['range_scale_bias_stddev'] = float(self.range_scale_state_stddev)
            values['range_bias_stddev'] = 0.0
        return values

    def localizer_values(self):
        """
        Return the ``LocalizerConfig`` fields this calibration sets, by name.

        The same values as the observer's, but the robot's range error: the
        localizer estimates its own range scale error (``range_scale_state_stddev``,
        ``localizer.update``), which is what the robot medians of the range bias
        measure, so ``range_bias_stddev`` is 0 there (counting it would count the same
        error twice); the bearing bias is shared by every sighting of the robot within
        the correlation time (``Localizer``). Range-only rows of the localizer are not
        corrected.
        """
        values = {name: float(getattr(self, name)) for name in LOCALIZER_FIELDS}
        values['range_scale_coeffs'] = tuple(float(c) for c in self.range_scale_coeffs)
        values['range_bias_stddev'] = 0.0
        values['range_scale_state_stddev'] = float(self.range_scale_state_stddev)
        values['range_scale_bearing_state_stddev'] = float(
            self.range_scale_bearing_state_stddev)
        return values

    def suggested_yaml(self):
        """Return the observer lines to put in ``config/mrclam.yaml``."""
        return ('/**/landmark_observer:\n  ros__parameters:\n'
                f'    range_stddev: {self.range_stddev:.4f}\n'
                f'    range_stddev_per_m: {self.range_stddev_per_m:.4f}\n'
                f'    range_stddev_per_m2: {self.range_stddev_per_m2:.5f}\n'
                f'    bearing_stddev: {self.bearing_stddev:.4f}\n'
                f'    range_bias_stddev: {self.range_bias_stddev:.4f}\n'
                f'    # or as a scale error: range_bias_stddev: 0.0, '
                f'range_scale_bias_stddev: {self.range_scale_state_stddev:.4f}\n'
                f'    bearing_bias_stddev: {self.bearing_bias_stddev:.4f}\n'
                f'    noise_correlation_time_s: {self.noise_correlation_time_s:.1f}\n'
                f'    range_correlated_fraction: {self.range_correlated_fraction:.2f}\n'
                f'    bearing_correlated_fraction: {self.bearing_correlated_fraction:.2f}\n'
                f'    range_scale_coeffs: {_yaml_value(tuple(self.range_scale_coeffs))}\n'
                f'    range_scale_per_m: {self.range_scale_per_m:.5f}\n'
                f'    range_scale_no_bearing: [{self.range_scale_no_bearing[0]:.4f}, '
                f'{self.range_scale_no_bearing[1]:.4f}]\n'
                f'    range_scale_bearing_limit: {self.range_scale_bearing_limit:.3f}\n'
                '/**/landmark_localizer:\n  ros__parameters:\n'
                + '\n'.join(f'    {k}: {_yaml_value(v)}'
                            for k, v in self.localizer_values().items())
                + '\nlandmark_mrclam:\n  ros__parameters:\n'
                f'    camera_delay_s: {self.camera_delay_s:.3f}')


def _yaml_value(value):
    if isinstance(value, tuple):
        return '[' + ', '.join(f'{v:.4f}' for v in value) + ']'
    return f'{value:.5g}'


def measurement_errors(dataset):
    """
    Return every sighting of a landmark with a true position, with its errors.

    Returns
    -------
    dict of ndarray
        ``robot`` (index), ``id``, ``time`` [s], ``range``, ``bearing`` (the readings),
        ``range_error``, ``bearing_error`` (measured minus true, bearing wrapped), one
        entry per sighting.

    """
    columns = {key: [] for key in ('robot', 'id', 'time', 'range', 'bearing', 'range_error',
                                   'bearing_error')}
    for index, robot in enumerate(dataset.robots):
        known = np.array([i in dataset.landmarks for i in robot.ids.tolist()], dtype=bool)
        if not known.any():
            continue
        truth = np.array([dataset.landmarks[i] for i in robot.ids[known].tolist()])
        pose, z = robot.poses[known], robot.z[known]
        d = truth - pose[:, :2]
        columns['robot'].append(np.full(len(z), index))
        columns['id'].append(robot.ids[known])
        columns['time'].append(robot.times[known])
        columns['range'].append(z[:, 0])
        columns['bearing'].append(z[:, 1])
        columns['range_error'].append(z[:, 0] - np.hypot(d[:, 0], d[:, 1]))
        columns['bearing_error'].append(wrap_angle(
            z[:, 1] - (np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2])))
    return {key: (np.concatenate(value) if value else np.empty(0))
            for key, value in columns.items()}


CORRELATION_SHORT_LAG_S = 0.5
"""Consecutive sightings of one pair at most this far apart measure the white noise [s]."""

CORRELATION_LAG_EDGES_S = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
"""Lag bins [s] of the correlations the correlation time is fitted to."""


def correlation_model(key, time, residuals, max_lag_steps=400):
    """
    Split residuals into white and time-correlated noise and fit the correlation time.

    The model: each residual is ``w + c``, ``w`` white, ``c`` a first-order
    Gauss-Markov process per robot-landmark pair (``key``) holding ``fraction`` of the
    variance, correlation ``exp(-lag / tau)``. Consecutive residuals of a pair at most
    ``CORRELATION_SHORT_LAG_S`` apart differ by about ``w1 - w2``, so the white
    standard deviation is ``central_sigma`` of those differences over ``sqrt(2)`` and
    ``fraction = 1 - white^2 / total^2`` (``total`` the ``central_sigma`` of the
    residuals). The correlation of pairs of residuals (clipped at 3 ``total``) is
    binned by lag (``CORRELATION_LAG_EDGES_S``) and ``tau`` is the least-squares fit of
    ``fraction * exp(-lag / tau)`` to it, weighted by the pairs per bin, over every
    quantity at once (one correlation time for the sensor).

    Parameters
    ----------
    key : ndarray of int, shape (N,)
        Robot-landmark pair of each residual.
    time : ndarray, shape (N,) [s]
        Stamp of each residual.
    residuals : dict of str to ndarray, shape (N,)
        Per quantity (``range`` normalised by its model standard deviation, ``bearing``).
    max_lag_steps : int
        Pairs at most this many sightings apart within a pair are correlated.

    Returns
    -------
    dict
        ``fraction`` per quantity, ``tau_s``, and per quantity the bins: ``lag_s``,
        ``correlation``, ``pairs``.

    """
    order = np.lexsort((time, key))
    k, t = key[order], time[order]
    same = k[1:] == k[:-1]
    dt = np.diff(t)
    short = same & (dt > 0.0) & (dt <= CORRELATION_SHORT_LAG_S)
    edges = np.asarray(CORRELATION_LAG_EDGES_S)
    out = {'fraction': {}, 'bins': {}}
    for name, values in residuals.items():
        values = np.asarray(values, dtype=np.float64)[order]
        total = central_sigma(values)
        white = central_sigma(np.diff(values)[short]) / math.sqrt(2.0) if short.any() else total
        fraction = min(max(1.0 - (white / total) ** 2, 0.0), 0.999) if total > 0 else 0.0
        r = np.clip(values, -3.0 * total, 3.0 * total)
        num, cnt, lags = (np.zeros(len(edges) - 1) for _ in range(3))
        for step in range(1, min(max_lag_steps, len(k))):
            lag = t[step:] - t[:-step]
            b = np.digitize(lag, edges) - 1
            m = (k[step:] == k[:-step]) & (b >= 0) & (b < len(num))
            if not m.any():
                continue
            np.add.at(num, b[m], (r[step:] * r[:-step])[m])
            np.add.at(cnt, b[m], 1.0)
            np.add.at(lags, b[m], lag[m])
        with np.errstate(invalid='ignore', divide='ignore'):
            out['bins'][name] = {'lag_s': (lags / cnt).tolist(),
                                 'correlation': (num / cnt / np.mean(r * r)).tolist(),
                                 'pairs': cnt.astype(int).tolist()}
        out['fraction'][name] = float(fraction)

    def cost(log_tau):
        total = 0.0
        for name, b in out['bins'].items():
            n = np.asarray(b['pairs'], dtype=np.float64)
            ok = n > 0
            model = out['fraction'][name] * np.exp(-np.asarray(b['lag_s'])[ok] / np.exp(log_tau))
            total += float(np.sum(n[ok] * (np.asarray(b['correlation'])[ok] - model) ** 2))
        return total

    fit = minimize_scalar(cost, bounds=(math.log(0.05), math.log(600.0)), method='bounded')
    out['tau_s'] = float(math.exp(fit.x))
    return out


def _rms_bias(medians, counts, noise_variance):
    """
    Return the RMS bias: the mean of median^2 less the median's own variance.

    Each robot (or pair) is one draw of the bias, whatever its number of sightings: the
    mean is over the draws, each weighing the same.
    """
    medians, counts = np.asarray(medians), np.asarray(counts, dtype=np.float64)
    if not len(medians):
        return 0.0
    excess = medians ** 2 - (math.pi / 2.0) * np.asarray(noise_variance) / counts
    return math.sqrt(max(0.0, float(np.mean(excess))))


ROBOT_RANGE_EDGES = (0.0, 1.5, 2.5, 3.5, 4.5, 1000.0)
"""True-range bins [m] of each robot's median range error (``Calibration.robots``)."""


def _robot_medians(dataset, e):
    """Return each robot's median errors: report entries and ``((range, bearing), n)``."""
    robots, robot_medians = [], []
    true = e['range'] - e['range_error']
    for index, robot in enumerate(dataset.robots):
        mine = e['robot'] == index
        if not mine.any():
            continue
        medians = (float(np.median(e['range_error'][mine])),
                   float(np.median(e['bearing_error'][mine])))
        by_range = []
        for low, high in zip(ROBOT_RANGE_EDGES[:-1], ROBOT_RANGE_EDGES[1:]):
            sel = mine & (true >= low) & (true < high)
            by_range.append({'low': low, 'high': high, 'n': int(sel.sum()), 'median': (
                float(np.median(e['range_error'][sel])) if sel.any() else None)})
        robots.append({'robot': robot.name, 'n': int(mine.sum()),
                       'range_median': medians[0], 'bearing_median': medians[1],
                       'range_by_range': by_range})
        robot_medians.append((medians, int(mine.sum())))
    return robots, robot_medians


def calibrate(dataset, min_pair=10, bins=10, part=None, delay=True):
    """
    Estimate the observer's sensor model from ground truth.

    Procedure:

    0. Camera delay (``camera_delay.estimate_camera_delay``, with ``delay``): the shift
       of the sighting stamps that minimises the robust loss of the bearing residuals;
       every later step works on the sightings moved back by it
       (``Dataset.with_camera_delay``), as the replay does with ``camera_delay_s``.
    1. Errors. For every landmark sighting kept by the reader (barcode of a landmark,
       stamp within the robot's ground truth), the true range and bearing follow from
       the ground-truth pose interpolated at the measurement stamp (``mrclam_data``:
       position linear, heading on the shortest arc) and the true landmark position:
       ``range_error = r - |m - p|``, ``bearing_error = wrap(b - (atan2(m - p) - theta))``.
    2. Overall statistics of the raw errors, per quantity: mean, plain standard
       deviation, median, robust standard deviation ``1.4826 * median(|e - median(e)|)``
       (the MAD, which outliers barely move) and the tail: the fraction of errors more
       than 3 robust standard deviations from the median (0.27 % for Gaussian errors).
    2b. Range scale (``range_calibration.remove_range_scale``): the relative range
       error against bearing and range, ``core.range_scale``'s model, fitted by a
       robust regression (``fit_range_scale``); the ranges are corrected with it and
       every later step works on the corrected ranges. The mean and standard
       deviation of the bearing part over the sightings are the model of a range-only
       row (``range_scale_no_bearing``).
    3. Bias model. The median error of every robot: an error shared by all sightings
       of a robot (camera mounting and calibration) does not average out when its
       sightings are fused, so these medians measure the bias the observer's
       ``*_bias_stddev`` (the dependent part) must cover. The medians of every
       robot-landmark pair with at least ``min_pair`` sightings are printed too: their
       spread is larger, but most of it depends on the viewing geometry and averages
       out over a robot's passes.
    4. Independent noise. Residuals: each error minus its robot's median. They have
       heavy tails (step 6), so the noise is the Gaussian that holds the same central
       ``CENTRAL_MASS`` (99 %) of the residuals, ``quantile(|res|, 0.99) / 2.576``
       (``central_sigma``): a fit to the core alone (the MAD) would make the moderate
       tail look like outliers to the fuser's gate; the far 1 % is left to the gate.
       Range residuals are split into ``bins`` bins of equal counts by range
       (``range_calibration.range_noise_bins``); per bin that standard deviation at
       the median range of the bin; then a least-squares fit of
       ``sigma_r(r)^2 = a^2 + (k r)^2 + (c r^2)^2`` over the bins (weights
       ``n / sigma^4``: relative errors of the bin variances; ``a^2, k^2, c^2 >= 0``;
       ``range_calibration.fit_range_noise``) gives ``range_stddev = a``,
       ``range_stddev_per_m = k`` and ``range_stddev_per_m2 = c``. ``bearing_stddev`` is the
       same standard deviation of all bearing residuals.
    5. Bias standard deviations: the root mean square of the robot medians, each
       robot one draw of the bias whatever its number of sightings (a robot's bias is
       shared by all its sightings; weighted by sightings, a robot seen little would
       hardly count), less the variance of a median of ``n`` noisy errors,
       ``(pi / 2) sigma^2 / n`` with ``sigma`` from step 4: ``range_bias_stddev`` and
       ``bearing_bias_stddev``. The same over the pair medians is printed for
       comparison. The same over the robots' median relative range errors (range
       error / true range) is ``range_scale_state_stddev``: the prior of the range
       scale error the localizer estimates per robot, and the observer's
       ``range_scale_bias_stddev`` when a robot's shared range error is modelled as a
       scale error (``Calibration.observer_values``; ``range_bias_stddev`` is then 0:
       what an offset would leave after each robot's median relative error is zero
       by construction, the median of ``b - b r / median(r)``). Each robot's own
       change of that error with the bearing gives ``range_scale_bearing_state_stddev``
       (``range_calibration.bearing_scale_spread``), the prior of the localizer's fifth
       state.
    6. Tails: the fraction of residuals beyond 3 model standard deviations
       (``sigma_r(r)``, ``bearing_stddev``); well above 0.27 % means heavy tails,
       which the gate of the fuser (``gate_probability``) has to reject.
    7. Time correlation (``correlation_model``): the residuals of step 4 (ranges
       divided by ``sigma_r(r)``) per robot-landmark pair, split into white noise and
       a first-order Gauss-Markov part: ``range_correlated_fraction``,
       ``bearing_correlated_fraction`` and ``noise_correlation_time_s``. The errors of
       consecutive sightings are far from independent (the viewing geometry, the
       camera latency while the robot turns): a fuser that treats thousands of views
       as independent becomes over-confident (``fuser.partial.CorrelatedNoise``).

    Parameters
    ----------
    dataset : mrclam_data.Dataset
        Loaded dataset with ground truth.
    min_pair : int
        Sightings a robot-landmark pair needs for steps 3-5.
    bins : int
        Range bins of step 4.
    part : mrclam_data.Part, optional
        Calibrate on this time slice and robot subset only (``Dataset.part``); None
        uses every sighting.
    delay : bool
        Estimate and remove the camera delay first (step 0); False takes the stamps
        as they are (a dataset already moved by ``with_camera_delay``).

    Returns
    -------
    Calibration

    Raises
    ------
    ValueError
        If there are too few sightings.

    """
    if part is not None:
        dataset = dataset.part(part)
    camera_delay = estimate_camera_delay(dataset) if delay else None
    if camera_delay is not None:
        dataset = dataset.with_camera_delay(camera_delay.delay_s)
    e = measurement_errors(dataset)
    count = len(e['range'])
    if count < max(2 * bins, min_pair):
        raise ValueError(f'{count} sightings of known landmarks: too few to calibrate')
    overall = {}
    for name in ('range', 'bearing'):
        err = e[f'{name}_error']
        sd = robust_sigma(err)
        overall[name] = {'n': count, 'mean': float(np.mean(err)), 'std': float(np.std(err)),
                         'median': float(np.median(err)), 'robust_sd': sd,
                         'tail_3sd': float(np.mean(np.abs(err - np.median(err)) > 3 * sd))}
    e, scale_coeffs, scale_per_m, scale = remove_range_scale(e)
    robots, robot_medians = _robot_medians(dataset, e)
    # Pairs: robot-landmark combinations with enough sightings.
    pair_key = e['robot'].astype(np.int64) * (int(e['id'].max()) + 1) + e['id'].astype(np.int64)
    keys, inverse, sizes = np.unique(pair_key, return_inverse=True, return_counts=True)
    pair_range_median = np.array([np.median(e['range_error'][inverse == p])
                                  for p in range(len(keys))])
    pair_bearing_median = np.array([np.median(e['bearing_error'][inverse == p])
                                    for p in range(len(keys))])
    big = sizes >= min_pair
    if not big.any():
        raise ValueError(f'no robot-landmark pair has {min_pair} sightings')
    robot_median_r = np.zeros(len(dataset.robots))
    robot_median_b = np.zeros(len(dataset.robots))
    for index in np.unique(e['robot']).astype(int):
        mine = e['robot'] == index
        robot_median_r[index] = np.median(e['range_error'][mine])
        robot_median_b[index] = np.median(e['bearing_error'][mine])
    robot_index = e['robot'].astype(int)
    res_r = e['range_error'] - robot_median_r[robot_index]
    res_b = e['bearing_error'] - robot_median_b[robot_index]
    ranges = e['range']
    # Range noise against range: central spread per bin of equal counts, then the fit.
    range_bins = range_noise_bins(ranges, res_r, central_sigma, bins)
    a, k, c = fit_range_noise([b['range'] for b in range_bins],
                              [b['robust_sd'] for b in range_bins],
                              [b['n'] for b in range_bins])
    for b in range_bins:
        b['model_sd'] = math.sqrt(a * a + (k * b['range']) ** 2 + (c * b['range'] ** 2) ** 2)
    sigma_b = central_sigma(res_b)
    # Biases: robot medians (the model) and pair medians (for comparison), less the
    # variance of a median of noisy errors.
    noise_r = a * a + (k * ranges) ** 2 + (c * ranges ** 2) ** 2
    mean_noise_r = float(np.mean(noise_r))
    range_bias = _rms_bias([m[0] for m, _ in robot_medians],
                           [n for _, n in robot_medians],
                           np.full(len(robot_medians), mean_noise_r))
    bearing_bias = _rms_bias([m[1] for m, _ in robot_medians],
                             [n for _, n in robot_medians],
                             np.full(len(robot_medians), sigma_b ** 2))
    pair_noise_r = np.array([np.mean(noise_r[inverse == p]) for p in np.flatnonzero(big)])
    pair_range = _rms_bias(pair_range_median[big], sizes[big], pair_noise_r)
    pair_bearing = _rms_bias(pair_bearing_median[big], sizes[big],
                             np.full(int(big.sum()), sigma_b ** 2))
    model_r = np.sqrt(noise_r)
    state_sd = _scale_spread(e, model_r)
    bearing_sd, slopes = bearing_scale_spread(e)
    tails = {'range': float(np.mean(np.abs(res_r) > 3.0 * model_r)),
             'bearing': float(np.mean(np.abs(res_b) > 3.0 * sigma_b))}
    correlation = correlation_model(pair_key, e['time'], {'range': res_r / model_r,
                                                          'bearing': res_b})
    return Calibration(count, overall, robots, int(big.sum()), range_bins, a, k, sigma_b,
                       range_bias, bearing_bias, pair_range, pair_bearing, tails,
                       correlation['fraction']['range'], correlation['fraction']['bearing'],
                       correlation['tau_s'], correlation, scale_coeffs, scale_per_m,
                       scale['no_bearing'], scale, state_sd, c,
                       0.0 if camera_delay is None else camera_delay.delay_s,
                       None if camera_delay is None else camera_delay.to_dict(), bearing_sd,
                       {dataset.robots[i].name: c1 for i, c1 in slopes.items()},
                       scale['bearing_limit'])


def _scale_spread(e, model_r):
    """Return the RMS of the robots' median relative range errors (``Calibration``)."""
    rel = e['range_error'] / (e['range'] - e['range_error'])
    noise = np.mean(np.square(model_r / e['range']))
    index = e['robot'].astype(int)
    robots = np.unique(index)
    return _rms_bias([float(np.median(rel[index == i])) for i in robots],
                     [int(np.sum(index == i)) for i in robots], np.full(len(robots), noise))


def _bin_label(b):
    return f'>{b["low"]:g} m' if b['high'] >= ROBOT_RANGE_EDGES[-1] else \
        f'{b["low"]:g}-{b["high"]:g} m'


def format_calibration(cal):
    """Return the calibration printout."""
    lines = [f'== calibration from {cal.count} landmark sightings against ground truth']
    if cal.camera_delay:
        lines.append(format_camera_delay(CameraDelay(**cal.camera_delay)) + '; every figure '
                     'below is of the sightings moved back by it')
    lines += [f"{'error':<8} {'mean':>9} {'std':>9} {'median':>9} {'robust sd':>10} "
              f"{'> 3 rsd':>8}"]
    for name, unit in (('range', 'm'), ('bearing', 'rad')):
        o = cal.overall[name]
        lines.append(f'{name:<8} {o["mean"]:9.4f} {o["std"]:9.4f} {o["median"]:9.4f} '
                     f'{o["robust_sd"]:10.4f} {100 * o["tail_3sd"]:7.2f}%   [{unit}]')
    if cal.scale:
        c0, c1, c2 = cal.range_scale_coeffs
        lines.append('range scale (reading = true range x g, g = 1 + c0 + c1 b + c2 b^2 + k r; '
                     f'robust fit): c0 {c0:+.4f}, c1 {c1:+.4f} /rad, c2 {c2:+.4f} /rad^2, '
                     f'k {cal.range_scale_per_m:+.5f} /m; relative residual sd '
                     f'{cal.scale["relative_sd"]:.4f}')
        lines.append(f"  {'bearing [rad]':>15} {'n':>6} {'median rel. error':>18} "
                     f"{'corrected':>10} {'rsd':>7} {'corrected':>10}")
        for b in cal.scale['bearing_bins']:
            lines.append(f'  {b["low"]:+6.2f} - {b["high"]:+5.2f} {b["n"]:6d} {b["raw"]:+18.4f} '
                         f'{b["corrected"]:+10.4f} {b["raw_sd"]:7.4f} {b["corrected_sd"]:10.4f}')
        t = cal.scale['short_tail']
        lines.append(f'  readings more than {SHORT_TAIL_M} m short: {100 * t["raw"]:.2f} % raw, '
                     f'{100 * t["corrected"]:.2f} % corrected (beyond 3 m: '
                     f'{100 * t["raw_beyond_3m"]:.2f} %, {100 * t["corrected_beyond_3m"]:.2f} %)')
        lines.append('  (every figure below is of the corrected ranges)')
    lines.append('per robot median error:')
    for r in cal.robots:
        lines.append(f'  {r["robot"]:<8} n {r["n"]:6d}  range {r["range_median"]:+8.4f} m  '
                     f'bearing {r["bearing_median"]:+8.4f} rad; range by true range: '
                     + ', '.join(f'{_bin_label(b)} {100 * b["median"]:+.1f} cm'
                                 for b in r.get('range_by_range', ()) if b['n']))
    lines.append('range residual spread (error minus its robot median; sd of the Gaussian '
                 f'holding the central {100 * CENTRAL_MASS:.0f} %) against range:')
    lines.append(f"  {'range [m]':>15} {'median':>7} {'n':>6} {'central sd':>10} {'model':>8}")
    for b in cal.range_bins:
        lines.append(f'  {b["low"]:6.2f} - {b["high"]:6.2f} {b["range"]:7.2f} {b["n"]:6d} '
                     f'{b["robust_sd"]:10.4f} {b["model_sd"]:8.4f}')
    lines.append('fit sigma_r(r)^2 = a^2 + (k r)^2 + (c r^2)^2: '
                 f'a = {cal.range_stddev:.4f} m, k = {cal.range_stddev_per_m:.4f} m/m, '
                 f'c = {cal.range_stddev_per_m2:.5f} m/m^2; bearing sd '
                 f'{cal.bearing_stddev:.4f} rad')
    lines.append(f'bias (RMS of robot medians, less their noise): range '
                 f'{cal.range_bias_stddev:.4f} m, bearing {cal.bearing_bias_stddev:.4f} rad; '
                 f'of the {cal.pairs} robot-landmark pair medians, for comparison: range '
                 f'{cal.pair_range_bias_rms:.4f} m, bearing {cal.pair_bearing_bias_rms:.4f} rad')
    if cal.range_scale_bearing_per_robot:
        lines.append('per robot range scale (RMS of the robot medians, less their noise) '
                     f'{cal.range_scale_state_stddev:.4f}; its change with the bearing '
                     f'{cal.range_scale_bearing_state_stddev:.4f} /rad (per robot: ' + ', '.join(
                         f'{name} {c1:+.4f}' for name, c1 in
                         cal.range_scale_bearing_per_robot.items()) + ')')
    lines.append(f'residuals beyond 3 model sd: range {100 * cal.residual_tails["range"]:.2f}%, '
                 f'bearing {100 * cal.residual_tails["bearing"]:.2f}% (Gaussian: 0.27%)')
    lines.append('time correlation (white + first-order Gauss-Markov per robot-landmark pair): '
                 f'correlated share of the variance: range {cal.range_correlated_fraction:.2f}, '
                 f'bearing {cal.bearing_correlated_fraction:.2f}; correlation time '
                 f'{cal.noise_correlation_time_s:.1f} s')
    lines.append('suggested values:')
    lines.append(cal.suggested_yaml())
    return '\n'.join(lines)
