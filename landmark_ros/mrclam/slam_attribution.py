"""
Where the ``--slam`` map's error comes from, on MRCLAM (docs/slam.md).

``python -m landmark_ros.mrclam.slam_attribution [--hide-ids] [--duration S] [--start S]
[--camera-delay S] [--known-map] [--yaw K C] [--no-robot-sightings]
[--odometry-delay S] [--json OUT] [DATASET]`` runs one mode of ``landmark_mrclam --slam``
(no anchors) with a ``RecordingLoop``, which keeps every row the observers placed (the
robot, the stamp, the pose it was placed with, the track the fuser gave it), and prints,
against the ground truth (read only here, to score):

1. the map's error split into one rigid transform of the whole map (shift, and rotation
   about the start poses' centroid: ``eval.slam_attribution.rigid_fit``) and the rest,
   and the shift's NEES under the map's own covariance (``shift_nees``);
2. per landmark: which robots' rows built it, the mean of the rows' errors split into
   the pose's part and the sensor's part (``row_parts``; the sensor's part also with the
   true pose at the stamp less ``camera_delay_s``, the camera's delay), and the fused
   error beside the mean of its rows';
3. per robot and period: the mean pose error (position, heading) at its sightings;
4. the sensor's part as range scale and bearing bias (with and without the delay);
5. with ``--hide-ids``: the confirmed tracks no true landmark matches, with their rows;
6. the odometry's turn against the truth (``fit_yaw``: a factor on the model's turn
   and a turn per metre driven, a veer); ``--yaw K C`` corrects the twists by them
   before the run (``corrected_twists``);
7. with ``--known-map``: the same localizers against the surveyed map, and the pose
   part their rows would have (``known_map_pose_parts``): the poses' own bias, without
   the loop's map.

``--camera-delay S`` moves the landmark sightings back by ``S`` before the run (the
loop's poses are then taken at the capture times, ``Dataset.with_camera_delay``; the
robot-to-robot sightings keep their stamps); the default 0 is what ``--slam`` does.
``--association localizer`` lets the localizers name the rows themselves with the IDs
hidden (``LoopConfig.association``); ``--no-robot-sightings`` and ``--odometry-delay``
are ablations.
"""

import argparse
from dataclasses import dataclass, field, replace
import json
from pathlib import Path
from typing import Dict, List

from landmark_ros.eval.slam_attribution import rigid_fit, row_parts, shift_nees
from landmark_ros.eval.slam_loop import TeamLoop
from landmark_ros.mrclam import localize, slam
from landmark_ros.mrclam.config import default_dataset_path, load_config
from landmark_ros.mrclam.data import interpolate_poses, load_dataset
from landmark_ros.mrclam.localize import metrics
from landmark_ros.mrclam.localize_data import odometry_scales
from landmark_ros.mrclam.slam_cli import _setup
from landmark_ros.mrclam.slam_plan import without_robot_sightings
import numpy as np

PERIOD_S = 150.0
"""Length of the periods of the pose-error table [s]."""


@dataclass
class Rows:
    """Every row the loop's observers placed, in order."""

    robot: List[int] = field(default_factory=list)
    stamp_ns: List[int] = field(default_factory=list)
    true_id: List[int] = field(default_factory=list)
    track_id: List[int] = field(default_factory=list)
    m: List[np.ndarray] = field(default_factory=list)
    pose: List[np.ndarray] = field(default_factory=list)
    P_dep: List[np.ndarray] = field(default_factory=list)

    def arrays(self) -> Dict[str, np.ndarray]:
        """Return the rows as arrays: (N,) ints, ``m`` (N, 2), ``pose`` (N, 3)."""
        return {'robot': np.array(self.robot, np.int64),
                'stamp_ns': np.array(self.stamp_ns, np.int64),
                'true_id': np.array(self.true_id, np.int64),
                'track_id': np.array(self.track_id, np.int64),
                'm': np.array(self.m).reshape(-1, 2), 'pose': np.array(self.pose).reshape(-1, 3),
                'P_dep': np.array(self.P_dep).reshape(-1, 2, 2)}


