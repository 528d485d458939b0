"""
Cross-validation of the MRCLAM replay: calibrate on one part, evaluate on the other.

A figure on the data the sensor model was estimated from says little about data it was
not. ``cross_validate`` splits a dataset into folds (``folds``), and for each fold
estimates the observer's sensor model from the ground truth of one part
(``calibrate.calibrate`` with its ``Part``), puts every estimated value into the
observer's configuration (``calibrated_config``: the rest of the params file is kept),
moves the sightings back by the camera delay estimated on the same part
(``Dataset.with_camera_delay``; the params file's ``camera_delay_s`` is not used) and
replays the other part through the pipeline objects (``offline.run_offline``), in
every mode asked for (``MODES``). Nothing of the evaluated part reaches the
configuration.

Schemes (``folds``):

``halves`` (default)
    Two folds: calibrate on the first half of the run (by time), evaluate on the second
    half; and the reverse.
``robots``
    Leave one robot out: calibrate on every other robot, evaluate on the one left out
    (one fold per robot; each evaluated map comes from one robot's sightings).

Localization (``LOCALIZE_MODES``, ``cross_validate_localize``): the calibration of the
fold (with the camera delay estimated on the same part, by which the sightings of
landmarks and robots are moved back, ``localize_data.with_camera_delay``, as
``--localize`` does with ``camera_delay_s``) goes into the localizer's configuration as
well (``Calibration.localizer_values``: range scale,
noise, correlated shares; the odometry model of the params file is kept) and every robot
of the evaluated part localizes (``localize.run``: from its
ground-truth pose at the start of its odometry, landmark sightings only) against the
surveyed map (``localize``) or the split-CI map the fuser builds from the evaluated part
with the fold's observer calibration (``localize_fused``). With ``halves`` the robots
run the whole log and the figures count the stamps of the evaluated half only (the
estimate at a stamp uses no ground truth; the calibration saw none of that half's);
with ``robots`` the left-out robot runs alone.
"""

from dataclasses import dataclass, replace
from typing import List, Sequence

from landmark_ros.mrclam import localize
from landmark_ros.mrclam.calibrate import calibrate
from landmark_ros.mrclam.data import Part
from landmark_ros.mrclam.localize_data import with_camera_delay
from landmark_ros.mrclam.offline import run_offline
import numpy as np

MODES = {'ids': ('rb', False), 'hide_ids': ('rb', True), 'range': ('range', False),
         'bearing': ('bearing', False)}
"""Mode name -> (``sensor``, ``hide_ids``) of ``run_offline``."""

LOCALIZE_MODES = {'localize': 'surveyed', 'localize_fused': 'fused'}
"""Localization mode name -> the map (``cross_validate_localize``)."""

SCHEMES = ('halves', 'robots')
"""Values of ``folds``'s ``scheme``."""


@dataclass(frozen=True)
class Fold:
    """One fold: the part the sensor model is estimated from, and the part evaluated."""

    name: str
    calibrate_on: Part
    evaluate_on: Part


def folds(dataset, scheme='halves') -> List[Fold]:
    """
    Return the folds of a cross-validation scheme.

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        The whole dataset.
    scheme : str
        ``halves``: two folds, the first and second half of the sightings' time span;
        ``robots``: one fold per robot, that robot left out of the calibration.

    Returns
    -------
    list of Fold

    Raises
    ------
    ValueError
        For an unknown scheme, or fewer than two robots with ``robots``.

    """
    if scheme == 'halves':
        middle = dataset.duration / 2.0
        first, second = Part(end_s=middle), Part(start_s=middle)
        return [Fold('first->second', first, second), Fold('second->first', second, first)]
    if scheme == 'robots':
        numbers = tuple(r.number for r in dataset.robots)
        if len(numbers) < 2:
            raise ValueError('leave one robot out needs at least two robots')
        return [Fold(f'robot{n}', Part(robots=tuple(m for m in numbers if m != n)),
                     Part(robots=(n,))) for n in numbers]
    raise ValueError(f'scheme must be one of {SCHEMES}, got {scheme!r}')


