"""
landmark_mrclam: replay a UTIAS MRCLAM dataset through the landmark pipeline.

Real data (5 robots reading barcodes on 15 landmarks, with Vicon ground truth) through
the same code as the nodes, then the fused maps against the true landmark positions::

    landmark_mrclam [DATASET] [--config config/mrclam.yaml] [--fusion METHOD]
                    [--through-nodes [--no-progress] [--keep-logs] [--domain-id N]]
                    [--sensor rb|range|bearing] [--json FILE] [--plot FILE] [--calibrate]
                    [--export-bag OUT (deprecated)] [--hide-ids]
                    [--cross-validate [--folds halves|robots] [--modes MODE ...]]

``DATASET`` is a MRCLAM directory (default: ``shared/data/mrclam/dataset6`` beside the
repository). Sightings, poses and ground truth come from ``landmark_ros.mrclam.data``:
landmark sightings only, each with the ground-truth pose interpolated at its stamp and
the covariance ``pose_stddev_*`` of the ``landmark_mrclam`` section of the config. The
fusion replays (offline, ``--through-nodes``, ``--sensor``, ``--hide-ids``) move the
sightings back by the config's ``camera_delay_s`` (``Dataset.with_camera_delay``);
``--localize`` and ``--slam`` too, with the robots' sightings of each other
(``localize_data.with_camera_delay``); ``--calibrate`` and ``--cross-validate`` estimate
the delay themselves (``camera_delay``) from the raw stamps.

The replay's modules, by role: ``config`` (the params file), ``data`` (the reader),
``offline``, ``player`` (through the nodes), ``calibrate``, ``report`` (tables, JSON,
plot); this one parses the command line.

Modes
-----
offline (default)
    ``landmark_ros.mrclam.offline``: the pipeline objects the nodes run, without ROS.
    One ``observer.Observer`` per robot gets, in global time order (ties by
    robot number), the robot's pose at each measurement stamp, then that stamp's
    observation message (integer nanosecond stamps, as the player publishes them);
    one ``fuser.Fuser`` per fusion method gets every landmark batch, source
    the robot's landmark topic ``/robotN/landmarks``, and fuses its queue every chunk
    (the same map as row by row). One map per fusion method, all three unless
    ``--fusion`` names one.
``--through-nodes``
    ``landmark_ros.mrclam.through_nodes`` and ``player`` (the only modules of the replay
    that import ROS, loaded for this mode only): the same data over DDS (loopback only, private
    ROS_DOMAIN_ID 100-149 from the process ID unless ``--domain-id``) through the real
    nodes, in processes started by
    ``landmark_ros.ros.launcher``: one ``landmark_observer`` per robot (namespace
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
``--sensor range`` / ``--sensor bearing``
    The offline replay with the bearings (ranges) dropped: each observer turns the
    range-only (bearing-only) rows into ``partial_observations`` and the fusers place
    the landmarks from those partial observations (``fuser.partial``). With ``--through-nodes`` the
    player publishes the clouds without the dropped field and the fusers also take
    ``/robotN/partial_observations`` (``player.Player``); not with ``--hide-ids``.
``--hide-ids``
    Landmarks without IDs: the observation messages go without their ``id`` field
    (through the nodes: every row ``UNKNOWN_ID``),
    the fusers associate the sightings (``fuser.tracks``, parameter
    ``association``) and each summary entry gains ``association_accuracy`` (a sighting
    is right when it went to the confirmed track matched, by optimal assignment on
    positions within 1 m, to its true landmark), ``oracle_accuracy`` (each sighting to
    the nearest true landmark by Mahalanobis distance, the true map known),
    ``tracks_confirmed``, ``true_landmarks`` and ``gospa_m`` (c = 1 m, p = 2,
    alpha = 2); RMSE and ANEES are those of the matched tracks. With
    ``--through-nodes`` the player sends the clouds in one global order (a barrier at
    every change of robot, ``replay_plan.sequential``) and the agreement gains
    ``same_track_ids`` (the fusers' own track IDs, matched to the same landmarks); the
    nodes do not publish which track each sighting went to, so the nodes' entries take
    the offline accuracies only when their maps agree exactly
    (``report.fill_node_association``), else null.
``--localize``
    Every robot localizes from its odometry and sightings (``landmark_localizer``'s
    pipeline object) against the surveyed and the fused map, with and without
    robot-to-robot sightings, dead reckoning as the floor
    (``landmark_ros.mrclam.localize_cli``); ``--json`` gains ``localization``.
``--slam``
    The team without motion capture: every robot's localizer, observer and the team's
    fuser in a closed loop from odometry and sightings, the ground truth only at the
    start (``landmark_ros.mrclam.slam``); with and without IDs and anchors;
    ``--json`` gains ``slam``. ``--through-nodes [--live-order]`` also runs the loop
    (IDs, no anchors) through the real nodes (``landmark_ros.mrclam.slam_nodes``);
    ``--json`` then gains ``slam_nodes`` and ``slam_agreement``. ``--duration``
    keeps the first seconds.
``--calibrate-odometry``
    The odometry delay and motion-model alphas from the ground truth, with a
    leave-one-robot-out cross-check (``landmark_ros.mrclam.localize_data``).
``--cross-validate [--folds halves|robots] [--modes MODE ...]``
    ``landmark_ros.mrclam.crossval``: per fold, the sensor model calibrated on one
    part of the run goes into the observer's configuration and the other part is
    replayed, moved back by the camera delay estimated on the first part, in every
    mode (``ids``, ``hide_ids``, ``range``, ``bearing``), split CI unless
    ``--fusion``; ``--modes localize localize_fused`` cross-validate
    ``--localize`` the same way (surveyed and fused map). Folds: the two halves of
    the run, both ways (default), or leave one robot out. ``--json`` writes
    ``{"mode": "cross_validation", "scheme", "dataset", "cross_validation": [{"fold",
    "calibrated_on", "evaluated_on", "mode", "fusion", "calibration",
    "camera_delay_s", "rmse_m",
    "anees", "anees_interval", "consistent", ..., and with hide_ids
    "association_accuracy", "oracle_accuracy", "tracks_confirmed", "true_landmarks",
    "gospa_m"}, ...]}``; a localization entry has "map", the localization keys
    ("position_rmse_m", "heading_rmse_rad", "anees", "inside_95_fraction"),
    "consistent" (every robot) and "robots".
``--calibrate``
    Estimate the camera delay and the sensor model from ground truth and print
    suggested YAML values (``landmark_ros.mrclam.calibrate.calibrate`` documents the
    procedure; ``camera_delay_s`` goes in the ``landmark_mrclam`` section), then the
    landmarks' apparent offsets (``landmark_ros.mrclam.landmark_offsets``).
``--export-bag OUT`` (deprecated, removed in the next release)
    Runs ``landmark_bag --from-mrclam DATASET -o OUT --config CONFIG`` (the bag tool
    owns the export; this replay does not import it) after a deprecation warning on
    stderr, and passes its output and exit code on.

Output
------
Per method the per-landmark table (``evaluation.format_table``), RMSE, average NEES
with its 95 % interval, then a summary table, one row per method.

``--json FILE`` writes one object::

    {"mode": "offline" | "through_nodes",
     "dataset": {"path", "robots", "duration_s", "counts": {...}},
     "config": {"observer": {...}, "fuser": {...}, "pose_stddev": [x, y, yaw]},
     "summary": [                      # one entry per fusion method, in run order
        {"fusion", "sensor", "landmarks_initialised",
         "rmse_m", "anees", "anees_interval": [low, high], "consistent",
         "landmarks_fused", "observations_used", "observations_rejected",
         "landmarks": [                # the method's landmarks, inside its entry
            {"id", "x", "y", "cov": [[xx, xy], [xy, yy]], "error_m", "nees",
             "observations", "rejections"}, ...]}, ...],
     "timing": {...},                  # seconds; speedup = dataset duration / replay
     "agreement": {METHOD: {"same_ids", "same_counts", "max_mean_diff_m",
                            "max_cov_diff_m2", "max_cov_dep_diff_m2",
                            "same_track_ids"}},  # through_nodes; the last with --hide-ids
     "nodes": {...}}                   # through_nodes: counters, diagnostics, CPU time

With ``--calibrate`` the object is ``{"calibration": {...}, "landmark_offsets": {...},
"dataset": {...}}`` (``Calibration.to_dict``, ``landmark_offsets.apparent_offsets``).
``--plot FILE`` draws the robot paths, the true landmarks and the fused landmarks with
their 2-sigma ellipses (matplotlib, ``landmark_ros.eval.plotting``).
"""