class RecordingLoop(TeamLoop):
    """A ``TeamLoop`` that records each placed row (``Rows``) with the pose it used."""

    def __init__(self, config, names):
        super().__init__(config, names)
        self.rows = Rows()
        self._poses: Dict[object, np.ndarray] = {}
        for observer in self.observers:
            observer.place = self._recording(observer.place)

    def _recording(self, place):
        def wrapped(ready):
            for item, pose, _ in ready:
                self._poses[item.token] = np.array(pose, np.float64)
            return place(ready)
        return wrapped

    def _place(self, robot, batch):
        ids, _ = self._rows[batch.token]
        pose = self._poses.pop(batch.token)
        super()._place(robot, batch)
        if not len(batch.ids) or len(batch.ids) != len(ids):
            return
        tracks = batch.ids
        if self.fuser.association_log:
            tracks = np.array([self.fuser.tracker.resolve(i) if i >= 0 else -1
                               for i in self.fuser.association_log[-1][2].tolist()])
        for k in range(len(ids)):
            self.rows.robot.append(robot)
            self.rows.stamp_ns.append(int(batch.stamp_ns))
            self.rows.true_id.append(int(ids[k]))
            self.rows.track_id.append(int(tracks[k]))
            self.rows.m.append(batch.m[k])
            self.rows.pose.append(pose)
            self.rows.P_dep.append(batch.P_dep[k])


def true_poses(dataset, robot, times_s):
    """Return the true poses (N, 3) of robots (N,) (indices) at ``times_s`` (N,) [s]."""
    out = np.zeros((len(robot), 3))
    for i, data in enumerate(dataset.robots):
        sel = robot == i
        if np.any(sel):
            out[sel], _ = interpolate_poses(data.gt_times, data.gt_poses, times_s[sel])
    return out


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def start_centroid(dataset, extras, delay_s):
    """Return the centroid (2,) of the robots' start poses (truth at the first odometry)."""
    starts = []
    for robot in dataset.robots:
        t0 = max(extras[robot.number].odom_times[0] + delay_s, robot.gt_times[0])
        pose, _ = interpolate_poses(robot.gt_times, robot.gt_poses, [t0])
        starts.append(pose[0, :2])
    return np.mean(starts, axis=0)


def map_study(records, landmarks, center):
    """Return the map part of the study (1.) for scored ``records`` (``id`` the true ID)."""
    scored = [r for r in records if r['id'] in landmarks]
    ids = [r['id'] for r in scored]
    m_est = np.array([r['mean'] for r in scored]).reshape(-1, 2)
    m_true = np.array([landmarks[i] for i in ids]).reshape(-1, 2)
    P = np.array([r['covariance'] for r in scored]).reshape(-1, 2, 2)
    P_dep = np.array([r.get('covariance_dependent', np.zeros((2, 2))) for r in scored])
    err = m_est - m_true
    shift_only = rigid_fit(m_est, m_true, center, rotate=False)
    rigid = rigid_fit(m_est, m_true, center)
    nees = np.einsum('ni,nij,nj->n', err, np.linalg.inv(P), err)
    return {'ids': ids, 'error': err.tolist(), 'nees': nees.tolist(),
            'rmse_m': float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))),
            'center': np.asarray(center).tolist(),
            'shift_m': shift_only.shift.tolist(),
            'shift_residual_rmse_m': shift_only.residual_rmse,
            'rigid_shift_m': rigid.shift.tolist(), 'rigid_angle_rad': rigid.angle,
            'rigid_residual_rmse_m': rigid.residual_rmse,
            'residual_error': rigid.residual.tolist(),
            'shift_nees': shift_nees(shift_only.shift, P),
            'sd_m': np.sqrt(np.trace(P, axis1=1, axis2=2) / 2).tolist(),
            'covariance_rmse_m': float(np.sqrt(np.mean(np.trace(P, axis1=1, axis2=2)))),
            'dependent_sd_m': np.sqrt(np.trace(P_dep, axis1=1, axis2=2) / 2).tolist()}


