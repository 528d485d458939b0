"""
The offline replay: the dataset through the observer and fuser code, no ROS (ROS-free).

Per robot, the rows go through ``rows.landmarks_from_rows`` (vectorised over all rows
of the robot with per-row poses: the same numbers as one call per observation cloud),
then through ``LandmarkMap.update`` in global time order (ties by robot number; calls
of ``FUSE_CHUNK`` rows, the same map as row by row). One map per fusion method.
"""

from collections import Counter
from dataclasses import dataclass, field, replace

from landmark_ros.core.landmark_map import LandmarkMap
from landmark_ros.mrclam.report import method_result
from landmark_ros.pipeline.rows import (landmark_row_problems, landmarks_from_rows,
                                        observation_noise)
import numpy as np


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
