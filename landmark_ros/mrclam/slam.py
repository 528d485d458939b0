"""
``landmark_mrclam --slam``: the team without motion capture on MRCLAM.

The five robots run the closed loop of ``eval.slam_loop.TeamLoop`` (per robot a
localizer and an observer, one split-CI fuser) from their odometry files and their
sightings of landmarks and of each other. The ground truth gives each robot its pose at
the start of its odometry (covariance ``initial_stddev``) and nothing else; it is read
again only to score the result. Events go in global time order (ties: odometry first,
then sightings, then robot sightings, then by robot): odometry twists stamped
``odometry_delay_s`` later (``localize_data.odometry_delay``), one sighting message per
robot and stamp (``Rows.messages``), robot sightings.

Modes: with IDs and with IDs hidden (the fuser's association names the landmarks, the
localizers use its track IDs), each without and with anchors: a map file of a few
surveyed landmarks (``slam_anchor_ids`` of the ``landmark_mrclam`` section, covariance
``localize.surveyed_map``), loaded by the fuser as its ``map_file`` (dependent part zero:
a survey shares no error with the robots).

Scores: per robot and overall the localization figures of ``localize.metrics``
(position and heading RMSE, pose ANEES, inside-95 fraction); the map's RMSE and ANEES
against the surveyed landmarks (``report.method_result``: the ANEES with its 95 %
interval); without IDs the confirmed tracks are matched to the true landmarks
(``eval.metrics.match_tracks``, within 1 m) and take their IDs for the scores.
"""

from dataclasses import dataclass, replace
import math
import os
import tempfile
import time
from typing import List, Optional, Sequence

from landmark_ros.eval.metrics import chi2_quantile, match_tracks
from landmark_ros.eval.slam_loop import LoopConfig, TeamLoop
from landmark_ros.fuser import map_file
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.mrclam.data import interpolate_poses, seconds_to_stamps_ns
from landmark_ros.mrclam.localize import consistent, KEYS, metrics, surveyed_map, Track
from landmark_ros.mrclam.report import method_result
import numpy as np

_ODOM, _OBS, _ROBOT = 0, 1, 2
DEFAULT_ANCHORS = (6, 11, 19)
"""Anchors of dataset 6 when the config names none: three landmarks far apart."""


@dataclass(frozen=True)
class SlamMode:
    """One run: IDs hidden or not, anchors or not."""

    hide_ids: bool = False
    anchors: bool = False

    @property
    def label(self) -> str:
        """Return a short name of the mode."""
        return (f'{"no IDs" if self.hide_ids else "IDs"}, '
                f'{"anchors" if self.anchors else "no anchors"}')


@dataclass
class SlamResult:
    """What one run leaves: the pose tracks, the map's records and scores."""

    mode: SlamMode
    tracks: List[Track]
    records: list
    entry: dict


def write_anchor_file(path, dataset, anchor_ids, world_frame='map'):
    """
    Write the surveyed landmarks ``anchor_ids`` as a fuser map file at ``path``.

    Covariances from ``localize.surveyed_map``; the dependent part is zero.
    """
    ids, m, P = surveyed_map(dataset)
    records = []
    for i, landmark_id in enumerate(ids.tolist()):
        if landmark_id not in anchor_ids:
            continue
        records.append({'id': landmark_id, 'mean': m[i].tolist(), 'covariance': P[i].tolist(),
                        'covariance_dependent': [[0.0, 0.0], [0.0, 0.0]],
                        'observations': 1, 'rejections': 0, 'sources': ['survey'],
                        'first_stamp_ns': 0, 'last_stamp_ns': 0})
    map_file.save(str(path), records, world_frame, 'split_covariance_intersection')
    return len(records)


