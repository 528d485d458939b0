"""
Save and load the fused map as versioned, human-readable JSON, atomically (ROS-free).

A save writes a temporary file in the same directory, flushes and fsyncs it, then
renames it over the map file (and fsyncs the directory), so a crash at any moment
leaves either the previous map or the new one, never a torn file. ``check_records``
checks loaded landmark records exactly as live landmark rows are checked.
"""

import datetime
import json
import os
import tempfile
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from landmark_ros.pipeline.rows import landmark_row_problems, MAX_LABEL_ID
import numpy as np

FORMAT = 'landmark_ros/map'
VERSION = 1


WAITING_KEY = 'waiting_partial_observations'
"""Key of the partial observations waiting to place a landmark."""

DEPRECATED_WAITING_KEY = 'waiting_views'
"""Its former name: still read, never written (removed in the next release)."""


class MapFileError(ValueError):
    """A map file that cannot be used: unreadable, corrupt, or of another version."""


def save(path: str, records: Sequence[Mapping[str, Any]], world_frame: str, fusion: str,
         next_id: Optional[int] = None, tracks: Optional[Mapping[str, Any]] = None,
         waiting_partial_observations: Optional[Sequence[Mapping[str, Any]]] = None,
         ) -> None:
    """
    Write the map to ``path`` atomically.

    Parameters
    ----------
    path : str
        Map file; its directory must exist.
    records : list of dict
        Landmarks, as ``LandmarkMap.to_records`` returns them.
    world_frame : str
        Frame of the landmark positions.
    fusion : str
        Fusion method that made the map.
    next_id : int, optional
        The next landmark ID the fuser allocates to landmarks found without an ID
        (kept so that an ID is never given twice, across restarts); omitted when None.
    tracks : dict, optional
        The tracks of landmarks found without IDs (``fuser.tracks.Tracker.to_dict``:
        tentative tracks and their rows, merge bookkeeping), so that a restart resumes
        them; omitted when None (files without it load with no tracks).
    waiting_partial_observations : list of dict, optional
        Partial observations (range-only, bearing-only) of landmarks not placed yet
        (``fuser.partial.PartialFusion.waiting_records``), so that a restart keeps
        them; omitted when None or empty (files without it load as before). Files
        that name it ``waiting_views`` (deprecated) still load
        (``waiting_partial_records``).

    """
    document = {
        'format': FORMAT,
        'version': VERSION,
        'saved_at': datetime.datetime.now(datetime.timezone.utc).isoformat(),
        'world_frame': world_frame,
        'fusion': fusion,
        'landmarks': records,
    }
    if next_id is not None:
        document['next_id'] = int(next_id)
    if tracks is not None:
        document['tracks'] = dict(tracks)
    if waiting_partial_observations:
        document[WAITING_KEY] = list(waiting_partial_observations)
    directory = os.path.dirname(os.path.abspath(path))
    handle, temporary = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.',
                                         suffix='.tmp', dir=directory)
    try:
        # mkstemp makes the file 0600; the map gets the mode of the file it replaces,
        # or the usual one (0666 less the umask), as open() would have given it.
        os.fchmod(handle, _file_mode(path))
        with os.fdopen(handle, 'w') as stream:
            json.dump(document, stream, indent=1, allow_nan=False)  # never a NaN or inf
            stream.write('\n')
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.unlink(temporary)
        raise
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _umask():
    """Return the process umask (from /proc where possible: reading it so is race-free)."""
    try:
        with open('/proc/self/status') as status:
            for line in status:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _file_mode(path):
    """Return the permission bits a new map file at ``path`` gets."""
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        return 0o666 & ~_umask()


def remove_stale_temporaries(path: str) -> List[str]:
    """
    Delete the temporary files interrupted saves of ``path`` left behind.

    Call it only while no other process saves the same map.

    Parameters
    ----------
    path : str
        Map file.

    Returns
    -------
    list of str
        The files removed.

    """
    directory = os.path.dirname(os.path.abspath(path))
    prefix = '.' + os.path.basename(path) + '.'
    removed: List[str] = []
    if not os.path.isdir(directory):
        return removed
    for name in os.listdir(directory):
        if name.startswith(prefix) and name.endswith('.tmp'):
            os.unlink(os.path.join(directory, name))
            removed.append(os.path.join(directory, name))
    return removed


