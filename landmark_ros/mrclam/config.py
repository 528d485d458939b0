"""
The replay's configuration: one ROS params file for the nodes and the replay (ROS-free).

``config/mrclam.yaml`` holds the ``landmark_observer`` and ``landmark_fuser`` sections
the nodes read with ``--params-file`` and a ``landmark_mrclam`` section of the replay's
own settings (the pose standard deviations, the camera delay). ``load_config`` reads all
three into one
``ReplayConfig``: the node sections through ``ObserverConfig.from_values`` and
``FuserConfig.from_values``, so the offline replay and the nodes validate the very same
values.
"""

from dataclasses import dataclass, fields
import math
import os
from pathlib import Path

from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
import numpy as np

PACKAGE_NAME = 'landmark_ros'
PACKAGE_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CONFIG_NAME = 'mrclam.yaml'
DEFAULT_DATASET = Path('shared') / 'data' / 'mrclam' / 'dataset6'


@dataclass(frozen=True)
class ReplayConfig:
    """The parameters of both nodes and of the replay, from one params file."""

    observer: ObserverConfig
    fuser: FuserConfig
    pose_stddev: tuple = (0.002, 0.002, 0.002)
    """Standard deviations of the reported poses: x [m], y [m], yaw [rad]."""
    path: Path = None
    camera_delay_s: float = 0.0
    """How long before its stamp a sighting was taken [s] (``mrclam.camera_delay``); the
    replay moves the stamps back by it (``Dataset.with_camera_delay``). 0: none."""

    @property
    def P_pose(self):
        """Return the pose covariance, shape (3, 3)."""
        return np.diag(np.square(np.asarray(self.pose_stddev, dtype=np.float64)))


def installed_share_directory(environ=None):
    """
    Return the package's installed ``share`` directory, or None.

    Reads the ament resource index the way ``ament_index_python`` does (a marker file
    ``share/ament_index/resource_index/packages/landmark_ros`` under a prefix of
    ``AMENT_PREFIX_PATH``), without importing it: this module stays ROS-free.

    Parameters
    ----------
    environ : mapping, optional
        The environment; ``os.environ`` by default.

    Returns
    -------
    Path or None

    """
    environ = os.environ if environ is None else environ
    for prefix in environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if not prefix:
            continue
        marker = (Path(prefix) / 'share' / 'ament_index' / 'resource_index' / 'packages'
                  / PACKAGE_NAME)
        if marker.is_file():
            return Path(prefix) / 'share' / PACKAGE_NAME
    return None


def default_config_path():
    """Return ``config/mrclam.yaml`` of the source tree, else of the installed share."""
    local = PACKAGE_ROOT / 'config' / DEFAULT_CONFIG_NAME
    if local.is_file():
        return local
    share = installed_share_directory()
    return local if share is None else share / 'config' / DEFAULT_CONFIG_NAME


def add_dataset_arguments(parser) -> None:
    """Add the positional ``dataset`` and ``--config`` of the replay's command lines."""
    parser.add_argument('dataset', nargs='?', type=Path, default=None,
                        help='MRCLAM dataset directory (default: shared/data/mrclam/dataset6 '
                        'beside the repository)')
    parser.add_argument('--config', type=Path, default=None,
                        help='ROS params file (default: config/mrclam.yaml)')


def default_dataset_path():
    """Return ``shared/data/mrclam/dataset6`` beside the repository (or the cwd)."""
    candidates = [PACKAGE_ROOT.parent / DEFAULT_DATASET, Path.cwd() / DEFAULT_DATASET,
                  Path.cwd().parent / DEFAULT_DATASET]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    return candidates[0]


def node_section(document, node_name):
    """
    Return the merged ``ros__parameters`` of every section that applies to ``node_name``.

    Sections are keyed by node name, optionally with a namespace or wildcard prefix
    (``/**/landmark_observer``, ``/robot1/landmark_observer``, ``landmark_observer``).
    """
    values = {}
    for key, section in (document or {}).items():
        if str(key).rstrip('/').split('/')[-1] != node_name:
            continue
        if not isinstance(section, dict) or not isinstance(
                section.get('ros__parameters', {}), dict):
            raise ValueError(f'section {key!r} must hold a ros__parameters mapping')
        values.update(section.get('ros__parameters') or {})
    return values


def load_config(path=None):
    """
    Read a ROS params file into the observer, fuser and replay configuration.

    Parameters
    ----------
    path : str or Path, optional
        Params file; ``config/mrclam.yaml`` by default.

    Returns
    -------
    ReplayConfig

    Raises
    ------
    ValueError
        If a value is invalid for its node.

    """
    import yaml
    path = Path(path) if path is not None else default_config_path()
    with open(path, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}
    if not isinstance(document, dict):
        raise ValueError(f'{path}: not a ROS params file (a mapping of node sections)')
    observer = ObserverConfig.from_values(node_section(document, 'landmark_observer'))
    fuser = FuserConfig.from_values(node_section(document, 'landmark_fuser'))
    replay = node_section(document, 'landmark_mrclam')
    stddev = tuple(float(replay.get(f'pose_stddev_{axis}', default))
                   for axis, default in zip(('x', 'y', 'yaw'), (0.002, 0.002, 0.002)))
    if not all(math.isfinite(s) and s >= 0.0 for s in stddev):
        raise ValueError(f'{path}: pose_stddev_* must be finite and >= 0, got {stddev}')
    delay = replay.get('camera_delay_s', 0.0)
    if isinstance(delay, bool) or not isinstance(delay, (int, float)) or not (
            math.isfinite(delay) and abs(delay) <= 1.0):
        raise ValueError(f'{path}: camera_delay_s must be a number of seconds in [-1, 1], '
                         f'got {delay!r}')
    return ReplayConfig(observer, fuser, stddev, path, float(delay))


def config_values(config):
    """Return a config dataclass as a plain dict (tuples as lists)."""
    values = {}
    for spec in fields(config):
        value = getattr(config, spec.name)
        values[spec.name] = list(value) if isinstance(value, tuple) else value
    return values