import argparse
from pathlib import Path
import subprocess
import sys
import time

from landmark_ros.fusion.landmark_map import FUSION_METHODS
from landmark_ros.mrclam.calibrate import calibrate, format_calibration
from landmark_ros.mrclam.config import (add_dataset_arguments, config_values,
                                        default_dataset_path, load_config)
from landmark_ros.mrclam.crossval import (cross_validate, cross_validate_localize,
                                          format_entry, format_localize_entry, HEADER,
                                          LOCALIZE_HEADER, LOCALIZE_MODES, MODES, SCHEMES)
from landmark_ros.mrclam.data import load_dataset
from landmark_ros.mrclam.landmark_offsets import apparent_offsets, format_offsets
from landmark_ros.mrclam.offline import run_offline, SENSORS
from landmark_ros.mrclam.replay_plan import PlayOptions
from landmark_ros.mrclam.report import (agreement, dataset_dict, dataset_report,
                                        fill_node_association, format_agreement,
                                        format_association, format_node_info, plot, report,
                                        write_json)


def parse_args(argv=None):
    """Return the parsed command line."""
    parser = argparse.ArgumentParser(
        prog='landmark_mrclam',
        description='Replay a UTIAS MRCLAM dataset through the landmark observer and fuser.')
    add_dataset_arguments(parser)
    parser.add_argument('--fusion', choices=FUSION_METHODS, default=None,
                        help='one fusion method (default: all three)')
    parser.add_argument('--sensor', choices=SENSORS, default='rb',
                        help='rb: range and bearing; range: bearings dropped (range-only '
                        'observations); bearing: ranges dropped (bearing-only observations)')
    parser.add_argument('--through-nodes', action='store_true',
                        help='replay over DDS through landmark_observer and landmark_fuser '
                        'processes')
    parser.add_argument('--hide-ids', action='store_true',
                        help='strip the landmark IDs before the observers: the fusers '
                        'associate the sightings (landmarks without IDs)')
    parser.add_argument('--cross-validate', action='store_true',
                        help='calibrate on one part of the run and evaluate on the other, '
                        'both ways, in every mode (split CI unless --fusion)')
    parser.add_argument('--folds', choices=SCHEMES, default='halves',
                        help='--cross-validate folds: the two halves of the run (default) '
                        'or leave one robot out')
    parser.add_argument('--modes', nargs='+', choices=list(MODES) + list(LOCALIZE_MODES),
                        default=list(MODES),
                        help='--cross-validate modes (default: the fusion modes; localize '
                        'and localize_fused cross-validate --localize)')
    parser.add_argument('--calibrate', action='store_true',
                        help='estimate the sensor model from ground truth and print it')
    parser.add_argument('--localize', action='store_true',
                        help='localize every robot from odometry and sightings (surveyed '
                        'and fused maps, with and without robot sightings)')
    parser.add_argument('--duration', type=float, default=None, metavar='SECONDS',
                        help='--localize and --slam (with --through-nodes too): only the '
                        'first SECONDS of the run')
    parser.add_argument('--slam', action='store_true',
                        help='the team without motion capture: localizers, observers and '
                        'the fuser in a closed loop (with and without IDs and anchors)')
    parser.add_argument('--live-order', action='store_true',
                        help='with --slam --through-nodes: the localizers take each '
                        'sighting before the odometry that passes its stamp (one shared '
                        'observations topic) instead of the offline order')
    parser.add_argument('--anchors', type=Path, default=None, metavar='MAP_FILE',
                        help='with --slam: a fuser map file of surveyed landmarks that '
                        'anchor the frame (default: slam_anchor_ids of the config)')
    parser.add_argument('--calibrate-odometry', action='store_true',
                        help='estimate the odometry delay and motion noise from ground truth')
    parser.add_argument('--export-bag', type=Path, default=None, metavar='OUT',
                        help='deprecated (removed in the next release): use landmark_bag '
                        '--from-mrclam DATASET -o OUT; writes the dataset as a rosbag2 (MCAP) '
                        'directory OUT for landmark_bag and stops (OUT must not exist)')
    parser.add_argument('--json', type=Path, default=None, help='write the results as JSON')
    parser.add_argument('--plot', type=Path, default=None, help='draw the maps (PNG, PDF...)')
    parser.add_argument('--no-progress', action='store_true',
                        help='no progress bar for --through-nodes (default: a tqdm bar on '
                        'stderr when it is a terminal)')
    parser.add_argument('--keep-logs', action='store_true',
                        help='keep the node logs of --through-nodes')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID of --through-nodes (default: 100-149 from the '
                        'process ID)')
    return parser.parse_args(argv)