def row_study(dataset, rows, landmarks, camera_delay_s):
    """Return the rows' parts (2.-4.): per row arrays with the true poses."""
    times = rows['stamp_ns'] * 1e-9
    known = np.isin(rows['true_id'], list(landmarks))
    m_true = np.array([landmarks.get(int(i), (np.nan, np.nan)) for i in rows['true_id']])
    truth = true_poses(dataset, rows['robot'], times)
    parts = row_parts(rows['m'], rows['pose'], truth, m_true)
    delayed = row_parts(rows['m'], rows['pose'],
                        true_poses(dataset, rows['robot'], times - camera_delay_s), m_true)
    pose_err = rows['pose'] - truth
    pose_err[:, 2] = _wrap(pose_err[:, 2])
    return {'known': known, 'times': times, 'parts': parts, 'delayed': delayed,
            'pose_error': pose_err, 'm_true': m_true}


def _per_landmark(rows, study, map_part, landmark_id):
    """Return one landmark's line: robots' row counts, mean parts, fused error."""
    sel = study['known'] & (rows['true_id'] == landmark_id)
    if 'track' in map_part:
        sel &= rows['track_id'] == map_part['track'][landmark_id]
    counts = np.bincount(rows['robot'][sel], minlength=5)
    parts, delayed = study['parts'], study['delayed']
    total = parts['pose'][sel] + parts['sensor'][sel]
    k = map_part['ids'].index(landmark_id)
    return {'id': landmark_id, 'rows_by_robot': counts.tolist(),
            'fused_error': map_part['error'][k], 'rows_mean_error': total.mean(axis=0).tolist(),
            'pose_part': parts['pose'][sel].mean(axis=0).tolist(),
            'sensor_part': parts['sensor'][sel].mean(axis=0).tolist(),
            'sensor_part_delayed': delayed['sensor'][sel].mean(axis=0).tolist(),
            'residual_error': map_part['residual_error'][k]}


def _sensor_lines(study):
    """Return the sensor part as range scale and bearing bias, with and without delay."""
    lines = []
    known = study['known']
    for name in ('parts', 'delayed'):
        p = study[name]
        r = p['range'][known]
        scale = float(np.sum(p['radial'][known] * r) / np.sum(r * r))
        bearing = float(np.sum(p['tangential'][known] * r) / np.sum(r * r))
        lines.append(f'  {"stamp" if name == "parts" else "stamp - delay"}: range error '
                     f'{np.mean(p["radial"][known]):+.4f} m mean ({scale * 100:+.2f} % of the '
                     f'range, least squares), bearing {bearing:+.4f} rad, sensor part mean '
                     f'({np.mean(p["sensor"][known][:, 0]):+.4f}, '
                     f'{np.mean(p["sensor"][known][:, 1]):+.4f}) m')
    return lines


def period_lines(rows, study, period_s=PERIOD_S):
    """Return per robot and period the mean pose error at its rows (position, heading)."""
    t = study['times']
    t0 = float(t.min()) if len(t) else 0.0
    period = np.floor((t - t0) / period_s).astype(int)
    lines = ['  period [s]  robot   rows   mean dx    mean dy   mean dtheta  '
             'mean pose part of rows (x, y) [m]']
    for p in range(period.max() + 1 if len(t) else 0):
        for robot in range(int(rows['robot'].max()) + 1):
            sel = (period == p) & (rows['robot'] == robot) & study['known']
            if not np.any(sel):
                continue
            e = study['pose_error'][sel]
            part = study['parts']['pose'][sel].mean(axis=0)
            lines.append(f'  {p * period_s:4.0f}-{(p + 1) * period_s:4.0f}   {robot + 1:5d} '
                         f'{np.count_nonzero(sel):6d} {e[:, 0].mean():+9.3f} '
                         f'{e[:, 1].mean():+9.3f} {e[:, 2].mean():+11.4f}  '
                         f'({part[0]:+.3f}, {part[1]:+.3f})')
    return lines


