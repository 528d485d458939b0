"""
The range scale error of a MRCLAM camera, estimated from ground truth (ROS-free).

The camera reads a barcode's range from its apparent size; lens distortion changes the
apparent size off the optical axis, so the range error depends on where the barcode is
in the image (the bearing), and slightly on the range (``core.range_scale`` has the
model). ``fit_range_scale`` estimates the model from readings and true ranges;
``remove_range_scale`` applies it to the errors ``mrclam.calibrate`` starts from, and
reports what it removes. On the corrected ranges, ``range_noise_bins`` and
``fit_range_noise`` estimate the range noise against range.
"""

import math

from landmark_ros.core import range_scale
import numpy as np
from scipy.optimize import nnls

MAD_TO_SIGMA = 1.4826
"""Median absolute deviation to standard deviation, for Gaussian data."""


def robust_sigma(values):
    """Return 1.4826 times the median absolute deviation from the median (NaN if empty)."""
    values = np.asarray(values, dtype=np.float64)
    if not len(values):
        return float('nan')
    return float(MAD_TO_SIGMA * np.median(np.abs(values - np.median(values))))


HUBER_K = 2.0
"""Huber's tuning constant of ``fit_range_scale``, in robust standard deviations."""

BISQUARE_C = 4.685
"""Tukey's bisquare tuning constant of ``fit_range_scale`` (95 % Gaussian efficiency)."""


def _robust_weights(e, huber):
    """Return IRLS weights of residuals ``e`` and their robust standard deviation."""
    sigma = max(robust_sigma(e), 1e-12)
    if huber:
        return np.minimum(1.0, HUBER_K * sigma / np.maximum(np.abs(e), 1e-300)), sigma
    u = e / (BISQUARE_C * sigma)
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0), sigma


def fit_range_scale(r, b, r_true, iterations=30):
    """
    Estimate the range scale error ``core.range_scale`` from readings and true ranges.

    The relative error of a reading, ``r / r_true - 1 = c0 + c1 b + c2 b^2 + k r + e``,
    is linear in the coefficients: a robust linear regression by iteratively
    reweighted least squares, so that the far tail of the readings (far too short
    ones: another barcode, a partly hidden one) does not pull the fit. The first
    ``iterations`` rounds use Huber's weights (Huber 1964; ``min(1, K s / |e|)``,
    ``K = HUBER_K``), which converge from the least-squares start; the same number of
    rounds then use Tukey's bisquare (``(1 - (e / (C s))^2)^2`` inside ``C s``, else 0,
    ``C = BISQUARE_C``), which gives the tail no weight at all (an M-estimator with a
    redescending function started from a robust fit, as in Maronna, Martin and
    Yohai, "Robust Statistics", 2006, ch. 4-5). ``s`` is the MAD-based standard
    deviation of the residuals, re-estimated every round.

    Parameters
    ----------
    r : ndarray, shape (N,)
        Range readings [m].
    b : ndarray, shape (N,)
        Bearing readings [rad] (the position in the image).
    r_true : ndarray, shape (N,)
        True ranges [m], positive.
    iterations : int
        Rounds of each weight function (each stops early when the coefficients
        settle to 1e-10); 1 gives plain least squares then one reweighting.

    Returns
    -------
    coeffs : tuple of 3 float
        ``(c0, c1, c2)``.
    per_m : float
        ``k`` [1/m].
    sigma : float
        Robust standard deviation of the relative residuals.

    Raises
    ------
    ValueError
        With fewer than 4 readings.

    """
    r, b, r_true = (np.asarray(v, dtype=np.float64).reshape(-1) for v in (r, b, r_true))
    if len(r) < 4:
        raise ValueError(f'{len(r)} readings: at least 4 are needed to fit the range scale')
    y = r / r_true - 1.0
    A = np.stack([np.ones_like(b), b, b * b, r], axis=1)
    w = np.ones_like(y)
    theta = np.zeros(4)
    for huber in (True, False):
        for step in range(iterations):
            sw = np.sqrt(w)
            new, *_ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)
            done = step > 0 and np.max(np.abs(new - theta)) < 1e-10
            theta = new
            w, sigma = _robust_weights(y - A @ theta, huber)
            if done:
                break
    return (float(theta[0]), float(theta[1]), float(theta[2])), float(theta[3]), sigma


SHORT_TAIL_M = 0.3
"""A reading this much shorter than the truth counts in the short tail [m]."""

BEARING_EDGES = (-0.6, -0.45, -0.3, -0.15, 0.0, 0.15, 0.3, 0.45, 0.6)
"""Bearing bins [rad] of the range scale report."""


def remove_range_scale(e):
    """
    Fit the range scale (``fit_range_scale``) and return the errors of corrected ranges.

    Returns ``(e, coeffs, per_m, report)``: ``e`` with ``range`` and ``range_error``
    of the corrected readings (``core.range_scale.correct``), and the report: per
    bearing bin the median relative error before and after, and the share of the
    short tail (``SHORT_TAIL_M``) before and after, overall and beyond 3 m.
    """
    true = e['range'] - e['range_error']
    coeffs, per_m, sigma = fit_range_scale(e['range'], e['bearing'], true)
    z_c, _ = range_scale.correct(np.stack([e['range'], e['bearing']], axis=1), coeffs, per_m)
    out = dict(e, range=z_c[:, 0], range_error=z_c[:, 0] - true)
    rel_raw, rel = e['range'] / true - 1.0, z_c[:, 0] / true - 1.0
    bins = []
    for low, high in zip(BEARING_EDGES[:-1], BEARING_EDGES[1:]):
        sel = (e['bearing'] >= low) & (e['bearing'] < high)
        if sel.any():
            bins.append({'low': low, 'high': high, 'n': int(sel.sum()),
                         'raw': float(np.median(rel_raw[sel])),
                         'corrected': float(np.median(rel[sel])),
                         'raw_sd': robust_sigma(rel_raw[sel]),
                         'corrected_sd': robust_sigma(rel[sel])})
    far = true > 3.0

    def too_short(err):
        return float(np.mean(err < -SHORT_TAIL_M)) if len(err) else 0.0
    short = {'raw': too_short(e['range_error']), 'corrected': too_short(out['range_error']),
             'raw_beyond_3m': too_short(e['range_error'][far]),
             'corrected_beyond_3m': too_short(out['range_error'][far])}
    s_b = coeffs[0] + e['bearing'] * (coeffs[1] + coeffs[2] * e['bearing'])
    return out, coeffs, per_m, {'bearing_bins': bins, 'short_tail': short,
                                'relative_sd': sigma,
                                'no_bearing': (float(np.mean(s_b)), float(np.std(s_b))),
                                'bearing_limit': float(np.max(np.abs(e['bearing']),
                                                              initial=0.0))}


