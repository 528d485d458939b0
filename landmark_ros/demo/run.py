"""
The multi-robot demo: simulator, one observer per robot and the fuser, end to end.

``make demo`` (or ``python -m landmark_ros.demo``) starts ``landmark_sim``, one
``landmark_observer`` per robot (namespaces ``robot1`` ...) and ``landmark_fuser``
as separate processes in a DDS domain of their own, on the loopback interface only.
It follows the run from its own node (fused map, ground truth, true and reported
poses, /diagnostics), stops everything cleanly, then prints each fused landmark
against the truth (error, NEES, observations, rejections), the RMSE and the
average NEES with its 95 % interval, and draws the run (``demo.png``).

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
average NEES lies in its interval; 1 when the evaluation fails; 2 when the run
itself fails (a process died, nothing arrived in time); 130 on Ctrl-C.

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
import math
import os
from pathlib import Path
import signal
import sys
import time

from landmark_ros.demo.launcher import (Launcher, ProcessExitedError, remove_unused_shm,
                                        shm_files_of, write_params_file)
from landmark_ros.eval.metrics import evaluate, format_table
from landmark_ros.eval.plotting import PlotUnavailableError
from landmark_ros.fusion.landmark_map import FUSION_METHODS
from landmark_ros.pipeline import map_file
from landmark_ros.ros.cloud import CloudError
from landmark_ros.ros.conversions import InputError, pose_from_msg, stamp_ns
from landmark_ros.ros.schemas import read_landmarks
from landmark_ros.sim.simulation import SENSOR_KINDS, SimConfig, Simulation
from tqdm import tqdm

DOMAIN_RANGE = (150, 200)
"""The demo picks its ROS_DOMAIN_ID in [150, 200), by PID, skipping busy ones."""
NEES_2SIGMA = 4.0
"""A 2D estimate whose truth lies outside its 2-sigma ellipse has NEES above 4."""
DEFAULT_SEED = 0
MIN_OBSERVATIONS_NO_IDS = 2
"""The fuser's ``min_observations`` with ``--no-ids``: a track needs a second row."""


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
    parser.add_argument('--no-progress', action='store_true',
                        help='no progress bar (default: a tqdm bar on stderr when it is a '
                        'terminal)')
    args = parser.parse_args(argv)
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
                     'views without IDs are out of scope')
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