def extra_track_lines(rows, study, records, landmarks, t0=0.0):
    """
    Return, per confirmed track no true landmark matched, its rows and their poses.

    Times in seconds from ``t0`` [s] (the first sighting).
    """
    lines = []
    for record in records:
        if record['id'] in landmarks:
            continue
        tid = record.get('track_id', record['id'])
        sel = rows['track_id'] == tid
        t = study['times'][sel] - t0
        e = study['pose_error'][sel]
        true_ids, counts = np.unique(rows['true_id'][sel], return_counts=True)
        mean = record['mean']
        nearest = min(landmarks, key=lambda i: np.hypot(*(np.subtract(landmarks[i], mean))))
        lines.append(f'  track {tid} at ({mean[0]:.2f}, {mean[1]:.2f}) m, nearest landmark '
                     f'{nearest} {np.hypot(*np.subtract(landmarks[nearest], mean)):.2f} m; '
                     f'{np.count_nonzero(sel)} rows, robots '
                     f'{sorted(set((rows["robot"][sel] + 1).tolist()))}, '
                     f'{t.min() if len(t) else 0:.1f} to {t.max() if len(t) else 0:.1f} s, true '
                     f'IDs {dict(zip(true_ids.tolist(), counts.tolist()))}; pose error at its '
                     f'rows: position {np.hypot(e[:, 0], e[:, 1]).mean() if len(e) else 0:.3f} '
                     f'm, heading {e[:, 2].mean() if len(e) else 0:+.3f} rad (mean)')
    return lines


def _vec(v):
    return f'({v[0]:+.3f}, {v[1]:+.3f})'


def report(dataset, loop, records, map_part, camera_delay_s):
    """Return the study's lines (module docstring) and its JSON document."""
    landmarks = dataset.landmarks
    rows = loop.rows.arrays()
    study = row_study(dataset, rows, landmarks, camera_delay_s)
    if any('track_id' in r for r in records):
        map_part['track'] = {r['id']: r['track_id'] for r in records if r['id'] in landmarks}
    lines = [f'map RMSE {map_part["rmse_m"]:.3f} m over {len(map_part["ids"])} landmarks; '
             f'one shift {_vec(map_part["shift_m"])} m leaves '
             f'{map_part["shift_residual_rmse_m"]:.3f} m; shift and rotation '
             f'{map_part["rigid_angle_rad"]:+.4f} rad about the start centroid '
             f'{_vec(map_part["center"])}: shift {_vec(map_part["rigid_shift_m"])} m, leaves '
             f'{map_part["rigid_residual_rmse_m"]:.3f} m',
             'the RMSE the covariance predicts (sqrt of the mean trace): '
             f'{map_part["covariance_rmse_m"]:.3f} m; '
             f'shift NEES (2 dof, 95 % below 5.99): errors shared '
             f'{map_part["shift_nees"]["shared"]:.2f}, independent '
             f'{map_part["shift_nees"]["independent"]:.2f}; landmark sd '
             f'{min(map_part["sd_m"]):.3f} to {max(map_part["sd_m"]):.3f} m '
             f'(dependent {min(map_part["dependent_sd_m"]):.3f} to '
             f'{max(map_part["dependent_sd_m"]):.3f} m)',
             "per landmark [m]: rows by robot 1-5; fused error; mean of its rows' errors = "
             'pose part + sensor part; sensor part with the true pose at stamp - delay; '
             'residual after the rigid fit']
    per = [_per_landmark(rows, study, map_part, i) for i in map_part['ids']]
    for p in per:
        lines.append(f'  {p["id"]:3d} {str(p["rows_by_robot"]):26s} {_vec(p["fused_error"])} '
                     f'{_vec(p["rows_mean_error"])} = {_vec(p["pose_part"])} + '
                     f'{_vec(p["sensor_part"])}; {_vec(p["sensor_part_delayed"])}; '
                     f'{_vec(p["residual_error"])}')
    known = study['known']
    lines.append(f'all rows: pose part {_vec(study["parts"]["pose"][known].mean(axis=0))}, '
                 f'sensor part {_vec(study["parts"]["sensor"][known].mean(axis=0))} m (mean)')
    lines += ['sensor part as range scale and bearing bias:']
    lines += _sensor_lines(study)
    lines += ['pose error at the rows by robot and period (estimate less truth):']
    lines += period_lines(rows, study)
    extra = extra_track_lines(rows, study, records, landmarks, dataset.time_span[0])
    if extra:
        lines += ['confirmed tracks no landmark matched:'] + extra
    document = {'map': {k: v for k, v in map_part.items() if k != 'track'},
                'landmarks': per}
    return lines, document


