"""
Rosbag2 files through ``rosbags``, with the real ROS 2 message classes.

Messages go in and out as raw CDR: ``rclpy.serialization`` turns them into the Python
message classes of the Jazzy wheels and back, and ``rosbags`` only stores the bytes. The
message definitions written into a bag (so Foxglove, ``ros2 bag`` and RViz can use it)
come from the ``rosbags`` typestore of ROS 2 Jazzy.

Outputs are atomic: ``BagOutput`` writes into a temporary directory beside the target
and renames it into place only when everything was written, so a failed run leaves no
half-written bag behind.
"""

from collections import Counter
from functools import lru_cache
import os
from pathlib import Path
import shutil
import tempfile

from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness
from rosbags.interfaces import QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer, WriterError
from rosbags.typesys import get_typestore, Stores
import yaml

BAG_VERSION = 9
"""rosbag2 metadata version of the bags written (the one ROS 2 Jazzy writes)."""

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
"""Storage identifiers of the bags written (``ros2 bag record --storage``): MCAP, Jazzy's
default, or SQLite 3, the default before it."""


class BagError(Exception):
    """A bag that cannot be used; the message is one line for the user."""


@lru_cache(maxsize=None)
def typestore():
    """Return the ``rosbags`` typestore of the ROS 2 Jazzy message definitions."""
    return get_typestore(Stores.ROS2_JAZZY)


def msgtype(message_class):
    """
    Return the ROS 2 type name of a message class.

    Parameters
    ----------
    message_class : type
        A generated message class, e.g. ``sensor_msgs.msg.PointCloud2``.

    Returns
    -------
    str
        ``package/msg/Name``, e.g. ``sensor_msgs/msg/PointCloud2``.

    """
    return f"{message_class.__module__.split('.')[0]}/msg/{message_class.__name__}"


def qos(depth=10, latched=False):
    """
    Return the QoS profile a topic is recorded with (``ros2 bag play`` offers it).

    Parameters
    ----------
    depth : int
        History depth.
    latched : bool
        Transient local (late subscribers such as RViz get the latest message), as the
        fuser publishes its map and markers; volatile otherwise. Both are reliable.

    Returns
    -------
    rosbags.interfaces.Qos

    """
    unset = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               unset, unset, QosLiveliness.AUTOMATIC, unset, False)


def open_bag(path):
    """
    Open a rosbag2 for reading.

    Parameters
    ----------
    path : str or Path
        A bag directory (with ``metadata.yaml``) or a single ``.mcap`` / ``.db3`` file.

    Returns
    -------
    rosbags.rosbag2.Reader
        Open; the caller closes it.

    Raises
    ------
    BagError
        If the path does not exist or is not a readable bag (truncated, wrong format).

    """
    path = Path(path)
    if not path.exists():
        raise BagError(f'{path}: no such bag')
    try:
        reader = Reader(path)
        reader.open()
    except Exception as error:  # noqa: B902 - storage back ends (apsw, zstd) raise many kinds
        raise BagError(f'{path}: not a readable rosbag2 ({one_line(error)})') from error
    return reader


def storage_of(path):
    """
    Return the storage identifier (``mcap`` or ``sqlite3``) of a bag ``open_bag`` opened.

    Parameters
    ----------
    path : str or Path
        A bag directory (its ``metadata.yaml`` names the storage) or a ``.mcap`` /
        ``.db3`` file.

    Returns
    -------
    str
        A key of ``STORAGES``; ``mcap`` for a storage this package does not write.

    """
    path = Path(path)
    if path.is_dir():
        try:
            with open(path / 'metadata.yaml', encoding='utf-8') as stream:
                metadata = yaml.safe_load(stream)['rosbag2_bagfile_information']
            identifier = metadata['storage_identifier']
        except (OSError, yaml.YAMLError, KeyError, TypeError):
            identifier = None
    else:
        identifier = {'.db3': 'sqlite3', '.mcap': 'mcap'}.get(path.suffix)
    return identifier if identifier in STORAGES else 'mcap'


def one_line(error):
    """Return an exception's message on one line, with its type when it is empty."""
    text = ' '.join(str(error).split())
    return text or type(error).__name__


def read_message(raw, message_class, topic):
    """
    Deserialise one message.

    Raises
    ------
    BagError
        If the bytes are not a valid CDR message of that class.

    """
    try:
        return deserialize_message(bytes(raw), message_class)
    except Exception as error:  # noqa: B902 - rclpy raises plain Exceptions here
        raise BagError(f'{topic}: a message cannot be deserialised as '
                       f'{msgtype(message_class)} ({one_line(error)})') from error


class BagOutput:
    """
    A rosbag2 written atomically: into a temporary directory, renamed at the end.

    Use as a context manager: leaving the block normally closes the bag and renames it
    to ``path``; leaving it with an exception (or ``KeyboardInterrupt``) deletes
    everything written.

    Parameters
    ----------
    path : str or Path
        The bag directory to create; it must not exist, its parent must.
    storage : str
        ``mcap`` or ``sqlite3`` (``STORAGES``).

    Raises
    ------
    BagError
        If ``path`` exists or its parent directory does not.
    ValueError
        If ``storage`` is none of ``STORAGES``.

    """

    def __init__(self, path, storage='mcap'):
        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {', '.join(STORAGES)}, got {storage!r}")
        self.path = Path(path)
        if self.path.exists() or self.path.is_symlink():
            raise BagError(f'{self.path} exists already: not overwriting it')
        parent = self.path.absolute().parent
        if not parent.is_dir():
            raise BagError(f'{parent}: no such directory for the output bag')
        self.counts = Counter()
        """Messages written per topic."""
        self._connections = {}
        self._temporary = Path(tempfile.mkdtemp(prefix=f'.{self.path.name}.', suffix='.partial',
                                                dir=parent))
        try:
            self._writer = Writer(self._temporary / self.path.name, version=BAG_VERSION,
                                  storage_plugin=STORAGES[storage])
            self._writer.open()
        except (WriterError, OSError) as error:
            shutil.rmtree(self._temporary, ignore_errors=True)
            raise BagError(f'cannot write {self.path}: {one_line(error)}') from error

    def add_topic(self, topic, message_class, latched=False, depth=10):
        """Register a topic of ``message_class`` (see ``qos`` for ``latched``)."""
        self._connections[topic] = self._writer.add_connection(
            topic, msgtype(message_class), typestore=typestore(),
            offered_qos_profiles=[qos(depth, latched)])

    def write(self, topic, time_ns, message):
        """Write ``message`` on a registered ``topic`` at bag time ``time_ns``."""
        self._writer.write(self._connections[topic], int(time_ns), serialize_message(message))
        self.counts[topic] += 1

    def commit(self):
        """Close the bag and move it to ``path``."""
        self._writer.close()
        os.rename(self._temporary / self.path.name, self.path)
        shutil.rmtree(self._temporary, ignore_errors=True)

    def abort(self):
        """Delete everything written."""
        try:
            self._writer.abort()
        finally:
            shutil.rmtree(self._temporary, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        if kind is None:
            try:
                self.commit()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()
        return False