def node_parameters(config, fusion, map_path):
    """
    Return the parameters of every node, for ``launcher.write_params_file``.

    The observers get the simulator's noise model exactly; the fuser confirms a
    landmark from its first observation (the simulator has no outliers), so that
    every landmark measured at all ends up in the map; without IDs from its
    ``MIN_OBSERVATIONS_NO_IDS``-th (a row the association gate misses must not
    become a landmark at once).
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
                    input_depth=200, max_wait_s=2.0)
    fuser = {
        'world_frame': config.frame,
        'input_topics': [f'/robot{i + 1}/landmarks' for i in range(config.robots)],
        'fusion': fusion, 'min_observations': MIN_OBSERVATIONS_NO_IDS if config.no_ids else 1,
        'map_file': str(map_path),
        'autosave_period_s': 0.0, 'diagnostics_period_s': 0.5, 'source_timeout_s': 60.0,
    }
    partial = partial_robots(config)
    if partial:
        fuser['constraint_topics'] = [f'/robot{i + 1}/landmark_constraints' for i in partial]
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


# The demo's own node ---------------------------------------------------------------------

class Monitor:
    """
    The demo's node: everything it needs to follow and evaluate the run.

    Parameters
    ----------
    domain_id : int or None
        The ROS_DOMAIN_ID; None probes ``DOMAIN_RANGE`` for one nobody uses.
    robots : int
        Number of robots.

    """

    def __init__(self, domain_id, robots, partial=()):
        self.robots = robots
        self.partial = set(partial)
        self.context = self.node = self.executor = None
        self.callbacks = 0
        if domain_id is None:
            for candidate in _domain_candidates():
                self._open(candidate)
                if not self._domain_busy():
                    domain_id = candidate
                    break
                self._close_context()
            else:  # all busy: take the first anyway
                domain_id = _domain_candidates()[0]
        if self.node is None:
            self._open(domain_id)
        self.domain_id = domain_id
        self._subscribe()

    def _open(self, domain_id):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        self.context = Context()
        # Python's own Ctrl-C handling: the demo decides how to shut down.
        rclpy.init(context=self.context, domain_id=domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('landmark_demo', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _domain_busy(self, window_s=0.6):
        """Whether other nodes show up in the domain within ``window_s``."""
        deadline = time.monotonic() + window_s
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
            if len(self.node.get_node_names()) > 1:
                return True
        return False

    def _subscribe(self):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
        from landmark_ros.ros.qos import LATCHED
        from rclpy.qos import qos_profile_sensor_data, QoSProfile
        from sensor_msgs.msg import PointCloud2
        # Poses only for the plot: the newest one each time the demo looks is enough,
        # and a busy demo skips poses instead of falling behind.
        stream = QoSProfile(depth=1, reliability=qos_profile_sensor_data.reliability)
        node = self.node
        self.fused = None
        self.fused_stamp_ns = None
        self.truth = None
        self.true_paths = [[] for _ in range(self.robots)]
        self.last_true_stamp_ns = None
        self.reported = [None] * self.robots
        self.reported_paths = [[] for _ in range(self.robots)]
        self.statuses = {}  # name -> list of (sequence, stamp_ns, values) since finish
        self.latest = {}  # name -> values
        self.sequence = 0
        self.finish_sequence = None
        self.read_errors = 0
        node.create_subscription(PointCloud2, '/fused_landmarks', self._on_fused, LATCHED)
        node.create_subscription(PointCloud2, '/ground_truth_landmarks', self._on_truth,
                                 LATCHED)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 100)
        for i in range(self.robots):
            node.create_subscription(
                PoseStamped, f'/robot{i + 1}/true_pose',
                lambda msg, i=i: self._on_true_pose(i, msg), stream)
            node.create_subscription(
                PoseWithCovarianceStamped, f'/robot{i + 1}/pose',
                lambda msg, i=i: self._on_pose(i, msg), stream)

    # Callbacks ----------------------------------------------------------------------------

    def _on_fused(self, msg):
        self.callbacks += 1
        try:
            self.fused = read_landmarks(msg)
            self.fused_stamp_ns = stamp_ns(msg.header.stamp)
        except CloudError:
            self.read_errors += 1

    def _on_truth(self, msg):
        self.callbacks += 1
        try:
            self.truth = read_landmarks(msg)
        except CloudError:
            self.read_errors += 1

    def _on_true_pose(self, robot, msg):
        self.callbacks += 1
        q = msg.pose.orientation
        yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
        self.true_paths[robot].append((msg.pose.position.x, msg.pose.position.y, yaw))
        self.last_true_stamp_ns = stamp_ns(msg.header.stamp)

    def _on_pose(self, robot, msg):
        self.callbacks += 1
        try:
            pose, P_pose = pose_from_msg(msg, msg.header.frame_id)
        except InputError:
            self.read_errors += 1
            return
        self.reported[robot] = (pose, P_pose)
        self.reported_paths[robot].append(pose)

    def _on_diagnostics(self, msg):
        self.callbacks += 1
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            self.sequence += 1
            self.latest[status.name] = values
            if status.name == '/landmark_sim' and values.get('finished') == 'true' \
                    and self.finish_sequence is None:
                self.finish_sequence = self.sequence
            if self.finish_sequence is not None:
                self.statuses.setdefault(status.name, []).append(
                    (self.sequence, stamp_ns(msg.header.stamp), values))

    # Queries ------------------------------------------------------------------------------

    def spin(self, timeout_s=0.05):
        """Handle what arrived, waiting at most ``timeout_s`` for the first callback."""
        self.executor.spin_once(timeout_sec=timeout_s)
        # Then whatever else is ready, without waiting.
        for _ in range(500):
            before = self.callbacks
            self.executor.spin_once(timeout_sec=0.0)
            if self.callbacks == before:
                break

    @property
    def sim(self):
        """Return the simulator's latest status values (empty before the first)."""
        return self.latest.get('/landmark_sim', {})

    @property
    def sim_finished(self):
        """Whether the simulator reported the end of the run."""
        return self.finish_sequence is not None

    def sim_time_s(self):
        """Return the simulated time of the newest true pose (or of the status) [s]."""
        start = self.sim.get('start_stamp_ns')
        if start and self.last_true_stamp_ns is not None:
            return max((self.last_true_stamp_ns - int(start)) * 1e-9, 0.0)
        return float(self.sim.get('sim_time_s', 0.0))

    def pipeline_ready(self):
        """Whether observers and fuser subscribe: the simulator may start."""
        node = self.node
        return all(node.count_subscribers(f'/robot{i + 1}/observations') > 0
                   and node.count_subscribers(f'/robot{i + 1}/pose') > 1
                   and node.count_subscribers(f'/robot{i + 1}/landmarks') > 0
                   and (i not in self.partial or node.count_subscribers(
                       f'/robot{i + 1}/landmark_constraints') > 0)
                   for i in range(self.robots)) and node.count_publishers(
                       '/fused_landmarks') > 0

    def source_statuses(self):
        """Return ``topic -> values`` of the fuser's per-source statuses."""
        prefix = '/landmark_fuser: '
        return {name[len(prefix):]: values for name, values in self.latest.items()
                if name.startswith(prefix)}

    def rejected(self):
        """Observations the fuser gated out so far."""
        return sum(int(v.get('gated_out', 0)) for v in self.source_statuses().values())

    def _settled(self, name, complete, idle, counter):
        """Whether a node's reports since the finish show it done with the run."""
        reports = self.statuses.get(name, [])
        if not reports:
            return False
        last = reports[-1][2]
        if not idle(last):
            return False
        if complete(last):
            return True
        # Something got lost on the way: done once the count stops moving.
        return len(reports) >= 2 and reports[-2][2].get(counter) == last.get(counter)

    def drained(self):
        """
        Whether every observation of the finished run went through the pipeline.

        The simulator finished; each observer took in what the simulator measured for
        its robot and has nothing waiting; the fuser took in what each observer put out
        and has nothing queued (or, when something was lost on the way, the counts
        stopped changing); the fused map holds every fused observation.
        """
        if not self.sim_finished:
            return False
        for i in range(self.robots):
            robot = f'robot{i + 1}'
            sent = self.sim.get(f'{robot}_observations')
            observer = f'/{robot}/landmark_observer'
            if not self._settled(observer, lambda v: v.get('observations_in') == sent,
                                 lambda v: v.get('pending_messages') == '0',
                                 'observations_in'):
                return False
            out = self.latest[observer].get('landmarks_out')
            source = f'/landmark_fuser: /{robot}/landmarks'
            if not self._settled(source, lambda v: v.get('observations_in') == out,
                                 lambda v: v.get('queued_messages') == '0',
                                 'observations_in'):
                return False
            if i in self.partial:
                views = self.latest[observer].get('constraints_out', '0')
                source = f'/landmark_fuser: /{robot}/landmark_constraints'
                if not self._settled(source, lambda v: v.get('constraints_in', '0') == views,
                                     lambda v: v.get('queued_views') == '0',
                                     'constraints_in'):
                    return False
        fused = sum(int(v.get('fused', 0)) for v in self.source_statuses().values())
        return (self.fused is not None and int(self.fused.observations.sum()) >= fused
                and self.truth is not None and str(int(self.truth.observations.sum()))
                == self.sim.get('observations_out'))

    def close(self):
        """
        Destroy the node and shut the context down.

        Returns
        -------
        list of str
            Fast DDS shared-memory files the demo used that nobody uses any more
            (shared port files it was the last user of), removed.

        """
        used = shm_files_of(os.getpid())
        self._close_context()
        return remove_unused_shm(used)

    def _close_context(self):
        import rclpy
        if self.executor is not None:
            self.executor.shutdown()
        if self.node is not None:
            self.node.destroy_node()
        if self.context is not None:
            rclpy.try_shutdown(context=self.context)
        self.context = self.node = self.executor = None


