"""
Save and load the fused map as versioned, human-readable JSON, atomically (ROS-free).

A save writes a temporary file in the same directory, flushes and fsyncs it, then
renames it over the map file (and fsyncs the directory), so a crash at any moment
leaves either the previous map or the new one, never a torn file. ``split_records``
checks loaded landmark records exactly as live landmark rows are checked; the loader
keeps every good record and writes the bad ones to a quarantine file beside the map
(``quarantine``); only a file that cannot be parsed at all is moved aside.
"""

import datetime
import json
import os
import tempfile
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

from landmark_ros.fuser.partial import parse_waiting_records
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
         first_new_id: Optional[int] = None) -> None:
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
    first_new_id : int, optional
        Start of the reserved ID range (``Fuser.reserved_from``): IDs from it up are
        the fuser's own, never taken from labelled input; omitted when None.

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
    if first_new_id is not None:
        document['first_new_id'] = int(first_new_id)
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


def reserved_from(document: Mapping[str, Any], first_new_id: int) -> int:
    """
    Return the start of the reserved ID range after loading ``document``.

    The smaller of the file's ``first_new_id`` and the configured one: IDs the fuser
    allocated before a restart stay reserved even if ``first_new_id`` was raised. A
    file without the key (or with a malformed one) keeps the configured start.

    Parameters
    ----------
    document : dict
        As ``load`` returns it.
    first_new_id : int
        The configured ``first_new_id``.

    Returns
    -------
    int

    """
    saved = document.get('first_new_id')
    if isinstance(saved, bool) or not isinstance(saved, int) or not 0 <= saved <= MAX_LABEL_ID:
        return int(first_new_id)
    return min(saved, int(first_new_id))


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
        Naming the first bad record and why (``split_records``' reason).

    """
    _, bad = split_records(records)
    if bad:
        index, reason = bad[0]
        raise ValueError(f'landmark record {index}: {reason}')


class Sections(NamedTuple):
    """What ``parse_sections`` keeps of a map document."""

    records: List[Dict[str, Any]]
    """The valid landmark records."""
    next_id: int
    """The next ID to allocate (at least ``first_new_id``)."""
    waiting: List[Any]
    """The valid waiting partial observations (``fuser.partial.parse_waiting_records``)."""
    reserved_from: int
    """Start of the reserved ID range (``reserved_from``)."""
    rejected: List[Dict[str, Any]]
    """``{'section', 'index', 'reason', 'record'}`` per rejected record or section."""
    deprecated_key: bool = False
    """Whether the waiting records came from ``DEPRECATED_WAITING_KEY``."""


def parse_sections(document: Mapping[str, Any], first_new_id: int) -> Sections:
    """
    Check each landmark record, ``next_id`` and each waiting partial observation alone.

    Parameters
    ----------
    document : dict
        As ``load`` returns it.
    first_new_id : int
        The configured ``first_new_id``.

    Returns
    -------
    Sections
        The valid parts; every bad record (or a malformed ``next_id`` or waiting list)
        in ``rejected``. The tracks are checked by ``Tracker.restore``.

    """
    landmarks = document['landmarks']
    records, bad = split_records(landmarks)
    rejected = [{'section': 'landmarks', 'index': i, 'reason': reason,
                 'record': landmarks[i]} for i, reason in bad]
    next_id = document.get('next_id', first_new_id)
    if isinstance(next_id, bool) or not isinstance(next_id, int) or not (
            0 <= next_id <= MAX_LABEL_ID + 1):
        rejected.append({'section': 'next_id', 'index': None, 'record': next_id,
                         'reason': f'not an integer in [0, {MAX_LABEL_ID + 1}]'})
        next_id = first_new_id   # allocation still skips the IDs the map knows
    try:
        waiting_records, deprecated = waiting_partial_records(document)
    except ValueError as error:
        rejected.append({'section': WAITING_KEY, 'index': None, 'reason': f'{error}',
                         'record': None})
        waiting_records, deprecated = [], False
    if not isinstance(waiting_records, list):
        rejected.append({'section': WAITING_KEY, 'index': None, 'reason': 'not a list',
                         'record': waiting_records})
        waiting_records = []
    waiting: List[Any] = []
    for i, record in enumerate(waiting_records):   # each on its own
        try:
            waiting += parse_waiting_records([record])
        except ValueError as error:
            rejected.append({'section': WAITING_KEY, 'index': i, 'reason': f'{error}',
                             'record': record})
    return Sections(records, max(next_id, first_new_id), waiting,
                    reserved_from(document, first_new_id), rejected, deprecated)


def split_records(records: Sequence[Any]) -> Tuple[List[Dict[str, Any]], List[Tuple[int, str]]]:
    """
    Separate the usable landmark records from the bad ones, with the live row checks.

    Each record is parsed on its own (a malformed field, an ID that is not an integer
    in [0, 2^32 - 2], a class that is not an integer), then every parsed record goes
    through ``rows.landmark_row_problems``, the fuser's check of live landmark rows
    (which includes the plausible ranges of ``pipeline.limits``).

    Parameters
    ----------
    records : sequence
        As ``LandmarkMap.to_records`` writes them (anything, in a damaged file).

    Returns
    -------
    good : list of dict
        The usable records, in file order.
    bad : list of (int, str)
        Index and reason of each rejected record, in file order.

    """
    parsed, bad = [], []
    for i, record in enumerate(records):
        try:
            parsed.append((i, record) + _parse_record(record))
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            bad.append((i, f'{error}'))
    if parsed:
        ids = np.array([p[2] for p in parsed], np.int64)
        m, P, P_dep = (np.array([p[k] for p in parsed]) for k in (3, 4, 5))
        valid, _ = landmark_row_problems(ids, m, P, P_dep)
        for ok, (i, _, landmark_id, m_i, P_i, P_dep_i) in zip(valid, parsed):
            if not ok:
                _, reasons = landmark_row_problems(
                    np.array([landmark_id]), m_i[None], P_i[None], P_dep_i[None])
                bad.append((i, f"id {landmark_id} rejected as {', '.join(sorted(reasons))}"))
        good = [record for ok, (_, record, *_rest) in zip(valid, parsed) if ok]
    else:
        good = []
    return good, sorted(bad)


def _parse_record(record):
    """Return ``(id, m, P, P_dep)`` of one landmark record, or raise."""
    raw = record['id']
    if isinstance(raw, bool) or not isinstance(raw, int) or not 0 <= raw <= MAX_LABEL_ID:
        raise ValueError(f'id {raw!r} is not an integer in [0, {MAX_LABEL_ID}]')
    landmark_class = record.get('class', 0)
    if isinstance(landmark_class, bool) or not isinstance(landmark_class, int):
        raise ValueError(f'class {landmark_class!r} is not an integer')
    return (raw, np.array(record['mean'], dtype=np.float64).reshape(2),
            np.array(record['covariance'], dtype=np.float64).reshape(2, 2),
            np.array(record['covariance_dependent'], dtype=np.float64).reshape(2, 2))


def quarantine(path: str, bad: Sequence[Mapping[str, Any]],
               now: Optional[datetime.datetime] = None) -> str:
    """
    Write rejected records beside the map file (``<path>.quarantine-<time>.json``).

    Parameters
    ----------
    path : str
        Map file.
    bad : list of dict
        ``{'section', 'index', 'reason', 'record'}`` per rejected record.
    now : datetime.datetime, optional
        Time for the name; the current UTC time by default.

    Returns
    -------
    str
        The file written.

    """
    now = now or datetime.datetime.now(datetime.timezone.utc)
    base = f"{path}.quarantine-{now.strftime('%Y%m%dT%H%M%SZ')}"
    target, counter = base + '.json', 1
    while os.path.exists(target):
        target, counter = f'{base}-{counter}.json', counter + 1
    with open(target, 'w') as stream:
        json.dump({'format': FORMAT + '/quarantine', 'map_file': path,
                   'rejected': list(bad)}, stream, indent=1, default=str)
        stream.write('\n')
    return target


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
