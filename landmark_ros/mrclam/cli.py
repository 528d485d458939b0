"""
landmark_mrclam: replay a UTIAS MRCLAM dataset through the landmark pipeline.

Real data (5 robots reading barcodes on 15 landmarks, with Vicon ground truth) through
the same code as the nodes, then the fused maps against the true landmark positions::

    landmark_mrclam [DATASET] [--config config/mrclam.yaml] [--fusion METHOD]
                    [--through-nodes [--no-progress] [--keep-logs] [--domain-id N]]
                    [--json FILE] [--plot FILE] [--calibrate]

``DATASET`` is a MRCLAM directory (default: ``shared/data/mrclam/dataset6`` beside the
repository). Sightings, poses and ground truth come from ``landmark_ros.mrclam.data``:
landmark sightings only, each with the ground-truth pose interpolated at its stamp and
the covariance ``pose_stddev_*`` of the ``landmark_mrclam`` section of the config.

Modes
-----
offline (default)
    Per robot, the rows go through ``observations.landmarks_from_rows`` (vectorised
    over all rows of the robot with per-row poses: the same numbers as one call per
    observation cloud), then through ``LandmarkMap.update`` in global time order
    (ties by robot number; calls of ``FUSE_CHUNK`` rows, the same map as row by row),
    ``source`` the robot's landmark topic ``/robotN/landmarks``, ``stamp`` the
    measurement time: what ``landmark_observer`` and ``landmark_fuser`` compute. One
    map per fusion method, all three unless ``--fusion`` names one.
``--through-nodes``
    The same data over DDS (loopback only, private ROS_DOMAIN_ID 100-149 from the
    process ID unless ``--domain-id``) through the real nodes, in processes started by
    ``landmark_ros.demo.launcher``: one ``landmark_observer`` per robot (namespace
    ``robotN``) and one ``landmark_fuser`` per fusion method, all running at once on
    the same observer outputs (namespace ``/mrclam/METHOD``), all with
    ``--params-file`` the config file, plus the transport overrides printed at start
    (``OBSERVER_TRANSPORT``, ``FUSER_TRANSPORT``: depths, periods, topics, method).
    A player in this process publishes, in global time order, each observation cloud
    (``schemas.observation_message``) right after the robot's pose at exactly its
    stamp (the interpolated ground truth), so the observer uses that very pose. Flow
    control makes the fused result the offline one (see ``Player``): reliable QoS
    everywhere (the observers' inputs through their QoS override parameters), a bounded
    number of clouds in flight per observer, paced by the observers' ``landmarks``
    outputs, and a barrier through every fuser's executor before a cloud whose
    landmarks another robot saw last, so every fuser takes the rows of each landmark in
    global time order. Then each fuser's map (``fused_landmarks``, transient local),
    its ``~/save`` file (per-landmark rejections) and ``/diagnostics`` are read, and the
    result is compared with the offline run: same landmarks, observation and rejection
    counts, means and covariances equal to float rounding (the pose heading goes
    through a quaternion: about 1e-16 rad; on dataset6 the means agree to 3e-15 m).
    Without the barrier the fusers see some rows of a landmark in another order, and
    the maps differ by millimetres to centimetres (covariance intersection).
``--calibrate``
    Estimate the sensor model from ground truth and print suggested YAML values
    (``calibrate`` documents the procedure).

Output
------
Per method the per-landmark table (``evaluation.format_table``), RMSE, average NEES
with its 95 % interval, then a summary table, one row per method.

``--json FILE`` writes one object::

    {"mode": "offline" | "through_nodes",
     "dataset": {"path", "robots", "duration_s", "counts": {...}},
     "config": {"observer": {...}, "fuser": {...}, "pose_stddev": [x, y, yaw]},
     "summary": [                      # one entry per fusion method, in run order
        {"fusion", "rmse_m", "anees", "anees_interval": [low, high], "consistent",
         "landmarks_fused", "observations_used", "observations_rejected",
         "landmarks": [                # the method's landmarks, inside its entry
            {"id", "x", "y", "cov": [[xx, xy], [xy, yy]], "error_m", "nees",
             "observations", "rejections"}, ...]}, ...],
     "timing": {...},                  # seconds; speedup = dataset duration / replay
     "agreement": {METHOD: {"same_ids", "same_counts", "max_mean_diff_m",
                            "max_cov_diff_m2", "max_cov_dep_diff_m2"}},  # through_nodes
     "nodes": {...}}                   # through_nodes: counters, diagnostics, CPU time

With ``--calibrate`` the object is ``{"calibration": {...}, "dataset": {...}}``
(``Calibration.to_dict``).
``--plot FILE`` draws the robot paths, the true landmarks and the fused landmarks with
their 2-sigma ellipses (matplotlib, ``landmark_ros.eval.plotting``).
"""

import argparse
from collections import Counter
from dataclasses import asdict, dataclass, field, fields, replace
import json
import math
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time

from landmark_ros.core.landmark_map import FUSION_METHODS, LandmarkMap
from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.eval import metrics as evaluation
from landmark_ros.mrclam.data import load_dataset
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.pipeline.rows import (landmark_row_problems, landmarks_from_rows,
                                        observation_noise)
from landmark_ros.ros.conversions import seconds_to_ns, stamp_ns
import numpy as np

PACKAGE_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CONFIG_NAME = 'mrclam.yaml'
DEFAULT_DATASET = Path('shared') / 'data' / 'mrclam' / 'dataset6'
MAD_TO_SIGMA = 1.4826
"""Median absolute deviation to standard deviation, for Gaussian data."""


# Configuration ---------------------------------------------------------------------------

@dataclass(frozen=True)
class ReplayConfig:
    """The parameters of both nodes and of the replay, from one params file."""

    observer: ObserverConfig
    fuser: FuserConfig
    pose_stddev: tuple = (0.002, 0.002, 0.002)
    """Standard deviations of the reported poses: x [m], y [m], yaw [rad]."""
    path: Path = None

    @property
    def P_pose(self):
        """Return the pose covariance, shape (3, 3)."""
        return np.diag(np.square(np.asarray(self.pose_stddev, dtype=np.float64)))


def default_config_path():
    """Return ``config/mrclam.yaml`` of the source tree, else of the installed share."""
    local = PACKAGE_ROOT / 'config' / DEFAULT_CONFIG_NAME
    if local.is_file():
        return local
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('landmark_ros')) / 'config' / DEFAULT_CONFIG_NAME
    except Exception:  # noqa: B902 - not installed with ament: report the local path
        return local


def default_dataset_path():
    """Return ``shared/data/mrclam/dataset6`` beside the repository (or the cwd)."""
    candidates = [PACKAGE_ROOT.parent / DEFAULT_DATASET, Path.cwd() / DEFAULT_DATASET,
                  Path.cwd().parent / DEFAULT_DATASET]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    return candidates[0]


def node_section(document, node_name):
    """
    Return the merged ``ros__parameters`` of every section that applies to ``node_name``.

    Sections are keyed by node name, optionally with a namespace or wildcard prefix
    (``/**/landmark_observer``, ``/robot1/landmark_observer``, ``landmark_observer``).
    """
    values = {}
    for key, section in (document or {}).items():
        if str(key).rstrip('/').split('/')[-1] != node_name:
            continue
        if not isinstance(section, dict) or not isinstance(
                section.get('ros__parameters', {}), dict):
            raise ValueError(f'section {key!r} must hold a ros__parameters mapping')
        values.update(section.get('ros__parameters') or {})
    return values


def load_config(path=None):
    """
    Read a ROS params file into the observer, fuser and replay configuration.

    Parameters
    ----------
    path : str or Path, optional
        Params file; ``config/mrclam.yaml`` by default.

    Returns
    -------
    ReplayConfig

    Raises
    ------
    ValueError
        If a value is invalid for its node.

    """
    import yaml
    path = Path(path) if path is not None else default_config_path()
    with open(path, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}
    if not isinstance(document, dict):
        raise ValueError(f'{path}: not a ROS params file (a mapping of node sections)')
    observer = ObserverConfig.from_values(node_section(document, 'landmark_observer'))
    fuser = FuserConfig.from_values(node_section(document, 'landmark_fuser'))
    replay = node_section(document, 'landmark_mrclam')
    stddev = tuple(float(replay.get(f'pose_stddev_{axis}', default))
                   for axis, default in zip(('x', 'y', 'yaw'), (0.002, 0.002, 0.002)))
    if not all(math.isfinite(s) and s >= 0.0 for s in stddev):
        raise ValueError(f'{path}: pose_stddev_* must be finite and >= 0, got {stddev}')
    return ReplayConfig(observer, fuser, stddev, path)


