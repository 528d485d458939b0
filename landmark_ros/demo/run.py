"""
The multi-robot demo: simulator, one observer per robot and the fuser, end to end.

``make demo`` (or ``python -m landmark_ros.demo``) starts ``landmark_sim``, one
``landmark_observer`` per robot (namespaces ``robot1`` ...) and ``landmark_fuser``
as separate processes in a DDS domain of their own, on the loopback interface only.
It follows the run from its own node (fused map, ground truth, true and reported
poses, /diagnostics), stops everything cleanly, then prints each fused landmark
against the truth (error, NEES, observations, rejections), the RMSE and the
average NEES with its 95 % interval, and draws the run (``demo.png``).

With ``--slam`` the observers take their poses from one ``landmark_localizer`` per robot,
running on the simulated wheel odometry against the fused map (``team.launch.py
localize:=true``; the simulator's reported pose goes to ``sim_pose``), and the fuser uses
split CI unless ``--fusion`` names another method than the default. The localizers'
poses are scored against the truth as with ``--localize`` (per robot position and
heading RMSE, pose ANEES, share inside the 95 % ellipse). The map's average NEES is
printed but not judged: the landmarks of one run share the frame error of the poses
that placed them, so one run's average does not follow the interval of independent
landmarks; ``eval.slam_montecarlo`` judges the loop's consistency over seeds.

With ``--no-ids`` the simulator publishes every observation without its landmark ID
(``UNKNOWN_ID``): the fuser associates the rows (its default, JCBB) and starts tracks
with new IDs. The report then matches the fused tracks to the true landmarks by optimal
assignment on positions within 1 m (``eval.metrics.evaluate_association``), evaluates
each matched track against its landmark, and prints the tracks confirmed, the extra
tracks (matched to nothing) and the GOSPA distance (c = 1 m, p = 2); it cannot see
which track each sighting went to, so instead of the association accuracy it prints
the share of the sightings the matched tracks hold (``observations_matched``: the sum
over true landmarks of min(track observations, true sightings) over all sightings, an
upper bound of the association accuracy). Success then also needs no extra track.

The exit code is 0 only when every landmark the robots measured was fused and the
average NEES lies in its interval (not judged with ``--slam``; with ``--localize`` and
``--slam`` every robot also needs localized poses); 1 when the evaluation fails; 2 when
the run itself fails (a process died, nothing arrived in time); 130 on Ctrl-C.

The noise model is exactly known to the observers. Without per-robot biases
(the default) the errors of different observations are independent, so the
``independent`` fusion (product of Gaussians) is the right one and the default.
With ``--range-bias``/``--bearing-bias`` each robot's measurements share a constant
bias: ``independent`` becomes overconfident and ``split_covariance_intersection``
is the safe choice (conservative here: its average NEES tends to fall below the
interval, since it takes each robot's pose errors, independent in this simulator,
for one shared error too).
"""

import argparse
from dataclasses import dataclass
import os
from pathlib import Path
import signal
import sys
import time

from landmark_ros.demo.localize import (add_slam_argument, evaluate as evaluate_localization,
                                        LocalizationCollector, localizer_parameters,
                                        sim_waits, slam_defaults, SLAM_VERDICT,
                                        start_localizers)
from landmark_ros.demo.monitor import Monitor
from landmark_ros.demo.report import (evaluate_run, MIN_OBSERVATIONS_NO_IDS, NEES_2SIGMA,
                                      plot_run, rejections_by_id)
from landmark_ros.eval.metrics import format_table
from landmark_ros.eval.plotting import PlotUnavailableError
from landmark_ros.fusion.landmark_map import FUSION_METHODS
from landmark_ros.ros import qos
from landmark_ros.ros.launcher import Launcher, ProcessExitedError, write_params_file
from landmark_ros.sim.simulation import SENSOR_KINDS, SimConfig, Simulation
from tqdm import tqdm

DEFAULT_SEED = 0