def calibrated_config(config, calibration):
    """Return ``config`` with every observer value the calibration estimates replaced."""
    scale_bias = config.observer.range_scale_bias_stddev > 0.0  # the params file's model
    return replace(config, observer=replace(config.observer,
                                            **calibration.observer_values(scale_bias)))


def cross_validate(dataset, config, modes: Sequence[str], methods: Sequence[str],
                   scheme='halves', progress=None) -> List[dict]:
    """
    Calibrate on one part and evaluate on the other, for every fold, mode and method.

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        The whole dataset.
    config : mrclam.config.ReplayConfig
        The params file; its observer's calibrated values are replaced per fold.
    modes : sequence of str
        Keys of ``MODES``.
    methods : sequence of str
        Fusion methods.
    scheme : str
        See ``folds``.
    progress : callable, optional
        Called with each entry as soon as it is ready (printing).

    Returns
    -------
    list of dict
        One entry per fold, mode and method: ``fold``, ``calibrated_on``,
        ``evaluated_on``, ``mode``, ``fusion``, ``calibration`` (the observer values
        used), ``camera_delay_s`` (the delay applied) [s], ``rmse_m``, ``anees``,
        ``anees_interval``, ``consistent``, ``landmarks_fused``, ``observations_used``,
        ``observations_rejected``, and with ``hide_ids`` the association scores
        (``association_accuracy``, ``oracle_accuracy``, ``tracks_confirmed``,
        ``true_landmarks``, ``gospa_m``), and with change detection ``move_alarms`` and
        ``move_tested_rows``.

    """
    entries = []
    for fold in folds(dataset, scheme):
        calibration = calibrate(dataset, part=fold.calibrate_on)
        fold_config = calibrated_config(config, calibration)
        delay_s = calibration.camera_delay_s
        evaluated = dataset.with_camera_delay(delay_s).part(fold.evaluate_on)
        for mode in modes:
            sensor, hide_ids = MODES[mode]
            run = run_offline(evaluated, fold_config, methods, sensor=sensor,
                              hide_ids=hide_ids)
            for method, result in run.results.items():
                summary = result.to_dict()
                del summary['landmarks']
                entry = {'fold': fold.name, 'calibrated_on': fold.calibrate_on.label(),
                         'evaluated_on': fold.evaluate_on.label(), 'mode': mode,
                         'calibration': calibration.observer_values(
                             config.observer.range_scale_bias_stddev > 0.0),
                         'camera_delay_s': delay_s, **summary}
                entries.append(entry)
                if progress is not None:
                    progress(entry)
    return entries


def format_entry(entry) -> str:
    """Return one line of the cross-validation table."""
    low, high = entry['anees_interval']
    rmse = entry['rmse_m']
    line = (f"{entry['fold']:<14} {entry['mode']:<9} {entry['fusion']:<30} "
            f"{_fmt(rmse, 100.0)} {_fmt(entry['anees'])} "
            f"{f'[{_fmt(low).strip()}, {_fmt(high).strip()}]':>15} "
            f"{'yes' if entry['consistent'] else 'no':>4} {entry['landmarks_fused']:5d}")
    if 'association_accuracy' in entry:
        line += (f"  assoc {100 * entry['association_accuracy']:.1f}% "
                 f"(oracle {100 * entry['oracle_accuracy']:.1f}%), tracks "
                 f"{entry['tracks_confirmed']}/{entry['true_landmarks']}")
    if 'move_alarms' in entry:
        line += f"  moved {entry['move_alarms']}/{entry['move_tested_rows']}"
    return line


def _fmt(value, scale=1.0):
    return f"{'-':>8}" if value is None else f'{scale * value:8.2f}'


HEADER = (f"{'fold':<14} {'mode':<9} {'fusion':<30} {'RMSE[cm]':>8} {'ANEES':>8} "
          f"{'95 % interval':>15} {'ok':>4} {'lms':>5}")
"""Heading of the ``format_entry`` lines."""