def export_bag(dataset_path, config, path):
    """
    Forward the deprecated ``--export-bag`` to ``landmark_bag --from-mrclam``; return its code.

    The bag tool sits above the replay (``bag/`` imports ``mrclam/``, not the reverse), so
    the export runs as the bag tool's command in a child process; its output is passed on.
    """
    print('landmark_mrclam: --export-bag is deprecated and will be removed in the next '
          f'release: use landmark_bag --from-mrclam {dataset_path} -o {path} '
          f'--config {config.path}', file=sys.stderr)
    command = [sys.executable, '-m', 'landmark_ros.bag.cli', '--from-mrclam',
               str(dataset_path), '-o', str(path), '--config', str(config.path)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, check=False)
    except KeyboardInterrupt:
        print('landmark_mrclam: interrupted: no bag written', file=sys.stderr)
        return 130
    sys.stdout.write(done.stdout)
    sys.stderr.write(done.stderr.replace('landmark_bag: ', 'landmark_mrclam: '))
    return done.returncode


def calibrate_command(args, dataset):
    """Run ``--calibrate``: print (and with ``--json`` write) the calibration; exit code."""
    try:
        calibration = calibrate(dataset)
    except ValueError as error:
        print(f'landmark_mrclam: {error}', file=sys.stderr)
        return 2
    print(format_calibration(calibration))
    offsets = apparent_offsets(dataset.with_camera_delay(calibration.camera_delay_s),
                               calibration.range_scale_coeffs, calibration.range_scale_per_m)
    print(format_offsets(offsets))
    if args.json:
        write_json(args.json, {'calibration': calibration.to_dict(),
                               'landmark_offsets': offsets, 'dataset': dataset_dict(dataset)})
    return 0


