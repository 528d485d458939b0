"""
The demo's own node: it follows the run (fused map, ground truth, poses, /diagnostics).

``Monitor`` subscribes to what the simulator, the observers and the fuser publish, and
answers the questions of ``demo.run``: is the pipeline up, has the simulator finished,
has every observation gone through (``drained``).
"""

import math
import os
import time

from landmark_ros.pipeline.counters import without_deprecated
from landmark_ros.ros.cloud import CloudError
from landmark_ros.ros.conversions import InputError, pose_from_msg, stamp_ns
from landmark_ros.ros.launcher import remove_unused_shm, shm_files_of
from landmark_ros.ros.schemas import read_landmarks

DOMAIN_RANGE = (150, 200)
"""The demo picks its ROS_DOMAIN_ID in [150, 200), by PID, skipping busy ones."""


class Monitor:
    """
    The demo's node: everything it needs to follow and evaluate the run.

    Parameters
    ----------
    domain_id : int or None
        The ROS_DOMAIN_ID; None probes ``DOMAIN_RANGE`` for one nobody uses.
    robots : int
        Number of robots.
    partial : iterable of int
        The robots whose sensors give range-only or bearing-only rows.
    every_true_pose : bool
        Take every true pose (reliable, deep queue: ``--localize`` pairs each with a
        localized pose) instead of the newest one for the plot.

    """

    def __init__(self, domain_id, robots, partial=(), every_true_pose=False):
        self.robots = robots
        self.every_true_pose = every_true_pose
        self.partial = set(partial)
        self.context = self.node = self.executor = None
        self.callbacks = 0
        self.localization = None
        """``demo.localize.LocalizationCollector`` with ``--localize``, else None."""
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
        from landmark_ros.ros.qos import LATCHED, reliable_output
        from rclpy.qos import qos_profile_sensor_data, QoSProfile
        from sensor_msgs.msg import PointCloud2
        # Poses only for the plot: the newest one each time the demo looks is enough,
        # and a busy demo skips poses instead of falling behind.
        stream = QoSProfile(depth=1, reliability=qos_profile_sensor_data.reliability)
        # One reader per true-pose topic: the simulator's wait for subscribers then
        # waits for this very reader.
        truth = reliable_output(1000) if self.every_true_pose else stream
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
                lambda msg, i=i: self._on_true_pose(i, msg), truth)
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
        if self.localization is not None:
            self.localization.truth[robot][self.last_true_stamp_ns] = self.true_paths[robot][-1]

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
            values = without_deprecated({kv.key: kv.value for kv in status.values})
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
                       f'/robot{i + 1}/partial_observations') > 0)
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

    def lost(self):
        """
        Return ``hop -> observations`` that went in at one end and not out at the other.

        Per robot: those the simulator measured and the observer never took in
        (``robotN -> observer``), and those the observer put out and the fuser never took
        in (``robotN observer -> fuser``); only the hops that lost some.
        """
        lost = {}
        for i in range(self.robots):
            robot = f'robot{i + 1}'
            observer = self.latest.get(f'/{robot}/landmark_observer', {})
            source = self.latest.get(f'/landmark_fuser: /{robot}/landmarks', {})
            hops = ((f'{robot} -> observer', self.sim.get(f'{robot}_observations'),
                     observer.get('observations_in')),
                    (f'{robot} observer -> fuser', observer.get('landmarks_out'),
                     source.get('observations_in')))
            for hop, sent, received in hops:
                if sent is not None and received is not None and int(sent) > int(received):
                    lost[hop] = int(sent) - int(received)
        return lost

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
                views = self.latest[observer].get('partial_out', '0')
                source = f'/landmark_fuser: /{robot}/partial_observations'
                if not self._settled(source, lambda v: v.get('partial_in', '0') == views,
                                     lambda v: v.get('queued_partial') == '0',
                                     'partial_in'):
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