def parse_args(argv=None):
    """Parse the command line."""
    parser = argparse.ArgumentParser(
        prog='python -m landmark_ros.demo',
        description='Simulated multi-robot landmark mapping: sim, observers and fuser as '
        'separate ROS 2 processes, evaluated against the ground truth.')
    parser.add_argument('--robots', type=int, default=3, help='number of robots (default 3)')
    parser.add_argument('--landmarks', type=int, default=20,
                        help='number of random landmarks (default 20)')
    parser.add_argument('--duration', type=float, default=20.0,
                        help='simulated time to run [s] (default 20)')
    parser.add_argument('--time-scale', type=float, default=2.0,
                        help='simulated seconds per wall-clock second (default 2)')
    parser.add_argument('--fusion', choices=FUSION_METHODS, default='independent',
                        help='fusion of the fuser (default independent: the right model '
                        'without biases)')
    parser.add_argument('--seed', type=int, default=DEFAULT_SEED,
                        help=f'seed of the world, paths and noise (default {DEFAULT_SEED})')
    parser.add_argument('--range-bias', type=float, default=0.0, metavar='STDDEV',
                        help='per-robot constant range bias, drawn from N(0, STDDEV^2) [m]')
    parser.add_argument('--bearing-bias', type=float, default=0.0, metavar='STDDEV',
                        help='per-robot constant bearing bias, from N(0, STDDEV^2) [rad]')
    parser.add_argument('--world-file', default='',
                        help='YAML list of {id, x, y} landmarks instead of random ones')
    parser.add_argument('--output', default='demo.png',
                        help='plot file (default demo.png); the process logs go to '
                        'log/<name>/ next to it')
    parser.add_argument('--log-dir', default=None, help='where the process logs go')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID of the run (default: a free one in 150..199)')
    parser.add_argument('--no-plot', action='store_true', help='do not draw the plot')
    parser.add_argument('--no-ids', action='store_true',
                        help='observations without landmark IDs: the fuser associates them; '
                        'tracks are matched to the truth by position')
    parser.add_argument('--sensors', type=_sensor_kinds, default=('rb',), metavar='KINDS',
                        help='sensor of each robot in turn, comma-separated: rb '
                        '(range-bearing), range (UWB, radio) or bearing (camera); e.g. '
                        'rb,range,bearing (default rb)')
    parser.add_argument('--localize', action='store_true',
                        help='also localize every robot on its wheel odometry against the '
                        'fused map (landmark_localizer) and report pose RMSE and ANEES')
    parser.add_argument('--no-progress', action='store_true',
                        help='no progress bar (default: a tqdm bar on stderr when it is a '
                        'terminal)')
    add_slam_argument(parser)
    args = slam_defaults(parser.parse_args(argv))
    if args.robots < 1 or args.landmarks < 1:
        parser.error('--robots and --landmarks must be at least 1')
    if not 0.0 < args.duration <= 3600.0:
        parser.error('--duration must be in (0, 3600] s')
    if not 0.01 <= args.time_scale <= 100.0:
        parser.error('--time-scale must be in [0.01, 100]')
    if args.range_bias < 0.0 or args.bearing_bias < 0.0:
        parser.error('bias standard deviations must not be negative')
    if args.no_ids and set(args.sensors) != {'rb'}:
        parser.error('--no-ids needs range-bearing sensors: range-only and bearing-only '
                     'observations without IDs are out of scope')
    if args.domain_id is not None and not 0 <= args.domain_id <= 232:
        parser.error('--domain-id must be in [0, 232]')
    try:
        sim_config(args)
    except ValueError as error:
        parser.error(str(error))
    return args


def _sensor_kinds(text):
    """Parse ``--sensors``: a comma-separated list of ``SENSOR_KINDS``."""
    kinds = tuple(kind.strip() for kind in text.split(','))
    if not all(kind in SENSOR_KINDS for kind in kinds):
        raise argparse.ArgumentTypeError(
            f"expected a comma-separated list of {', '.join(SENSOR_KINDS)}, got {text!r}")
    return kinds


def sim_config(args):
    """Return the simulator's configuration for the command line."""
    return SimConfig(robots=args.robots, landmarks=args.landmarks, seed=args.seed,
                     world_file=args.world_file, duration_s=args.duration,
                     time_scale=args.time_scale, range_bias_stddev=args.range_bias,
                     bearing_bias_stddev=args.bearing_bias, wait_for_subscribers_s=20.0,
                     ground_truth_period_s=0.5, diagnostics_period_s=0.5,
                     no_ids=bool(getattr(args, 'no_ids', False)),
                     sensor_kinds=tuple(getattr(args, 'sensors', ('rb',))))


