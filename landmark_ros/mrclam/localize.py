"""
``landmark_mrclam --localize``: every robot localizes from its odometry and sightings.

Each robot runs one ``localizer.Localizer`` (the node's pipeline object) from its
ground-truth pose at the start of its odometry (covariance ``initial_stddev``), fed in
global time order (ties: odometry first, then by robot): its odometry twists (stamped
``odometry_delay_s`` later, ``localize_data.odometry_delay``), its landmark sightings
(range-bearing rows with IDs, one message per robot and stamp) and, in the cooperative
mode, its sightings of other robots with the other's estimate at that stamp, copied as a
message would carry it (``Localizer.add_robot_sighting``; nothing else is shared).

Maps: ``surveyed`` (``Landmark_Groundtruth.dat`` with the covariance
``surveyed_stddev^2 + file std-dev^2`` per axis) and ``fused`` (the split-CI map the
fuser builds in the offline replay, ``offline.run_offline``, with its covariances).
Modes: landmark sightings only, and cooperative (with robot-to-robot sightings); dead
reckoning (no sightings) is the floor.

Per robot and overall, over every odometry stamp inside the ground truth: position and
heading RMSE, average NEES of the 3-dof pose (3 is consistent), the fraction of stamps
whose true position lies inside the 95 % ellipse of the position, rows used and gated.
"""

from dataclasses import dataclass
import math
import time

from landmark_ros.core.gating import chi2_threshold
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
from landmark_ros.mrclam.data import interpolate_poses, seconds_to_stamps_ns
from landmark_ros.mrclam.localize_data import heading_error
import numpy as np

MAPS = ('surveyed', 'fused')
SURVEYED_STDDEV = 0.01
"""Stated standard deviation of a surveyed landmark per axis [m], beyond the file's."""
KEYS = ('position_rmse_m', 'heading_rmse_rad', 'anees', 'inside_95_fraction')
_ODOM, _OBS, _ROBOT = 0, 1, 2


@dataclass
class Track:
    """One robot's estimates at its odometry stamps, with the truth there."""

    robot: int
    times: np.ndarray
    x: np.ndarray
    P: np.ndarray
    truth: np.ndarray
    counts: dict


def surveyed_map(dataset, stddev=SURVEYED_STDDEV):
    """Return ids (N,), m (N, 2), P_m (N, 2, 2) of the surveyed landmarks."""
    ids = np.array(sorted(dataset.landmarks), np.int64)
    m = np.array([dataset.landmarks[i] for i in ids]).reshape(-1, 2)
    s = np.array([dataset.landmark_stddev[i] for i in ids]).reshape(-1, 2)
    P = np.zeros((len(ids), 2, 2))
    P[:, 0, 0] = stddev ** 2 + s[:, 0] ** 2
    P[:, 1, 1] = stddev ** 2 + s[:, 1] ** 2
    return ids, m, P


def fused_map(dataset, replay_config):
    """Return ids, m, P_m of the map the split-CI fuser builds in the offline replay."""
    from landmark_ros.mrclam.offline import run_offline
    method = 'split_covariance_intersection'
    records = run_offline(dataset, replay_config, [method]).results[method].records
    ids = np.array([r['id'] for r in records], np.int64)
    m = np.array([r['mean'] for r in records], dtype=np.float64).reshape(-1, 2)
    P = np.array([r['covariance'] for r in records], dtype=np.float64).reshape(-1, 2, 2)
    return ids, m, P


def _events(dataset, extras, delay_s, sightings, cooperative):
    """Return the events as parallel arrays sorted by (time, kind, robot)."""
    t, kind, robot, index = [], [], [], []
    for r_i, robot_data in enumerate(dataset.robots):
        ex = extras[robot_data.number]
        n = len(ex.odom_times)
        t.append(ex.odom_times + delay_s)
        kind.append(np.full(n, _ODOM))
        robot.append(np.full(n, r_i))
        index.append(np.arange(n))
        if sightings and len(robot_data.times):
            new = np.ones(len(robot_data.times), bool)
            new[1:] = robot_data.times[1:] != robot_data.times[:-1]
            starts = np.flatnonzero(new)
            t.append(robot_data.times[starts])
            kind.append(np.full(len(starts), _OBS))
            robot.append(np.full(len(starts), r_i))
            index.append(starts)
        if cooperative and len(ex.sighting_times):
            t.append(ex.sighting_times)
            kind.append(np.full(len(ex.sighting_times), _ROBOT))
            robot.append(np.full(len(ex.sighting_times), r_i))
            index.append(np.arange(len(ex.sighting_times)))
    t, kind = np.concatenate(t), np.concatenate(kind)
    robot, index = np.concatenate(robot), np.concatenate(index)
    order = np.lexsort((robot, kind, t))
    return t[order], kind[order], robot[order], index[order]