def cross_validate_localize(dataset, extras, config, localizer, modes: Sequence[str],
                            scheme='halves', progress=None) -> List[dict]:
    """
    Cross-validate ``--localize``: calibrate on one part, localize and score the other.

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        The whole dataset.
    extras : dict
        ``localize_data.RobotExtras`` by robot number (odometry, robot sightings).
    config : mrclam.config.ReplayConfig
        The params file (the fused map's observer and fuser).
    localizer : tuple (LocalizerConfig, float)
        The localizer section of the params file and the odometry delay [s]; the
        calibrated values of each fold replace the sensor model's.
    modes : sequence of str
        Keys of ``LOCALIZE_MODES``.
    scheme : str
        See ``folds``.
    progress : callable, optional
        Called with each entry as soon as it is ready.

    Returns
    -------
    list of dict
        One entry per fold and mode: ``fold``, ``calibrated_on``, ``evaluated_on``,
        ``mode``, ``map``, ``calibration`` (the localizer values used), the
        ``localize.KEYS`` overall, ``consistent`` (every robot), and ``robots`` (per
        robot the same keys and ``robot``).

    """
    base, delay_s = localizer
    entries = []
    origin = dataset.time_span[0]
    for fold in folds(dataset, scheme):
        calibration = calibrate(dataset, part=fold.calibrate_on)
        values = calibration.localizer_values()
        fold_config = replace(base, **values)
        delayed, delayed_extras = with_camera_delay(dataset, extras,
                                                    calibration.camera_delay_s)
        evaluated = delayed.part(fold.evaluate_on)
        runner = delayed if scheme == 'halves' else evaluated
        window = (origin + fold.evaluate_on.start_s, origin + fold.evaluate_on.end_s)
        for mode in modes:
            name = LOCALIZE_MODES[mode]
            if name == 'surveyed':
                the_map = localize.surveyed_map(dataset)
            else:
                the_map = _fused_map(evaluated, calibrated_config(config, calibration))
            tracks = localize.run(runner, delayed_extras, fold_config, the_map, False,
                                  delay_s)
            robots, overall = localize.metrics([_in_window(t, window) for t in tracks])
            entry = {'fold': fold.name, 'calibrated_on': fold.calibrate_on.label(),
                     'evaluated_on': fold.evaluate_on.label(), 'mode': mode, 'map': name,
                     'calibration': {k: (list(v) if isinstance(v, tuple) else v)
                                     for k, v in values.items()},
                     'camera_delay_s': calibration.camera_delay_s,
                     **overall, 'consistent': all(map(localize.consistent, robots)),
                     'robots': robots}
            entries.append(entry)
            if progress is not None:
                progress(entry)
    return entries


def _fused_map(dataset, config):
    """Return ids, m, P_m of the split-CI map the offline replay builds from ``dataset``."""
    method = 'split_covariance_intersection'
    records = run_offline(dataset, config, [method]).results[method].records
    ids = np.array([r['id'] for r in records], np.int64)
    m = np.array([r['mean'] for r in records], dtype=np.float64).reshape(-1, 2)
    P = np.array([r['covariance'] for r in records], dtype=np.float64).reshape(-1, 2, 2)
    return ids, m, P


def _in_window(track, window):
    """Return the track restricted to the stamps in ``[start, end)`` [s]."""
    keep = (track.times >= window[0]) & (track.times < window[1])
    return replace(track, times=track.times[keep], x=track.x[keep], P=track.P[keep],
                   truth=track.truth[keep])


def format_localize_entry(entry) -> str:
    """Return the lines of one localization fold: overall, then per robot."""
    lines = []
    for row in [dict(entry, robot='all')] + entry['robots']:
        lines.append(f"{entry['fold']:<14} {entry['mode']:<15} {str(row['robot']):>5} "
                     f"{row['position_rmse_m']:9.3f} {row['heading_rmse_rad']:9.4f} "
                     f"{row['anees']:7.2f} {row['inside_95_fraction']:7.3f} "
                     f"{'yes' if localize.consistent(row) else 'no':>4}")
    return '\n'.join(lines)


LOCALIZE_HEADER = (f"{'fold':<14} {'mode':<15} {'robot':>5} {'pos RMSE':>9} {'yaw RMSE':>9} "
                   f"{'ANEES':>7} {'in 95%':>7} {'ok':>4}")
"""Heading of the ``format_localize_entry`` lines."""
