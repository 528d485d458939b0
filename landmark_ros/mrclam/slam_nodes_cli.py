"""
``landmark_mrclam --slam --through-nodes``: run the loop through the nodes and compare.

The node run (``slam_nodes.run_through_nodes``: no anchors, no robot sightings; IDs
shown, or hidden with ``--hide-ids``, the localizers then naming the rows themselves,
``slam_association: localizer``) beside ``slam_plan.offline_reference`` (the offline
loop with the same events) and the offline ``--slam`` entry of the same mode. ``--json`` gains
``slam_nodes`` (the node run: the keys of a ``slam`` entry) and ``slam_agreement``
(``compare``: the published poses, the final map and the rows, against the reference;
the figures against the reference and against the full offline run). With
``--live-order`` the localizers take the sightings before the odometry that passes
their stamp (``slam_nodes``): the agreement then measures what that order changes.
"""

from pathlib import Path
import shutil
import sys
import tempfile

from landmark_ros.mrclam import slam
from landmark_ros.mrclam.data import interpolate_poses
from landmark_ros.mrclam.localize import KEYS, metrics, Track
from landmark_ros.mrclam.localize_nodes import real_time_factor
from landmark_ros.mrclam.slam_plan import offline_reference, without_robot_sightings
import numpy as np

FIGURES = KEYS + ('map_rmse_m', 'map_anees')


def _pose_diffs(offline, nodes):
    """Return (same stamps, position, heading, covariance) differences of pose lists."""
    same, dpos, dyaw, dcov = True, 0.0, 0.0, 0.0
    for a, b in zip(offline, nodes):
        if not np.array_equal(a['stamps_ns'], b['stamps_ns']):
            same = False
            continue
        if len(a['x']):
            d = a['x'] - b['x']
            dpos = max(dpos, float(np.max(np.hypot(d[:, 0], d[:, 1]))))
            dyaw = max(dyaw, float(np.max(np.abs(np.angle(np.exp(1j * d[:, 2]))))))
            dcov = max(dcov, float(np.max(np.abs(a['P'] - b['P']))))
    return same, dpos, dyaw, dcov


def compare(reference, nodes):
    """
    Return the agreement of a node run with the offline loop of the same events.

    Keys: ``same_stamps`` (every robot the same published pose stamps),
    ``max_position_diff_m``, ``max_heading_diff_rad``, ``max_cov_diff`` (the published
    poses: the pose of each odometry before the sightings it places), ``same_map_ids``,
    ``max_map_mean_diff_m``, ``max_map_cov_diff`` (the final map), ``same_rows``
    (rows used and gated, batches re-filtered, per localizer),
    ``track_max_position_diff_m`` (against ``TeamLoop``'s own tracks, the estimates
    after those sightings).
    """
    loop = reference.loop
    same, dpos, dyaw, dcov = _pose_diffs(reference.published, nodes['published'])
    tracks = [dict(zip(('stamps_ns', 'x', 'P'), t.arrays())) for t in loop.tracks]
    _, track_dpos, _, _ = _pose_diffs(tracks, nodes['published'])
    ids, m, P, _, _ = loop.fuser.map.snapshot()
    the_map = nodes['map']
    same_ids = np.array_equal(ids, the_map['ids'])
    rows = all(int(loc.counters[key]) == int(track.counts.get(key, 0))
               for loc, track in zip(loop.localizers, nodes['tracks'])
               for key in ('rows_used', 'rows_gated', 'refiltered'))
    return {'same_stamps': same, 'max_position_diff_m': dpos, 'max_heading_diff_rad': dyaw,
            'max_cov_diff': dcov, 'same_map_ids': bool(same_ids),
            'max_map_mean_diff_m': float(np.max(np.abs(m - the_map['m']), initial=0.0))
            if same_ids else float('nan'),
            'max_map_cov_diff': float(np.max(np.abs(P - the_map['P']), initial=0.0))
            if same_ids else float('nan'),
            'same_rows': bool(rows), 'track_max_position_diff_m': track_dpos}


def node_entry(dataset, nodes, hide_ids=False):
    """Return the node run's entry: the keys of a ``slam`` entry."""
    robots, overall = metrics(nodes['tracks'])
    the_map = nodes['map']
    records = [{'id': int(i), 'mean': mean.tolist(), 'covariance': cov.tolist(),
                'observations': int(n)} for i, mean, cov, n in zip(
                    the_map['ids'], the_map['m'], the_map['P'], the_map['observations'])]
    _, scores = slam.map_entry(dataset, records, hide_ids)
    info = nodes['info']
    return {'ids_hidden': bool(hide_ids), 'anchors': False, 'robot_sightings': False,
            **{key: overall[key] for key in KEYS}, **scores,
            'rows_used': overall['rows_used'], 'rows_gated': overall['rows_gated'],
            'seconds': info['play_wall_s'], 'cpu_seconds': info['node_cpu_s'],
            'real_time_factor': real_time_factor(dataset.duration, info),
            'startup_s': info['startup_s'], 'player': dict(info), 'robots': robots}