def cross_validate_command(args, dataset, config):
    """Run ``--cross-validate``: print each fold's figures per mode; exit code."""
    methods = [args.fusion or 'split_covariance_intersection']
    print(f'== cross-validation ({args.folds}): calibrated on one part, evaluated on the '
          'other')
    fusion_modes = [m for m in args.modes if m in MODES]
    localize_modes = [m for m in args.modes if m in LOCALIZE_MODES]
    entries = []
    try:
        if fusion_modes:
            print(HEADER)
            entries += cross_validate(dataset, config, fusion_modes, methods, args.folds,
                                      progress=lambda e: print(format_entry(e), flush=True))
        if localize_modes:
            entries += cross_validate_localize_command(args, dataset, config, localize_modes)
    except ValueError as error:
        print(f'landmark_mrclam: {error}', file=sys.stderr)
        return 2
    if args.json:
        write_json(args.json, {'mode': 'cross_validation', 'dataset': dataset_dict(dataset),
                               'scheme': args.folds, 'cross_validation': entries})
        print(f'wrote {args.json}')
    return 0


def cross_validate_localize_command(args, dataset, config, modes):
    """Run the ``--cross-validate`` localization modes; return their entries."""
    from landmark_ros.mrclam.config import node_section
    from landmark_ros.mrclam.localize import localizer_config
    from landmark_ros.mrclam.localize_data import load_all_extras
    import yaml
    with open(config.path, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}
    localizer = (localizer_config(node_section(document, 'landmark_localizer')),
                 float(node_section(document, 'landmark_mrclam').get('odometry_delay_s', 0.0)))
    print(LOCALIZE_HEADER)
    return cross_validate_localize(
        dataset, load_all_extras(dataset), config, localizer, modes, args.folds,
        progress=lambda e: print(format_localize_entry(e), flush=True))


