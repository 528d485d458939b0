"""
The ``--slam`` mode of ``landmark_mrclam``: the team without motion capture.

``mrclam.slam.run_all`` with the params file's observer, fuser and localizer sections
(``config/mrclam.yaml``) and, from its ``landmark_mrclam`` section, the odometry delay
(``odometry_delay_s``), the camera delay (``camera_delay_s``: every sighting moved back,
``localize_data.with_camera_delay``) and the anchors (``slam_anchor_ids``: surveyed
landmarks written as a fuser map file; ``--anchors FILE`` takes a map file instead).
Runs the four modes (IDs shown or hidden, without or with anchors); with ``--hide-ids``
only the two without IDs. Prints the per-robot table, the map figures and which of the issue's
targets hold; ``--json`` gains ``slam`` (one entry per mode), ``--plot FILE`` draws one
picture per mode (``FILE`` stem + ``-ids|-noids`` + ``-anchors``).

One mode in its own process (a whole run takes minutes; one mode per process keeps the
runs apart): ``python -m landmark_ros.mrclam.slam_cli [--hide-ids] [--anchors]
[--duration S] [--start S] [--range-scale-state] [--precision-sources K]
[--no-robot-sightings] [--estimator loop|team_ekf] [--json OUT] [DATASET]`` prints the
same table and the map's landmarks one per line (error, NEES); ``--estimator team_ekf``
runs the reference that keeps every correlation (``eval.team_ekf``,
docs/slam-analysis.md) instead of the loop. The ``ok`` column: the
robot is consistent (pose ANEES 1.5 to 4.5 and at least 90 % of its poses inside their
95 % ellipse, ``localize.consistent``).
"""

import argparse
from dataclasses import replace
from pathlib import Path

from landmark_ros.mrclam import slam
from landmark_ros.mrclam.config import (add_dataset_arguments, default_dataset_path,
                                        load_config)
from landmark_ros.mrclam.data import load_dataset
from landmark_ros.mrclam.localize import localizer_config
from landmark_ros.mrclam.localize_cli import _Bar, _sections
from landmark_ros.mrclam.localize_data import load_all_extras, with_camera_delay
from landmark_ros.mrclam.localize_plan import slice_run
from landmark_ros.mrclam.report import write_json
from landmark_ros.mrclam.slam_plan import without_robot_sightings
import numpy as np


def _modes(args):
    if args.hide_ids:
        return tuple(mode for mode in slam.MODES if mode.hide_ids)
    return slam.MODES


def _plot(args, dataset, results):
    from landmark_ros.mrclam.localize_plot import plot_run
    path = Path(args.plot)
    for result in results:
        mode = result.mode
        out = path.with_name(f'{path.stem}-{"noids" if mode.hide_ids else "ids"}'
                             f'{"-anchors" if mode.anchors else ""}{path.suffix}')
        plot_run(out, dataset, result.tracks, f'MRCLAM {dataset.path.name}, no motion capture '
                 f'({mode.label}): paths and map, 2 sigma', landmarks=result.records)
        print(f'wrote {out}')


def _setup(replay_config, dataset, duration, start_s=0.0, overrides=None):
    """
    Return the loop config, odometry delay, anchor IDs, dataset and extras (sliced).

    ``duration`` [s] (None: to the end) from ``start_s`` [s] after the first sighting;
    ``overrides``: values of the ``landmark_mrclam`` section to replace.
    """
    localizer_values, replay_values = _sections(replay_config.path)
    replay_values = {**replay_values, **(overrides or {})}
    config = slam.loop_config(replay_config, localizer_config(localizer_values),
                              replay_values)
    delay_s = float(replay_values.get('odometry_delay_s', 0.0))
    anchor_ids = tuple(int(i) for i in replay_values.get('slam_anchor_ids',
                                                         slam.DEFAULT_ANCHORS))
    dataset, extras = with_camera_delay(dataset, load_all_extras(dataset),
                                        replay_config.camera_delay_s)
    if duration is not None or start_s:
        dataset, extras = slice_run(dataset, extras, duration, start_s)
    return config, delay_s, anchor_ids, dataset, extras