def load(path: str, world_frame: str) -> Dict[str, Any]:
    """
    Read a map file written by ``save``.

    Parameters
    ----------
    path : str
        Map file.
    world_frame : str
        The frame the caller works in; the file must use the same.

    Returns
    -------
    document : dict
        With ``landmarks`` (the records), ``fusion``, ``saved_at``.

    Raises
    ------
    MapFileError
        If the file is not valid JSON, not a landmark_ros map, of another version,
        or in another frame.
    FileNotFoundError
        If there is no file.

    """
    with open(path) as stream:
        text = stream.read()
    try:
        document = json.loads(text)
    except json.JSONDecodeError as error:
        raise MapFileError(f'not valid JSON: {error}') from error
    if not isinstance(document, dict) or document.get('format') != FORMAT:
        raise MapFileError(f'not a {FORMAT} file')
    if document.get('version') != VERSION:
        raise MapFileError(f"version {document.get('version')!r}, expected {VERSION}")
    if document.get('world_frame') != world_frame:
        raise MapFileError(
            f"map in frame {document.get('world_frame')!r}, expected {world_frame!r}")
    if not isinstance(document.get('landmarks'), list):
        raise MapFileError('no landmark list')
    return document


def move_aside(path: str, now: Optional[datetime.datetime] = None) -> str:
    """
    Rename an unusable map file out of the way and return its new name.

    Parameters
    ----------
    path : str
        Map file.
    now : datetime.datetime, optional
        Time for the new name; the current UTC time by default.

    Returns
    -------
    str
        ``<path>.bad-<YYYYmmddTHHMMSSZ>`` (with a counter if that exists).

    """
    now = now or datetime.datetime.now(datetime.timezone.utc)
    base = f"{path}.bad-{now.strftime('%Y%m%dT%H%M%SZ')}"
    target, counter = base, 1
    while os.path.exists(target):
        target, counter = f'{base}-{counter}', counter + 1
    os.replace(path, target)
    return target


def check_records(records: Sequence[Dict[str, Any]]) -> None:
    """
    Check saved landmark records with exactly the checks a live landmark row passes.

    Parameters
    ----------
    records : sequence of dict
        As ``LandmarkMap.to_records`` writes them.

    Raises
    ------
    ValueError
        Naming the first bad record and why: a malformed field, an ID that is not an
        integer in [0, 2^32 - 1], or a row reason of ``rows.landmark_row_problems``.

    """
    count = len(records)
    ids = np.zeros(count, np.int64)
    m = np.zeros((count, 2))
    P = np.zeros((count, 2, 2))
    P_dep = np.zeros((count, 2, 2))
    for i, record in enumerate(records):
        try:
            raw = record['id']
            if isinstance(raw, bool) or not isinstance(raw, int) or not 0 <= raw <= MAX_LABEL_ID:
                raise ValueError(f'id {raw!r} is not an integer in [0, {MAX_LABEL_ID}]')
            landmark_class = record.get('class', 0)
            if isinstance(landmark_class, bool) or not isinstance(landmark_class, int):
                raise ValueError(f'class {landmark_class!r} is not an integer')
            ids[i] = raw
            m[i] = np.array(record['mean'], dtype=np.float64).reshape(2)
            P[i] = np.array(record['covariance'], dtype=np.float64).reshape(2, 2)
            P_dep[i] = np.array(record['covariance_dependent'], dtype=np.float64).reshape(2, 2)
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f'landmark record {i}: {error}') from error
    valid, _ = landmark_row_problems(ids, m, P, P_dep)
    if not valid.all():
        bad = int(np.flatnonzero(~valid)[0])
        one = slice(bad, bad + 1)
        _, reasons = landmark_row_problems(ids[one], m[one], P[one], P_dep[one])
        raise ValueError(f'landmark record {bad} (id {int(ids[bad])}): rejected as '
                         f"{', '.join(sorted(reasons))}")


def waiting_partial_records(document: Mapping[str, Any]) -> Tuple[Any, bool]:
    """
    Return a loaded map file's waiting partial observations, under either key.

    Parameters
    ----------
    document : dict
        A map file as ``load`` returns it.

    Returns
    -------
    records : object
        The value of ``WAITING_KEY`` or, in a file written before the rename, of
        ``DEPRECATED_WAITING_KEY``; an empty list when neither is there. Checked by
        ``fuser.partial.parse_waiting_records``.
    deprecated : bool
        Whether the records came from ``DEPRECATED_WAITING_KEY``.

    Raises
    ------
    ValueError
        If the file holds both keys (one of them would be dropped silently).

    """
    if WAITING_KEY in document and DEPRECATED_WAITING_KEY in document:
        raise ValueError(f'both {WAITING_KEY} and {DEPRECATED_WAITING_KEY}')
    if DEPRECATED_WAITING_KEY in document:
        return document[DEPRECATED_WAITING_KEY], True
    return document.get(WAITING_KEY, []), False
