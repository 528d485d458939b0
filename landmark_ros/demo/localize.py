"""
``--localize`` of the demo: the team localizes on wheel odometry against the fused map.

With ``--localize`` the demo also starts one ``landmark_localizer`` per robot (namespace
``robotN``): its ``odometry`` is the simulator's wheel odometry (``robotN/odometry``,
the noise model of ``landmark_ros.sim.odometry``), its ``observations`` the simulator's
sightings (the ones the observer gets), its map the fuser's ``/fused_landmarks`` as it
grows; its ``pose`` goes to ``robotN/localized_pose`` (``robotN/pose`` is the
simulator's reported pose, which the observers use to build the map: the loop stays
open). Each localizer starts at its robot's true first pose (standard deviations 5 cm,
5 cm, 0.05 rad) and knows the simulator's models: ``odometry_alphas``, ``range_stddev``,
``bearing_stddev``. The map is made from the same sightings the localizer applies, so
it is correlated with the pose: split CI (the default ``correlation``).

``LocalizationCollector`` (on the demo's node) pairs each localized pose with the true
pose of the same stamp; ``evaluate`` gives per robot and overall the position and
heading RMSE, the average NEES of the 3-dof pose (3 is consistent) and the fraction of
poses whose true position lies inside the 95 % ellipse
(``landmark_ros.mrclam.localize.metrics``, the MRCLAM replay's figures).
"""

import math

from landmark_ros.mrclam.localize import format_table, metrics, Track
from landmark_ros.ros import qos
from landmark_ros.ros.conversions import InputError, pose_from_msg, stamp_ns
import numpy as np

INITIAL_STDDEV = (0.05, 0.05, 0.05)
"""Standard deviations of the localizers' initial poses (x [m], y [m], yaw [rad])."""


def localizer_parameters(config, sim):
    """Return ``name -> parameters`` of every robot's localizer (``write_params_file``)."""
    out = {}
    for robot in range(config.robots):
        _, true, _, _ = sim.reported_pose(robot, 0)
        out[f'/robot{robot + 1}/landmark_localizer'] = {
            'map_frame': config.frame, 'odometry_alphas': list(config.odometry_alphas),
            'range_stddev': config.range_stddev, 'range_stddev_per_m': 0.0,
            'bearing_stddev': config.bearing_stddev, 'input_depth': 1000,
            'initial_pose': [float(v) for v in true], 'initial_stddev': list(INITIAL_STDDEV),
            'diagnostics_period_s': 0.5}
    return out


def start_localizers(launcher, config, params_path, slam=False):
    """
    Start one localizer per robot (inputs reliable); return the simulator's extra remaps.

    ``--localize``: the localizers' ``pose`` goes to ``localized_pose``, the observers keep
    the simulator's. ``--slam``: the observers read the localizers' ``pose`` and the
    simulator's reported pose goes to ``sim_pose`` (the returned remaps).
    """
    remaps = []
    for robot in range(config.robots):
        ns = f'/robot{robot + 1}'
        args = ['-r', f'__ns:={ns}', '-r', 'fused_landmarks:=/fused_landmarks',
                '--params-file', str(params_path)]
        if slam:
            remaps += ['-r', f'robot{robot + 1}/pose:={ns}/sim_pose']
        else:
            args[2:2] = ['-r', 'pose:=localized_pose']
        args += qos.replayed_input_arguments(ns, ('odometry', 'observations'))
        launcher.start_module(f'localizer_robot{robot + 1}', 'landmark_ros.nodes.localizer',
                              args)
    return remaps


def add_slam_argument(parser):
    """Add ``--slam``: the team without motion capture (localizers on wheel odometry)."""
    parser.add_argument('--slam', action='store_true',
                        help='no motion capture: a landmark_localizer per robot on the '
                        "simulated wheel odometry and the fused map gives the observer's "
                        'pose (team.launch.py localize:=true)')


def slam_defaults(args):
    """
    Return ``args`` with ``--slam``'s fusion: split CI unless another than the default.

    The observers' rows then carry the localizers' pose errors, shared between rows: the
    default ``independent`` fusion would be over-confident.
    """
    if getattr(args, 'slam', False) and args.fusion == 'independent':
        args.fusion = 'split_covariance_intersection'
    return args


def sim_waits(args):
    """Return the simulator's ``wait_for_*`` overrides for the demo's mode (a dict)."""
    if not (getattr(args, 'localize', False) or getattr(args, 'slam', False)):
        return {}
    # The localizers start from the first pose: they must get the first odometry; the
    # monitor must get every true pose to pair with the localized ones; with --slam the
    # simulator's reported pose goes to sim_pose, which nobody takes.
    return {'wait_for_odometry_subscribers': True, 'wait_for_true_pose_subscribers': True,
            'wait_for_pose_subscribers': not getattr(args, 'slam', False)}


