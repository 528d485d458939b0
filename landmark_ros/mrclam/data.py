"""
Reader of UTIAS MRCLAM datasets (ROS-free, vectorised numpy).

A dataset directory holds ``Barcodes.dat`` (subject, barcode),
``Landmark_Groundtruth.dat`` (subject, x, y, x std-dev, y std-dev) and, per robot
``N`` (however many there are), ``RobotN_Groundtruth.dat`` (time, x, y, theta) and
``RobotN_Measurement.dat`` (time, barcode, range, bearing). Files are whitespace
separated with ``#`` comment lines; CRLF line endings and trailing whitespace are
fine. Times are Unix seconds.

Measurements are kept when their barcode maps (``Barcodes.dat``) to a landmark
subject (6 and up) and their stamp lies in the robot's ground-truth time span; the
robot pose at each kept stamp is interpolated from the ground truth (position
linearly, heading linearly on the unwrapped heading, i.e. on the shortest arc
between two samples). Everything dropped is counted in ``Dataset.counts``:

``robot_sightings``
    Barcode of a robot (subjects 1-5): robot-to-robot sightings.
``unknown_barcode``
    Barcode in no table.
``outside_groundtruth``
    Stamp before the first or after the last ground-truth pose of the robot.
"""

from collections import Counter
from dataclasses import dataclass, field, replace
import math
from pathlib import Path
import re
from typing import Optional, Tuple
import warnings

from landmark_ros.core.pose2 import wrap_angle
import numpy as np

ROBOT_SUBJECTS = frozenset(range(1, 6))
"""Subjects that are robots; every other subject is a landmark."""

DEFAULT_POSE_STDDEV = (0.002, 0.002, 0.002)
"""Standard deviations of the reported poses: x [m], y [m], yaw [rad]."""

_ROBOT_FILE = re.compile(r'^Robot(\d+)_Measurement\.dat$')


def read_table(path, columns):
    """
    Read a whitespace-separated numeric table with ``#`` comments.

    Parameters
    ----------
    path : str or Path
        The file.
    columns : int
        Columns every data line must have.

    Returns
    -------
    ndarray, shape (N, columns)

    Raises
    ------
    ValueError
        If a data line has another number of columns or a non-numeric value.

    """
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', UserWarning)  # empty file: "input contained no data"
        try:
            table = np.loadtxt(path, comments='#', dtype=np.float64, ndmin=2)
        except ValueError as error:
            raise ValueError(f'{path}: {error}') from error
    if table.size == 0:
        return np.empty((0, columns))
    if table.shape[1] != columns:
        raise ValueError(f'{path}: {table.shape[1]} columns, expected {columns}')
    return table


def seconds_to_stamps_ns(seconds):
    """
    Return Unix times as the integer nanoseconds of the message stamps that carry them.

    ``sec = floor(t)``, ``nanosec = round((t - sec) 1e9)`` (half to even), carried into
    ``sec`` at 1e9: the stamps ``landmark_ros.ros.conversions.set_stamp`` writes, so the
    offline replay and the messages of ``--through-nodes`` hold the same stamps.

    Parameters
    ----------
    seconds : array_like, shape (N,)
        Times [s], finite and non-negative.

    Returns
    -------
    ndarray of int64, shape (N,)
        Stamps [ns].

    """
    seconds = np.asarray(seconds, dtype=np.float64)
    sec = np.floor(seconds)
    nanosec = np.rint((seconds - sec) * 1e9).astype(np.int64)
    sec = sec.astype(np.int64)
    carry = nanosec >= 1_000_000_000
    sec[carry] += 1
    nanosec[carry] -= 1_000_000_000
    return sec * 1_000_000_000 + nanosec


def interpolate_poses(gt_times, gt_poses, times):
    """
    Interpolate ground-truth poses at ``times``.

    Parameters
    ----------
    gt_times : ndarray, shape (M,)
        Ground-truth stamps, increasing [s].
    gt_poses : ndarray, shape (M, 3)
        Poses (x, y, theta) at those stamps.
    times : ndarray, shape (N,)
        Where to interpolate [s].

    Returns
    -------
    poses : ndarray, shape (N, 3)
        Interpolated poses, heading wrapped to [-pi, pi); stamps outside the
        ground-truth span take the nearest end pose.
    inside : ndarray of bool, shape (N,)
        Whether each stamp lies within ``[gt_times[0], gt_times[-1]]``.

    """
    times = np.asarray(times, dtype=np.float64)
    if len(gt_times) == 0:
        return np.full((len(times), 3), np.nan), np.zeros(len(times), bool)
    heading = np.unwrap(gt_poses[:, 2])
    poses = np.stack([np.interp(times, gt_times, gt_poses[:, 0]),
                      np.interp(times, gt_times, gt_poses[:, 1]),
                      wrap_angle(np.interp(times, gt_times, heading))], axis=1)
    inside = (times >= gt_times[0]) & (times <= gt_times[-1])
    return poses, inside