def config_values(config):
    """Return a config dataclass as a plain dict (tuples as lists)."""
    values = {}
    for spec in fields(config):
        value = getattr(config, spec.name)
        values[spec.name] = list(value) if isinstance(value, tuple) else value
    return values


# Offline: the observer and fuser computations --------------------------------------------

@dataclass
class Observed:
    """The observer's output for every row of ``Dataset.rows``, in global time order."""

    rows: object
    """The ``mrclam_data.Rows`` the results are for."""
    kept: np.ndarray
    """Rows that became valid landmarks (observer and fuser row checks), shape (N,)."""
    m: np.ndarray
    """World-frame positions, shape (N, 2) (NaN where not kept)."""
    P: np.ndarray
    """Total covariances, shape (N, 2, 2)."""
    P_dep: np.ndarray
    """Dependent parts, shape (N, 2, 2)."""
    reasons: Counter = field(default_factory=Counter)
    """Rows rejected by the observer and fuser checks, by reason."""


def observer_parameters(config):
    """
    Return what ``landmark_observer`` derives from its parameters.

    Returns
    -------
    noise : tuple of float
        ``range_variance``, ``bearing_variance``, ``range_variance_per_m2`` for
        ``observation_noise``.
    sensor_pose : ndarray, shape (3,), or None
    R_bias : ndarray, shape (2, 2), or None

    """
    noise = (config.range_stddev ** 2, config.bearing_stddev ** 2,
             config.range_stddev_per_m ** 2)
    sensor_pose = np.array(config.sensor_pose)
    R_bias = None
    if config.range_bias_stddev or config.bearing_bias_stddev:
        R_bias = np.diag([config.range_bias_stddev ** 2, config.bearing_bias_stddev ** 2])
    return noise, (sensor_pose if sensor_pose.any() else None), R_bias


def observe(rows, config, P_pose, per_message=False):
    """
    Turn sightings into world-frame landmarks as ``landmark_observer`` does.

    Parameters
    ----------
    rows : mrclam_data.Rows
        Sightings in global time order.
    config : ObserverConfig
        The observer's parameters.
    P_pose : ndarray, shape (3, 3)
        Covariance of every pose.
    per_message : bool
        Call the core once per observation cloud (as the node does with one cloud per
        callback) instead of once per robot over all its rows; same results.

    Returns
    -------
    Observed

    """
    noise, sensor_pose, R_bias = observer_parameters(config)
    count = len(rows)
    kept = np.zeros(count, bool)
    m, P, P_dep = np.full((count, 2), np.nan), np.zeros((count, 2, 2)), np.zeros((count, 2, 2))
    reasons = Counter()
    if per_message:
        starts, ends = rows.messages()
        groups = [np.arange(a, b) for a, b in zip(starts.tolist(), ends.tolist())]
    else:
        groups = [np.flatnonzero(rows.robot == r) for r in np.unique(rows.robot).tolist()]
    for index in groups:
        z = rows.z[index]
        R = observation_noise({'range': z[:, 0]}, *noise)
        pose = rows.poses[index[0]] if per_message else rows.poses[index]
        ok, m_k, P_k, P_dep_k, why = landmarks_from_rows(
            rows.ids[index], z, R, pose, P_pose, sensor_pose, R_bias)
        reasons.update(why)
        where = index[ok]
        kept[where], m[where], P[where], P_dep[where] = True, m_k, P_k, P_dep_k
    # What the fuser checks before queueing rows.
    where = np.flatnonzero(kept)
    valid, why = landmark_row_problems(rows.ids[where], m[where], P[where], P_dep[where])
    reasons.update(why)
    kept[where[~valid]] = False
    return Observed(rows, kept, m, P, P_dep, reasons)


@dataclass
class MethodResult:
    """One fusion method's map against the ground truth."""

    fusion: str
    records: list
    """The confirmed landmarks, as ``LandmarkMap.to_records`` gives them."""
    results: list
    """``evaluation.LandmarkResult`` per landmark with a true position."""
    summary: object
    """``evaluation.Summary``."""
    observations_used: int
    """Observations fused (accepted) over the run."""
    observations_rejected: int
    """Observations gated out or left out of a confirmation."""

    def to_dict(self):
        """Return the JSON summary entry, with the landmarks inside."""
        by_id = {r.id: r for r in self.results}
        landmarks = []
        for record in self.records:
            result = by_id.get(record['id'])
            landmarks.append({
                'id': int(record['id']), 'x': record['mean'][0], 'y': record['mean'][1],
                'cov': np.asarray(record['covariance'], dtype=float).reshape(2, 2).tolist(),
                'error_m': None if result is None else result.error_m,
                'nees': None if result is None else result.nees,
                'observations': int(record['observations']),
                'rejections': int(record.get('rejections', 0))})
        low, high = self.summary.anees_interval
        return {'fusion': self.fusion, 'rmse_m': _number(self.summary.rmse_m),
                'anees': _number(self.summary.anees),
                'anees_interval': [_number(low), _number(high)],
                'consistent': bool(self.summary.consistent),
                'landmarks_fused': len(self.records),
                'observations_used': int(self.observations_used),
                'observations_rejected': int(self.observations_rejected),
                'landmarks': landmarks}


def _number(value):
    return None if value is None or not math.isfinite(value) else float(value)


def method_result(fusion, records, truth, used, rejected):
    """Evaluate map records against ``truth`` (id -> (x, y))."""
    records = sorted(records, key=lambda r: r['id'])
    ids = np.array([r['id'] for r in records], dtype=np.int64)
    m = np.array([r['mean'] for r in records], dtype=np.float64).reshape(-1, 2)
    P = np.array([r['covariance'] for r in records], dtype=np.float64).reshape(-1, 2, 2)
    results, summary = evaluation.evaluate(
        ids, m, P, truth, [r['observations'] for r in records],
        [r.get('rejections', 0) for r in records])
    return MethodResult(fusion, records, results, summary, used, rejected)


FUSE_CHUNK = 1024
"""Rows per ``LandmarkMap.update`` call offline."""


def fuse(observed, fuser_config, chunk=FUSE_CHUNK):
    """
    Fuse observed rows in global time order with ``LandmarkMap``, as the fuser does.

    The rows go in calls of ``chunk`` rows: a batch gives the same map as its rows one
    by one (each landmark's rows stay in order), and the rows of known landmarks of a
    batch are fused vectorised, in rounds of distinct landmarks. The fuser batches the
    rows it has queued the same way, only in other sizes.

    Returns
    -------
    landmark_map : LandmarkMap
    accepted, rejected : collections.Counter
        Observations fused and rejected, by source.

    """
    rows = observed.rows
    landmark_map = LandmarkMap(fuser_config.fusion, fuser_config.gate_probability,
                               fuser_config.min_observations,
                               fuser_config.max_consecutive_rejections)
    k = np.flatnonzero(observed.kept)
    topics = np.array(rows.topics, dtype=str)
    accepted, rejected = Counter(), Counter()
    for start in range(0, len(k), max(1, int(chunk))):
        part = k[start:start + chunk]
        result = landmark_map.update(rows.ids[part], observed.m[part], observed.P[part],
                                     observed.P_dep[part], topics[rows.robot[part]],
                                     rows.times[part])
        accepted.update(result.accepted)
        rejected.update(result.rejected)
    return landmark_map, accepted, rejected


def run_offline(dataset, config, methods):
    """
    Run every method offline.

    Returns
    -------
    results : dict
        Fusion method -> MethodResult.
    observed : Observed

    """
    observed = observe(dataset.rows(), config.observer, config.P_pose)
    results = {}
    for method in methods:
        landmark_map, accepted, rejected = fuse(observed, replace(config.fuser, fusion=method))
        results[method] = method_result(method, landmark_map.to_records(), dataset.landmarks,
                                        sum(accepted.values()), sum(rejected.values()))
    return results, observed


# Reports ---------------------------------------------------------------------------------

def summary_table(results):
    """Return one line per method: landmarks, RMSE, average NEES and its interval."""
    lines = [f"{'fusion':<30} {'landmarks':>9} {'RMSE [cm]':>9} {'ANEES':>9} "
             f"{'95 % interval':>15} {'consistent':>10} {'used':>7} {'rejected':>8}"]
    for result in results.values():
        s = result.summary
        low, high = s.anees_interval
        lines.append(f'{result.fusion:<30} {len(result.records):9d} {100 * s.rmse_m:9.2f} '
                     f'{s.anees:9.2f} {f"[{low:.2f}, {high:.2f}]":>15} '
                     f"{'yes' if s.consistent else 'no':>10} {result.observations_used:7d} "
                     f'{result.observations_rejected:8d}')
    return '\n'.join(lines)