SLAM_VERDICT = ("--slam: the map's average NEES is not judged here: the landmarks of one "
                'run share the frame error of the poses that placed them, so it does not '
                'follow the interval of independent landmarks; consistency is judged over '
                'seeds by python -m landmark_ros.eval.slam_montecarlo (docs/slam.md)')
"""What ``--slam`` prints instead of judging the map's average NEES."""


class LocalizationCollector:
    """
    Every true and localized pose of every robot, by stamp (on the demo's node).

    The true poses come from the monitor's own true-pose readers (``Monitor`` with
    ``every_true_pose``, which fills ``truth``): one reader per topic, so that the
    simulator's wait for subscribers covers it.
    """

    def __init__(self, node, robots, topic='localized_pose'):
        """Subscribe to every robot's localized pose (``robotN/<topic>``) on ``node``."""
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from landmark_ros.ros.qos import reliable_output
        self.node, self.robots = node, robots
        self.truth = [{} for _ in range(robots)]
        self.estimates = [{} for _ in range(robots)]
        self.read_errors = 0
        self.subscriptions = [
            node.create_subscription(PoseWithCovarianceStamped, f'/robot{i + 1}/{topic}',
                                     lambda msg, i=i: self._on_estimate(i, msg),
                                     reliable_output(1000))
            for i in range(robots)]

    def _on_estimate(self, robot, msg):
        try:
            x, P = pose_from_msg(msg, msg.header.frame_id)
        except InputError:
            self.read_errors += 1
            return
        self.estimates[robot][stamp_ns(msg.header.stamp)] = (x, P)

    def ready(self, statuses):
        """
        Return whether every localizer runs and this node's readers matched its pose.

        ``statuses`` (the monitor's latest diagnostics by status name) must hold each
        localizer's: a localizer publishes them once its filter is built (its imports
        can take seconds under load while the simulator would already be running).
        The match is the reader's own (``get_publisher_count``): the ROS graph can list
        a publisher before the DDS reader has matched it.
        """
        return all(subscription.get_publisher_count() > 0
                   and f'/robot{i + 1}/landmark_localizer' in statuses
                   for i, subscription in enumerate(self.subscriptions))

    def complete(self):
        """Return whether every robot has a localized pose at each true pose's stamp."""
        return all(len(e) >= len(t) for e, t in zip(self.estimates, self.truth))

    def tracks(self, statuses=None):
        """
        Return one ``mrclam.localize.Track`` per robot: the stamps with both poses.

        ``statuses`` (the monitor's latest diagnostics values by status name) give the
        localizers' counters (rows used and gated).
        """
        out = []
        for i in range(self.robots):
            stamps = sorted(set(self.truth[i]) & set(self.estimates[i]))
            x = np.array([self.estimates[i][s][0] for s in stamps]).reshape(-1, 3)
            P = np.array([self.estimates[i][s][1] for s in stamps]).reshape(-1, 3, 3)
            truth = np.array([self.truth[i][s] for s in stamps]).reshape(-1, 3)
            values = (statuses or {}).get(f'/robot{i + 1}/landmark_localizer', {})
            counts = {k: int(v) for k, v in values.items() if str(v).isdigit()}
            out.append(Track(i + 1, np.array(stamps) * 1e-9, x, P, truth, counts))
        return out


def evaluate(collector, statuses=None):
    """Return ``(entry, text)``: the figures (``metrics``) and their table, or None."""
    tracks = collector.tracks(statuses)
    if any(len(t.times) == 0 for t in tracks):
        return None, ('localization: no localized pose paired with a true pose for some '
                      f'robot (true poses {[len(t) for t in collector.truth]}, localized '
                      f'{[len(e) for e in collector.estimates]}, unreadable '
                      f'{collector.read_errors})')
    robots, overall = metrics(tracks)
    entry = {'map': 'fused (live)', 'cooperative': False, **overall, 'robots': robots,
             'seconds': math.nan, 'cpu_seconds': math.nan}
    counts = ', '.join(f'robot {t.robot}: {len(t.times)}' for t in tracks)
    counts += (f'; true poses {[len(t) for t in collector.truth]}, localized '
               f'{[len(e) for e in collector.estimates]}')
    text = format_table([entry], math.nan).rsplit('\n', 1)[0]
    return entry, (f'Localization on wheel odometry against the fused map (poses {counts}):'
                   f'\n{text}')
