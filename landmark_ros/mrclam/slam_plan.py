"""
What ``landmark_mrclam --slam --through-nodes`` sends, in which order (ROS-free).

The offline loop (``eval.slam_loop.TeamLoop`` driven by ``mrclam.slam.run``) takes its
events in global time order (ties: odometry, then sightings, then by robot). A sighting
message of robot ``r`` is *placed* by its observer when a pose at or after its stamp is
known: at once when the robot's newest odometry is at or after the stamp and no message
waits before it, else at the first later odometry of ``r``, in arrival order. A message
older than the robot's first pose takes it if within the observer's ``max_pose_gap_s``
(the node's observer places it when that first pose arrives), else is dropped by the
observer (``observation_too_old``) and never reaches the localizer. The loop's observers
run on the stamps' clock: a message still waiting ``max_wait_s`` after its stamp when
the robot's next message comes takes the newest pose if within ``max_pose_gap_s``
(*stale*), else is dropped (``no_pose_in_time``). Each placed message is one *step*, in
the order the loop places them:

1. the localizer of ``r`` has published the pose of every odometry message of ``r``
   processed so far (``Steps.poses``) and of no later one: the sightings go to it after
   that odometry and before the next, against the map fused from every earlier step;
2. the observer places the message with those poses; the fuser fuses its landmarks;
   the map that results is the one every later step's localizer uses.

``plan`` computes the steps from the stamps alone; ``slam_nodes`` makes the nodes follow
them. ``offline_reference`` runs the offline loop without the robot-to-robot sightings
(the nodes' run has none: see ``slam_nodes``) and records, besides the loop's tracks,
the pose each odometry gave *before* the sightings it placed: what the node publishes
on ``pose`` (``TeamLoop`` records the estimate after them).
"""

from collections import deque
from dataclasses import dataclass, replace
from typing import Dict, List

from landmark_ros.eval.slam_loop import LoopConfig, TeamLoop
from landmark_ros.mrclam.data import interpolate_poses, seconds_to_stamps_ns
from landmark_ros.mrclam.localize_plan import batches
import numpy as np

_ODOM, _OBS = 0, 1


@dataclass(frozen=True)
class Steps:
    """The placed sighting messages of every robot in the offline loop's order (``S``)."""

    robot: np.ndarray
    """Index of the robot in ``dataset.robots``, shape (S,)."""
    start: np.ndarray
    """First row of the message in the robot's rows, shape (S,)."""
    end: np.ndarray
    """One past its last row, shape (S,)."""
    stamp_ns: np.ndarray
    """Stamp of the message [ns], shape (S,)."""
    poses: np.ndarray
    """Odometry messages of the robot processed before the localizer takes it (at least
    one: see ``plan``), shape (S,)."""
    stale: np.ndarray
    """Placed with the newest pose after waiting ``max_wait_s`` for the next, (S,)."""
    dropped: int
    """Messages the observer dropped (too old for its poses, or no pose in time)."""

    def __len__(self):
        """Return the number of steps."""
        return len(self.robot)


def start_stamps(dataset, extras, delay_s):
    """Return each robot's start (its first odometry stamp, delay added) [ns], shape (R,)."""
    return np.array([int(seconds_to_stamps_ns([extras[r.number].odom_times[0] + delay_s])[0])
                     for r in dataset.robots], np.int64)


def start_pose(robot, extras, delay_s):
    """Return a robot's true pose (3,) at its first odometry stamp (delay added)."""
    pose, _ = interpolate_poses(robot.gt_times, robot.gt_poses,
                                [extras[robot.number].odom_times[0] + delay_s])
    return pose[0]


def _events(dataset, extras, delay_s):
    """Return (stamp, kind, robot, index) of every odometry and sighting message, sorted."""
    events = []
    for i, robot in enumerate(dataset.robots):
        odom_ns = seconds_to_stamps_ns(extras[robot.number].odom_times + delay_s)
        events += [(int(t), _ODOM, i, k) for k, t in enumerate(odom_ns)]
        starts, _ = batches(robot.times)
        if len(starts):
            obs_ns = seconds_to_stamps_ns(robot.times[starts])
            events += [(int(t), _OBS, i, j) for j, t in enumerate(obs_ns)]
    events.sort()
    return events


class _Observer:
    """The stamps an ``Observer`` holds for one robot: first and newest pose, pending."""

    def __init__(self, first_ns, config):
        self.first = self.newest = int(first_ns)
        self.gap_ns = int(config.max_pose_gap_s * 1e9)
        self.max_wait_s = config.max_wait_s
        self.processed = 0
        self.pending = deque()

    def pose(self, stamp):
        """Take the pose of an odometry message; return the (stamp, index) it places."""
        self.processed += 1
        self.newest = stamp
        placed = []
        while self.pending and self.pending[0][0] <= stamp:
            placed.append(self.pending.popleft())
        return placed

    def sightings(self, stamp, k):
        """
        Take a message at its own stamp (the offline loop's clock); return what it settles.

        ``(placed, stale, dropped)``: messages placed with bracketing poses, placed with
        the newest pose after ``max_wait_s`` (``Observer.drain``, final lookup), dropped.
        """
        if not self.pending and self.first - self.gap_ns <= stamp <= self.newest:
            return [(stamp, k)], [], 0
        self.pending.append((stamp, k))
        placed, stale, dropped = [], [], 0
        while self.pending:
            head, _ = self.pending[0]
            if head < self.first - self.gap_ns:
                dropped += 1
            elif head <= self.newest:
                placed.append(self.pending[0])
            elif stamp - head < self.max_wait_s * 1e9:
                break
            elif head - self.newest <= self.gap_ns:
                stale.append(self.pending[0])
            else:
                dropped += 1
            self.pending.popleft()
        return placed, stale, dropped


