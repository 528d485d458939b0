"""
What ``landmark_mrclam --localize --through-nodes`` sends, in which order (ROS-free).

The offline run (``mrclam.localize.run``) feeds each robot's ``Localizer`` its odometry
and its sightings in time order, odometry first at equal stamps. A sighting between
two odometry stamps waits inside the localizer until the odometry passes its stamp
(``waiting_for_odometry``), and is applied by the next odometry message, before that
message's pose is returned. A node gets the same calls in the same order when:

- a sighting batch with a stamp strictly between odometry ``k - 1`` and ``k`` is taken
  by the node before odometry ``k`` (taken earlier it waits in the localizer all the
  same);
- a batch stamped exactly at odometry ``k`` (or before the first) is taken after
  odometry ``k`` and before odometry ``k + 1``: taken before ``k``, odometry ``k``
  would apply it and publish a pose with it, where the offline run records the pose
  without it;
- every batch after the first odometry: before it the node has no pose and drops the
  batch (``not_initialised``), where the offline run, initialised at the start, keeps
  it waiting.

The node's two subscriptions give no order between them, so the player enforces it
(``mrclam.localize_nodes``): a batch of the second kind waits for the pose of
odometry ``k`` (every odometry message gives one pose); after any batch, the next
odometry waits until the node's diagnostics count every batch sent in
(``observation_messages_in``): DDS does not order the player's two writers.

``slice_run`` cuts a run to its first seconds (``--duration``) or to a later window
(``--start``).
"""

from dataclasses import dataclass, replace
import math
from typing import List

from landmark_ros.mrclam.data import seconds_to_stamps_ns
import numpy as np

ODOMETRY, SIGHTINGS = 0, 1
"""Kinds of the items of a ``Schedule``."""


@dataclass(frozen=True)
class Schedule:
    """One robot's messages in sending order (``M`` items)."""

    kind: np.ndarray
    """``ODOMETRY`` or ``SIGHTINGS`` per item, shape (M,)."""
    index: np.ndarray
    """Odometry index, or first row of the sighting batch in the robot's rows, (M,)."""
    end: np.ndarray
    """Sighting batch: one past its last row; odometry: unused, shape (M,)."""
    stamp_ns: np.ndarray
    """Stamp per item [ns], shape (M,)."""
    after_poses: np.ndarray
    """Poses to have received before sending the item (0: none needed), shape (M,)."""
    barrier: np.ndarray
    """Odometry item preceded by sightings: it waits for them to be taken, shape (M,) bool."""

    def __len__(self):
        """Return the number of items."""
        return len(self.kind)


def batches(times):
    """Return the first and one-past-last row of each run of equal stamps, (B,), (B,)."""
    times = np.asarray(times)
    if not len(times):
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    new = np.ones(len(times), bool)
    new[1:] = times[1:] != times[:-1]
    starts = np.flatnonzero(new)
    return starts, np.append(starts[1:], len(times))


def schedule(robot, extras, delay_s, strict=False):
    """
    Return a robot's ``Schedule`` (module docstring).

    With ``strict`` a batch between odometry ``k - 1`` and ``k`` also waits for the pose
    of ``k - 1``: the node then takes it with the same newest odometry as the offline
    run, which the association of rows without IDs needs (it places the rows from the
    newest pose at or before their stamp).

    Parameters
    ----------
    robot : mrclam.data.Robot
        Its sightings (``times``, ``ids``, ``z``).
    extras : mrclam.localize_data.RobotExtras
        Its odometry (``odom_times``).
    delay_s : float
        Added to the odometry stamps [s], as in the offline run.
    strict : bool
        Every batch also waits for the pose of the odometry before it (above).

    """
    odom_ns = seconds_to_stamps_ns(extras.odom_times + delay_s)
    starts, ends = batches(robot.times)
    obs_ns = seconds_to_stamps_ns(robot.times[starts]) if len(starts) else np.zeros(0, np.int64)
    # Odometry k that applies each batch: the first with a stamp at or after it.
    k = np.searchsorted(odom_ns, obs_ns, side='left')
    tie = (k < len(odom_ns)) & (odom_ns[np.minimum(k, len(odom_ns) - 1)] == obs_ns)
    tie |= k == 0
    # Sending order: odometry k at 4k, a batch that k applies at 4k - 2 (just before),
    # a batch tied with k (or before the first) at 4k + 2 (just after).
    odom_slot = np.arange(len(odom_ns)) * 4
    obs_slot = np.where(tie, 4 * k + 2, 4 * k - 2)
    slot = np.concatenate([odom_slot, obs_slot])
    kind = np.concatenate([np.full(len(odom_ns), ODOMETRY), np.full(len(starts), SIGHTINGS)])
    index = np.concatenate([np.arange(len(odom_ns)), starts])
    end = np.concatenate([np.zeros(len(odom_ns), np.intp), ends])
    stamp = np.concatenate([odom_ns, obs_ns])
    # Every batch after the first pose: before any odometry the node has no pose at all.
    after = np.concatenate([np.zeros(len(odom_ns), np.int64),
                            np.where(tie, k + 1, np.maximum(k, 1) if strict else 1)])
    order = np.lexsort((index, slot))
    kind, index, end, stamp, after = (a[order] for a in (kind, index, end, stamp, after))
    barrier = np.zeros(len(kind), bool)
    barrier[1:] = (kind[1:] == ODOMETRY) & (kind[:-1] == SIGHTINGS)
    return Schedule(kind, index, end, stamp, after, barrier)


def slice_run(dataset, extras, seconds, start_s=0.0):
    """
    Return the dataset and extras cut to ``seconds`` of the sightings from ``start_s``.

    ``start_s`` [s] counts from the first sighting (``dataset.time_span[0]``); every
    robot keeps the sightings, odometry and robot sightings stamped before
    ``first + start_s + seconds`` (the odometry by its own stamps, without delay) and,
    with ``start_s`` > 0, from ``first + start_s`` on; ``seconds`` None keeps
    everything after the start. The ground truth stays whole (a replay starts each
    robot at the truth at its first kept odometry).
    """
    first = dataset.time_span[0]
    begin = first + float(start_s) if start_s > 0 else -math.inf
    end = math.inf if seconds is None else first + float(start_s) + float(seconds)
    robots: List = []
    for robot in dataset.robots:
        keep = (robot.times >= begin) & (robot.times < end)
        robots.append(replace(robot, times=robot.times[keep], ids=robot.ids[keep],
                              z=robot.z[keep], poses=robot.poses[keep]))
    cut = {}
    for number, ex in extras.items():
        k = (ex.odom_times >= begin) & (ex.odom_times < end)
        s = (ex.sighting_times >= begin) & (ex.sighting_times < end)
        cut[number] = replace(ex, odom_times=ex.odom_times[k], odom_twist=ex.odom_twist[k],
                              sighting_times=ex.sighting_times[s],
                              sighting_robot=ex.sighting_robot[s],
                              sighting_z=ex.sighting_z[s])
    return replace(dataset, robots=robots), cut


def hide_ids(dataset, unknown_id):
    """Return the dataset with every sighting's landmark ID replaced by ``unknown_id``."""
    return replace(dataset, robots=[replace(r, ids=np.full(len(r.ids), unknown_id, np.int64))
                                    for r in dataset.robots])