def _events(dataset, extras, delay_s, starts, ends):
    """Return the events (time, kind, robot, index) sorted by (time, kind, robot)."""
    rows = dataset.rows()
    t = [rows.times[starts]]
    kind = [np.full(len(starts), _OBS)]
    robot = [rows.robot[starts]]
    index = [np.arange(len(starts))]
    for r_i, robot_data in enumerate(dataset.robots):
        ex = extras[robot_data.number]
        for times, k in ((ex.odom_times + delay_s, _ODOM), (ex.sighting_times, _ROBOT)):
            t.append(times)
            kind.append(np.full(len(times), k))
            robot.append(np.full(len(times), r_i))
            index.append(np.arange(len(times)))
    t, kind = np.concatenate(t), np.concatenate(kind)
    robot, index = np.concatenate(robot), np.concatenate(index)
    order = np.lexsort((robot, kind, t))
    return t[order], kind[order], robot[order], index[order]


def _start(loop, dataset, extras, config, delay_s):
    """Start every robot at its true pose at the start of its odometry."""
    for i, robot in enumerate(dataset.robots):
        start = max(extras[robot.number].odom_times[0] + delay_s, robot.gt_times[0])
        pose, _ = interpolate_poses(robot.gt_times, robot.gt_poses, [start])
        loop.start(i, int(seconds_to_stamps_ns([start])[0]), pose[0],
                   np.diag(np.square(config.initial_stddev)))