def node_parameters(config, fusion, map_path, slam=False):
    """
    Return the parameters of every node, for ``launcher.write_params_file``.

    The observers get the simulator's noise model exactly; the fuser confirms a
    landmark from its first observation (the simulator has no outliers), so that
    every landmark measured at all ends up in the map; without IDs from its
    ``MIN_OBSERVATIONS_NO_IDS``-th (a row the association gate misses must not
    become a landmark at once). ``slam``: the loop, where the fuser runs without change
    detection (its rows carry the localizers' slow pose errors; docs/slam.md).
    """
    sim = {name: getattr(config, name) for name in (
        'robots', 'landmarks', 'seed', 'world_file', 'duration_s', 'time_scale',
        'range_stddev', 'bearing_stddev', 'range_bias_stddev', 'bearing_bias_stddev',
        'pose_xy_stddev', 'pose_yaw_stddev', 'wait_for_subscribers_s',
        'ground_truth_period_s', 'diagnostics_period_s', 'no_ids')}
    sim['sensor_kinds'] = list(config.sensor_kinds)
    observer = {name: getattr(config, name) for name in (
        'range_stddev', 'bearing_stddev', 'range_bias_stddev', 'bearing_bias_stddev')}
    # Deep input queues and a long wait for the pose after an observation: on a loaded
    # machine a starved observer must catch up, not drop poses or observations.
    observer.update(world_frame=config.frame, diagnostics_period_s=0.5, marker_rate_hz=0.0,
                    input_depth=200, output_depth=200, max_wait_s=2.0)
    fuser = {
        'world_frame': config.frame,
        'input_topics': [f'/robot{i + 1}/landmarks' for i in range(config.robots)],
        'fusion': fusion, 'min_observations': MIN_OBSERVATIONS_NO_IDS if config.no_ids else 1,
        'map_file': str(map_path),
        'autosave_period_s': 0.0, 'diagnostics_period_s': 0.5, 'source_timeout_s': 60.0,
    }
    if slam:
        fuser['move_false_alarm_rate'] = 0.0
    partial = partial_robots(config)
    if partial:
        fuser['partial_observation_topics'] = [f'/robot{i + 1}/partial_observations'
                                               for i in partial]
    return {'/landmark_sim': sim, '/**/landmark_observer': observer,
            '/landmark_fuser': fuser}


def partial_robots(config):
    """Return the 0-based indices of the robots with a range-only or bearing-only sensor."""
    return [i for i in range(config.robots) if config.sensor_kind(i) != 'rb']


def landmarks_by_kind(config):
    """
    Return, for each sensor kind, the IDs the simulated robots of that kind measure.

    Replays ``Simulation.measure`` (deterministic in the seed) for the whole run, so the
    demo knows which landmarks only range-only or bearing-only robots saw: those need
    several views with enough geometry and may stay unplaced.
    """
    sim = Simulation(config)
    count = sim.observations_until(int(round(config.duration_s * 1e9)))
    seen = {kind: set() for kind in SENSOR_KINDS}
    for robot in range(config.robots):
        kind = config.sensor_kind(robot)
        for j in range(count):
            ids = sim.measure(robot, j).ids
            seen[kind].update(int(i) for i in ids if i >= 0)
    return seen


# Running ----------------------------------------------------------------------------------

class RunError(RuntimeError):
    """The run itself failed (not the evaluation)."""


def progress_bar(duration_s, progress=None):
    """
    Return the run's tqdm bar on stderr, counting simulated seconds.

    Parameters
    ----------
    duration_s : float
        Simulated time of the run [s].
    progress : bool or None
        None: a bar only when stderr is a terminal (nothing in logs and pipes);
        True: always; False: never (``--no-progress``).

    """
    return tqdm(total=duration_s, desc='sim', unit='s', file=sys.stderr,
                disable=None if progress is None else not progress, dynamic_ncols=True,
                mininterval=0.25, miniters=0,
                bar_format='{desc} {n:.1f}/{total:g} s |{bar}| {elapsed}<{remaining}{postfix}')


def progress_text(monitor):
    """Return what the bar shows after the simulated time."""
    seen = fused = 0
    if monitor.truth is not None:
        seen = int((monitor.truth.observations > 0).sum())
    if monitor.fused is not None:
        fused = len(monitor.fused.ids)
    fused_observations = 0 if monitor.fused is None else int(monitor.fused.observations.sum())
    return (f"observations {monitor.sim.get('observations_out', '0')} | landmarks seen "
            f'{seen}, fused {fused} ({fused_observations} observations) | rejected '
            f'{monitor.rejected()}')