def range_noise_bins(ranges, residuals, spread, bins=10):
    """
    Split range residuals into bins of equal counts by range and measure their spread.

    Parameters
    ----------
    ranges : ndarray, shape (N,)
        Ranges of the residuals [m].
    residuals : ndarray, shape (N,)
        Range residuals [m].
    spread : callable
        Standard deviation of an array of residuals (``calibrate.central_sigma``).
    bins : int
        Bins, at most one per 10 residuals.

    Returns
    -------
    list of dict
        Per bin, by increasing range: ``low``, ``high`` [m], ``range`` (median) [m],
        ``n`` and ``robust_sd`` (``spread`` of its residuals) [m].

    """
    ranges, residuals = np.asarray(ranges, dtype=float), np.asarray(residuals, dtype=float)
    order = np.argsort(ranges, kind='stable')
    out = []
    for chunk in np.array_split(order, min(bins, max(1, len(order) // 10))):
        if len(chunk):
            out.append({'low': float(ranges[chunk].min()), 'high': float(ranges[chunk].max()),
                        'range': float(np.median(ranges[chunk])), 'n': int(len(chunk)),
                        'robust_sd': float(spread(residuals[chunk]))})
    return out


def fit_range_noise(r, sigma, counts):
    """
    Fit ``sigma_r(r)^2 = a^2 + (k r)^2 + (c r^2)^2`` to binned spreads.

    Weighted non-negative least squares on the variances in ``(a^2, k^2, c^2)``: a
    variance estimated from ``n`` errors has a standard deviation proportional to
    ``sigma^2 / sqrt(n)``, so the weights are ``n / sigma^4`` (relative errors count,
    and the short ranges are not drowned by the long ones). The constant term is the
    noise of reading the barcode's edges, the linear one an error of its apparent size
    in pixels (the range goes as 1 / size), the quadratic one what grows faster at
    long range (a barcode a few pixels wide, blur). With fewer than 3 bins only ``a``
    and ``k`` are fitted.

    Parameters
    ----------
    r : array_like, shape (B,)
        Range of each bin [m].
    sigma : array_like, shape (B,)
        Standard deviation of the bin's residuals [m].
    counts : array_like, shape (B,)
        Residuals per bin.

    Returns
    -------
    a : float
        Constant part [m] (``range_stddev``).
    k : float
        Part per metre [m/m] (``range_stddev_per_m``).
    c : float
        Part per squared metre [m/m^2] (``range_stddev_per_m2``).

    Raises
    ------
    ValueError
        Without any bin.

    """
    r2 = np.asarray(r, dtype=float) ** 2
    s2 = np.asarray(sigma, dtype=float) ** 2
    if not len(r2):
        raise ValueError('no range bin to fit the range noise to')
    sw = np.sqrt(np.asarray(counts, dtype=float) / np.maximum(s2, 1e-300) ** 2)
    columns = [np.ones_like(r2), r2, r2 * r2][:3 if len(r2) >= 3 else 2]
    solution, _ = nnls(np.stack(columns, axis=1) * sw[:, None], s2 * sw)
    a2, k2, c2 = (list(solution) + [0.0])[:3]
    return math.sqrt(a2), math.sqrt(k2), math.sqrt(c2)


def bearing_scale_spread(e, min_sightings=50):
    """
    Return the spread of the robots' own change of the range scale with the bearing.

    After the shared correction (``remove_range_scale``) each robot's relative range
    errors are fitted again (``fit_range_scale``: ``c0 + c1 b + c2 b^2 + k r``); its
    ``c1`` [1/rad] is what its own lens adds (MRCLAM dataset 6: robot 5 -0.037, the
    others -0.000 to +0.017, each the same in both halves of the run). Returns the root
    mean square of the robots' ``c1`` less the variance of a least-squares slope,
    ``sigma^2 / (n var(b))`` (each robot one draw, as ``_rms_bias``): the prior standard
    deviation of the localizer's ``range_scale_bearing_state_stddev``; and the ``c1``
    per robot index. Robots with fewer than ``min_sightings`` are left out.
    """
    true = e['range'] - e['range_error']
    index = e['robot'].astype(int)
    slopes, excess = {}, []
    for robot in np.unique(index).tolist():
        mine = index == robot
        if np.count_nonzero(mine) < min_sightings:
            continue
        coeffs, _, sigma = fit_range_scale(e['range'][mine], e['bearing'][mine], true[mine])
        slopes[robot] = float(coeffs[1])
        noise = sigma ** 2 / (np.count_nonzero(mine) * np.var(e['bearing'][mine]))
        excess.append(coeffs[1] ** 2 - noise)
    return (math.sqrt(max(0.0, float(np.mean(excess)))) if excess else 0.0), slopes