def report(results):
    """Return the per-method tables and the summary table."""
    parts = []
    for result in results.values():
        parts.append(evaluation.format_table(
            result.results, result.summary,
            f'== {result.fusion}: {len(result.records)} landmarks, '
            f'{result.observations_used} observations fused, '
            f'{result.observations_rejected} rejected'))
    parts.append('== summary\n' + summary_table(results))
    return '\n\n'.join(parts)


def dataset_report(dataset):
    """Return what was read and dropped."""
    c = dataset.counts
    start, end = dataset.time_span
    robots = ', '.join(f'{r.name} {len(r.times)}' for r in dataset.robots)
    return (f'dataset {dataset.path}: {len(dataset.robots)} robots, '
            f'{len(dataset.landmarks)} true landmarks, {dataset.duration:.1f} s of '
            f'sightings\n  measurements read {c["read"]}, kept {c["kept"]} ({robots}); '
            f'dropped: robot sightings {c["robot_sightings"]}, unknown barcodes '
            f'{c["unknown_barcode"]}, outside ground truth {c["outside_groundtruth"]}')


def dataset_dict(dataset):
    """Return the dataset description for the JSON output."""
    return {'path': str(dataset.path), 'robots': [r.name for r in dataset.robots],
            'duration_s': dataset.duration, 'counts': dict(dataset.counts),
            'landmarks_true': len(dataset.landmarks)}


def write_json(path, document):
    """Write ``document`` as indented JSON."""
    with open(path, 'w', encoding='utf-8') as stream:
        json.dump(document, stream, indent=1, allow_nan=False)
        stream.write('\n')


# Plot ------------------------------------------------------------------------------------

PLOT_COLOURS = {'independent': 'tab:red', 'covariance_intersection': 'tab:green',
                'split_covariance_intersection': 'tab:blue'}


def plot(path, dataset, results, title='MRCLAM'):
    """
    Draw the map and, beside it, every landmark's estimates around its true position.

    Left: the ground-truth robot paths, the true landmarks with their IDs and the fused
    landmarks with 2-sigma ellipses, per method. Right: one small panel per landmark
    with a true position, centred on it in centimetres, where the ellipses can be told
    apart.

    Raises
    ------
    landmark_ros.eval.plotting.PlotUnavailableError
        If matplotlib is not installed.

    """
    from landmark_ros.eval import plotting
    fig, ax = plotting.new_figure((16.0, 9.0))
    ax.set_position([0.05, 0.07, 0.45, 0.86])
    for robot in dataset.robots:
        step = max(1, len(robot.gt_times) // 4000)
        ax.plot(robot.gt_poses[::step, 0], robot.gt_poses[::step, 1], linewidth=0.5,
                alpha=0.35, color='0.45')
    ax.plot([], [], linewidth=0.5, color='0.45', label='robot paths (ground truth)')
    ids = sorted(dataset.landmarks)
    truth = np.array([dataset.landmarks[i] for i in ids]).reshape(-1, 2)
    ax.plot(truth[:, 0], truth[:, 1], 'k+', markersize=10, label='true landmarks')
    for landmark_id, (x, y) in zip(ids, truth):
        ax.annotate(str(landmark_id), (x, y), xytext=(4, 4), textcoords='offset points',
                    fontsize='small')
    reach = 1.0
    for method, result in results.items():
        colour = PLOT_COLOURS.get(method, 'tab:purple')
        for i, record in enumerate(result.records):
            plotting.draw_ellipse(ax, record['mean'], record['covariance'], 2.0, color=colour,
                                  linewidth=1.0,
                                  label=f'{method} (2 sigma)' if i == 0 else None)
            if record['id'] in dataset.landmarks:
                error = np.subtract(record['mean'], dataset.landmarks[record['id']])
                sd = math.sqrt(max(np.linalg.eigvalsh(np.asarray(record['covariance']))))
                reach = max(reach, 100.0 * (np.abs(error).max() + 2.0 * sd))
    ax.set_title(title)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(True, alpha=0.4)
    ax.legend(loc='best', fontsize='small')
    # One panel per landmark, in centimetres around the true position.
    columns = max(1, math.ceil(math.sqrt(len(ids))))
    rows = max(1, math.ceil(len(ids) / columns))
    width, height = 0.43 / columns, 0.86 / rows
    reach = min(1.1 * reach, 100.0)
    for k, landmark_id in enumerate(ids):
        row, column = divmod(k, columns)
        panel = fig.add_axes([0.55 + column * width + 0.1 * width,
                              0.93 - (row + 1) * height + 0.15 * height,
                              0.8 * width, 0.7 * height])
        panel.plot([0.0], [0.0], 'k+', markersize=8)
        for method, result in results.items():
            colour = PLOT_COLOURS.get(method, 'tab:purple')
            for record in result.records:
                if record['id'] != landmark_id:
                    continue
                offset = 100.0 * np.subtract(record['mean'], dataset.landmarks[landmark_id])
                plotting.draw_ellipse(panel, offset, 1e4 * np.asarray(record['covariance']),
                                      2.0, color=colour, linewidth=1.0)
                panel.plot(offset[0], offset[1], '.', color=colour, markersize=4)
        panel.set_xlim(-reach, reach)
        panel.set_ylim(-reach, reach)
        panel.set_aspect('equal')
        panel.set_title(f'{landmark_id} [cm]', fontsize='x-small', pad=2)
        panel.tick_params(labelsize='xx-small')
        panel.grid(True, alpha=0.3)
    fig.savefig(path, dpi=110)


# Calibration -----------------------------------------------------------------------------

def robust_sigma(values):
    """Return 1.4826 times the median absolute deviation from the median (NaN if empty)."""
    values = np.asarray(values, dtype=np.float64)
    if not len(values):
        return float('nan')
    return float(MAD_TO_SIGMA * np.median(np.abs(values - np.median(values))))


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
    z = math.sqrt(2.0) * evaluation.erfinv(mass)
    return float(np.quantile(np.abs(values - np.median(values)), mass) / z)


def _fit_range_model(r, sigma, counts):
    """
    Fit ``sigma^2 = a^2 + (k r)^2`` to binned spreads; return ``(a, k)``.

    Weighted least squares on the variances, with ``a^2, k^2 >= 0``: a variance
    estimated from ``n`` errors has a standard deviation proportional to
    ``sigma^2 / sqrt(n)``, so the weights are ``n / sigma^4`` (relative errors count,
    and the short ranges are not drowned by the long ones).
    """
    r2, s2 = np.asarray(r, dtype=float) ** 2, np.asarray(sigma, dtype=float) ** 2
    w = np.asarray(counts, dtype=float) / np.maximum(s2, 1e-300) ** 2
    sw = np.sqrt(w)
    A = np.stack([np.ones_like(r2), r2], axis=1) * sw[:, None]
    (a2, k2), *_ = np.linalg.lstsq(A, s2 * sw, rcond=None)
    if a2 < 0.0:
        a2, k2 = 0.0, float(np.sum(w * s2 * r2) / np.sum(w * r2 * r2))
    if k2 < 0.0:
        a2, k2 = float(np.sum(w * s2) / np.sum(w)), 0.0
    return math.sqrt(max(a2, 0.0)), math.sqrt(max(k2, 0.0))


@dataclass
class Calibration:
    """Sensor model estimated from ground truth (``calibrate``)."""

    count: int
    overall: dict
    """Raw errors: per quantity (range, bearing) n, mean, std, median, robust_sd, tail."""
    robots: list
    """Per robot: name, n, range and bearing median error."""
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

    def to_dict(self):
        """Return plain values for JSON."""
        return asdict(self)

    def suggested_yaml(self):
        """Return the observer lines to put in ``config/mrclam.yaml``."""
        return ('/**/landmark_observer:\n  ros__parameters:\n'
                f'    range_stddev: {self.range_stddev:.4f}\n'
                f'    range_stddev_per_m: {self.range_stddev_per_m:.4f}\n'
                f'    bearing_stddev: {self.bearing_stddev:.4f}\n'
                f'    range_bias_stddev: {self.range_bias_stddev:.4f}\n'
                f'    bearing_bias_stddev: {self.bearing_bias_stddev:.4f}')


def measurement_errors(dataset):
    """
    Return every sighting of a landmark with a true position, with its errors.

    Returns
    -------
    dict of ndarray
        ``robot`` (index), ``id``, ``range``, ``range_error``, ``bearing_error``
        (measured minus true, bearing wrapped), one entry per sighting.

    """
    columns = {key: [] for key in ('robot', 'id', 'range', 'range_error', 'bearing_error')}
    for index, robot in enumerate(dataset.robots):
        known = np.array([i in dataset.landmarks for i in robot.ids.tolist()], dtype=bool)
        if not known.any():
            continue
        truth = np.array([dataset.landmarks[i] for i in robot.ids[known].tolist()])
        pose, z = robot.poses[known], robot.z[known]
        d = truth - pose[:, :2]
        columns['robot'].append(np.full(len(z), index))
        columns['id'].append(robot.ids[known])
        columns['range'].append(z[:, 0])
        columns['range_error'].append(z[:, 0] - np.hypot(d[:, 0], d[:, 1]))
        columns['bearing_error'].append(wrap_angle(
            z[:, 1] - (np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2])))
    return {key: (np.concatenate(value) if value else np.empty(0))
            for key, value in columns.items()}