@dataclass
class Robot:
    """One robot's landmark sightings and ground truth."""

    number: int
    """N of ``RobotN_*``."""
    times: np.ndarray
    """Stamps of the kept sightings, non-decreasing [s], shape (K,)."""
    ids: np.ndarray
    """Landmark subjects, int64, shape (K,)."""
    z: np.ndarray
    """Range [m] and bearing [rad], shape (K, 2)."""
    poses: np.ndarray
    """Ground-truth pose interpolated at each stamp, shape (K, 3)."""
    gt_times: np.ndarray
    """Ground-truth stamps [s], shape (M,)."""
    gt_poses: np.ndarray
    """Ground-truth poses, shape (M, 3)."""
    counts: Counter = field(default_factory=Counter)
    """Measurements read, kept and dropped (by reason) for this robot."""

    @property
    def name(self):
        """Return ``robotN``: the namespace of the robot's nodes."""
        return f'robot{self.number}'

    @property
    def landmarks_topic(self):
        """Return the robot observer's output topic, the fuser's source name."""
        return f'/{self.name}/landmarks'


@dataclass(frozen=True)
class Part:
    """A time slice and robot subset of a dataset (``Dataset.part``)."""

    start_s: float = -math.inf
    """First stamp kept, after the dataset's first kept sighting [s] (inclusive)."""
    end_s: float = math.inf
    """Stamps from here on are dropped [s] (exclusive)."""
    robots: Optional[Tuple[int, ...]] = None
    """Robot numbers (``N`` of ``RobotN``) kept; None keeps every robot."""

    def label(self):
        """Return a short description: ``0-600 s, robots 1 2``."""
        parts = []
        if math.isfinite(self.start_s) or math.isfinite(self.end_s):
            low = '' if not math.isfinite(self.start_s) else f'{self.start_s:.0f}'
            high = 'end' if not math.isfinite(self.end_s) else f'{self.end_s:.0f}'
            parts.append(f'{low or "0"}-{high} s')
        if self.robots is not None:
            parts.append('robots ' + ' '.join(str(n) for n in self.robots))
        return ', '.join(parts) or 'all'


