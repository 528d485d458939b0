"""
Where the camera sees each landmark, against its surveyed position.

Every sighting of a surveyed landmark is placed in the world from the robot's true pose
(``core.sensors.landmark_from_observation``, the range scale corrected as the
calibration estimated it, ``update.correct_ranges``, the stamps moved back by its
camera delay); its *apparent offset* is that placement less the surveyed position. The
sensor noise and a robot's bias average out over a landmark's many sightings from
several robots; what is left per landmark is an error no number of sightings removes
(the barcode is not where the motion-capture markers put the landmark, or it reads so
from every side). A map built from the sightings estimates the apparent position, so
against the surveyed one it keeps that offset: ``localize.SURVEYED_STDDEV`` states it
for the surveyed map a localizer uses.

``landmark_mrclam --calibrate`` prints the table (``format_offsets``): per landmark the
mean offset [m] with its standard error, the same from each half of the run, and the
RMS over the landmarks per axis, less the part the standard errors explain, with the
correlation of the halves' offsets per axis (a persistent offset repeats in both).
"""

import math

from landmark_ros.core import sensors
from landmark_ros.localizer.update import correct_ranges, RANGE_BEARING
import numpy as np

MAX_OFFSET_M = 0.5
"""Placements farther than this from the surveyed position are left out (misreadings)."""


def _placements(dataset, coeffs, per_m):
    """Return per sighting of a surveyed landmark: its ID, stamp [s] and offset (2,) [m]."""
    ids, times, offsets = [], [], []
    for robot in dataset.robots:
        known = np.array([i in dataset.landmarks for i in robot.ids.tolist()], dtype=bool)
        if not known.any():
            continue
        z, _ = correct_ranges(robot.z[known], np.full(int(known.sum()), RANGE_BEARING),
                              None, coeffs, per_m)
        good = np.all(np.isfinite(z), axis=1) & (z[:, 0] >= sensors.MIN_RANGE)
        truth = np.array([dataset.landmarks[i] for i in robot.ids[known].tolist()])
        placed = sensors.landmark_from_observation(robot.poses[known][good], z[good])
        ids.append(robot.ids[known][good])
        times.append(robot.times[known][good])
        offsets.append(placed - truth[good])
    if not ids:
        return np.empty(0, np.int64), np.empty(0), np.empty((0, 2))
    return np.concatenate(ids), np.concatenate(times), np.concatenate(offsets)


def apparent_offsets(dataset, coeffs=(0.0, 0.0, 0.0), per_m=0.0, min_rows=20):
    """
    Return each surveyed landmark's apparent offset and the summary over the landmarks.

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        Sightings (stamps already moved back by the camera delay) and ground truth.
    coeffs, per_m :
        The range scale correction (``core.range_scale``), as calibrated.
    min_rows : int
        Landmarks with fewer sightings in either half are left out.

    Returns
    -------
    dict
        ``landmarks``: per landmark ``id``, ``rows``, ``offset_m`` (2,), ``stderr_m``
        (2,), ``first_half_m``, ``second_half_m``; ``rms_m`` (2,): RMS of the offsets
        per axis, ``excess_rms_m`` (2,): the same less the standard errors' share;
        ``halves_correlation`` (2,); ``rows_used``, ``rows_left_out``.

    """
    ids, times, offsets = _placements(dataset, coeffs, per_m)
    keep = np.linalg.norm(offsets, axis=1) <= MAX_OFFSET_M
    middle = 0.5 * (times.min() + times.max()) if len(times) else 0.0
    entries = []
    for landmark_id in sorted(dataset.landmarks):
        rows = keep & (ids == landmark_id)
        first, second = rows & (times < middle), rows & (times >= middle)
        if min(first.sum(), second.sum()) < min_rows:
            continue
        o = offsets[rows]
        entries.append({'id': int(landmark_id), 'rows': int(rows.sum()),
                        'offset_m': o.mean(axis=0).tolist(),
                        'stderr_m': (o.std(axis=0) / math.sqrt(len(o))).tolist(),
                        'first_half_m': offsets[first].mean(axis=0).tolist(),
                        'second_half_m': offsets[second].mean(axis=0).tolist()})
    return {'landmarks': entries, **_summary(entries), 'rows_used': int(keep.sum()),
            'rows_left_out': int((~keep).sum())}


def _summary(entries):
    """Return the RMS, the excess RMS and the halves' correlation per axis."""
    if len(entries) < 3:
        return {'rms_m': [math.nan] * 2, 'excess_rms_m': [math.nan] * 2,
                'halves_correlation': [math.nan] * 2}
    mean = np.array([e['offset_m'] for e in entries])
    se = np.array([e['stderr_m'] for e in entries])
    first = np.array([e['first_half_m'] for e in entries])
    second = np.array([e['second_half_m'] for e in entries])
    rms = np.sqrt(np.mean(mean ** 2, axis=0))
    excess = np.sqrt(np.maximum(np.mean(mean ** 2 - se ** 2, axis=0), 0.0))
    corr = [float(np.corrcoef(first[:, k], second[:, k])[0, 1]) for k in range(2)]
    return {'rms_m': rms.tolist(), 'excess_rms_m': excess.tolist(),
            'halves_correlation': corr}


def format_offsets(result):
    """Return the table of ``apparent_offsets`` as text."""
    lines = ["landmarks' apparent offsets (sightings placed from the true poses, less the "
             'surveyed position) [cm]:',
             f'{"id":>4s} {"rows":>6s} {"x":>7s} {"y":>7s} {"se x":>6s} {"se y":>6s}  '
             f'{"1st half x, y":>14s}  {"2nd half x, y":>14s}']
    for e in result['landmarks']:
        (x, y), (sx, sy) = e['offset_m'], e['stderr_m']
        (ax, ay), (bx, by) = e['first_half_m'], e['second_half_m']
        lines.append(f'{e["id"]:4d} {e["rows"]:6d} {100 * x:7.2f} {100 * y:7.2f} '
                     f'{100 * sx:6.2f} {100 * sy:6.2f}  {100 * ax:6.2f} {100 * ay:6.2f}  '
                     f'{100 * bx:6.2f} {100 * by:6.2f}')
    rx, ry = result['rms_m']
    ex, ey = result['excess_rms_m']
    cx, cy = result['halves_correlation']
    lines.append(f'  RMS {100 * rx:.2f}, {100 * ry:.2f} cm per axis ({100 * ex:.2f}, '
                 f'{100 * ey:.2f} beyond the standard errors); halves correlate {cx:.2f} '
                 f'(x), {cy:.2f} (y); {result["rows_used"]} rows, {result["rows_left_out"]} '
                 f'farther than {MAX_OFFSET_M} m left out')
    return '\n'.join(lines)