def record_nodes(document, timing, offline, results, info):
    """Add the replay through the nodes to the JSON document and the timing."""
    document['mode'] = 'through_nodes'
    document['agreement'] = agreement(offline, results)
    fill_node_association(offline, results, document['agreement'])
    timing.update({k: info[k] for k in ('wall_s', 'startup_s', 'play_wall_s', 'speedup')})
    document['nodes'] = {k: info[k] for k in ('clouds', 'rows', 'rows_out',
                                              'partial_rows_out', 'barriers',
                                              'barrier_rounds', 'probes', 'fusers',
                                              'observers', 'cloud_mismatch', 'cpu_s')}
    # Deprecated alias of partial_rows_out, removed in the next release.
    document['nodes']['constraint_rows_out'] = document['nodes']['partial_rows_out']


def write_outputs(args, dataset, results, document):
    """Write ``--json`` and ``--plot``; return False when the plot cannot be drawn."""
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
            return False
    return True


def other_command(args, dataset, config):
    """Run the mode other than the fusion replay that ``args`` asks for: its exit code."""
    if args.export_bag is not None:
        return export_bag(args.dataset or default_dataset_path(), config, args.export_bag)
    if args.slam:
        from landmark_ros.mrclam import slam_cli
        return slam_cli.run_slam(args, dataset, config,
                                 {'mode': 'offline', 'dataset': dataset_dict(dataset)})
    if args.localize or args.calibrate_odometry:
        from landmark_ros.mrclam import localize_cli
        document = {'mode': 'offline', 'dataset': dataset_dict(dataset)}
        if args.calibrate_odometry:
            return localize_cli.calibrate(args, dataset, config, document)
        return localize_cli.localize(args, dataset, config, document)
    if args.calibrate:
        return calibrate_command(args, dataset)
    if args.cross_validate:
        return cross_validate_command(args, dataset, config)
    return None


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
    code = other_command(args, dataset, config)
    if code is not None:
        return code
    if config.camera_delay_s:
        dataset = dataset.with_camera_delay(config.camera_delay_s)
        print(f'sightings moved back by camera_delay_s = {config.camera_delay_s} s '
              f'({dataset.counts["kept"]} kept)')
    methods = [args.fusion] if args.fusion else list(FUSION_METHODS)
    if args.through_nodes and args.sensor != 'rb' and args.hide_ids:
        print('landmark_mrclam: --hide-ids needs --sensor rb through the nodes',
              file=sys.stderr)
        return 2
    t0 = time.monotonic()
    run = run_offline(dataset, config, methods, sensor=args.sensor, hide_ids=args.hide_ids)
    offline = run.results
    offline_s = time.monotonic() - t0
    problems = run.problems
    if problems:
        print(f'observer/fuser row checks rejected: {dict(problems)}')
    timing = {'load_s': load_s, 'offline_s': offline_s, 'duration_s': dataset.duration}
    document = {'mode': 'offline', 'dataset': dataset_dict(dataset),
                'config': {'observer': config_values(config.observer),
                           'fuser': config_values(config.fuser),
                           'pose_stddev': list(config.pose_stddev)}}
    results = offline
    if args.through_nodes:
        # The only ROS import of the replay, and only for this mode.
        from landmark_ros.mrclam.through_nodes import run_through_nodes
        options = PlayOptions(progress=False if args.no_progress else None,
                              hide_ids=args.hide_ids, sensor=args.sensor)
        try:
            results, info = run_through_nodes(dataset, config, methods, options,
                                              keep_logs=args.keep_logs,
                                              domain_id=args.domain_id)
        except RuntimeError as error:  # ReplayError too
            print(f'landmark_mrclam: {error}', file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            print('landmark_mrclam: interrupted', file=sys.stderr)
            return 130
        record_nodes(document, timing, offline, results, info)
    print()
    print(report(results))
    if args.hide_ids:
        print()
        print(format_association(results))
    print()
    print(f'offline: {offline_s:.2f} s for {len(methods)} method(s) '
          f'({dataset.duration / offline_s:.0f}x real time)')
    if args.through_nodes:
        print(format_node_info(info))
        print(format_agreement(document['agreement']))
    document['summary'] = [result.to_dict() for result in results.values()]
    document['timing'] = timing
    if not write_outputs(args, dataset, results, document):
        return 2
    if args.through_nodes and not all(
            e['same_ids'] and e['same_counts'] for e in document['agreement'].values()):
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