@dataclass
class Dataset:
    """A loaded MRCLAM dataset."""

    path: Path
    robots: list
    """Robot objects, by increasing number."""
    landmarks: dict
    """True landmark positions: subject -> (x, y) [m]."""
    landmark_stddev: dict
    """Standard deviations of the true positions: subject -> (sx, sy) [m]."""
    barcodes: dict
    """Barcode -> subject."""
    pose_stddev: tuple = DEFAULT_POSE_STDDEV
    """Standard deviations of the reported poses: x [m], y [m], yaw [rad]."""
    counts: Counter = field(default_factory=Counter)
    """Totals over the robots: ``read``, ``kept`` and the dropped counts by reason."""

    @property
    def P_pose(self):
        """Return the covariance of every reported pose, shape (3, 3)."""
        return np.diag(np.square(np.asarray(self.pose_stddev, dtype=np.float64)))

    @property
    def time_span(self):
        """Return the first and last kept measurement stamps [s]."""
        times = [r.times for r in self.robots if len(r.times)]
        if not times:
            return (0.0, 0.0)
        return (min(t[0] for t in times), max(t[-1] for t in times))

    @property
    def duration(self):
        """Return the time from the first to the last kept measurement [s]."""
        start, end = self.time_span
        return end - start

    def part(self, part):
        """
        Return the dataset restricted to a time slice and a subset of its robots.

        Parameters
        ----------
        part : Part
            Which sightings to keep.

        Returns
        -------
        Dataset
            The robots of ``part.robots`` (all if None), each with the sightings whose
            stamp lies in ``[start, end)`` after the first kept sighting of the dataset;
            ground truth, landmarks and ``counts`` (of the whole file) unchanged.

        """
        origin = self.time_span[0]
        robots = []
        for robot in self.robots:
            if part.robots is not None and robot.number not in part.robots:
                continue
            t = robot.times - origin
            keep = (t >= part.start_s) & (t < part.end_s)
            robots.append(replace(robot, times=robot.times[keep], ids=robot.ids[keep],
                                  z=robot.z[keep], poses=robot.poses[keep]))
        return replace(self, robots=robots)

    def with_camera_delay(self, seconds):
        """
        Return the dataset with every sighting stamped ``seconds`` earlier.

        A camera that stamps its sightings ``seconds`` after they were taken
        (``mrclam.camera_delay``) gets its stamps moved back: each robot's sightings at
        ``times - seconds``, with the ground-truth pose interpolated there. Sightings
        that fall outside the robot's ground truth are dropped and counted in
        ``outside_groundtruth`` (``kept`` less them), per robot and in total.

        Parameters
        ----------
        seconds : float
            The delay [s], finite; 0 returns the dataset itself.

        Returns
        -------
        Dataset

        Raises
        ------
        ValueError
            If ``seconds`` is not finite.

        """
        seconds = float(seconds)
        if not math.isfinite(seconds):
            raise ValueError(f'camera delay must be finite, got {seconds}')
        if seconds == 0.0:
            return self
        robots, counts = [], Counter(self.counts)
        for robot in self.robots:
            times = robot.times - seconds
            poses, inside = interpolate_poses(robot.gt_times, robot.gt_poses, times)
            dropped = int((~inside).sum())
            robot_counts = Counter(robot.counts)
            for tally in (robot_counts, counts):
                tally['outside_groundtruth'] += dropped
                tally['kept'] -= dropped
            robots.append(replace(robot, times=times[inside], ids=robot.ids[inside],
                                  z=robot.z[inside], poses=poses[inside],
                                  counts=robot_counts))
        return replace(self, robots=robots, counts=counts)

    def rows(self):
        """
        Return every kept sighting of every robot in global time order.

        Ties in time are broken by robot number, then by file order.

        Returns
        -------
        Rows

        """
        if not self.robots:
            empty = np.empty(0)
            return Rows(np.empty(0, np.int64), empty, np.empty(0, np.int64),
                        np.empty((0, 2)), np.empty((0, 3)), [])
        robot = np.concatenate([np.full(len(r.times), i, np.int64)
                                for i, r in enumerate(self.robots)])
        times = np.concatenate([r.times for r in self.robots])
        order = np.lexsort((robot, times))  # stable: file order within equal keys
        return Rows(robot[order], times[order],
                    np.concatenate([r.ids for r in self.robots])[order],
                    np.concatenate([r.z for r in self.robots])[order],
                    np.concatenate([r.poses for r in self.robots])[order],
                    [r.landmarks_topic for r in self.robots])


@dataclass
class Rows:
    """Sightings of all robots in global time order (``Dataset.rows``)."""

    robot: np.ndarray
    """Index into ``Dataset.robots`` per row, shape (N,)."""
    times: np.ndarray
    """Stamps [s], shape (N,)."""
    ids: np.ndarray
    """Landmark subjects, shape (N,)."""
    z: np.ndarray
    """Range and bearing, shape (N, 2)."""
    poses: np.ndarray
    """Robot poses, shape (N, 3)."""
    topics: list
    """Landmark topic of each robot index."""

    def __len__(self):
        return len(self.times)

    @property
    def stamps_ns(self):
        """Return the stamps as message stamps [ns] (``seconds_to_stamps_ns``), shape (N,)."""
        return seconds_to_stamps_ns(self.times)

    def messages(self):
        """
        Split the rows into messages: consecutive rows of one robot at one stamp.

        One message is what a robot's observer receives as one observation cloud.

        Returns
        -------
        starts, ends : ndarray of int, shape (K,)
            Row ranges ``[start, end)`` of the messages, in global time order.

        """
        count = len(self.times)
        if not count:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        new = np.ones(count, bool)
        new[1:] = (self.robot[1:] != self.robot[:-1]) | (self.times[1:] != self.times[:-1])
        starts = np.flatnonzero(new)
        return starts, np.append(starts[1:], count)