def show_progress(bar, monitor):
    """Move the bar to the simulated time (tqdm limits the redraws)."""
    if bar.disable:
        return
    bar.set_postfix_str(progress_text(monitor), refresh=False)
    bar.update(min(monitor.sim_time_s(), bar.total) - bar.n)


def wait_until(monitor, launcher, predicate, timeout_s, what, progress=None):
    """Spin until ``predicate()``; raise RunError after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise RunError(f'timed out after {timeout_s:.0f} s waiting for {what}')
        monitor.spin(0.05)
        launcher.check()
        if progress is not None:
            show_progress(progress, monitor)


def drive(config, launcher, monitor, params_path, progress, slam=False):
    """Start the processes, follow the run and wait for the pipeline to drain."""
    ros_args = ['--params-file', str(params_path)]
    sim_remaps = start_localizers(launcher, config, params_path, slam) if slam else []
    from_sim = ('observations',) if slam else ('observations', 'pose')  # else localizers'
    for i in range(config.robots):
        ns = f'/robot{i + 1}'
        launcher.start_module(f'observer_robot{i + 1}', 'landmark_ros.nodes.observer',
                              ['-r', f'__ns:={ns}', *ros_args,
                               *qos.replayed_input_arguments(ns, from_sim)])
    launcher.start_module('fuser', 'landmark_ros.nodes.fuser', ros_args)
    wait_until(monitor, launcher, monitor.pipeline_ready, 60.0,
               'the observers and the fuser to come up')
    localization = monitor.localization
    if localization is not None:  # --localize starts them now, --slam did above
        if not slam:
            start_localizers(launcher, config, params_path)
        wait_until(monitor, launcher, lambda: localization.ready(monitor.latest), 60.0,
                   'the localizers to come up')
    launcher.start_module('sim', 'landmark_ros.nodes.sim', [*ros_args, *sim_remaps])
    wall = config.duration_s / config.time_scale
    wait_until(monitor, launcher, lambda: monitor.sim_finished, 2.0 * wall + 60.0,
               'the simulation to finish', progress)
    try:
        wait_until(monitor, launcher, monitor.drained, 15.0,
                   'the last observations to be fused', progress)
        drained = True
    except RunError:
        drained = False
    localization = monitor.localization
    if localization is not None:  # the localizers may lag behind the fuser
        try:
            wait_until(monitor, launcher, localization.complete, 30.0,
                       'the last localized poses', progress)
        except RunError:
            pass  # evaluated on what arrived; the counts are printed
    show_progress(progress, monitor)
    progress.close()
    return drained


@dataclass(frozen=True)
class RunPaths:
    """Where a run writes: the plot, the logs, the fuser's map file, the parameters."""

    output: Path
    log_dir: Path
    map_path: Path
    params_path: Path


def prepare(args):
    """Create the log folder, set the ROS environment; return the run's ``RunPaths``."""
    output = Path(args.output).resolve()
    log_dir = Path(args.log_dir).resolve() if args.log_dir else (
        output.parent / 'log' / output.stem)
    log_dir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault('ROS_LOG_DIR', str(log_dir / 'ros'))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    map_path = log_dir / 'fused_map.json'
    if map_path.exists():
        map_path.unlink()  # the fuser would start from it
    return RunPaths(output, log_dir, map_path, log_dir / 'params.yaml')


def announce(args, config, monitor, log_dir):
    """Print what the run simulates, its noise model and its domain."""
    print(f'landmark_ros demo: {config.robots} robots, '
          + (f'landmarks of {config.world_file}' if config.world_file
             else f'{config.landmarks} landmarks')
          + f', seed {config.seed}, {config.duration_s:g} s simulated at '
          f'x{config.time_scale:g}, fusion {args.fusion}'
          + ('' if config.sensor_kinds == ('rb',)
             else f", sensors {','.join(config.sensor_kinds)} (robot 1, 2, ... in turn)"))
    print(f'noise: range {config.range_stddev} m, bearing {config.bearing_stddev} rad, '
          f'pose {config.pose_xy_stddev} m / {config.pose_yaw_stddev} rad, bias '
          f'{config.range_bias_stddev} m / {config.bearing_bias_stddev} rad per robot; '
          f'ROS_DOMAIN_ID {monitor.domain_id}, logs in {log_dir}', flush=True)
    if args.fusion == 'independent' and (config.range_bias_stddev
                                         or config.bearing_bias_stddev):
        print("note: independent fusion ignores the bias shared by a robot's "
              'observations; expect overconfidence (split_covariance_intersection '
              'is the safe choice)')


