"""
The fuser's map file: save, load, restore and quarantine (ROS-free).

``Fuser.save`` and ``Fuser.load`` call these functions with the fuser itself: they
read and set its map, tracker, partial fusion, counters and logger. The file format
and its checks are in ``map_file``; this module decides what a fuser keeps of a file,
logs it and counts it.
"""

from typing import Any, Dict, List, TYPE_CHECKING

from landmark_ros.fuser import map_file

if TYPE_CHECKING:  # pragma: no cover
    from landmark_ros.fuser.fuser import Fuser


def save(fuser: 'Fuser') -> bool:
    """Write ``map_file`` atomically; return whether it worked."""
    try:
        records = fuser.map.to_records()
        for record in records:
            record['class'] = fuser.tracker.classes.get(record['id'], 0)
        map_file.save(fuser.config.map_file, records, fuser.config.world_frame,
                      fuser.config.fusion, next_id=fuser.tracker.next_id,
                      first_new_id=fuser.reserved_from,
                      tracks=fuser.tracker.to_dict(),
                      waiting_partial_observations=fuser.partial.waiting_records())
    except (OSError, ValueError) as error:
        fuser.counters.add('save_failed', 1, f'cannot save {fuser.config.map_file}: {error}')
        return False
    fuser.unsaved = False
    fuser.counters.add('saves', 1)
    return True


def load(fuser: 'Fuser') -> None:
    """
    Load ``map_file`` if set: every valid record is kept, the bad ones quarantined.

    A file that cannot be parsed at all (not JSON, not a map, another version or
    frame) is moved aside and the fuser starts empty. Otherwise each landmark
    record is checked on its own (``map_file.split_records``: the live row checks),
    and a malformed ``next_id``, waiting partial observations or tracks section is
    dropped on its own; what was dropped is written to a quarantine file beside the
    map and counted in ``map_records_rejected``.
    """
    path = fuser.config.map_file
    if not path:
        return
    for stale in map_file.remove_stale_temporaries(path):
        fuser.logger.info(f'removed {stale}, left by an interrupted save')
    try:
        document = map_file.load(path, fuser.config.world_frame)
    except FileNotFoundError:
        fuser.logger.info(f'no map file {path} yet: starting with an empty map')
        return
    except (OSError, ValueError) as error:
        try:
            moved = map_file.move_aside(path)
        except OSError as move_error:
            moved = f'(could not be moved: {move_error})'
        fuser.counters.add('map_file_rejected', 1)
        fuser.logger.error(f'map file {path} is unusable ({error}); moved it to {moved} '
                           'and starting with an empty map')
        return
    rejected = _restore(fuser, document)
    if rejected:
        _quarantine(fuser, path, rejected)
    if document.get('fusion') != fuser.config.fusion:
        fuser.logger.warning(
            f"map file {path} was made with fusion {document.get('fusion')!r}, this "
            f'fuser uses {fuser.config.fusion!r}')
    fuser.map_changed = True
    fuser.logger.info(f'loaded {len(fuser.map)} landmarks from {path}')


def _restore(fuser: 'Fuser', document: Dict[str, Any]) -> List[Dict[str, Any]]:
    """Restore what ``document`` holds that passes the checks; return what did not."""
    loaded = map_file.parse_sections(document, fuser.config.first_new_id)
    rejected = list(loaded.rejected)
    if loaded.deprecated_key:
        fuser.logger.warning(
            f'map file: key {map_file.DEPRECATED_WAITING_KEY!r} is deprecated, read as '
            f'{map_file.WAITING_KEY!r} (the next save writes the new key)')
    fuser.map.reset()
    fuser.map.load_records(loaded.records)
    fuser.partial.reset()
    fuser.partial.restore(loaded.waiting)
    fuser.tracker.reset()
    fuser.tracker.next_id = loaded.next_id
    fuser.reserved_from = loaded.reserved_from
    for record in loaded.records:
        if record.get('class', 0):
            fuser.tracker.classes[record['id']] = record['class']
    try:
        fuser.tracker.restore(document.get('tracks'), fuser.map)
    except ValueError as error:
        fuser.tracker.reset()
        fuser.tracker.next_id = loaded.next_id
        rejected.append({'section': 'tracks', 'index': None, 'reason': f'{error}',
                         'record': document.get('tracks')})
    rejected += [{'section': 'tracks', 'index': landmark_id, 'record': None,
                  'reason': f"tentative track rejected as {', '.join(reasons)}"}
                 for landmark_id, reasons in fuser.tracker.rejected_tracks]
    return rejected


def _quarantine(fuser: 'Fuser', path: str, rejected: List[Dict[str, Any]]) -> None:
    """Write rejected map-file records beside the map; count and log them."""
    try:
        written = map_file.quarantine(path, rejected)
    except OSError as error:
        written = f'(not written: {error})'
    fuser.counters.add('map_records_rejected', len(rejected))
    section, index, reason = (rejected[0][key] for key in ('section', 'index', 'reason'))
    fuser.logger.error(
        f'map file {path}: {len(rejected)} record(s) rejected, the rest loaded; first: '
        f'{section} record {index} {reason}; rejected records in {written}')