def run_slam(args, dataset, replay_config, document):
    """Run ``--slam``; return the exit code (0 also when targets fail: they print)."""
    config, delay_s, anchor_ids, dataset, extras = _setup(replay_config, dataset,
                                                          args.duration)
    if args.duration is not None:
        document['dataset']['duration_s'] = dataset.duration
    bar = None if args.no_progress else _Bar
    modes = _modes(args)
    if args.anchors is not None:
        no_anchors = [m for m in modes if not m.anchors]
        results = slam.run_all(dataset, extras, config, (), delay_s, no_anchors, bar)
        results += [slam.run_mode(dataset, extras, config, m, delay_s, str(args.anchors))
                    for m in modes if m.anchors]
    else:
        results = slam.run_all(dataset, extras, config, anchor_ids, delay_s, modes, bar)
    print(slam.format_table(results, dataset.duration))
    print('targets (no anchors):')
    for name, holds in slam.targets(results):
        print(f'  {"holds" if holds else "FAILS"}: {name}')
    document['slam'] = [result.entry for result in results]
    document['slam_anchors'] = (str(args.anchors) if args.anchors is not None
                                else list(anchor_ids))
    document['localizer_config'] = {k: (list(v) if isinstance(v, tuple) else v)
                                    for k, v in vars(replace(config.localizer)).items()}
    document['odometry_delay_s'] = delay_s
    code = 0
    if args.through_nodes:
        from landmark_ros.mrclam.slam_nodes_cli import through_nodes
        # The observers publish the loop's precision sources (landmarks/precision_k).
        nodes_config = replace(config, hide_ids=bool(args.hide_ids))
        code = through_nodes(args, (dataset, extras, nodes_config, replay_config.path,
                                    delay_s), results, document)
    if args.json:
        write_json(args.json, document)
        print(f'wrote {args.json}')
    if args.plot:
        _plot(args, dataset, results)
    return code


def _landmark_lines(records, truth):
    """Return one line per scored landmark: ID, error [m], NEES, standard deviations."""
    from landmark_ros.mrclam.report import method_result
    lines = []
    for row in method_result('split_covariance_intersection', records, truth, 0, 0).results:
        sd = np.sqrt(np.linalg.eigvalsh(row.P))
        lines.append(f'  landmark {row.id:3d}: error {row.error_m:.3f} m, NEES {row.nees:7.2f}, '
                     f'sd {sd[0]:.3f} {sd[1]:.3f} m, {row.observations} rows')
    return lines


def main(argv=None):
    """Run one ``--slam`` mode (module docstring); return the exit code."""
    parser = argparse.ArgumentParser(prog='python -m landmark_ros.mrclam.slam_cli',
                                     description='landmark_mrclam --slam, one mode.')
    add_dataset_arguments(parser)
    parser.add_argument('--hide-ids', action='store_true',
                        help='sightings without IDs: the loop (or the team EKF) associates '
                        'them')
    parser.add_argument('--anchors', action='store_true',
                        help='anchor the frame with slam_anchor_ids of the config (default 6, '
                        '11, 19)')
    parser.add_argument('--duration', type=float, default=None, metavar='SECONDS',
                        help='only SECONDS of the run (from --start)')
    parser.add_argument('--start', type=float, default=0.0, metavar='SECONDS',
                        help='start this long after the first sighting (the robots at '
                        'their true pose then, an empty map): --start 443 is the second '
                        'half of dataset 6')
    parser.add_argument('--json', type=Path, default=None,
                        help='write the figures (a slam entry) as JSON')
    parser.add_argument('--range-scale-state', action='store_true',
                        help='the localizers (or the team EKF) keep the range scale states '
                        'of the localizer section (slam_range_scale_state: true)')
    parser.add_argument('--precision-sources', type=int, default=None, metavar='K',
                        help="the observers' precision sources in the loop "
                        '(slam_precision_sources of the config; 1: one source per robot)')
    parser.add_argument('--no-robot-sightings', action='store_true',
                        help="leave out the robots' sightings of each other (as "
                        '--through-nodes does)')
    parser.add_argument('--estimator', default='loop', choices=('loop', 'team_ekf'),
                        help='loop: the pipeline of the nodes (TeamLoop); team_ekf: the reference '
                        'that keeps every correlation (eval.team_ekf)')
    args = parser.parse_args(argv)
    replay_config = load_config(args.config)
    dataset = load_dataset(args.dataset or default_dataset_path(), replay_config.pose_stddev)
    overrides = {'slam_range_scale_state': True} if args.range_scale_state else {}
    if args.precision_sources is not None:
        overrides['slam_precision_sources'] = args.precision_sources
    config, delay_s, anchor_ids, dataset, extras = _setup(replay_config, dataset,
                                                          args.duration, args.start, overrides)
    if args.no_robot_sightings:
        extras = without_robot_sightings(extras)
    mode = slam.SlamMode(args.hide_ids, args.anchors)
    loop_class = slam.TeamLoop
    if args.estimator == 'team_ekf':
        from landmark_ros.eval.team_ekf import TeamEKF
        loop_class = TeamEKF
    result, = slam.run_all(dataset, extras, config, anchor_ids, delay_s, (mode,),
                           loop_class=loop_class)
    result.entry['estimator'] = args.estimator
    print(slam.format_table([result], dataset.duration))
    print('\n'.join(_landmark_lines(result.records, dataset.landmarks)))
    if args.json:
        options = {'range_scale_state': args.range_scale_state, 'duration_s': args.duration,
                   'start_s': args.start, 'dataset': str(dataset.path),
                   'precision_sources': config.observer.precision_sources,
                   'robot_sightings': not args.no_robot_sightings}
        write_json(args.json, {'slam': [dict(result.entry, options=options)]})
        print(f'wrote {args.json}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
