"""
A MRCLAM dataset as a rosbag2 (MCAP): what the robots' observers would receive.

``export_dataset(dataset, pose_stddev, path)`` writes, in global time order (ties by
robot number, as ``Dataset.rows``), per observation message of the replay (the rows of
one robot at one stamp, ``Rows.messages``):

``/robotN/pose`` (geometry_msgs/PoseWithCovarianceStamped, frame ``map``)
    The ground-truth pose interpolated at the measurement stamp, with the covariance
    ``diag(pose_stddev ** 2)`` in its (x, y, yaw) entries (``schemas.pose_message``).
``/robotN/observations`` (sensor_msgs/PointCloud2, frame ``robotN/camera``)
    The sightings of that stamp (``schemas.observation_message``: ``id``, ``range``,
    ``bearing``), written right after the pose, with the same stamp.

and once, at the first stamp, ``/ground_truth_landmarks`` (the ``landmarks`` schema,
frame ``map``, zero covariance; recorded transient local). Bag times are the message
stamps. Replayed through ``landmark_observer`` and ``landmark_fuser`` (``ros2 bag play``)
or ``landmark_bag``, the bag gives what ``landmark_mrclam`` computes.

Run as ``python -m landmark_ros.bag.export DATASET OUTPUT [--config FILE]``.
"""

import argparse
from pathlib import Path
import sys

from geometry_msgs.msg import PoseWithCovarianceStamped
from landmark_ros.bag.params import node_parameters, read_document
from landmark_ros.bag.storage import BagError, BagOutput
from landmark_ros.mrclam.data import DEFAULT_POSE_STDDEV, load_dataset
from landmark_ros.ros.conversions import seconds_to_ns
from landmark_ros.ros.schemas import landmark_message, make_header, observation_message
from landmark_ros.ros.schemas import pose_message
import numpy as np
from sensor_msgs.msg import PointCloud2

GROUND_TRUTH_TOPIC = '/ground_truth_landmarks'
WORLD_FRAME = 'map'


def pose_stddev_from_config(path):
    """
    Return ``pose_stddev_x``, ``_y``, ``_yaw`` of a params file's ``landmark_mrclam`` section.

    Parameters
    ----------
    path : str or Path
        A parameter file such as ``config/mrclam.yaml``.

    Returns
    -------
    tuple of 3 float
        x [m], y [m], yaw [rad]; the MRCLAM defaults where the file sets none.

    Raises
    ------
    ValueError
        If the file cannot be read or a value is not a finite number >= 0.

    """
    section = node_parameters(read_document(path), '/landmark_mrclam')
    stddev = []
    for axis, default in zip(('x', 'y', 'yaw'), DEFAULT_POSE_STDDEV):
        value = section.get(f'pose_stddev_{axis}', default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                np.isfinite(value) and value >= 0.0):
            raise ValueError(f'{path}: pose_stddev_{axis} must be a finite number >= 0, '
                             f'got {value!r}')
        stddev.append(float(value))
    return tuple(stddev)


def export_dataset(dataset, pose_stddev, path):
    """
    Write a MRCLAM dataset as a rosbag2 (MCAP) of the observers' inputs and ground truth.

    Parameters
    ----------
    dataset : landmark_ros.mrclam.data.Dataset or str or Path
        A loaded dataset, or its directory (read with ``load_dataset``).
    pose_stddev : sequence of 3 float
        Standard deviations of the reported poses: x [m], y [m], yaw [rad]; in the
        replay, ``pose_stddev_*`` of the ``landmark_mrclam`` section of
        ``config/mrclam.yaml`` (``pose_stddev_from_config``).
    path : str or Path
        The bag directory to create; it must not exist. Written atomically: nothing is
        left there if the export fails.

    Returns
    -------
    dict
        Messages written per topic.

    Raises
    ------
    BagError
        If ``path`` exists, or its parent directory does not.
    FileNotFoundError, ValueError
        If ``dataset`` is a directory that is missing or malformed.

    """
    if not hasattr(dataset, 'rows'):
        dataset = load_dataset(dataset, pose_stddev)
    P_pose = np.diag(np.square(np.asarray(pose_stddev, dtype=np.float64).reshape(3)))
    rows = dataset.rows()
    starts, ends = rows.messages()
    names = [robot.name for robot in dataset.robots]
    with BagOutput(path) as out:
        out.add_topic(GROUND_TRUTH_TOPIC, PointCloud2, latched=True, depth=1)
        for name in names:
            out.add_topic(f'/{name}/pose', PoseWithCovarianceStamped)
            out.add_topic(f'/{name}/observations', PointCloud2)
        if dataset.landmarks:
            first = float(rows.times[0]) if len(rows) else 0.0
            ids = sorted(dataset.landmarks)
            out.write(GROUND_TRUTH_TOPIC, seconds_to_ns(first), landmark_message(
                make_header(first, WORLD_FRAME), ids,
                np.array([dataset.landmarks[i] for i in ids], dtype=np.float64).reshape(-1, 2),
                np.zeros((len(ids), 2, 2))))
        for a, b in zip(starts.tolist(), ends.tolist()):
            name = names[int(rows.robot[a])]
            stamp = float(rows.times[a])
            time_ns = seconds_to_ns(stamp)
            out.write(f'/{name}/pose', time_ns,
                      pose_message(stamp, rows.poses[a], P_pose, WORLD_FRAME))
            out.write(f'/{name}/observations', time_ns, observation_message(
                make_header(stamp, f'{name}/camera'), rows.ids[a:b], rows.z[a:b]))
    return dict(out.counts)


def main(argv=None):
    """Export a MRCLAM dataset as a bag; return the exit code (2 on bad input)."""
    parser = argparse.ArgumentParser(
        prog='python -m landmark_ros.bag.export',
        description='Write a MRCLAM dataset as a rosbag2 (MCAP): /robotN/pose, '
                    '/robotN/observations, /ground_truth_landmarks.')
    parser.add_argument('dataset', type=Path, help='MRCLAM dataset directory')
    parser.add_argument('output', type=Path, help='bag directory to create')
    parser.add_argument('--config', type=Path, default=None,
                        help='params file with a landmark_mrclam section (pose_stddev_*); '
                             'default: the MRCLAM values 0.002 m, 0.002 m, 0.002 rad')
    args = parser.parse_args(argv)
    try:
        stddev = (pose_stddev_from_config(args.config) if args.config is not None
                  else DEFAULT_POSE_STDDEV)
        counts = export_dataset(args.dataset, stddev, args.output)
    except (BagError, FileNotFoundError, ValueError) as error:
        print(f'{parser.prog}: error: {error}', file=sys.stderr)
        return 2
    listed = ', '.join(f'{topic} {count}' for topic, count in sorted(counts.items()))
    print(f'wrote {args.output}: {listed}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