def robot_numbers(path):
    """Return the robot numbers N with a ``RobotN_Measurement.dat`` in ``path``, sorted."""
    numbers = []
    for entry in Path(path).iterdir():
        match = _ROBOT_FILE.match(entry.name)
        if match:
            numbers.append(int(match.group(1)))
    return sorted(numbers)


def load_robot(path, number, barcodes, landmark_subjects):
    """
    Read one robot's measurements and ground truth; keep its landmark sightings.

    Parameters
    ----------
    path : Path
        Dataset directory.
    number : int
        Robot number N.
    barcodes : dict
        Barcode -> subject.
    landmark_subjects : set of int
        Subjects that are landmarks.

    Returns
    -------
    Robot

    """
    path = Path(path)
    gt = read_table(path / f'Robot{number}_Groundtruth.dat', 4)
    gt = gt[np.argsort(gt[:, 0], kind='stable')]
    # Repeated ground-truth stamps would make interpolation ambiguous: keep the first.
    if len(gt) > 1:
        gt = gt[np.concatenate([[True], np.diff(gt[:, 0]) > 0])]
    meas = read_table(path / f'Robot{number}_Measurement.dat', 4)
    meas = meas[np.argsort(meas[:, 0], kind='stable')]
    counts = Counter(read=len(meas))
    codes = np.rint(meas[:, 1]).astype(np.int64)
    table = np.array(sorted(barcodes.items()), dtype=np.int64).reshape(-1, 2)
    position = np.clip(np.searchsorted(table[:, 0], codes), 0, max(len(table) - 1, 0))
    known = (table[position, 0] == codes) if len(table) else np.zeros(len(codes), bool)
    subjects = np.where(known, table[position, 1] if len(table) else 0, -1)
    robot = known & np.isin(subjects, list(ROBOT_SUBJECTS))
    landmark = known & np.isin(subjects, list(landmark_subjects)) & ~robot
    unknown = ~(robot | landmark)
    counts['robot_sightings'] = int(robot.sum())
    counts['unknown_barcode'] = int(unknown.sum())
    poses, inside = interpolate_poses(gt[:, 0], gt[:, 1:4], meas[:, 0])
    counts['outside_groundtruth'] = int((landmark & ~inside).sum())
    keep = landmark & inside
    counts['kept'] = int(keep.sum())
    return Robot(number, meas[keep, 0].copy(), subjects[keep].astype(np.int64),
                 meas[keep][:, 2:4].copy(), poses[keep], gt[:, 0].copy(), gt[:, 1:4].copy(),
                 counts)


def load_dataset(path, pose_stddev=DEFAULT_POSE_STDDEV):
    """
    Load a MRCLAM dataset directory.

    Parameters
    ----------
    path : str or Path
        Directory with ``Barcodes.dat``, ``Landmark_Groundtruth.dat`` and the
        ``RobotN_Groundtruth.dat`` / ``RobotN_Measurement.dat`` pairs.
    pose_stddev : sequence of 3 float
        Standard deviations of the reported poses: x [m], y [m], yaw [rad].

    Returns
    -------
    Dataset

    Raises
    ------
    FileNotFoundError
        If the directory or one of its files is missing.
    ValueError
        If a file is malformed.

    """
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f'no MRCLAM dataset directory {path}')
    barcode_table = read_table(path / 'Barcodes.dat', 2).astype(np.int64)
    barcodes = {int(code): int(subject) for subject, code in barcode_table}
    truth = read_table(path / 'Landmark_Groundtruth.dat', 5)
    landmarks = {int(row[0]): (float(row[1]), float(row[2])) for row in truth}
    stddev = {int(row[0]): (float(row[3]), float(row[4])) for row in truth}
    subjects = set(landmarks) | {s for s in barcodes.values() if s not in ROBOT_SUBJECTS}
    numbers = robot_numbers(path)
    if not numbers:
        raise FileNotFoundError(f'no RobotN_Measurement.dat in {path}')
    robots = [load_robot(path, n, barcodes, subjects) for n in numbers]
    counts = Counter()
    for robot in robots:
        counts.update(robot.counts)
    for key in ('read', 'kept', 'robot_sightings', 'unknown_barcode', 'outside_groundtruth'):
        counts.setdefault(key, 0)
    return Dataset(path, robots, landmarks, stddev, barcodes,
                   tuple(float(s) for s in pose_stddev), counts)