def run(dataset, extras, loop_config: LoopConfig, delay_s=0.0, progress=None,
        loop_class=TeamLoop) -> TeamLoop:
    """
    Run the closed loop over the whole dataset; return the loop (tracks, fuser).

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        Sightings and ground truth (the starting poses only).
    extras : dict
        ``localize_data.RobotExtras`` by robot number (odometry, robot sightings).
    loop_config : LoopConfig
        The pipeline objects' parameters and whether the IDs are hidden.
    delay_s : float
        Added to the odometry stamps [s].
    progress : callable, optional
        ``progress(fraction)`` now and then.
    loop_class : type
        ``TeamLoop`` or a subclass (``slam_attribution.RecordingLoop``).

    """
    rows = dataset.rows()
    starts, ends = rows.messages()
    loop = loop_class(loop_config, [r.name for r in dataset.robots])
    _start(loop, dataset, extras, loop_config.localizer, delay_s)
    number_to_index = {r.number: i for i, r in enumerate(dataset.robots)}
    t, kind, who, index = _events(dataset, extras, delay_s, starts, ends)
    stamps = seconds_to_stamps_ns(t)
    step = max(1, len(t) // 100)
    for e in range(len(t)):
        i, k = int(who[e]), int(index[e])
        ex = extras[dataset.robots[i].number]
        if kind[e] == _ODOM:
            loop.odometry(i, int(stamps[e]), twist=ex.odom_twist[k])
        elif kind[e] == _OBS:
            a, b = int(starts[k]), int(ends[k])
            loop.sightings(i, int(stamps[e]), rows.ids[a:b], rows.z[a:b])
        else:
            j = number_to_index.get(int(ex.sighting_robot[k]))
            if j is not None:
                loop.robot_sighting(i, int(stamps[e]), j, ex.sighting_z[k])
        if progress is not None and e % step == 0:
            progress(e / len(t))
    return loop


def pose_tracks(dataset, loop) -> List[Track]:
    """Return one ``localize.Track`` per robot: estimates and truth at odometry stamps."""
    out = []
    for i, (robot, track) in enumerate(zip(dataset.robots, loop.tracks)):
        stamps, x, P = track.arrays()
        times = stamps * 1e-9
        truth, inside = interpolate_poses(robot.gt_times, robot.gt_poses, times)
        out.append(Track(robot.number, times[inside], x[inside], P[inside], truth[inside],
                         loop.robot_counts(i)))
    return out


def map_entry(dataset, records, hide_ids, max_distance_m=1.0):
    """
    Return the map's scores and the records with true IDs where matched.

    Without IDs the confirmed tracks are matched one to one with the true landmarks
    (``match_tracks``, at most ``max_distance_m``); the others keep their track IDs
    (and count in ``tracks_confirmed``, not in the scores).
    """
    if hide_ids and records:
        true_ids = sorted(dataset.landmarks)
        true_m = np.array([dataset.landmarks[i] for i in true_ids]).reshape(-1, 2)
        match = match_tracks([r['mean'] for r in records], true_m, max_distance_m)
        records = [dict(r, track_id=r['id'], id=true_ids[j] if j >= 0 else r['id'])
                   for r, j in zip(records, match.tolist())]
    result = method_result('split_covariance_intersection', records, dataset.landmarks, 0, 0)
    low, high = result.summary.anees_interval
    return records, {'map_rmse_m': float(result.summary.rmse_m),
                     'map_anees': float(result.summary.anees),
                     'map_anees_interval': [float(low), float(high)],
                     'map_landmarks_scored': len(result.results),
                     'tracks_confirmed': len(records),
                     'true_landmarks': len(dataset.landmarks)}


def joint_map_entry(dataset, ids, m, P):
    """
    Return the map's NEES with its joint covariance, against the surveyed landmarks.

    ``ids`` (L,), ``m`` (L, 2), ``P`` (2L, 2L); the landmarks with a survey are scored
    at once: ``map_joint_nees``, its degrees of freedom and the 95 % chi-square interval.
    """
    keep = [k for k, i in enumerate(ids.tolist()) if i in dataset.landmarks]
    cols = np.array([[2 * k, 2 * k + 1] for k in keep], np.int64).reshape(-1)
    truth = np.array([dataset.landmarks[int(ids[k])] for k in keep]).reshape(-1)
    e = m[keep].reshape(-1) - truth
    dof = len(e)
    nees = float(e @ np.linalg.solve(P[np.ix_(cols, cols)], e)) if dof else math.nan
    return {'map_joint_nees': nees, 'map_joint_dof': dof,
            'map_joint_nees_interval': [chi2_quantile(dof, 0.025), chi2_quantile(dof, 0.975)]
            if dof else [math.nan, math.nan]}


def _percentiles(values):
    """Return min, median and 95th percentile of ``values`` [m] (NaN when empty)."""
    if not len(values):
        return {'min': math.nan, 'median': math.nan, 'p95': math.nan}
    low, median, p95 = np.percentile(values, [0.0, 50.0, 95.0])
    return {'min': float(low), 'median': float(median), 'p95': float(p95)}


def run_mode(dataset, extras, loop_config, mode: SlamMode, delay_s=0.0,
             anchor_path: Optional[str] = None, progress=None,
             loop_class=TeamLoop) -> SlamResult:
    """
    Run one mode; return its tracks, map records and JSON entry.

    ``loop_class``: ``TeamLoop`` or ``eval.team_ekf.TeamEKF`` (the reference; its
    entry adds the map's joint NEES, ``joint_map_entry``, without IDs over the tracks
    matched to a true landmark).
    """
    fuser = loop_config.fuser
    if mode.anchors:
        fuser = replace(fuser, map_file=str(anchor_path))
    config = replace(loop_config, fuser=fuser, hide_ids=mode.hide_ids)
    t0, cpu0 = time.monotonic(), time.process_time()
    loop = run(dataset, extras, config, delay_s, progress, loop_class)
    tracks = pose_tracks(dataset, loop)
    robots, overall = metrics(tracks)
    records, scores = map_entry(dataset, loop.map_records(), mode.hide_ids)
    if hasattr(loop, 'joint_map'):
        ids, m, P = loop.joint_map()
        if mode.hide_ids:  # the tracks matched to a true landmark take its ID
            true_id = {r['track_id']: r['id'] for r in records}
            ids = np.array([true_id.get(i, -1) for i in ids.tolist()], np.int64)
        scores.update(joint_map_entry(dataset, ids, m, P))
    entry = {'ids_hidden': mode.hide_ids, 'anchors': mode.anchors,
             **{key: overall[key] for key in KEYS}, **scores,
             'rows_used': overall['rows_used'], 'rows_gated': overall['rows_gated'],
             'robot_rows_used': overall['robot_rows_used'],
             'loop_counts': dict(loop.counts),
             **({'dependent_stddev_m': _percentiles(loop.dependent_stddevs)}
                if getattr(loop, 'dependent_stddevs', None) else {}),
             'seconds': time.monotonic() - t0, 'cpu_seconds': time.process_time() - cpu0,
             'robots': robots}
    return SlamResult(mode, tracks, records, entry)


MODES = (SlamMode(False, False), SlamMode(True, False), SlamMode(False, True),
         SlamMode(True, True))


def run_all(dataset, extras, loop_config, anchor_ids: Sequence[int], delay_s=0.0,
            modes=MODES, progress_factory=None, loop_class=TeamLoop) -> List[SlamResult]:
    """
    Run every mode (anchors from ``anchor_ids``, written to a temporary map file).

    ``loop_class``: as ``run_mode``.
    """
    results = []
    with tempfile.TemporaryDirectory(prefix='landmark_slam_') as directory:
        anchor_path = os.path.join(directory, 'anchors.json')
        write_anchor_file(anchor_path, dataset, set(anchor_ids),
                          loop_config.fuser.world_frame)
        for mode in modes:
            progress = progress_factory(mode.label) if progress_factory else None
            results.append(run_mode(dataset, extras, loop_config, mode, delay_s, anchor_path,
                                    progress.update if progress else None, loop_class))
            if progress:
                progress.close()
    return results


def format_table(results: Sequence[SlamResult], duration_s: float) -> str:
    """Return per mode the per-robot pose figures and the map's."""
    lines = [f'{"mode":24s} {"robot":>5s} {"pos RMSE":>9s} {"yaw RMSE":>9s} {"ANEES":>7s} '
             f'{"in 95%":>7s} {"used":>6s} {"gated":>6s}  ok']
    for result in results:
        entry = result.entry
        for row in entry['robots'] + [dict(entry, robot='all')]:
            lines.append(f'{result.mode.label:24s} {str(row["robot"]):>5s} '
                         f'{row["position_rmse_m"]:9.3f} {row["heading_rmse_rad"]:9.4f} '
                         f'{row["anees"]:7.2f} {row["inside_95_fraction"]:7.3f} '
                         f'{row["rows_used"]:6d} {row["rows_gated"]:6d}  '
                         f'{"yes" if consistent(row) else "no"}')
        low, high = entry['map_anees_interval']
        lines.append(f'  map: RMSE {entry["map_rmse_m"]:.3f} m, ANEES {entry["map_anees"]:.2f} '
                     f'(interval {low:.2f} to {high:.2f}), {entry["tracks_confirmed"]} '
                     f'confirmed of {entry["true_landmarks"]} true landmarks; '
                     f'{entry["seconds"]:.0f} s wall, {entry["cpu_seconds"]:.0f} s CPU '
                     f'({duration_s / entry["cpu_seconds"]:.0f}x real time by CPU time)')
        if 'map_joint_nees' in entry:
            low, high = entry['map_joint_nees_interval']
            lines.append(f'  map joint NEES {entry["map_joint_nees"]:.1f} '
                         f'({entry["map_joint_dof"]} dof, interval {low:.1f} to {high:.1f})')
        dep = entry.get('dependent_stddev_m')
        if dep is None:
            continue
        lines.append(f'  messages\' dependent standard deviation [m]: min {dep["min"]:.3f}, '
                     f'median {dep["median"]:.3f}, 95th percentile {dep["p95"]:.3f}')
    return '\n'.join(lines)


def targets(results: Sequence[SlamResult]):
    """Return, for the modes without anchors, each of the issue's goals and whether it holds."""
    out = []
    for result in results:
        entry, mode = result.entry, result.mode
        if mode.anchors:
            continue
        low, high = entry['map_anees_interval']
        tag = 'IDs hidden' if mode.hide_ids else 'IDs'
        out += [(f'{tag}: position RMSE <= 0.20 m overall', entry['position_rmse_m'] <= 0.20),
                (f'{tag}: every robot consistent', all(map(consistent, entry['robots']))),
                (f'{tag}: map RMSE <= 0.10 m', entry['map_rmse_m'] <= 0.10),
                (f'{tag}: map ANEES inside its interval', low <= entry['map_anees'] <= high)]
        if mode.hide_ids:
            out.append((f'{tag}: {entry["true_landmarks"]} confirmed tracks',
                        entry['tracks_confirmed'] == entry['true_landmarks']))
    return out


def loop_config(replay_config, localizer: LocalizerConfig,
                replay_values: Optional[dict] = None) -> LoopConfig:
    """
    Return the loop's parameters: the params file's observer and fuser sections.

    From ``replay_values`` (the ``landmark_mrclam`` section), the precision sources:
    ``slam_precision_sources`` and ``slam_precision_base_m``, the observers'
    ``precision_sources`` and ``precision_base_m`` in the loop (default: the observer
    section's; ``observer.precision``); and
    ``slam_correlated_noise``, the localizers' ``correlated_noise`` in the loop (default:
    the localizer section's);
    ``slam_association`` (``LoopConfig.association``, default ``fuser``): with IDs
    hidden, whose pairing names a row for the localizer;
    ``slam_range_scale_state`` (default false): whether the localizers keep the range
    scale state (``range_scale_state_stddev``) against the map the loop builds. Off,
    they run without it and count the robot's range error as the observer does, a bias
    (``range_bias_stddev`` of the observer section, the same calibration): a map built
    from the team's own ranges holds each robot's scale error in the landmarks it placed
    and the team's mean scale as its own, and its uncertainty (0.1 to 0.2 m) hides a
    1 % scale (3 cm at 3 m); split CI discounts the state's prior at every update
    against such a map (``docs/slam.md``), and the scale drifts to tens of per cent.
    The fuser's ``source_correlation`` is ``unknown``, its change detection off and the
    localizers' ``correlation`` ``split_ci`` whatever the file says (``consider`` needs a
    map whose errors are independent of the robot's; the loop's map is built from its
    poses; the rows' pose errors are slow, not the white rows change detection tests).
    """
    values = replay_values or {}
    association = str(values.get('slam_association', 'fuser'))
    if association not in ('fuser', 'localizer'):
        raise ValueError(f"slam_association must be 'fuser' or 'localizer', got {association!r}")
    if 'slam_correlated_noise' in values:
        localizer = replace(localizer, correlated_noise=str(values['slam_correlated_noise']))
    if (not bool(values.get('slam_range_scale_state', False))
            and localizer.range_scale_state_stddev > 0.0):
        localizer = replace(localizer, range_scale_state_stddev=0.0,
                            range_scale_bearing_state_stddev=0.0,
                            range_bias_stddev=replay_config.observer.range_bias_stddev)
    if localizer.correlation == 'consider':
        localizer = replace(localizer, correlation='split_ci')
    # The loop's poses share the map: their errors are correlated across robots. The
    # rows carry the localizers' pose errors, slow per robot: change detection's white
    # reference model does not hold for them.
    fuser = replace(replay_config.fuser, source_correlation='unknown', move_false_alarm_rate=0.0)
    observer = replay_config.observer
    observer = replace(observer, precision_sources=int(values.get(
        'slam_precision_sources', observer.precision_sources)), precision_base_m=float(
        values.get('slam_precision_base_m', observer.precision_base_m)))
    return LoopConfig(localizer, observer, fuser, association=association)