def reference_entry(dataset, reference):
    """Return the figures of the offline loop without robot sightings, published poses."""
    tracks = []
    for robot, pub, loc in zip(dataset.robots, reference.published, reference.loop.localizers):
        times = pub['stamps_ns'] * 1e-9
        truth, inside = interpolate_poses(robot.gt_times, robot.gt_poses, times)
        tracks.append(Track(robot.number, times[inside], pub['x'][inside], pub['P'][inside],
                            truth[inside], dict(loc.counters.counts)))
    robots, overall = metrics(tracks)
    _, scores = slam.map_entry(dataset, reference.loop.map_records(),
                               reference.loop.config.hide_ids)
    return {**{key: overall[key] for key in KEYS}, **scores, 'robots': robots}


def through_nodes(args, data, results, document):
    """
    Run ``--slam --through-nodes``; fill ``document``; return the exit code.

    ``data`` is ``(dataset, extras, loop_config, config_path, delay_s)``; ``results``
    the offline ``slam.SlamResult`` list (its no-anchors entry of the same IDs mode is
    compared).
    Returns 1 when the run failed or does not agree (stamps, rows or map IDs differ;
    with ``--live-order`` only when it failed: the differences are then measured).
    """
    from landmark_ros.mrclam.replay_plan import domain_id_for, ReplayError
    from landmark_ros.mrclam.slam_nodes import run_through_nodes
    dataset, extras, loop_config, config_path, delay_s = data
    if loop_config.hide_ids and loop_config.association != 'localizer':
        print('landmark_mrclam: --slam --through-nodes --hide-ids needs slam_association: '
              "localizer (a localizer node cannot take the fuser's track IDs)",
              file=sys.stderr)
        return 1
    extras = without_robot_sightings(extras)
    reference = offline_reference(dataset, extras, loop_config, delay_s)
    domain = domain_id_for() if args.domain_id is None else int(args.domain_id)
    work = Path(tempfile.mkdtemp(prefix='landmark_mrclam_slam_'))
    print(f'through the nodes: ROS_DOMAIN_ID={domain}, loopback only; logs in {work}')
    live = bool(getattr(args, 'live_order', False))
    try:
        nodes = run_through_nodes(dataset, extras, loop_config, (config_path, work),
                                  delay_s, domain, live)
    except (RuntimeError, ReplayError) as error:
        print(f'landmark_mrclam: {error}', file=sys.stderr)
        return 1
    entry = node_entry(dataset, nodes, loop_config.hide_ids)
    agreement = {'order': 'live' if live else 'offline', **compare(reference, nodes)}
    ref_entry = reference_entry(dataset, reference)
    agreement['max_figure_diff'] = max(abs(entry[k] - ref_entry[k]) for k in FIGURES)
    offline = next((r.entry for r in results
                    if r.mode.hide_ids == loop_config.hide_ids and not r.mode.anchors), None)
    if offline is not None:
        agreement['figures_minus_offline_slam'] = {k: entry[k] - offline[k] for k in FIGURES}
    document['mode'] = 'through_nodes'
    document['slam_nodes'] = [entry]
    document['slam_agreement'] = [agreement]
    print(format_agreement(entry, agreement, dataset.duration, loop_config.hide_ids))
    # In the live order the differences are the measurement, not a failure.
    ok = live or (agreement['same_stamps'] and agreement['same_rows']
                  and agreement['same_map_ids'])
    if ok and not args.keep_logs:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


def format_agreement(entry, a, duration_s, hide_ids=False):
    """Return the node run's figures and its agreement as text."""
    ids = 'IDs hidden' if hide_ids else 'IDs'
    lines = [f'through the nodes ({a["order"]} order; {ids}, no anchors, no robot sightings): '
             f'position RMSE '
             f'{entry["position_rmse_m"]:.3f} m, heading RMSE {entry["heading_rmse_rad"]:.4f} '
             f'rad, ANEES {entry["anees"]:.2f}, in 95% {entry["inside_95_fraction"]:.3f}; '
             f'map RMSE {entry["map_rmse_m"]:.3f} m, ANEES {entry["map_anees"]:.2f}, '
             f'{entry["tracks_confirmed"]} landmarks; {entry["seconds"]:.1f} s wall '
             f'({duration_s / max(entry["seconds"], 1e-9):.2f}x real time), '
             f'{entry["cpu_seconds"]:.1f} s node CPU',
             f'agreement with the offline loop of the same events: same stamps '
             f'{a["same_stamps"]}, same rows {a["same_rows"]}, same map IDs '
             f'{a["same_map_ids"]}; published poses: position {a["max_position_diff_m"]:.3g} m, '
             f'heading {a["max_heading_diff_rad"]:.3g} rad, covariance '
             f'{a["max_cov_diff"]:.3g}; map: mean {a["max_map_mean_diff_m"]:.3g} m, '
             f'covariance {a["max_map_cov_diff"]:.3g}; figures {a["max_figure_diff"]:.3g}; '
             f'TeamLoop tracks (after the sightings) {a["track_max_position_diff_m"]:.3g} m']
    if 'figures_minus_offline_slam' in a:
        lines.append('figures minus the offline --slam run (with robot sightings): ' + ', '.join(
            f'{k} {v:+.4f}' for k, v in a['figures_minus_offline_slam'].items()))
    return '\n'.join(lines)