def known_map_pose_parts(dataset, extras, localizer, delay_s):
    """
    Return the localizer's figures against the surveyed map and its rows' pose parts.

    The loop's localizer config, robot sightings on (``localize.run``); the pose part of
    each sighting row of a known landmark to first order: the position error plus the
    heading error times the sight vector turned by 90 degrees, at the sighting stamp
    (the track interpolated). Returns ``(overall figures, per robot mean (2,), all
    rows' mean (2,))`` [m].
    """
    tracks = localize.run(dataset, extras, localizer, localize.surveyed_map(dataset),
                          cooperative=True, delay_s=delay_s)
    _, overall = metrics(tracks)
    per_robot, parts = [], []
    for robot, track in zip(dataset.robots, tracks):
        e = track.x - track.truth
        e[:, 2] = _wrap(e[:, 2])
        known = np.isin(robot.ids, list(dataset.landmarks))
        t = robot.times[known]
        err = np.stack([np.interp(t, track.times, e[:, c]) for c in range(3)], 1)
        xy = np.stack([np.interp(t, track.times, track.truth[:, c]) for c in range(2)], 1)
        sight = np.array([dataset.landmarks[i] for i in robot.ids[known]]).reshape(-1, 2) - xy
        part = err[:, :2] + err[:, 2:] * np.stack([-sight[:, 1], sight[:, 0]], 1)
        per_robot.append(part.mean(axis=0))
        parts.append(part)
    return overall, per_robot, np.concatenate(parts).mean(axis=0)


def corrected_twists(extras, yaw_factor, yaw_per_m, yaw_rate_scale):
    """
    Return ``extras`` with each yaw rate ``w`` replaced by ``k w + c |v| / s``.

    ``k`` = ``yaw_factor`` (on top of the localizer's ``yaw_rate_scale`` ``s``), ``c`` =
    ``yaw_per_m`` [rad/m]: the model turns ``s k w + c |v|``, a veer while driving.
    """
    out = {}
    for number, ex in extras.items():
        v, w = ex.odom_twist[:, 0], ex.odom_twist[:, 1]
        out[number] = replace(ex, odom_twist=np.column_stack(
            [v, yaw_factor * w + yaw_per_m * np.abs(v) / yaw_rate_scale]))
    return out


def fit_yaw(dataset, extras, delay_s, yaw_rate_scale, window_s=2.0):
    """
    Return ``(k, c)``: true turn = ``k`` x model turn + ``c`` x distance, pooled robots.

    The turn factor and veer of ``localize_data.odometry_scales`` over windows of
    ``window_s`` [s], the factor taken relative to ``yaw_rate_scale`` (the model turn is
    the odometry's turn times it; ``corrected_twists`` takes them).
    """
    numbers = [robot.number for robot in dataset.robots]
    _, turn, _, veer = odometry_scales(dataset, extras, numbers, delay_s,
                                       turn_window_s=window_s)
    return turn / yaw_rate_scale, veer


