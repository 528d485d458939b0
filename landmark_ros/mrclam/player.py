"""
The player of the replay through the real nodes: the dataset into DDS, in order.

``Player`` publishes the dataset into the observers in global time order with flow
control (``replay_plan.dependencies``: the order of each landmark's rows at every
fuser is the offline one), and follows the outputs, diagnostics and saved maps of the
fusers. ``through_nodes.run_through_nodes`` starts the nodes and runs it.
"""

import sys
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.mrclam.replay_plan import (FUSER_BATCH, FUSER_WINDOW, OBSERVER_WINDOW,
                                             partial_topic, plan_clouds, PlayOptions,
                                             ReplayError)
from landmark_ros.pipeline.counters import without_deprecated
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.ros.cloud import CloudWriter
from landmark_ros.ros.conversions import stamp_ns
from landmark_ros.ros.schemas import observation_message, pose_message
import numpy as np
from rcl_interfaces.srv import GetParameters
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from tqdm import tqdm

NS_PER_S = 1_000_000_000


def stamp_msg(stamp_ns):
    """Return integer nanoseconds as a ``builtin_interfaces/Time``."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


_PARTIAL_WRITERS = {'range': CloudWriter((('id', np.uint32), ('range', np.float64))),
                    'bearing': CloudWriter((('id', np.uint32), ('bearing', np.float64)))}
"""Observation clouds of one column, by the column kept (``--sensor range|bearing``)."""


def stamped_messages(stamp_ns, frame_id, pose, P_pose, ids, z, sensor='rb'):
    """
    Return a robot's pose and observation messages, both stamped ``stamp_ns``.

    Parameters
    ----------
    stamp_ns : int
        Stamp [ns].
    frame_id : str
        Frame of the observation cloud (the pose is in ``map``).
    pose : ndarray, shape (3,)
        Robot pose (x [m], y [m], theta [rad]).
    P_pose : ndarray, shape (3, 3)
        Its covariance.
    ids : ndarray of int, shape (N,)
        Landmark IDs.
    z : ndarray, shape (N, 2)
        Range [m] and bearing [rad] per row.
    sensor : str
        ``rb`` sends both columns; ``range`` (``bearing``) sends a cloud without the
        ``bearing`` (``range``) field, as the offline replay drops that column
        (``offline.observe``): the observer's rows are then range-only (bearing-only).

    Returns
    -------
    pose : geometry_msgs.msg.PoseWithCovarianceStamped
    observations : sensor_msgs.msg.PointCloud2

    """
    pose_msg = pose_message(0.0, pose, P_pose)
    pose_msg.header.stamp = stamp_msg(stamp_ns)
    header = Header(stamp=stamp_msg(stamp_ns), frame_id=frame_id)
    if sensor == 'rb':
        return pose_msg, observation_message(header, ids, z)
    writer = _PARTIAL_WRITERS[sensor]
    z = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    rows = writer.rows(len(z))
    rows['id'] = np.asarray(ids).reshape(-1)
    rows[sensor] = z[:, 0 if sensor == 'range' else 1]
    return pose_msg, writer.message(header, rows)


class Player:
    """
    Publish the dataset into the nodes in time order, with flow control.

    Poses. Each observer receives its robot's pose at exactly the stamp of the next
    cloud, then the cloud, both reliable, so it uses that very pose (no interpolation)
    and publishes one ``landmarks`` cloud per observation cloud, in order.

    Order at the fusers. A fuser takes one robot's clouds in order (one reliable
    writer), but across robots in the order its executor sees them, not the order
    they were sent. The map only depends on the order of the rows of each landmark
    (``LandmarkMap`` treats landmarks apart), so a cloud waits until every fuser has
    taken the last cloud of another robot with one of its landmarks
    (``dependencies``); robots whose clouds wait for nothing go on meanwhile, in
    time order. To know that a cloud was taken, the player waits for its
    ``landmarks`` output (it subscribes too: the output reached the fusers when it
    reached the player), then runs a barrier: rounds of an empty ``get_parameters``
    request to every fuser, one round after the other. In each pass, an executor
    serves every subscription with data (the fuser's callback takes up to
    ``FUSER_BATCH`` waiting clouds of that source) before the services, so a round
    guarantees that many more clouds of every robot taken.

    Flow control. At most ``OBSERVER_WINDOW`` clouds per robot wait for their
    ``landmarks`` output and at most ``FUSER_WINDOW`` are not known to be taken by
    the fusers (a barrier then runs), far below every queue depth, so nothing is
    dropped. Discovery: the player waits for matched publishers, subscriptions and
    services, then sends empty probe clouds until the diagnostics of every fuser
    count one from every robot, so every link carries data before the first cloud.

    Without IDs (``hide_ids``) the clouds carry ``UNKNOWN_ID`` in every row and each
    cloud follows the one before it (``sequential``): a barrier at every change of
    robot, so every fuser takes all the clouds in global time order, as offline.

    With ``sensor`` ``range`` or ``bearing`` the clouds go without the dropped column
    (``stamped_messages``), each observer publishes an empty ``landmarks`` cloud per
    cloud (still the pace) and a ``partial_observations`` cloud when some partial rows
    pass its checks (``expected_partial``: the observers' pipeline run on the same
    clouds), which the fusers take from ``partial_observation_topics``. The player subscribes
    to those too (stamps checked as the outputs), and a cloud counts as out of its
    observer only once both its outputs arrived; a barrier then covers both
    subscriptions of every robot (each pass takes up to ``FUSER_BATCH`` waiting clouds
    of each), so ``dependencies`` order each landmark's views across robots.
    """

    def __init__(self, node, executor, dataset, rows, config, methods, launcher,
                 options=PlayOptions()):
        self.node, self.executor = node, executor
        self.dataset, self.rows, self.config = dataset, rows, config
        self.methods, self.launcher = list(methods), launcher
        self.progress, self.stall_timeout_s = options.progress, options.stall_timeout_s
        self.robots = dataset.robots
        self.hide_ids = bool(options.hide_ids)
        self.sensor = options.sensor
        plan = plan_clouds(rows, config, len(self.robots), options)
        self.starts, self.ends = plan.starts, plan.ends
        self.msg_robot, self.msg_stamps_ns = plan.msg_robot, plan.msg_stamps_ns
        self.requirements, self.local = plan.requirements, plan.local
        self.totals, self.robot_clouds = plan.totals, plan.robot_clouds
        self.expected_ns = plan.expected_ns
        self.partial_ns, self.partial_before = plan.partial_ns, plan.partial_before
        self.partial_observation_topics = [partial_topic(r.landmarks_topic) for r in self.robots]
        self._create_endpoints(node)
        self._reset_counters()

    def _create_endpoints(self, node):
        """Create the publishers, subscriptions and clients of the player's node."""
        reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                              reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # No QoS event handlers: each is a waitable the executor polls on every wake-up.
        quiet_pub = {'event_callbacks': PublisherEventCallbacks(use_default_callbacks=False)}
        quiet_sub = {'event_callbacks': SubscriptionEventCallbacks(
            use_default_callbacks=False)}
        self.pose_pubs, self.obs_pubs, self.out_subs, self.partial_subs = [], [], [], []
        for index, robot in enumerate(self.robots):
            self.pose_pubs.append(node.create_publisher(
                PoseWithCovarianceStamped, f'/{robot.name}/pose', reliable, **quiet_pub))
            self.obs_pubs.append(node.create_publisher(
                PointCloud2, f'/{robot.name}/observations', reliable, **quiet_pub))
            self.out_subs.append(node.create_subscription(
                PointCloud2, robot.landmarks_topic,
                lambda msg, index=index: self._on_output(msg, index), reliable, **quiet_sub))
            if self.sensor != 'rb':
                self.partial_subs.append(node.create_subscription(
                    PointCloud2, self.partial_observation_topics[index],
                    lambda msg, index=index: self._on_partial_observations(msg, index), reliable,
                    **quiet_sub))
        self.fused = {}
        self.fused_subs, self.barrier_clients, self.save_clients = [], [], []
        for method in self.methods:
            ns = f'/mrclam/{method}'
            self.fused_subs.append(node.create_subscription(
                PointCloud2, f'{ns}/fused_landmarks',
                lambda msg, method=method: self.fused.__setitem__(method, msg), latched,
                **quiet_sub))
            self.barrier_clients.append(node.create_client(
                GetParameters, f'{ns}/landmark_fuser/get_parameters'))
            self.save_clients.append(node.create_client(Trigger, f'{ns}/landmark_fuser/save'))
        self.diagnostics = {}
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
                                 **quiet_sub)

    def _reset_counters(self):
        """Set the counts of clouds sent, out of the observers and taken to zero."""
        count = len(self.robots)
        self.sent = [0] * count
        self.out = [0] * count
        self.landmarks_out = [0] * count
        self.partial_out = [0] * count
        self.partial_rows_out = 0
        self.taken = [0] * count
        self.probes_sent = [0] * count
        self.probes_out = [0] * count
        self.rows_out = 0
        self.sent_total = 0
        self.barrier = None
        self.barriers = 0
        self.barrier_rounds = 0
        self._last_progress = time.monotonic()
        self._bar = None
        self._probe_stamp_ns = None

    # Callbacks -------------------------------------------------------------------------

    def _on_output(self, msg, index):
        stamp = stamp_ns(msg.header.stamp)
        if self._probe_stamp_ns is not None and stamp < self._data_start_ns:
            self.probes_out[index] += 1
            return
        k = self.landmarks_out[index]
        expected = self.expected_ns[index][k] if k < len(self.expected_ns[index]) else None
        if stamp != expected:
            raise ReplayError(f'{self.robots[index].name}: landmarks output stamped {stamp} '
                              f'ns, expected {expected} ns (cloud {k}): a cloud was lost')
        self.landmarks_out[index] += 1
        self.rows_out += msg.width * msg.height
        self._advance(index)

    def _on_partial_observations(self, msg, index):
        stamp = stamp_ns(msg.header.stamp)
        k = self.partial_out[index]
        expected = self.partial_ns[index]
        expected = expected[k] if k < len(expected) else None
        if stamp != expected:
            raise ReplayError(f'{self.robots[index].name}: partial observations stamped '
                              f'{stamp} ns, expected {expected} ns (partial observation cloud '
                              f'{k}): lost, or the observer node and its pipeline disagree')
        self.partial_out[index] += 1
        self.partial_rows_out += msg.width * msg.height
        self._advance(index)

    def _advance(self, index):
        """Count the clouds whose outputs (landmarks, partial observations if any) all arrived."""
        before = self.partial_before[index]
        out = self.out[index]
        while (out < self.landmarks_out[index]
               and before[out + 1] <= self.partial_out[index]):
            out += 1
        if out != self.out[index]:
            self.out[index] = out
            self._last_progress = time.monotonic()

    def _on_diagnostics(self, msg):
        stamp = stamp_ns(msg.header.stamp)
        for status in msg.status:
            values = without_deprecated({kv.key: kv.value for kv in status.values})
            self.diagnostics[status.name] = (stamp, values, status.message)

    # Helpers ---------------------------------------------------------------------------

    def spin(self, timeout_s=0.05):
        """Run one callback (or wait up to ``timeout_s``)."""
        self.executor.spin_once(timeout_sec=timeout_s)

    def spin_until(self, predicate, timeout_s, what):
        """Spin until ``predicate()``; raise ReplayError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        last_check = 0.0
        while not predicate():
            now = time.monotonic()
            if now > deadline:
                raise ReplayError(f'timed out after {timeout_s:.0f} s waiting for {what}')
            if now - last_check > 0.5:
                self.launcher.check()
                last_check = now
            self.spin(0.05)

    def fuser_name(self, method):
        """Return the fully qualified name of a method's fuser."""
        return f'/mrclam/{method}/landmark_fuser'

    def fuser_sources(self, method, newer_than_ns=None):
        """Return ``topic -> values`` of a fuser's latest diagnostics, or None."""
        name = self.fuser_name(method)
        main = self.diagnostics.get(name)
        if main is None or (newer_than_ns is not None and main[0] <= newer_than_ns):
            return None
        sources = {}
        for robot in self.robots:
            entry = self.diagnostics.get(f'{name}: {robot.landmarks_topic}')
            if entry is None or entry[0] != main[0]:
                return None
            sources[robot.landmarks_topic] = entry[1]
        for topic in self.partial_observation_topics if self.partial_subs else ():
            entry = self.diagnostics.get(f'{name}: {topic}')
            if entry is None or entry[0] != main[0]:
                return None
            sources[topic] = entry[1]
        return sources

    # Barrier ---------------------------------------------------------------------------

    def start_barrier(self, clouds):
        """
        Start a barrier over the outputs received so far.

        When it completes, each fuser has taken at least ``clouds`` more of the
        covered clouds of every robot (all of them if fewer were left): one round per
        ``FUSER_BATCH`` clouds, as each pass of a fuser's executor takes up to that
        many waiting clouds of every source.
        """
        rounds = max(1, -(-clouds // FUSER_BATCH))
        self.barrier = {'cover': list(self.out), 'rounds': rounds, 'left': rounds,
                        'pending': 0}
        self.barriers += 1
        self._barrier_round()

    def _barrier_round(self):
        barrier = self.barrier
        barrier['pending'] = len(self.barrier_clients)
        self.barrier_rounds += 1
        for client in self.barrier_clients:
            request = GetParameters.Request(names=[])
            client.call_async(request).add_done_callback(self._barrier_reply)

    def _barrier_reply(self, future):
        barrier = self.barrier
        barrier['pending'] -= 1
        if barrier['pending']:
            return
        barrier['left'] -= 1
        if barrier['left'] > 0:
            self._barrier_round()
            return
        covered = barrier['rounds'] * FUSER_BATCH
        self.taken = [max(t, min(c, t + covered)) for t, c in zip(self.taken, barrier['cover'])]
        self.barrier = None
        self._last_progress = time.monotonic()

    # Sending ---------------------------------------------------------------------------

    def send(self, j):
        """Publish cloud ``j``: the robot's pose at its stamp, then the observations."""
        r = int(self.msg_robot[j])
        a, b = int(self.starts[j]), int(self.ends[j])
        ids = np.full(b - a, UNKNOWN_ID, np.int64) if self.hide_ids else self.rows.ids[a:b]
        pose, cloud = stamped_messages(self.msg_stamps_ns[j], f'{self.robots[r].name}/camera',
                                       self.rows.poses[a], self.config.P_pose,
                                       ids, self.rows.z[a:b], self.sensor)
        self.pose_pubs[r].publish(pose)
        self.obs_pubs[r].publish(cloud)
        self.sent[r] += 1
        self.sent_total += 1

    def pump(self):
        """
        Send every cloud that may go now; return how many clouds a barrier must cover.

        A robot's next cloud may go when fewer than ``OBSERVER_WINDOW`` of its clouds
        wait for their output, fewer than ``FUSER_WINDOW`` are not known to be taken
        by the fusers, and the clouds it must follow (``dependencies``) are taken.
        Robots go in the order of their next clouds in time; a blocked robot does
        not hold the others up.

        Returns
        -------
        int
            Clouds per robot a barrier must cover to unblock a robot whose blocking
            clouds are back from their observers (0: nothing a barrier can unblock).

        """
        clouds = 0
        progress = True
        while progress:
            progress = False
            order = sorted((self.robot_clouds[r][self.sent[r]], r)
                           for r in range(len(self.robots)) if self.sent[r] < self.totals[r])
            for j, r in order:
                if self.sent[r] - self.out[r] >= OBSERVER_WINDOW:
                    continue
                if self.sent[r] - self.taken[r] >= FUSER_WINDOW:
                    if self.out[r] > self.taken[r]:
                        clouds = max(clouds, self.out[r] - self.taken[r])
                    continue
                blocked = False
                for a, local in self.requirements[j]:
                    if self.taken[a] <= local:
                        blocked = True
                        if self.out[a] > local:
                            clouds = max(clouds, local + 1 - self.taken[a])
                if blocked:
                    continue
                self.send(j)
                progress = True
                self._last_progress = time.monotonic()
        return clouds

    # Phases ----------------------------------------------------------------------------

    def connect(self, timeout_s=120.0):
        """Wait for every publisher, subscription and service to be matched."""
        def matched():
            return (all(p.get_subscription_count() > 0 for p in self.pose_pubs + self.obs_pubs)
                    and all(s.get_publisher_count() > 0 for s in self.out_subs + self.fused_subs
                            + self.partial_subs)
                    and all(c.service_is_ready() for c in self.barrier_clients
                            + self.save_clients)
                    and all(self.node.count_subscribers(r.landmarks_topic) >= 1 + len(
                        self.methods) for r in self.robots)
                    and all(self.node.count_subscribers(t) >= 1 + len(self.methods)
                            for t in (self.partial_observation_topics if self.partial_subs
                                      else ())))
        self.spin_until(matched, timeout_s, 'the nodes to start and match')

    def probe(self, timeout_s=60.0):
        """Send empty clouds until every fuser has one from every robot."""
        t0_ns = int(self.msg_stamps_ns[0]) if len(self.rows) else 200 * NS_PER_S
        self._data_start_ns = t0_ns - NS_PER_S
        self._probe_stamp_ns = t0_ns - 100 * NS_PER_S
        deadline = time.monotonic() + timeout_s

        def seen():
            for method in self.methods:
                sources = self.fuser_sources(method)
                if sources is None or any(int(v.get('messages_in', 0)) < 1
                                          for k, v in sources.items()
                                          if k not in self.partial_observation_topics):
                    return False
            return True

        while not seen():
            if time.monotonic() > deadline:
                raise ReplayError('the fusers never received the probe clouds')
            self._probe_stamp_ns += NS_PER_S // 100
            for r, robot in enumerate(self.robots):
                pose, cloud = stamped_messages(
                    self._probe_stamp_ns, f'{robot.name}/camera',
                    robot.poses[0] if len(robot.poses) else np.zeros(3), self.config.P_pose,
                    np.zeros(0, np.int64), np.zeros((0, 2)))
                self.pose_pubs[r].publish(pose)
                self.obs_pubs[r].publish(cloud)
                self.probes_sent[r] += 1
            try:
                self.spin_until(seen, 1.0, 'probes')
            except ReplayError:
                pass
        # Every probe the observers published reaches the fusers before the first real
        # cloud; the barrier makes sure the fusers have taken them all.
        try:
            self.spin_until(lambda: self.probes_out == self.probes_sent, 2.0, 'probe outputs')
        except ReplayError:
            pass
        self.start_barrier(max(self.probes_sent) + 2)
        self.spin_until(lambda: self.barrier is None, 30.0, 'the probe barrier')
        self.taken = [0] * len(self.robots)

    def play(self):
        """Send every cloud with flow control; return when every fuser took them all."""
        total = len(self.starts)
        last_check = 0.0
        while True:
            clouds = self.pump()
            if self.barrier is None:
                if self.sent_total == total and self.out == self.sent:
                    if self.taken == self.out:
                        break
                    clouds = max(o - t for o, t in zip(self.out, self.taken))
                if clouds:
                    self.start_barrier(clouds)
            self.show_progress()
            now = time.monotonic()
            if now - self._last_progress > self.stall_timeout_s:
                raise ReplayError(f'no progress for {self.stall_timeout_s:.0f} s: sent '
                                  f'{self.sent}, outputs {self.out}, taken {self.taken}')
            if now - last_check > 1.0:
                self.launcher.check()
                last_check = now
            self.spin(0.05)
        self.show_progress()

    def show_progress(self):
        """Update the progress bar: clouds through the observers, data time, speed."""
        bar = self._bar
        if bar is None or bar.disable:
            return
        done = sum(self.out)
        elapsed = time.monotonic() - self._t_play
        dataset_s = (int(self.msg_stamps_ns[min(done, bar.total) - 1] - self.msg_stamps_ns[0])
                     / NS_PER_S if done and bar.total else 0.0)
        speed = dataset_s / elapsed if elapsed > 0 else 0.0
        bar.set_postfix_str(f'{dataset_s:.1f} s of data, {speed:.1f}x real time, '
                            f'{self.barriers} barriers', refresh=False)
        bar.update(done - bar.n)

    def finish(self, timeout_s=60.0):
        """
        Wait for the fused maps: diagnostics after the last take, then ``~/save``.

        Returns
        -------
        dict
            Method -> ``{'sources': topic -> diagnostics values, 'saved': bool}``.

        """
        after = time.time_ns()
        # A status after the last take with nothing queued (clouds and views) comes
        # after the fuse of everything played.
        for method in self.methods:
            def fused(method=method):
                sources = self.fuser_sources(method, newer_than_ns=after)
                return sources is not None and all(
                    v.get('queued_messages') == '0' and v.get('queued_partial') == '0'
                    for v in sources.values())
            self.spin_until(fused, timeout_s, f'the {method} fuser to fuse its queue')
        final = {}
        for method, client in zip(self.methods, self.save_clients):
            future = client.call_async(Trigger.Request())
            self.spin_until(future.done, timeout_s, f'the {method} fuser to save its map')
            response = future.result()
            if not response.success:
                raise ReplayError(f'{method} fuser could not save its map: {response.message}')
            final[method] = {'sources': self.fuser_sources(method)}
        # Observer diagnostics after the last output, for the report.
        self.spin_until(lambda: all(
            self.diagnostics.get(f'/{r.name}/landmark_observer', (0,))[0] > after
            for r in self.robots), timeout_s, 'the observer diagnostics')
        return final

    def run(self):
        """Connect, probe, play and finish; return the fusers' final diagnostics."""
        self.connect()
        self.probe()
        self._t_play = time.monotonic()
        self._bar = progress_bar(len(self.starts), self.progress)
        try:
            self.play()
        finally:
            self._bar.close()
        self.play_wall_s = time.monotonic() - self._t_play
        return self.finish()


def progress_bar(total, progress=None):
    """
    Return the replay's tqdm bar on stderr, counting observation clouds.

    Parameters
    ----------
    total : int
        Clouds to play.
    progress : bool or None
        None: a bar only when stderr is a terminal (nothing in logs and pipes);
        True: always; False: never (``--no-progress``).

    """
    return tqdm(total=total, desc='replay', unit='cloud', file=sys.stderr,
                disable=None if progress is None else not progress, dynamic_ncols=True,
                mininterval=0.2, miniters=0)