def execute(args, config, paths):
    """
    Run the processes and follow them; return ``(exit code or None, monitor)``.

    The exit code is 2 when the run failed, 130 on Ctrl-C, None when the run can be
    evaluated (the monitor then holds what it saw).
    """
    slam = getattr(args, 'slam', False)
    localized = slam or getattr(args, 'localize', False)
    parameters = node_parameters(config, args.fusion, paths.map_path, slam)
    if localized:
        parameters.update(localizer_parameters(config, Simulation(config)))
    parameters['/landmark_sim'].update(sim_waits(args))
    write_params_file(paths.params_path, parameters)
    progress = progress_bar(config.duration_s, False if args.no_progress else None)
    removed_shm = []
    monitor = launcher = None
    try:
        monitor = Monitor(args.domain_id, config.robots, partial_robots(config),
                          every_true_pose=localized)
        if localized:   # --slam: the localizers' pose is the one the observers take
            monitor.localization = LocalizationCollector(
                monitor.node, config.robots, 'pose' if slam else 'localized_pose')
        announce(args, config, monitor, paths.log_dir)
        with Launcher(paths.log_dir, monitor.domain_id) as launcher:
            drained = drive(config, launcher, monitor, paths.params_path, progress, slam)
            monitor.spin(0.0)
            codes = launcher.stop()
            removed_shm += launcher.removed_shm
        unclean = [f'{name} (exit {code})' for name, code in codes.items() if code != 0]
    except ProcessExitedError as error:
        progress.close()
        print(f'demo failed: {error}', file=sys.stderr)
        return 2, monitor
    except RunError as error:
        progress.close()
        print(f'demo failed: {error}; the process logs are in {paths.log_dir}',
              file=sys.stderr)
        return 2, monitor
    except KeyboardInterrupt:
        progress.close()
        print('demo interrupted: every process was stopped', file=sys.stderr)
        return 130, monitor
    finally:
        if monitor is not None:
            removed_shm += monitor.close()
        if launcher is not None:    # what the monitor's node still mapped at the stop
            removed_shm += launcher.remove_shm_in_use()
    if removed_shm:
        print('note: removed Fast DDS shared-memory files left unused by the run: '
              f"{' '.join(os.path.basename(f) for f in removed_shm)}")
    if unclean:
        print(f"warning: not every process stopped cleanly: {', '.join(unclean)}")
    if monitor.truth is None:
        print('demo failed: no ground truth received', file=sys.stderr)
        return 2, monitor
    if not drained:
        print('warning: the pipeline did not settle in time; the last observations may '
              'be missing from the map')
    lost = monitor.lost()
    if lost:
        print('warning: observations lost on the way (a starved machine?): '
              + ', '.join(f'{hop} {count}' for hop, count in sorted(lost.items())))
    return None, monitor


def print_evaluation(args, config, monitor, evaluation):
    """Print the per-landmark table, the counts and (without IDs) the track matching."""
    results, summary, seen, _, association = evaluation
    print()
    print(format_table(results, summary, title=f'Fused landmarks ({args.fusion} fusion) '
                       'against the ground truth'))
    gated = monitor.rejected()
    observations = int(monitor.sim.get('observations_out', 0))
    print(f'{observations} observations of {len(seen)} of {len(monitor.truth.ids)} landmarks '
          f"by {config.robots} robots; {gated} rejected by the fuser's gate; "
          f'{sum(r.nees > NEES_2SIGMA for r in results)} of {len(results)} true positions '
          'outside their 2σ ellipse')
    if association is not None:
        print(f"without IDs: {association['tracks']} tracks confirmed, "
              f"{len(association['track_to_true'])} matched to a true landmark (of "
              f"{len(seen)} measured), {association['extra_tracks']} extra; GOSPA "
              f"{association['gospa_m']:.3f} m; the matched tracks hold "
              f"{100 * association['observations_matched']:.1f} % of the sightings")


def plot(args, config, output, monitor, evaluation):
    """Draw the run into ``output`` unless ``--no-plot``; report what happened."""
    if args.no_plot:
        return
    results, summary, seen, unfused, _ = evaluation
    title = (f'{config.robots} robots, {len(seen)} landmarks measured, seed {config.seed}'
             f'\n{args.fusion} fusion: RMSE {100 * summary.rmse_m:.1f} cm, '
             f'ANEES {summary.anees:.2f}')
    try:
        plot_run(output, monitor, results, seen, unfused, title)
        print(f'plot: {output}')
    except PlotUnavailableError as error:
        print(f'note: no plot ({error})')
    except OSError as error:
        print(f'warning: cannot write the plot: {error}')