def run(dataset, extras, config, the_map=None, cooperative=False, delay_s=0.0,
        progress=None):
    """
    Localize every robot; return one ``Track`` per robot, in dataset order.

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        The loaded dataset (sightings, ground truth).
    extras : dict
        ``localize_data.RobotExtras`` by robot number.
    config : LocalizerConfig
        The localizer parameters (every robot the same).
    the_map : tuple (ids, m, P_m), optional
        None: dead reckoning (no sightings).
    cooperative : bool
        Apply the robot-to-robot sightings.
    delay_s : float
        Added to the odometry stamps [s].
    progress : callable, optional
        ``progress(fraction)`` now and then.

    """
    robots = dataset.robots
    number_to_index = {r.number: i for i, r in enumerate(robots)}
    locs = [Localizer(config) for _ in robots]
    t, kind, who, index = _events(dataset, extras, delay_s, the_map is not None, cooperative)
    records = [[] for _ in robots]
    for i, (r, loc) in enumerate(zip(robots, locs)):
        ex = extras[r.number]
        start = max(ex.odom_times[0] + delay_s, r.gt_times[0])
        pose, _ = interpolate_poses(r.gt_times, r.gt_poses, [start])
        loc.initialize(int(seconds_to_stamps_ns([start])[0]), pose[0],
                       np.diag(np.square(config.initial_stddev)))
        if the_map is not None:
            loc.set_map(*the_map)
    stamps = seconds_to_stamps_ns(t)
    step = max(1, len(t) // 100)
    for e in range(len(t)):
        i, k, loc = who[e], index[e], locs[who[e]]
        if kind[e] == _ODOM:
            est = loc.add_odometry(stamps[e], twist=extras[robots[i].number].odom_twist[k])
            if est is not None:
                records[i].append((stamps[e], est.x, est.P))
        elif kind[e] == _OBS:
            r = robots[i]
            end = k + 1
            while end < len(r.times) and r.times[end] == r.times[k]:
                end += 1
            loc.add_observations(stamps[e], r.ids[k:end], r.z[k:end])
        else:
            ex = extras[robots[i].number]
            j = number_to_index.get(int(ex.sighting_robot[k]))
            other = None if j is None else locs[j].pose_at(stamps[e])
            if other is not None:
                loc.add_robot_sighting(stamps[e], ex.sighting_z[k], other,
                                       other_id=robots[j].name)
        if progress is not None and e % step == 0:
            progress(e / len(t))
    return [_track(r, rec, loc) for r, rec, loc in zip(robots, records, locs)]


def _track(robot, rec, loc):
    times = np.array([s for s, _, _ in rec], np.int64) * 1e-9
    x = np.array([a for _, a, _ in rec]).reshape(-1, 3)
    P = np.array([b for _, _, b in rec]).reshape(-1, 3, 3)
    truth, inside = interpolate_poses(robot.gt_times, robot.gt_poses, times)
    return Track(robot.number, times[inside], x[inside], P[inside], truth[inside],
                 dict(loc.counters.counts))


def metrics(tracks):
    """Return per-robot entries and the overall one (``KEYS`` plus rows used/gated)."""
    inside_threshold = chi2_threshold(2, 0.95)
    entries, pooled = [], []
    for tr in tracks:
        e = tr.x - tr.truth
        e[:, 2] = heading_error(tr.x[:, 2], tr.truth[:, 2])
        nees = np.einsum('ni,ni->n', e, np.linalg.solve(tr.P, e[..., None])[..., 0])
        pos = np.einsum('ni,ni->n', e[:, :2],
                        np.linalg.solve(tr.P[:, :2, :2], e[:, :2, None])[..., 0])
        pooled.append((e, nees, pos))
        entries.append({'robot': tr.robot, **_figures(e, nees, pos, inside_threshold),
                        'rows_used': int(tr.counts.get('rows_used', 0)),
                        'rows_gated': int(tr.counts.get('rows_gated', 0)),
                        'robot_rows_used': int(tr.counts.get('robot_rows_used', 0)),
                        'robot_rows_gated': int(tr.counts.get('robot_rows_gated', 0))})
    e = np.concatenate([p[0] for p in pooled])
    overall = _figures(e, np.concatenate([p[1] for p in pooled]),
                       np.concatenate([p[2] for p in pooled]), inside_threshold)
    for key in ('rows_used', 'rows_gated', 'robot_rows_used', 'robot_rows_gated'):
        overall[key] = sum(entry[key] for entry in entries)
    return entries, overall


def _figures(e, nees, pos, threshold):
    return {'position_rmse_m': float(math.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1)))),
            'heading_rmse_rad': float(math.sqrt(np.mean(e[:, 2] ** 2))),
            'anees': float(np.mean(nees)),
            'inside_95_fraction': float(np.mean(pos <= threshold))}


