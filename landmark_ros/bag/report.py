"""
The fused map of a processed bag against its ground truth, as the MRCLAM replay reports it.

``evaluate_map`` gives the replay's summary entry (``landmark_mrclam --json``): fusion,
RMSE, average NEES and its 95 % interval, the landmarks fused, the observations used and
rejected, and per landmark its estimate, error, NEES and observation count
(``landmark_ros.eval.metrics``).
"""

import math

from landmark_ros.eval import metrics
import numpy as np


def _number(value):
    return None if value is None or not math.isfinite(value) else float(value)


def evaluate_map(fuser, truth):
    """
    Evaluate the fuser's confirmed map against true landmark positions.

    Parameters
    ----------
    fuser : landmark_ros.fuser.fuser.Fuser
        The fuser after the bag.
    truth : dict
        ``id -> (x, y)`` [m].

    Returns
    -------
    entry : dict
        ``fusion``, ``rmse_m``, ``anees``, ``anees_interval``, ``consistent``,
        ``landmarks_fused``, ``observations_used``, ``observations_rejected`` and
        ``landmarks`` (``id``, ``x``, ``y``, ``cov``, ``error_m``, ``nees``,
        ``observations``, ``rejections``), in the replay's JSON form.
    results : list of landmark_ros.eval.metrics.LandmarkResult
    summary : landmark_ros.eval.metrics.Summary

    """
    records = sorted(fuser.map.to_records(), key=lambda r: r['id'])
    ids = np.array([r['id'] for r in records], dtype=np.int64)
    m = np.array([r['mean'] for r in records], dtype=np.float64).reshape(-1, 2)
    P = np.array([r['covariance'] for r in records], dtype=np.float64).reshape(-1, 2, 2)
    results, summary = metrics.evaluate(ids, m, P, truth, [r['observations'] for r in records],
                                        [r.get('rejections', 0) for r in records])
    by_id = {r.id: r for r in results}
    used = sum(source.counts['fused'] for source in fuser.sources.values())
    rejected = sum(source.counts['gated_out'] for source in fuser.sources.values())
    landmarks = []
    for record, mean, cov in zip(records, m, P):
        result = by_id.get(record['id'])
        landmarks.append({
            'id': int(record['id']), 'x': float(mean[0]), 'y': float(mean[1]),
            'cov': cov.tolist(),
            'error_m': None if result is None else result.error_m,
            'nees': None if result is None else result.nees,
            'observations': int(record['observations']),
            'rejections': int(record.get('rejections', 0))})
    low, high = summary.anees_interval
    entry = {'fusion': fuser.config.fusion, 'rmse_m': _number(summary.rmse_m),
             'anees': _number(summary.anees), 'anees_interval': [_number(low), _number(high)],
             'consistent': bool(summary.consistent), 'landmarks_fused': len(records),
             'observations_used': int(used), 'observations_rejected': int(rejected),
             'landmarks': landmarks}
    return entry, results, summary


def format_report(entry, results, summary):
    """Return the per-landmark table and the summary line of one evaluation."""
    table = metrics.format_table(
        results, summary, f"== {entry['fusion']}: {entry['landmarks_fused']} landmarks, "
        f"{entry['observations_used']} observations fused, "
        f"{entry['observations_rejected']} rejected")
    return table