def split_waiting(config, results, seen, unfused):
    """
    Return ``(unfused, waiting)``: landmarks missing from the map, and those excused.

    Range-only and bearing-only views place a landmark only once their geometry fixes
    it: a landmark no range-bearing robot saw may rightly still wait (``waiting``);
    ``unfused`` keeps the others. Prints the count per sensor kind.
    """
    if not partial_robots(config):
        return unfused, []
    by_kind = landmarks_by_kind(config)
    fused_set = {int(result.id) for result in results}
    for kind in SENSOR_KINDS:
        ids = by_kind[kind] & set(seen)
        if ids and kind in config.sensor_kinds:
            print(f'{kind}: {len(ids)} landmarks measured, '
                  f'{len(ids & fused_set)} of them in the map')
    only_partial = set(seen) - by_kind['rb']
    waiting = sorted(set(unfused) & only_partial)
    unfused = sorted(set(unfused) - only_partial)
    print(f'{len(only_partial)} landmarks seen by range-only or bearing-only robots '
          f'only: {len(only_partial) - len(waiting)} placed'
          + (f', {waiting} still waiting for partial observations with enough geometry'
             if waiting else ''))
    return unfused, waiting


def failures_of(evaluation, unfused, judge_anees=True):
    """
    Return why the run fails its evaluation (empty when it passes).

    ``judge_anees`` False (``--slam``): the map's average NEES is printed, not judged.
    """
    results, summary, _, _, association = evaluation
    failures = []
    if unfused:
        failures.append(f'landmarks measured but not fused: {unfused}')
    if association is not None and association['extra_tracks']:
        failures.append(f"{association['extra_tracks']} tracks matched to no true landmark")
    if not results:
        failures.append('no fused landmark to evaluate')
    elif judge_anees and not summary.consistent:
        low, high = summary.anees_interval
        kind = ('overconfident: errors larger than the covariances claim'
                if summary.anees > high else
                'conservative: covariances larger than the errors')
        failures.append(f'average NEES {summary.anees:.2f} outside [{low:.2f}, {high:.2f}] '
                        f'({kind})')
    return failures


def judge(args, config, paths, monitor, started):
    """Evaluate the finished run against the ground truth, print it; return the exit code."""
    rejections = rejections_by_id(paths.map_path, config.frame)
    if not rejections and monitor.fused is not None and len(monitor.fused.ids):
        print(f'warning: no saved map in {paths.map_path}: rejections per landmark unknown')
    evaluation = evaluate_run(monitor, rejections, getattr(args, 'no_ids', False))
    print_evaluation(args, config, monitor, evaluation)
    plot(args, config, paths.output, monitor, evaluation)
    results, _, seen, unfused, _ = evaluation
    unfused, waiting = split_waiting(config, results, seen, unfused)
    slam = getattr(args, 'slam', False)
    failures = failures_of(evaluation, unfused, judge_anees=not slam)
    if slam:
        print(SLAM_VERDICT)
    localization = monitor.localization
    if localization is not None:
        entry, text = evaluate_localization(localization, monitor.latest)
        print(text)
        if entry is None:
            failures.append('no localized poses')
    print(f'wall time {time.monotonic() - started:.1f} s')
    if failures:
        print('FAILED: ' + '; '.join(failures))
        return 1
    fused_count = (f'{len(seen) - len(waiting)} of {len(seen)} measured landmarks fused '
                   f'({len(waiting)} seen only by partial sensors wait for more partial '
                   'observations)'
                   if waiting else f'all {len(seen)} measured landmarks fused')
    print(f"OK: {fused_count}{'' if slam else ', consistent'} ({args.fusion} fusion)")
    return 0


def run(args, started=None):
    """Run the demo; return the exit code."""
    started = time.monotonic() if started is None else started
    config = sim_config(args)
    paths = prepare(args)
    code, monitor = execute(args, config, paths)
    if code is not None:
        return code
    return judge(args, config, paths, monitor, started)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None):
    """Console entry point."""
    started = time.monotonic()
    args = parse_args(argv)
    # SIGTERM (a supervisor, a test deadline) stops the run as cleanly as Ctrl-C does.
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        return run(args, started)
    except KeyboardInterrupt:  # after the processes were stopped: while plotting
        print('demo interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