def _domain_candidates():
    low, high = DOMAIN_RANGE
    first = os.getpid() % (high - low)
    return [low + (first + 7 * k) % (high - low) for k in range(4)]


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


def drive(config, launcher, monitor, params_path, progress):
    """Start the processes, follow the run and wait for the pipeline to drain."""
    ros_args = ['--params-file', str(params_path)]
    for i in range(config.robots):
        launcher.start_module(f'observer_robot{i + 1}', 'landmark_ros.nodes.observer',
                              ['-r', f'__ns:=/robot{i + 1}', *ros_args])
    launcher.start_module('fuser', 'landmark_ros.nodes.fuser', ros_args)
    wait_until(monitor, launcher, monitor.pipeline_ready, 60.0,
               'the observers and the fuser to come up')
    launcher.start_module('sim', 'landmark_ros.nodes.sim', ros_args)
    wall = config.duration_s / config.time_scale
    wait_until(monitor, launcher, lambda: monitor.sim_finished, 2.0 * wall + 60.0,
               'the simulation to finish', progress)
    try:
        wait_until(monitor, launcher, monitor.drained, 15.0,
                   'the last observations to be fused', progress)
        drained = True
    except RunError:
        drained = False
    show_progress(progress, monitor)
    progress.close()
    return drained


def rejections_by_id(path, frame):
    """Return ``id -> rejections`` from the fuser's saved map ({} if unreadable)."""
    try:
        document = map_file.load(str(path), frame)
    except (OSError, ValueError):
        return {}
    return {int(r['id']): int(r.get('rejections', 0)) for r in document['landmarks']}