def _weighted_bias(medians, counts, noise_variance):
    """Return the RMS bias: mean of median^2 minus the median's own variance, weighted."""
    medians, counts = np.asarray(medians), np.asarray(counts, dtype=np.float64)
    if not len(medians):
        return 0.0
    excess = medians ** 2 - (math.pi / 2.0) * np.asarray(noise_variance) / counts
    return math.sqrt(max(0.0, float(np.sum(counts * excess) / np.sum(counts))))


def calibrate(dataset, min_pair=10, bins=10):
    """
    Estimate the observer's sensor model from ground truth.

    Procedure:

    1. Errors. For every landmark sighting kept by the reader (barcode of a landmark,
       stamp within the robot's ground truth), the true range and bearing follow from
       the ground-truth pose interpolated at the measurement stamp (``mrclam_data``:
       position linear, heading on the shortest arc) and the true landmark position:
       ``range_error = r - |m - p|``, ``bearing_error = wrap(b - (atan2(m - p) - theta))``.
    2. Overall statistics of the raw errors, per quantity: mean, plain standard
       deviation, median, robust standard deviation ``1.4826 * median(|e - median(e)|)``
       (the MAD, which outliers barely move) and the tail: the fraction of errors more
       than 3 robust standard deviations from the median (0.27 % for Gaussian errors).
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
       Range residuals are split into ``bins`` bins of equal counts by range; per bin
       that standard deviation at the median range of the bin; then a least-squares
       fit of ``sigma_r(r)^2 = a^2 + (k r)^2`` over the bins (weights ``n / sigma^4``:
       relative errors of the bin variances; ``a^2, k^2 >= 0``) gives
       ``range_stddev = a`` and ``range_stddev_per_m = k``. ``bearing_stddev`` is the
       same standard deviation of all bearing residuals.
    5. Bias standard deviations: the root mean square of the robot medians, weighted
       by sightings, less the variance of a median of ``n`` noisy errors,
       ``(pi / 2) sigma^2 / n`` with ``sigma`` from step 4: ``range_bias_stddev`` and
       ``bearing_bias_stddev``. The same over the pair medians is printed for
       comparison.
    6. Tails: the fraction of residuals beyond 3 model standard deviations
       (``sigma_r(r)``, ``bearing_stddev``); well above 0.27 % means heavy tails,
       which the gate of the fuser (``gate_probability``) has to reject.

    Parameters
    ----------
    dataset : mrclam_data.Dataset
        Loaded dataset with ground truth.
    min_pair : int
        Sightings a robot-landmark pair needs for steps 3-5.
    bins : int
        Range bins of step 4.

    Returns
    -------
    Calibration

    Raises
    ------
    ValueError
        If there are too few sightings.

    """
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
    robots = []
    robot_medians = []
    for index, robot in enumerate(dataset.robots):
        mine = e['robot'] == index
        if not mine.any():
            continue
        medians = (float(np.median(e['range_error'][mine])),
                   float(np.median(e['bearing_error'][mine])))
        robots.append({'robot': robot.name, 'n': int(mine.sum()),
                       'range_median': medians[0], 'bearing_median': medians[1]})
        robot_medians.append((medians, int(mine.sum())))
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
    order = np.argsort(ranges, kind='stable')
    range_bins = []
    for chunk in np.array_split(order, min(bins, max(1, len(order) // 10))):
        if not len(chunk):
            continue
        range_bins.append({'low': float(ranges[chunk].min()), 'high': float(ranges[chunk].max()),
                           'range': float(np.median(ranges[chunk])), 'n': int(len(chunk)),
                           'robust_sd': central_sigma(res_r[chunk])})
    a, k = _fit_range_model([b['range'] for b in range_bins],
                            [b['robust_sd'] for b in range_bins], [b['n'] for b in range_bins])
    for b in range_bins:
        b['model_sd'] = math.sqrt(a * a + (k * b['range']) ** 2)
    sigma_b = central_sigma(res_b)
    # Biases: robot medians (the model) and pair medians (for comparison), less the
    # variance of a median of noisy errors.
    mean_noise_r = float(np.mean(a * a + (k * e['range']) ** 2))
    range_bias = _weighted_bias([m[0] for m, _ in robot_medians],
                                [n for _, n in robot_medians],
                                np.full(len(robot_medians), mean_noise_r))
    bearing_bias = _weighted_bias([m[1] for m, _ in robot_medians],
                                  [n for _, n in robot_medians],
                                  np.full(len(robot_medians), sigma_b ** 2))
    pair_noise_r = np.array([np.mean(a * a + (k * e['range'][inverse == p]) ** 2)
                             for p in np.flatnonzero(big)])
    pair_range = _weighted_bias(pair_range_median[big], sizes[big], pair_noise_r)
    pair_bearing = _weighted_bias(pair_bearing_median[big], sizes[big],
                                  np.full(int(big.sum()), sigma_b ** 2))
    model_r = np.sqrt(a * a + (k * ranges) ** 2)
    tails = {'range': float(np.mean(np.abs(res_r) > 3.0 * model_r)),
             'bearing': float(np.mean(np.abs(res_b) > 3.0 * sigma_b))}
    return Calibration(count, overall, robots, int(big.sum()), range_bins, a, k, sigma_b,
                       range_bias, bearing_bias, pair_range, pair_bearing, tails)


def format_calibration(cal):
    """Return the calibration printout."""
    lines = [f'== calibration from {cal.count} landmark sightings against ground truth',
             f"{'error':<8} {'mean':>9} {'std':>9} {'median':>9} {'robust sd':>10} "
             f"{'> 3 rsd':>8}"]
    for name, unit in (('range', 'm'), ('bearing', 'rad')):
        o = cal.overall[name]
        lines.append(f'{name:<8} {o["mean"]:9.4f} {o["std"]:9.4f} {o["median"]:9.4f} '
                     f'{o["robust_sd"]:10.4f} {100 * o["tail_3sd"]:7.2f}%   [{unit}]')
    lines.append('per robot median error:')
    for r in cal.robots:
        lines.append(f'  {r["robot"]:<8} n {r["n"]:6d}  range {r["range_median"]:+8.4f} m  '
                     f'bearing {r["bearing_median"]:+8.4f} rad')
    lines.append('range residual spread (error minus its robot median; sd of the Gaussian '
                 f'holding the central {100 * CENTRAL_MASS:.0f} %) against range:')
    lines.append(f"  {'range [m]':>15} {'median':>7} {'n':>6} {'central sd':>10} {'model':>8}")
    for b in cal.range_bins:
        lines.append(f'  {b["low"]:6.2f} - {b["high"]:6.2f} {b["range"]:7.2f} {b["n"]:6d} '
                     f'{b["robust_sd"]:10.4f} {b["model_sd"]:8.4f}')
    lines.append(f'fit sigma_r(r)^2 = a^2 + (k r)^2: a = {cal.range_stddev:.4f} m, '
                 f'k = {cal.range_stddev_per_m:.4f} m/m; bearing sd {cal.bearing_stddev:.4f} '
                 'rad')
    lines.append(f'bias (RMS of robot medians, less their noise): range '
                 f'{cal.range_bias_stddev:.4f} m, bearing {cal.bearing_bias_stddev:.4f} rad; '
                 f'of the {cal.pairs} robot-landmark pair medians, for comparison: range '
                 f'{cal.pair_range_bias_rms:.4f} m, bearing {cal.pair_bearing_bias_rms:.4f} rad')
    lines.append(f'residuals beyond 3 model sd: range {100 * cal.residual_tails["range"]:.2f}%, '
                 f'bearing {100 * cal.residual_tails["bearing"]:.2f}% (Gaussian: 0.27%)')
    lines.append('suggested values:')
    lines.append(cal.suggested_yaml())
    return '\n'.join(lines)


# Through the nodes -----------------------------------------------------------------------

def cpu_seconds(pids):
    """Return the CPU time (user + system) of running processes, from /proc (Linux)."""
    ticks = os.sysconf('SC_CLK_TCK') if hasattr(os, 'sysconf') else 100
    result = {}
    for name, pid in pids.items():
        try:
            with open(f'/proc/{pid}/stat') as stream:
                parts = stream.read().rsplit(')', 1)[1].split()
            result[name] = (int(parts[11]) + int(parts[12])) / ticks
        except (OSError, IndexError, ValueError):
            pass
    return result


OBSERVER_TRANSPORT = {
    'input_depth': 1000, 'output_depth': 1000, 'max_pending': 1000,
    'pose_buffer_s': 3600.0, 'max_wait_s': 30.0, 'marker_rate_hz': 0.0,
    'diagnostics_period_s': 1.0,
}
"""Observer parameters the replay sets on top of the config file (transport only)."""

OBSERVER_WINDOW = 8
"""Observation clouds in flight per observer (sent, no ``landmarks`` output yet)."""

FUSER_WINDOW = 64
"""Clouds per robot sent but not yet known to be taken by every fuser."""

FUSER_BATCH = FUSER_WINDOW if 'max_batch_messages' in {
    spec.name for spec in fields(FuserConfig)} else 1
"""Clouds of one source a fuser callback takes at most (its ``max_batch_messages``)."""

FUSER_TRANSPORT = {
    'update_period_s': 0.05, 'publish_rate_hz': 5.0, 'max_queue_messages': 100000,
    'input_depth': 1000, 'diagnostics_period_s': 0.25, 'source_timeout_s': 86400.0,
    'autosave_period_s': 0.0,
}
"""Fuser parameters the replay sets on top of the config file (besides topics, method)."""
if FUSER_BATCH > 1:
    FUSER_TRANSPORT['max_batch_messages'] = FUSER_BATCH


def _param(name, value):
    if isinstance(value, bool):
        text = 'true' if value else 'false'
    elif isinstance(value, (list, tuple)):
        text = '[' + ', '.join(f"'{v}'" for v in value) + ']'
    else:
        text = str(value)
    return ['-p', f'{name}:={text}']


def observer_arguments(robot, config_path):
    """Return the ROS arguments of a robot's observer process."""
    ns = f'/{robot.name}'
    arguments = ['-r', f'__ns:={ns}', '--params-file', str(config_path)]
    for name, value in OBSERVER_TRANSPORT.items():
        arguments += _param(name, value)
    for topic in ('pose', 'observations'):
        arguments += _param(f'qos_overrides.{ns}/{topic}.subscription.reliability',
                            'reliable')
    return arguments


def fuser_arguments(method, topics, config_path, map_path):
    """Return the ROS arguments of one fuser process."""
    arguments = ['-r', f'__ns:=/mrclam/{method}', '--params-file', str(config_path)]
    for name, value in dict(FUSER_TRANSPORT, input_topics=list(topics), fusion=method,
                            map_file=str(map_path)).items():
        arguments += _param(name, value)
    return arguments


def dependencies(rows, starts, ends):
    """
    Return, per cloud, the clouds of other robots it must follow at the fuser.

    For each landmark of cloud ``j``, the last earlier cloud with that landmark: when
    it is another robot's, ``j`` must reach the fuser after it. Earlier clouds with
    the landmark need no entry: that cloud itself followed them (the clouds of one
    robot stay in order by themselves).

    Returns
    -------
    requirements : list of tuple of (int, int)
        Per cloud, ``(robot, local)`` pairs: the cloud ``local`` (index among the
        clouds of robot index ``robot``) must be taken by the fusers first; one pair
        per robot, the latest.
    local : ndarray of int, shape (K,)
        Index of each cloud among its robot's clouds.

    """
    count = len(starts)
    msg_robot = rows.robot[starts].tolist()
    local = np.zeros(count, np.int64)
    seen = Counter()
    last = {}
    requirements = []
    ids = rows.ids.tolist()
    for j in range(count):
        r = msg_robot[j]
        local[j] = seen[r]
        seen[r] += 1
        need = {}
        for landmark in set(ids[starts[j]:ends[j]]):
            i = last.get(landmark, -1)
            if i >= 0 and msg_robot[i] != r:
                need[msg_robot[i]] = max(need.get(msg_robot[i], -1), int(local[i]))
            last[landmark] = j
        requirements.append(tuple(sorted(need.items())))
    return requirements, local


class ReplayError(RuntimeError):
    """The replay through the nodes failed (process exit, stall, lost message)."""


class Player:
    """
    Publish the dataset into the nodes in time order, with flow control.

    Poses. Each observer receives its robot's pose at exactly the stamp of the next
    cloud, then the cloud, both reliable, so it uses that very pose (no interpolation)
    and publishes one ``landmarks`` cloud per observation cloud, in order.

    Order at the fusers. A fuser takes one robot's clouds in order (one reliable
    writer), but across robots in the order its executor sees them, not the order
    they were sent. The map only depends on the order of the rows of each landmark
    (``LandmarkMap`` treats landmarks apart), so a cloud waits until every fuser has
    taken the last cloud of another robot with one of its landmarks
    (``dependencies``); robots whose clouds wait for nothing go on meanwhile, in
    time order. To know that a cloud was taken, the player waits for its
    ``landmarks`` output (it subscribes too: the output reached the fusers when it
    reached the player), then runs a barrier: rounds of an empty ``get_parameters``
    request to every fuser, one round after the other. In each pass, an executor
    serves every subscription with data (the fuser's callback takes up to
    ``FUSER_BATCH`` waiting clouds of that source) before the services, so a round
    guarantees that many more clouds of every robot taken.

    Flow control. At most ``OBSERVER_WINDOW`` clouds per robot wait for their
    ``landmarks`` output and at most ``FUSER_WINDOW`` are not known to be taken by
    the fusers (a barrier then runs), far below every queue depth, so nothing is
    dropped. Discovery: the player waits for matched publishers, subscriptions and
    services, then sends empty probe clouds until the diagnostics of every fuser
    count one from every robot, so every link carries data before the first cloud.
    """

    def __init__(self, node, executor, dataset, rows, config, methods, launcher,
                 progress=True, stall_timeout_s=60.0):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from rcl_interfaces.srv import GetParameters
        from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from std_srvs.srv import Trigger
        self.node, self.executor = node, executor
        self.dataset, self.rows, self.config = dataset, rows, config
        self.methods, self.launcher = list(methods), launcher
        self.progress, self.stall_timeout_s = progress, stall_timeout_s
        self.robots = dataset.robots
        self.starts, self.ends = rows.messages()
        self.msg_robot = rows.robot[self.starts]
        self.msg_times = rows.times[self.starts]
        self.requirements, self.local = dependencies(rows, self.starts, self.ends)
        self.totals = np.bincount(self.msg_robot, minlength=len(self.robots)).tolist()
        self.robot_clouds = [np.flatnonzero(self.msg_robot == r).tolist()
                             for r in range(len(self.robots))]
        self.expected_ns = [[] for _ in self.robots]
        for j in range(len(self.starts)):
            self.expected_ns[self.msg_robot[j]].append(
                seconds_to_ns(float(self.msg_times[j])))
        reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                              reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # No QoS event handlers: each is a waitable the executor polls on every wake-up.
        quiet_pub = {'event_callbacks': PublisherEventCallbacks(use_default_callbacks=False)}
        quiet_sub = {'event_callbacks': SubscriptionEventCallbacks(
            use_default_callbacks=False)}
        self.pose_pubs, self.obs_pubs, self.out_subs = [], [], []
        for index, robot in enumerate(self.robots):
            self.pose_pubs.append(node.create_publisher(
                PoseWithCovarianceStamped, f'/{robot.name}/pose', reliable, **quiet_pub))
            self.obs_pubs.append(node.create_publisher(
                PointCloud2, f'/{robot.name}/observations', reliable, **quiet_pub))
            self.out_subs.append(node.create_subscription(
                PointCloud2, robot.landmarks_topic,
                lambda msg, index=index: self._on_output(msg, index), reliable, **quiet_sub))
        self.fused = {}
        self.fused_subs, self.barrier_clients, self.save_clients = [], [], []
        for method in self.methods:
            ns = f'/mrclam/{method}'
            self.fused_subs.append(node.create_subscription(
                PointCloud2, f'{ns}/fused_landmarks',
                lambda msg, method=method: self.fused.__setitem__(method, msg), latched,
                **quiet_sub))
            self.barrier_clients.append(node.create_client(
                GetParameters, f'{ns}/landmark_fuser/get_parameters'))
            self.save_clients.append(node.create_client(Trigger, f'{ns}/landmark_fuser/save'))
        self.diagnostics = {}
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
                                 **quiet_sub)
        self._GetParameters = GetParameters
        self._Trigger = Trigger
        count = len(self.robots)
        self.sent = [0] * count
        self.out = [0] * count
        self.taken = [0] * count
        self.probes_sent = [0] * count
        self.probes_out = [0] * count
        self.rows_out = 0
        self.sent_total = 0
        self.barrier = None
        self.barriers = 0
        self.barrier_rounds = 0
        self._last_progress = time.monotonic()
        self._last_bar = 0.0
        self._last_decile = -1
        self._probe_stamp = None

    # Callbacks -------------------------------------------------------------------------

    def _on_output(self, msg, index):
        stamp = stamp_ns(msg.header.stamp)
        if self._probe_stamp is not None and stamp < self._data_start_ns:
            self.probes_out[index] += 1
            return
        k = self.out[index]
        expected = self.expected_ns[index][k] if k < len(self.expected_ns[index]) else None
        if stamp != expected:
            raise ReplayError(f'{self.robots[index].name}: landmarks output stamped {stamp} '
                              f'ns, expected {expected} ns (cloud {k}): a cloud was lost')
        self.out[index] += 1
        self.rows_out += msg.width * msg.height
        self._last_progress = time.monotonic()

    def _on_diagnostics(self, msg):
        stamp = stamp_ns(msg.header.stamp)
        for status in msg.status:
            self.diagnostics[status.name] = (stamp, {kv.key: kv.value for kv in status.values},
                                             status.message)

    # Helpers ---------------------------------------------------------------------------

    def spin(self, timeout_s=0.05):
        """Run one callback (or wait up to ``timeout_s``)."""
        self.executor.spin_once(timeout_sec=timeout_s)

    def spin_until(self, predicate, timeout_s, what):
        """Spin until ``predicate()``; raise ReplayError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        last_check = 0.0
        while not predicate():
            now = time.monotonic()
            if now > deadline:
                raise ReplayError(f'timed out after {timeout_s:.0f} s waiting for {what}')
            if now - last_check > 0.5:
                self.launcher.check()
                last_check = now
            self.spin(0.05)

    def fuser_name(self, method):
        """Return the fully qualified name of a method's fuser."""
        return f'/mrclam/{method}/landmark_fuser'

    def fuser_sources(self, method, newer_than_ns=None):
        """Return ``topic -> values`` of a fuser's latest diagnostics, or None."""
        name = self.fuser_name(method)
        main = self.diagnostics.get(name)
        if main is None or (newer_than_ns is not None and main[0] <= newer_than_ns):
            return None
        sources = {}
        for robot in self.robots:
            entry = self.diagnostics.get(f'{name}: {robot.landmarks_topic}')
            if entry is None or entry[0] != main[0]:
                return None
            sources[robot.landmarks_topic] = entry[1]
        return sources

    # Barrier ---------------------------------------------------------------------------

    def start_barrier(self, clouds):
        """
        Start a barrier over the outputs received so far.

        When it completes, each fuser has taken at least ``clouds`` more of the
        covered clouds of every robot (all of them if fewer were left): one round per
        ``FUSER_BATCH`` clouds, as each pass of a fuser's executor takes up to that
        many waiting clouds of every source.
        """
        rounds = max(1, -(-clouds // FUSER_BATCH))
        self.barrier = {'cover': list(self.out), 'rounds': rounds, 'left': rounds,
                        'pending': 0}
        self.barriers += 1
        self._barrier_round()

    def _barrier_round(self):
        barrier = self.barrier
        barrier['pending'] = len(self.barrier_clients)
        self.barrier_rounds += 1
        for client in self.barrier_clients:
            request = self._GetParameters.Request(names=[])
            client.call_async(request).add_done_callback(self._barrier_reply)

    def _barrier_reply(self, future):
        barrier = self.barrier
        barrier['pending'] -= 1
        if barrier['pending']:
            return
        barrier['left'] -= 1
        if barrier['left'] > 0:
            self._barrier_round()
            return
        covered = barrier['rounds'] * FUSER_BATCH
        self.taken = [max(t, min(c, t + covered)) for t, c in zip(self.taken, barrier['cover'])]
        self.barrier = None
        self._last_progress = time.monotonic()

    # Sending ---------------------------------------------------------------------------

    def send(self, j):
        """Publish cloud ``j``: the robot's pose at its stamp, then the observations."""
        from landmark_ros.ros.schemas import make_header, observation_message, pose_message
        r = int(self.msg_robot[j])
        a, b = int(self.starts[j]), int(self.ends[j])
        stamp = float(self.msg_times[j])
        self.pose_pubs[r].publish(pose_message(stamp, self.rows.poses[a], self.config.P_pose))
        self.obs_pubs[r].publish(observation_message(
            make_header(stamp, f'{self.robots[r].name}/camera'), self.rows.ids[a:b],
            self.rows.z[a:b]))
        self.sent[r] += 1
        self.sent_total += 1

    def pump(self):
        """
        Send every cloud that may go now; return how many clouds a barrier must cover.

        A robot's next cloud may go when fewer than ``OBSERVER_WINDOW`` of its clouds
        wait for their output, fewer than ``FUSER_WINDOW`` are not known to be taken
        by the fusers, and the clouds it must follow (``dependencies``) are taken.
        Robots go in the order of their next clouds in time; a blocked robot does
        not hold the others up.

        Returns
        -------
        int
            Clouds per robot a barrier must cover to unblock a robot whose blocking
            clouds are back from their observers (0: nothing a barrier can unblock).

        """
        clouds = 0
        progress = True
        while progress:
            progress = False
            order = sorted((self.robot_clouds[r][self.sent[r]], r)
                           for r in range(len(self.robots)) if self.sent[r] < self.totals[r])
            for j, r in order:
                if self.sent[r] - self.out[r] >= OBSERVER_WINDOW:
                    continue
                if self.sent[r] - self.taken[r] >= FUSER_WINDOW:
                    if self.out[r] > self.taken[r]:
                        clouds = max(clouds, self.out[r] - self.taken[r])
                    continue
                blocked = False
                for a, local in self.requirements[j]:
                    if self.taken[a] <= local:
                        blocked = True
                        if self.out[a] > local:
                            clouds = max(clouds, local + 1 - self.taken[a])
                if blocked:
                    continue
                self.send(j)
                progress = True
                self._last_progress = time.monotonic()
        return clouds

    # Phases ----------------------------------------------------------------------------

    def connect(self, timeout_s=120.0):
        """Wait for every publisher, subscription and service to be matched."""
        def matched():
            return (all(p.get_subscription_count() > 0 for p in self.pose_pubs + self.obs_pubs)
                    and all(s.get_publisher_count() > 0 for s in self.out_subs + self.fused_subs)
                    and all(c.service_is_ready() for c in self.barrier_clients
                            + self.save_clients)
                    and all(self.node.count_subscribers(r.landmarks_topic) >= 1 + len(
                        self.methods) for r in self.robots))
        self.spin_until(matched, timeout_s, 'the nodes to start and match')

    def probe(self, timeout_s=60.0):
        """Send empty clouds until every fuser has one from every robot."""
        t0 = float(self.rows.times[0]) if len(self.rows) else 0.0
        self._data_start_ns = seconds_to_ns(t0 - 1.0)
        self._probe_stamp = t0 - 100.0
        deadline = time.monotonic() + timeout_s
        from landmark_ros.ros.schemas import make_header, observation_message, pose_message

        def seen():
            for method in self.methods:
                sources = self.fuser_sources(method)
                if sources is None or any(int(v.get('messages_in', 0)) < 1
                                          for v in sources.values()):
                    return False
            return True

        while not seen():
            if time.monotonic() > deadline:
                raise ReplayError('the fusers never received the probe clouds')
            self._probe_stamp += 0.01
            for r, robot in enumerate(self.robots):
                pose = robot.poses[0] if len(robot.poses) else np.zeros(3)
                self.pose_pubs[r].publish(pose_message(self._probe_stamp, pose,
                                                       self.config.P_pose))
                self.obs_pubs[r].publish(observation_message(
                    make_header(self._probe_stamp, f'{robot.name}/camera'), np.zeros(0, np.int64),
                    np.zeros((0, 2))))
                self.probes_sent[r] += 1
            try:
                self.spin_until(seen, 1.0, 'probes')
            except ReplayError:
                pass
        # Every probe the observers published reaches the fusers before the first real
        # cloud; the barrier makes sure the fusers have taken them all.
        try:
            self.spin_until(lambda: self.probes_out == self.probes_sent, 2.0, 'probe outputs')
        except ReplayError:
            pass
        self.start_barrier(max(self.probes_sent) + 2)
        self.spin_until(lambda: self.barrier is None, 30.0, 'the probe barrier')
        self.taken = [0] * len(self.robots)

    def play(self):
        """Send every cloud with flow control; return when every fuser took them all."""
        total = len(self.starts)
        last_check = 0.0
        while True:
            clouds = self.pump()
            if self.barrier is None:
                if self.sent_total == total and self.out == self.sent:
                    if self.taken == self.out:
                        break
                    clouds = max(o - t for o, t in zip(self.out, self.taken))
                if clouds:
                    self.start_barrier(clouds)
            self.show_progress()
            now = time.monotonic()
            if now - self._last_progress > self.stall_timeout_s:
                raise ReplayError(f'no progress for {self.stall_timeout_s:.0f} s: sent '
                                  f'{self.sent}, outputs {self.out}, taken {self.taken}')
            if now - last_check > 1.0:
                self.launcher.check()
                last_check = now
            self.spin(0.05)
        self.show_progress(final=True)

    def show_progress(self, final=False):
        """
        Show the progress on stderr.

        A bar redrawn about 5 times a second on a terminal; otherwise a line at every
        10 % (logs and pipes get no carriage returns).
        """
        if not self.progress:
            return
        now = time.monotonic()
        total = len(self.starts)
        done = sum(self.out)
        tty = sys.stderr.isatty()
        decile = 10 * done // max(total, 1)
        if tty and not final and now - self._last_bar < 0.2:
            return
        if not tty and decile <= self._last_decile:
            return
        self._last_bar = now
        self._last_decile = decile
        elapsed = now - self._t_play
        dataset_s = float(self.msg_times[min(done, total) - 1] - self.msg_times[0]) \
            if done and total else 0.0
        speed = dataset_s / elapsed if elapsed > 0 else 0.0
        width = 30
        filled = int(width * done / max(total, 1))
        line = (f'[{"#" * filled}{"." * (width - filled)}] {done}/{total} clouds, '
                f'{dataset_s:6.1f} s of data in {elapsed:5.1f} s ({speed:5.1f}x real time), '
                f'{self.barriers} barriers')
        if tty:
            sys.stderr.write('\r' + line + ('\n' if final else ''))
        else:
            sys.stderr.write(line + '\n')
        sys.stderr.flush()

    def finish(self, timeout_s=60.0):
        """
        Wait for the fused maps: diagnostics after the last take, then ``~/save``.

        Returns
        -------
        dict
            Method -> ``{'sources': topic -> diagnostics values, 'saved': bool}``.

        """
        after = time.time_ns()
        for method in self.methods:
            def fused(method=method):
                sources = self.fuser_sources(method, newer_than_ns=after)
                return sources is not None and all(
                    v.get('queued_messages') == '0' for v in sources.values())
            self.spin_until(fused, timeout_s, f'the {method} fuser to fuse its queue')
        final = {}
        for method, client in zip(self.methods, self.save_clients):
            future = client.call_async(self._Trigger.Request())
            self.spin_until(future.done, timeout_s, f'the {method} fuser to save its map')
            response = future.result()
            if not response.success:
                raise ReplayError(f'{method} fuser could not save its map: {response.message}')
            final[method] = {'sources': self.fuser_sources(method)}
        # Observer diagnostics after the last output, for the report.
        self.spin_until(lambda: all(
            self.diagnostics.get(f'/{r.name}/landmark_observer', (0,))[0] > after
            for r in self.robots), timeout_s, 'the observer diagnostics')
        return final

    def run(self):
        """Connect, probe, play and finish; return the fusers' final diagnostics."""
        self.connect()
        self.probe()
        self._t_play = time.monotonic()
        self.play()
        self.play_wall_s = time.monotonic() - self._t_play
        return self.finish()


def _records_from_cloud(msg):
    from landmark_ros.ros.schemas import read_landmarks
    rows = read_landmarks(msg)
    return rows


def domain_id_for(pid=None):
    """Return the private ROS_DOMAIN_ID of a replay: 100 to 149, from the process ID."""
    return 100 + (os.getpid() if pid is None else pid) % 50


def run_through_nodes(dataset, config, methods, progress=True, keep_logs=False, out=print,
                      domain_id=None):
    """
    Replay the dataset through the real nodes; return the results per method.

    The nodes run as processes of ``landmark_ros.demo.launcher.Launcher`` (stopped with
    SIGINT, then SIGTERM and SIGKILL, whatever happens) in a private ROS domain on the
    loopback interface; this process joins it with its own context.

    Returns
    -------
    results : dict
        Method -> MethodResult: each fuser's saved map (``~/save``), with the
        per-landmark rejections; its ``fused_landmarks`` must equal it.
    info : dict
        Timing, message counts, CPU time per process and the node diagnostics.

    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from landmark_ros.demo.launcher import Launcher, ProcessExitedError
    from landmark_ros.pipeline import map_file

    t_start = time.monotonic()
    domain = domain_id_for() if domain_id is None else int(domain_id)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    work = Path(tempfile.mkdtemp(prefix='landmark_mrclam_'))
    rows = dataset.rows()
    topics = [robot.landmarks_topic for robot in dataset.robots]
    config_path = Path(config.path).resolve()
    context = Context()
    node = executor = None
    ok = False
    out(f'through the nodes: ROS_DOMAIN_ID={domain}, loopback only; logs in {work}')
    out(f'  observers {", ".join(r.name for r in dataset.robots)}: --params-file {config_path}'
        f' + {OBSERVER_TRANSPORT} + reliable pose/observations')
    out(f'  fusers /mrclam/<method>: --params-file {config_path} + {FUSER_TRANSPORT}')
    launcher = Launcher(work, domain_id=domain)
    try:
        for robot in dataset.robots:
            launcher.start_module(f'observer_{robot.name}', 'landmark_ros.nodes.observer',
                                  observer_arguments(robot, config_path))
        map_paths = {}
        for method in methods:
            map_paths[method] = work / f'{method}.json'
            launcher.start_module(f'fuser_{method}', 'landmark_ros.nodes.fuser',
                                  fuser_arguments(method, topics, config_path,
                                                  map_paths[method]))
        rclpy.init(args=['landmark_mrclam'], context=context, domain_id=domain)
        node = rclpy.create_node('landmark_mrclam_player', context=context,
                                 start_parameter_services=False)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        player = Player(node, executor, dataset, rows, config, methods, launcher, progress)
        t_connect = time.monotonic()
        cpu_player = time.process_time()
        try:
            final = player.run()
        except ProcessExitedError as error:
            raise ReplayError(str(error)) from error
        cpu = cpu_seconds({name: p.pid for name, p in launcher.processes.items()})
        cpu['player'] = time.process_time() - cpu_player
        results = {}
        mismatch = {}
        for method in methods:
            document = map_file.load(map_paths[method], config.fuser.world_frame)
            records = sorted(document['landmarks'], key=lambda r: r['id'])

            def cloud_matches(method=method, records=records):
                msg = player.fused.get(method)
                if msg is None:
                    return False
                cloud = _records_from_cloud(msg)
                return (cloud.ids.tolist() == [r['id'] for r in records]
                        and np.array_equal(cloud.m, np.array(
                            [r['mean'] for r in records]).reshape(-1, 2))
                        and np.array_equal(cloud.P, np.array(
                            [r['covariance'] for r in records]).reshape(-1, 2, 2))
                        and cloud.observations.tolist() == [r['observations'] for r in records])
            try:
                player.spin_until(cloud_matches, 10.0, f'{method} fused_landmarks')
            except ReplayError:
                mismatch[method] = 'fused_landmarks never matched the saved map'
            sources = final[method]['sources']
            used = sum(int(v.get('fused', 0)) for v in sources.values())
            rejected = sum(int(v.get('gated_out', 0)) for v in sources.values())
            results[method] = method_result(method, records, dataset.landmarks, used, rejected)
        observers = {r.name: player.diagnostics[f'/{r.name}/landmark_observer'][1]
                     for r in dataset.robots}
        info = {
            'wall_s': time.monotonic() - t_start,
            'startup_s': t_connect - t_start,
            'play_wall_s': player.play_wall_s,
            'speedup': dataset.duration / player.play_wall_s if player.play_wall_s else None,
            'clouds': int(len(player.starts)), 'rows': int(len(rows)),
            'rows_out': int(player.rows_out),
            'barriers': player.barriers, 'barrier_rounds': player.barrier_rounds,
            'probes': list(player.probes_sent),
            'fusers': {m: final[m]['sources'] for m in methods},
            'observers': observers, 'cloud_mismatch': mismatch,
            'cpu_s': {name: round(value, 2) for name, value in cpu.items()},
        }
        ok = True
        return results, info
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        codes = launcher.stop()
        bad = {name: code for name, code in codes.items() if code != 0}
        if bad:
            out(f'processes exited with {bad}')
        if ok and not keep_logs and not bad:
            shutil.rmtree(work, ignore_errors=True)
        else:
            out(f'logs kept in {work}')


def agreement(offline, nodes):
    """
    Compare the maps of both modes, per method.

    Returns
    -------
    dict
        Method -> ``same_ids``, ``same_counts`` (observations and rejections per
        landmark, used and rejected totals), ``max_mean_diff_m``,
        ``max_cov_diff_m2``, ``max_cov_dep_diff_m2``.

    """
    document = {}
    for method, node_result in nodes.items():
        a = {r['id']: r for r in offline[method].records}
        b = {r['id']: r for r in node_result.records}
        entry = {'same_ids': sorted(a) == sorted(b)}
        common = sorted(set(a) & set(b))

        def diff(key):
            if not common:
                return 0.0
            return float(max(np.max(np.abs(np.asarray(a[i][key]) - np.asarray(b[i][key])))
                             for i in common))
        entry['max_mean_diff_m'] = diff('mean')
        entry['max_cov_diff_m2'] = diff('covariance')
        entry['max_cov_dep_diff_m2'] = diff('covariance_dependent')
        entry['same_counts'] = bool(
            all(a[i]['observations'] == b[i]['observations']
                and a[i]['rejections'] == b[i]['rejections'] for i in common)
            and offline[method].observations_used == node_result.observations_used
            and offline[method].observations_rejected == node_result.observations_rejected)
        document[method] = entry
    return document


def format_agreement(document):
    """Return the agreement lines."""
    lines = ['== agreement through the nodes vs offline']
    for method, e in document.items():
        lines.append(f'  {method:<30} same landmarks {"yes" if e["same_ids"] else "NO"}, '
                     f'same counts {"yes" if e["same_counts"] else "NO"}, max |dmean| '
                     f'{e["max_mean_diff_m"]:.2e} m, max |dP| {e["max_cov_diff_m2"]:.2e} m^2, '
                     f'max |dP_dep| {e["max_cov_dep_diff_m2"]:.2e} m^2')
    return '\n'.join(lines)


def format_node_info(info):
    """Return the timing and per-node counter lines of a run through the nodes."""
    lines = [f'== through the nodes: {info["clouds"]} clouds ({info["rows"]} rows) in '
             f'{info["play_wall_s"]:.1f} s ({info["speedup"]:.1f}x real time), '
             f'{info["wall_s"]:.1f} s in all with {info["startup_s"]:.1f} s start-up; '
             f'{info["barriers"]} barriers ({info["barrier_rounds"]} rounds)']
    keys = ('poses_in', 'observation_messages_in', 'observations_in', 'landmarks_out')
    for name, values in info['observers'].items():
        problems = {k: v for k, v in values.items() if k not in keys + (
            'pose_buffer_size', 'pending_messages') and v != '0'}
        lines.append(f'  observer {name}: ' + ', '.join(f'{k} {values.get(k)}' for k in keys)
                     + (f'; problems {problems}' if problems else ''))
    for method, sources in info['fusers'].items():
        parts = [f'{topic} in {v.get("messages_in")} msgs/{v.get("observations_in")} rows, '
                 f'fused {v.get("fused", 0)}, gated {v.get("gated_out", 0)}'
                 for topic, v in sources.items()]
        lines.append(f'  fuser {method}: ' + '; '.join(parts))
    cpu = ', '.join(f'{name} {value:.1f}' for name, value in info['cpu_s'].items())
    lines.append(f'  CPU [s]: {cpu}; total {sum(info["cpu_s"].values()):.1f}')
    for method, problem in info['cloud_mismatch'].items():
        lines.append(f'  WARNING {method}: {problem}')
    return '\n'.join(lines)


# Command line ----------------------------------------------------------------------------

def parse_args(argv=None):
    """Return the parsed command line."""
    parser = argparse.ArgumentParser(
        prog='landmark_mrclam',
        description='Replay a UTIAS MRCLAM dataset through the landmark observer and fuser.')
    parser.add_argument('dataset', nargs='?', type=Path, default=None,
                        help='MRCLAM dataset directory (default: shared/data/mrclam/dataset6 '
                        'beside the repository)')
    parser.add_argument('--config', type=Path, default=None,
                        help='ROS params file (default: config/mrclam.yaml)')
    parser.add_argument('--fusion', choices=FUSION_METHODS, default=None,
                        help='one fusion method (default: all three)')
    parser.add_argument('--through-nodes', action='store_true',
                        help='replay over DDS through landmark_observer and landmark_fuser '
                        'processes')
    parser.add_argument('--calibrate', action='store_true',
                        help='estimate the sensor model from ground truth and print it')
    parser.add_argument('--json', type=Path, default=None, help='write the results as JSON')
    parser.add_argument('--plot', type=Path, default=None, help='draw the maps (PNG, PDF...)')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    parser.add_argument('--keep-logs', action='store_true',
                        help='keep the node logs of --through-nodes')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID of --through-nodes (default: 100-149 from the '
                        'process ID)')
    return parser.parse_args(argv)


def main(argv=None):
    """Run the replay from the command line; return the exit code."""
    args = parse_args(argv)
    try:
        config = load_config(args.config)
        t0 = time.monotonic()
        dataset = load_dataset(args.dataset or default_dataset_path(), config.pose_stddev)
        load_s = time.monotonic() - t0
    except (OSError, ValueError) as error:
        print(f'landmark_mrclam: {error}', file=sys.stderr)
        return 2
    print(dataset_report(dataset))
    print(f'config {config.path}; loaded in {load_s:.2f} s')
    if args.calibrate:
        try:
            calibration = calibrate(dataset)
        except ValueError as error:
            print(f'landmark_mrclam: {error}', file=sys.stderr)
            return 2
        print(format_calibration(calibration))
        if args.json:
            write_json(args.json, {'calibration': calibration.to_dict(),
                                   'dataset': dataset_dict(dataset)})
        return 0
    methods = [args.fusion] if args.fusion else list(FUSION_METHODS)
    t0 = time.monotonic()
    offline, observed = run_offline(dataset, config, methods)
    offline_s = time.monotonic() - t0
    if observed.reasons:
        print(f'observer/fuser row checks rejected: {dict(observed.reasons)}')
    timing = {'load_s': load_s, 'offline_s': offline_s, 'duration_s': dataset.duration}
    document = {'mode': 'offline', 'dataset': dataset_dict(dataset),
                'config': {'observer': config_values(config.observer),
                           'fuser': config_values(config.fuser),
                           'pose_stddev': list(config.pose_stddev)}}
    results = offline
    if args.through_nodes:
        try:
            results, info = run_through_nodes(
                dataset, config, methods,
                progress=not args.no_progress, keep_logs=args.keep_logs,
                domain_id=args.domain_id)
        except (ReplayError, RuntimeError) as error:
            print(f'landmark_mrclam: {error}', file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            print('landmark_mrclam: interrupted', file=sys.stderr)
            return 130
        document['mode'] = 'through_nodes'
        document['agreement'] = agreement(offline, results)
        timing.update({k: info[k] for k in ('wall_s', 'startup_s', 'play_wall_s', 'speedup')})
        document['nodes'] = {k: info[k] for k in ('clouds', 'rows', 'rows_out', 'barriers',
                                                  'barrier_rounds', 'probes', 'fusers',
                                                  'observers', 'cloud_mismatch', 'cpu_s')}
    print()
    print(report(results))
    print()
    print(f'offline: {offline_s:.2f} s for {len(methods)} method(s) '
          f'({dataset.duration / offline_s:.0f}x real time)')
    if args.through_nodes:
        print(format_node_info(info))
        print(format_agreement(document['agreement']))
    document['summary'] = [result.to_dict() for result in results.values()]
    document['timing'] = timing
    if args.json:
        write_json(args.json, document)
        print(f'wrote {args.json}')
    if args.plot:
        from landmark_ros.eval.plotting import PlotUnavailableError
        try:
            plot(args.plot, dataset, results,
                 f'MRCLAM {dataset.path.name}: fused landmarks (2 sigma)')
            print(f'wrote {args.plot}')
        except PlotUnavailableError as error:
            print(f'landmark_mrclam: {error}', file=sys.stderr)
            return 2
    if args.through_nodes and not all(
            e['same_ids'] and e['same_counts'] for e in document['agreement'].values()):
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