def plan(dataset, extras, delay_s, observer) -> Steps:
    """
    Return the ``Steps`` of a run (module docstring), from the stamps alone.

    Parameters
    ----------
    dataset : mrclam.data.Dataset
        Per robot its sightings (``times``; one message per run of equal stamps).
    extras : dict
        ``localize_data.RobotExtras`` by robot number (``odom_times``).
    delay_s : float
        Added to the odometry stamps [s], as in the offline run.
    observer : pipeline.config.ObserverConfig
        The observers' ``max_pose_gap_s`` (a message at most this much older than the
        first pose takes it; older, it is dropped) and ``max_wait_s`` (in the offline
        loop's clock, the stamps: a message waiting that long when the next one comes
        takes the newest pose within ``max_pose_gap_s`` or is dropped).

    """
    observers = [_Observer(t, observer) for t in start_stamps(dataset, extras, delay_s)]
    spans = [batches(r.times) for r in dataset.robots]
    out: List[tuple] = []
    dropped = 0
    for stamp, kind, i, k in _events(dataset, extras, delay_s):
        obs = observers[i]
        if kind == _ODOM:
            out += [(i, j, s, obs.processed, False) for s, j in obs.pose(stamp)]
            continue
        placed, stale, lost = obs.sightings(stamp, k)
        out += [(i, j, s, obs.processed, False) for s, j in placed]
        out += [(i, j, s, obs.processed, True) for s, j in stale]
        dropped += lost
    # Before any odometry the localizer drops the sightings either way (they wait, then
    # are too old for the first odometry's pose; a node has no pose yet): the pose of
    # the first odometry may come first, and the node's observer needs it.
    robot = np.array([o[0] for o in out], np.int64)
    j = np.array([o[1] for o in out], np.int64)
    start = np.array([spans[r][0][b] for r, b in zip(robot, j)], np.int64)
    end = np.array([spans[r][1][b] for r, b in zip(robot, j)], np.int64)
    return Steps(robot, start, end, np.array([o[2] for o in out], np.int64),
                 np.array([max(o[3], 1) for o in out], np.int64),
                 np.array([o[4] for o in out], bool), dropped)


def without_robot_sightings(extras):
    """Return ``extras`` with no robot-to-robot sighting (the nodes' run replays none)."""
    return {number: replace(ex, sighting_times=ex.sighting_times[:0],
                            sighting_robot=ex.sighting_robot[:0],
                            sighting_z=ex.sighting_z[:0])
            for number, ex in extras.items()}


class _Published:
    """An observer that records the poses it is given (what the node publishes)."""

    def __init__(self, observer):
        self._observer = observer
        self.poses: List[tuple] = []

    def add_pose(self, stamp_ns, pose, P_pose, now_ns=0):
        """Record the pose, then hand it to the observer."""
        self.poses.append((int(stamp_ns), np.array(pose), np.array(P_pose)))
        return self._observer.add_pose(stamp_ns, pose, P_pose, now_ns)

    def __getattr__(self, name):
        return getattr(self._observer, name)


@dataclass
class Reference:
    """The offline loop without robot sightings, with the poses each odometry published."""

    loop: TeamLoop
    published: List[Dict[str, np.ndarray]]
    """Per robot ``stamps_ns`` (K,), ``x`` (K, 3), ``P`` (K, 3, 3): the poses given to
    the observer after each odometry message (the start pose left out)."""


def offline_reference(dataset, extras, loop_config: LoopConfig, delay_s) -> Reference:
    """
    Run the offline loop as the nodes' run does; return it with the published poses.

    The events of ``mrclam.slam.run`` without the robot-to-robot sightings; each robot
    starts at its true pose at its first odometry stamp (``start_stamps``).
    """
    loop = TeamLoop(loop_config, [r.name for r in dataset.robots])
    starts = start_stamps(dataset, extras, delay_s)
    P0 = np.diag(np.square(loop_config.localizer.initial_stddev))
    for i, robot in enumerate(dataset.robots):
        loop.start(i, int(starts[i]), start_pose(robot, extras, delay_s), P0)
    recorders = [_Published(o) for o in loop.observers]
    loop.observers = recorders
    spans = [batches(r.times) for r in dataset.robots]
    for stamp, kind, i, k in _events(dataset, extras, delay_s):
        robot = dataset.robots[i]
        if kind == _ODOM:
            loop.odometry(i, stamp, twist=extras[robot.number].odom_twist[k])
        else:
            a, b = spans[i][0][k], spans[i][1][k]
            loop.sightings(i, stamp, robot.ids[a:b], robot.z[a:b])
    published = []
    for rec in recorders:
        published.append({'stamps_ns': np.array([p[0] for p in rec.poses], np.int64),
                          'x': np.array([p[1] for p in rec.poses]).reshape(-1, 3),
                          'P': np.array([p[2] for p in rec.poses]).reshape(-1, 3, 3)})
    return Reference(loop, published)