def plot_run(path, monitor, results, seen_ids, unfused_ids, title):
    """
    Draw paths, final poses, true landmarks and the fused estimates.

    The fused estimates are drawn at their true landmark with the error and the
    2-sigma ellipse magnified by one common factor (centimetres on a map of
    metres), so whether the truth lies inside the ellipse reads off directly.
    """
    from landmark_ros.eval import plotting
    import numpy as np
    truth = monitor.truth
    points = np.vstack([truth.m] + [np.array(p).reshape(-1, 3)[:, :2]
                                    for p in monitor.true_paths])
    width, height = np.ptp(points, axis=0) + 1.0
    # Equal axes with 20 % more height on top for the legend: size the figure to fit.
    fig, ax = plotting.new_figure((8.0, float(np.clip(6.8 * 1.2 * height / width + 1.5,
                                                      4.0, 12.0))))
    colours = ['tab:blue', 'tab:green', 'tab:purple', 'tab:brown', 'tab:pink', 'tab:cyan',
               'tab:olive', 'tab:gray']
    for i in range(monitor.robots):
        colour = colours[i % len(colours)]
        path_xy = np.array(monitor.true_paths[i]).reshape(-1, 3)
        if len(path_xy):
            ax.plot(path_xy[:, 0], path_xy[:, 1], color=colour, linewidth=1.0, alpha=0.7)
        if monitor.reported[i] is not None:
            pose, P_pose = monitor.reported[i]
            plotting.draw_robot(ax, pose, P_pose, size=0.8, colour=colour,
                                label=f'robot{i + 1} (path, final pose, 2σ)', sigma=2.0)
    seen = np.isin(truth.ids, list(seen_ids))
    ax.scatter(truth.m[seen, 0], truth.m[seen, 1], marker='+', color='black', s=60,
               label='true landmarks', zorder=3)
    if (~seen).any():
        ax.scatter(truth.m[~seen, 0], truth.m[~seen, 1], marker='+', color='silver', s=60,
                   label='never measured', zorder=3)
    for landmark_id, m in zip(truth.ids.tolist(), truth.m):
        ax.annotate(str(landmark_id), m, textcoords='offset points', xytext=(4, 4),
                    fontsize=7)
    true_by_id = {int(i): m for i, m in zip(truth.ids.tolist(), truth.m)}
    if results:
        sizes = [2.0 * math.sqrt(max(np.linalg.eigvalsh(r.P)[-1], 1e-12)) for r in results]
        scale = max(1.0, round(0.35 / float(np.median(sizes))))
        label = f'fused, 2σ ellipse (error and ellipse ×{scale:g})'
        for r in results:
            true = true_by_id[r.id]
            shown = true + scale * (r.m - true)
            plotting.draw_ellipse(ax, shown, scale ** 2 * r.P, sigma=2.0, color='tab:orange',
                                  linewidth=1.2, label=label)
            ax.plot(*shown, marker='.', color='tab:orange')
            label = None
        outliers = [r for r in results if r.nees > NEES_2SIGMA]
        if outliers:
            xy = np.array([true_by_id[r.id] for r in outliers])
            ax.scatter(xy[:, 0], xy[:, 1], s=260, facecolors='none', edgecolors='red',
                       linewidths=1.5, label='truth outside 2σ', zorder=4)
    if unfused_ids:
        xy = np.array([true_by_id[i] for i in unfused_ids])
        ax.scatter(xy[:, 0], xy[:, 1], marker='x', s=80, color='red',
                   label='measured, not fused', zorder=4)
    # Room above the map for the legend.
    (x_low, y_low), (_, y_high) = ax.dataLim.get_points()
    ax.update_datalim([(x_low, y_high + 0.2 * (y_high - y_low))])
    ax.autoscale_view()
    plotting.finish(fig, ax, path, title)