def consistent(entry):
    """Return whether an entry meets the issue's consistency rule."""
    return 1.5 <= entry['anees'] <= 4.5 and entry['inside_95_fraction'] >= 0.9


def run_all(dataset, extras, config, maps, delay_s, progress_factory=None):
    """
    Run dead reckoning and every map and mode; return the JSON entries and the tracks.

    ``maps`` is a dict name -> (ids, m, P_m). Entries: ``map`` (``dead_reckoning`` for
    the floor), ``cooperative``, the ``KEYS``, rows, ``seconds`` and ``robots``.
    """
    runs = [('dead_reckoning', None, False)]
    for name, the_map in maps.items():
        runs += [(name, the_map, False), (name, the_map, True)]
    entries, tracks = [], {}
    for name, the_map, coop in runs:
        t0, cpu0 = time.monotonic(), time.process_time()
        progress = progress_factory(f'{name}{" + robots" if coop else ""}') \
            if progress_factory else None
        result = run(dataset, extras, config, the_map, coop, delay_s,
                     progress.update if progress else None)
        if progress:
            progress.close()
        robots, overall = metrics(result)
        entries.append({'map': name, 'cooperative': coop, **overall,
                        'seconds': time.monotonic() - t0,
                        'cpu_seconds': time.process_time() - cpu0, 'robots': robots})
        tracks[(name, coop)] = result
    return entries, tracks


def format_table(entries, duration_s):
    """Return the per-robot and overall figures as text, with the targets that hold."""
    lines = [f'{"map":15s} {"coop":5s} {"robot":>5s} {"pos RMSE":>9s} {"yaw RMSE":>9s} '
             f'{"ANEES":>7s} {"in 95%":>7s} {"used":>6s} {"gated":>6s} {"r used":>6s}  ok']
    for entry in entries:
        rows = entry['robots'] + [dict(entry, robot='all')]
        for row in rows:
            ok = 'yes' if consistent(row) else 'no'
            lines.append(f'{entry["map"]:15s} {str(entry["cooperative"]):5s} '
                         f'{str(row["robot"]):>5s} {row["position_rmse_m"]:9.3f} '
                         f'{row["heading_rmse_rad"]:9.4f} {row["anees"]:7.2f} '
                         f'{row["inside_95_fraction"]:7.3f} {row["rows_used"]:6d} '
                         f'{row["rows_gated"]:6d} {row["robot_rows_used"]:6d}  {ok}')
        lines.append(f'  ({entry["seconds"]:.1f} s wall, {entry["cpu_seconds"]:.1f} s CPU: '
                     f'{duration_s / entry["seconds"]:.0f}x real time by the wall clock, '
                     f'{duration_s / entry["cpu_seconds"]:.0f}x by CPU time)')
    return '\n'.join(lines)


def targets(entries):
    """Return the issue's targets as (name, holds) pairs."""
    by = {(e['map'], e['cooperative']): e for e in entries}
    out = []
    s, c, f = by.get(('surveyed', False)), by.get(('surveyed', True)), by.get(('fused', False))
    if s:
        out.append(('surveyed: RMSE <= 0.12 m overall', s['position_rmse_m'] <= 0.12))
        out.append(('surveyed: RMSE <= 0.15 m every robot',
                    all(r['position_rmse_m'] <= 0.15 for r in s['robots'])))
        out.append(('surveyed: consistent every robot', all(map(consistent, s['robots']))))
    if s and c:
        out.append(('surveyed + robots: RMSE no worse overall',
                    c['position_rmse_m'] <= s['position_rmse_m']))
        out.append(('surveyed + robots: consistent every robot',
                    all(map(consistent, c['robots']))))
    if f:
        out.append(('fused: RMSE <= 0.15 m overall', f['position_rmse_m'] <= 0.15))
        out.append(('fused: consistent every robot', all(map(consistent, f['robots']))))
    return out


def localizer_config(values):
    """Return the ``LocalizerConfig`` of a params-file section (unknown keys ignored)."""
    return LocalizerConfig.from_values(values)