def main(argv=None):
    """Run the study (module docstring); return the exit code."""
    parser = argparse.ArgumentParser(description='Where the --slam map error comes from.')
    parser.add_argument('dataset', nargs='?', type=Path, default=None)
    parser.add_argument('--config', type=Path, default=None)
    parser.add_argument('--hide-ids', action='store_true')
    parser.add_argument('--duration', type=float, default=None, metavar='SECONDS')
    parser.add_argument('--start', type=float, default=0.0, metavar='SECONDS')
    parser.add_argument('--camera-delay', type=float, default=0.0, metavar='SECONDS',
                        help='move the sightings back by this before the run')
    parser.add_argument('--known-map', action='store_true',
                        help='also localize against the surveyed map (the loop '
                        'localizer config) and print the pose part of its rows')
    parser.add_argument('--yaw', nargs=2, type=float, default=None, metavar=('K', 'C'),
                        help='correct the yaw rates (corrected_twists) before the run')
    parser.add_argument('--association', choices=('fuser', 'localizer'), default='fuser',
                        help='with --hide-ids, who names the rows for the localizers')
    parser.add_argument('--no-robot-sightings', action='store_true',
                        help='leave out the robot-to-robot sightings')
    parser.add_argument('--odometry-delay', type=float, default=None, metavar='SECONDS',
                        help='instead of odometry_delay_s of the config')
    parser.add_argument('--json', type=Path, default=None)
    args = parser.parse_args(argv)
    replay_config = load_config(args.config)
    dataset = load_dataset(args.dataset or default_dataset_path(), replay_config.pose_stddev)
    if args.camera_delay:
        dataset = dataset.with_camera_delay(args.camera_delay)
    config, delay_s, _, dataset, extras = _setup(replay_config, dataset, args.duration,
                                                 args.start)
    config = replace(config, hide_ids=args.hide_ids, association=args.association)
    if args.no_robot_sightings:
        extras = without_robot_sightings(extras)
    if args.odometry_delay is not None:
        delay_s = args.odometry_delay
    scale = config.localizer.odometry_yaw_rate_scale
    k, c = fit_yaw(dataset, extras, delay_s, scale)
    print(f'odometry turn against the truth (2 s windows, pooled): true = {k:.4f} x model '
          f'turn {c:+.4f} rad/m x distance')
    if args.yaw:
        extras = corrected_twists(extras, args.yaw[0], args.yaw[1], scale)
    if args.known_map:
        known, per_robot, mean = known_map_pose_parts(dataset, extras, config.localizer,
                                                      delay_s)
        print(f'against the surveyed map: position RMSE {known["position_rmse_m"]:.3f} m, '
              f'pose ANEES {known["anees"]:.2f}; rows\' pose part (first order) '
              f'{_vec(mean)} m, per robot ' + ', '.join(_vec(p) for p in per_robot))
    loop = slam.run(dataset, extras, config, delay_s, loop_class=RecordingLoop)
    tracks = slam.pose_tracks(dataset, loop)
    _, overall = metrics(tracks)
    records, scores = slam.map_entry(dataset, loop.map_records(), args.hide_ids)
    print(f'position RMSE {overall["position_rmse_m"]:.3f} m, pose ANEES '
          f'{overall["anees"]:.2f}; map RMSE {scores["map_rmse_m"]:.3f} m, ANEES '
          f'{scores["map_anees"]:.2f}, {scores["tracks_confirmed"]} tracks confirmed')
    center = start_centroid(dataset, extras, delay_s)
    remaining = replay_config.camera_delay_s - args.camera_delay
    lines, document = report(dataset, loop, records, map_study(records, dataset.landmarks,
                                                               center), remaining)
    print('\n'.join(lines))
    if args.json:
        document['scores'] = {**scores, 'position_rmse_m': overall['position_rmse_m'],
                              'anees': overall['anees']}
        args.json.write_text(json.dumps(document, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