def evaluate_run(monitor, rejections, no_ids=False):
    """
    Return the per-landmark results, summary, seen and unfused IDs, and the association.

    With ``no_ids`` the fused tracks are first matched to the true landmarks
    (``match_tracks_to_truth``) and take their IDs; the last value is then that
    dict, else None.
    """
    import numpy as np
    truth = monitor.truth
    needed = MIN_OBSERVATIONS_NO_IDS if no_ids else 1
    seen = [int(i) for i, n in zip(truth.ids.tolist(), truth.observations.tolist())
            if n >= needed]
    fused = monitor.fused
    association = None
    truth_xy = {int(i): tuple(m) for i, m in zip(truth.ids.tolist(), truth.m)}
    if fused is None:
        fused_ids = np.empty(0, np.int64)
        results, summary = evaluate(fused_ids, np.empty((0, 2)), np.empty((0, 2, 2)), {})
    else:
        fused_ids = fused.ids
        rejected = [rejections.get(int(i), 0) for i in fused.ids.tolist()]
        if no_ids:
            association = match_tracks_to_truth(fused, truth)
            fused_ids = np.array([association['track_to_true'].get(int(i), -1)
                                  for i in fused.ids.tolist()], np.int64)
        results, summary = evaluate(fused_ids, fused.m, fused.P, truth_xy, fused.observations,
                                    rejected)
    unfused = sorted(set(seen) - set(fused_ids.tolist()))
    return results, summary, seen, unfused, association


def match_tracks_to_truth(fused, truth):
    """
    Match tracks found without IDs to the true landmarks (``--no-ids``).

    Parameters
    ----------
    fused : landmark_ros.ros.schemas.LandmarkCloud
        The fused map (``ids``, ``m``, ``observations``).
    truth : landmark_ros.ros.schemas.LandmarkCloud
        The simulator's ground truth (``ids``, ``m``, ``observations``: sightings).

    Returns
    -------
    dict
        ``track_to_true`` (track ID -> true ID, optimal assignment on positions
        within 1 m), ``tracks``, ``extra_tracks`` (matched to nothing), ``gospa_m``
        (c = 1 m, p = 2, alpha = 2), ``observations_matched`` (share of the sightings
        held by the matched tracks: sum of min(track, true) over the matches over
        all sightings; an upper bound of the association accuracy).

    """
    import numpy as np
    from landmark_ros.eval.metrics import evaluate_association
    seen = truth.observations > 0
    truth_xy = {int(i): tuple(m) for i, m, s in zip(truth.ids.tolist(), truth.m, seen) if s}
    summary = evaluate_association(np.zeros(0, np.int64), np.zeros(0, np.int64),
                                   np.zeros((0, 2)), np.zeros((0, 2, 2)), fused.ids,
                                   fused.m, truth_xy)
    sightings = dict(zip(truth.ids.tolist(), truth.observations.tolist()))
    held = sum(min(int(n), int(sightings[summary.track_to_true[int(i)]]))
               for i, n in zip(fused.ids.tolist(), fused.observations.tolist())
               if int(i) in summary.track_to_true)
    total = int(truth.observations.sum())
    return {'track_to_true': summary.track_to_true, 'tracks': len(fused.ids),
            'extra_tracks': len(fused.ids) - len(summary.track_to_true),
            'gospa_m': summary.gospa_m,
            'observations_matched': held / total if total else 1.0}


def run(args, started=None):
    """Run the demo; return the exit code."""
    started = time.monotonic() if started is None else started
    config = sim_config(args)
    output = Path(args.output).resolve()
    log_dir = Path(args.log_dir).resolve() if args.log_dir else (
        output.parent / 'log' / output.stem)
    log_dir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault('ROS_LOG_DIR', str(log_dir / 'ros'))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    map_path = log_dir / 'fused_map.json'
    if map_path.exists():
        map_path.unlink()  # the fuser would start from it
    params_path = log_dir / 'params.yaml'
    write_params_file(params_path, node_parameters(config, args.fusion, map_path))
    progress = progress_bar(config.duration_s, False if args.no_progress else None)
    removed_shm = []
    monitor = None
    try:
        monitor = Monitor(args.domain_id, config.robots, partial_robots(config))
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
        with Launcher(log_dir, monitor.domain_id) as launcher:
            drained = drive(config, launcher, monitor, params_path, progress)
            monitor.spin(0.0)
            codes = launcher.stop()
            removed_shm += launcher.removed_shm
        unclean = [f'{name} (exit {code})' for name, code in codes.items() if code != 0]
    except ProcessExitedError as error:
        progress.close()
        print(f'demo failed: {error}', file=sys.stderr)
        return 2
    except RunError as error:
        progress.close()
        print(f'demo failed: {error}; the process logs are in {log_dir}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        progress.close()
        print('demo interrupted: every process was stopped', file=sys.stderr)
        return 130
    finally:
        if monitor is not None:
            removed_shm += monitor.close()
    if removed_shm:
        print('note: removed Fast DDS shared-memory files left unused by the run: '
              f"{' '.join(os.path.basename(f) for f in removed_shm)}")
    if unclean:
        print(f"warning: not every process stopped cleanly: {', '.join(unclean)}")
    if monitor.truth is None:
        print('demo failed: no ground truth received', file=sys.stderr)
        return 2
    if not drained:
        print('warning: the pipeline did not settle in time; the last observations may '
              'be missing from the map')

    rejections = rejections_by_id(map_path, config.frame)
    if not rejections and monitor.fused is not None and len(monitor.fused.ids):
        print(f'warning: no saved map in {map_path}: rejections per landmark unknown')
    results, summary, seen, unfused, association = evaluate_run(
        monitor, rejections, getattr(args, 'no_ids', False))
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

    if not args.no_plot:
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

    failures = []
    waiting = []
    if partial_robots(config):
        # Range-only and bearing-only views place a landmark only once their geometry
        # fixes it: a landmark no range-bearing robot saw may rightly still wait.
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
              + (f', {waiting} still waiting for views with enough geometry'
                 if waiting else ''))
    if unfused:
        failures.append(f'landmarks measured but not fused: {unfused}')
    if association is not None and association['extra_tracks']:
        failures.append(f"{association['extra_tracks']} tracks matched to no true landmark")
    if not results:
        failures.append('no fused landmark to evaluate')
    elif not summary.consistent:
        low, high = summary.anees_interval
        kind = ('overconfident: errors larger than the covariances claim'
                if summary.anees > high else
                'conservative: covariances larger than the errors')
        failures.append(f'average NEES {summary.anees:.2f} outside [{low:.2f}, {high:.2f}] '
                        f'({kind})')
    print(f'wall time {time.monotonic() - started:.1f} s')
    if failures:
        print('FAILED: ' + '; '.join(failures))
        return 1
    fused_count = (f'{len(seen) - len(waiting)} of {len(seen)} measured landmarks fused '
                   f'({len(waiting)} seen only by partial sensors wait for views)'
                   if waiting else f'all {len(seen)} measured landmarks fused')
    print(f'OK: {fused_count}, consistent ({args.fusion} fusion)')
    return 0


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
