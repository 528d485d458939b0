"""Event counters with rate-limited logging, and their diagnostics status (ROS-free)."""

from collections import Counter
from dataclasses import dataclass, field
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Protocol, Tuple


class Counters:
    """
    Count events by name and log each kind at most once per ``throttle_s``.

    Parameters
    ----------
    log : callable
        ``log(text)``, e.g. a node logger's ``warning``.
    throttle_s : float
        Shortest interval between two log lines of the same kind [s].
    clock : callable, optional
        Monotonic time in seconds; for tests.

    """

    def __init__(self, log: Callable[[str], Any], throttle_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.counts: Counter[str] = Counter()
        self._log = log
        self.throttle_s = throttle_s
        self._clock = clock
        self._last_log: Dict[str, float] = {}
        self._unlogged: Counter[str] = Counter()

    def add(self, name: str, count: int = 1, detail: Optional[str] = None) -> None:
        """
        Count ``count`` events of kind ``name``; log ``detail`` if not throttled.

        Parameters
        ----------
        name : str
            Name used in error messages.
        count : int
            Number of events.
        detail : str, optional
            What happened, for the log line; nothing is logged without it.

        """
        if count <= 0:
            return
        self.counts[name] += count
        if detail is None:
            return
        now = self._clock()
        last = self._last_log.get(name)
        if last is not None and now - last < self.throttle_s:
            self._unlogged[name] += count
            return
        self._last_log[name] = now
        skipped = self._unlogged.pop(name, 0)
        more = f' ({skipped} more since the last report)' if skipped else ''
        self._log(f'{name} x{count}: {detail}{more}')

    def __getitem__(self, name: str) -> int:
        return self.counts[name]


DEPRECATED_KEYS = {
    'constraints_in': 'partial_in', 'constraints_out': 'partial_out',
    'views_fused': 'partial_fused', 'views_gated': 'partial_gated',
    'views_too_close': 'partial_too_close', 'views_dropped': 'partial_dropped',
    'views_superseded': 'partial_superseded', 'queued_views': 'queued_partial',
    'constraint_nonfinite': 'partial_nonfinite',
}
"""Former diagnostics keys and their new names: for one release, a status also carries each
present new key under its old name (same value), so that dashboards keep working; they go in
the next release. Readers of the package's own statuses drop them (``without_deprecated``)."""


def without_deprecated(values: Mapping[str, Any]) -> Dict[str, Any]:
    """Return diagnostics key-values without the deprecated aliases of ``DEPRECATED_KEYS``."""
    return {key: value for key, value in values.items() if key not in DEPRECATED_KEYS}


def status_values(
        counters: Mapping[str, int], extra: Optional[Mapping[str, Any]] = None,
) -> List[Tuple[str, str]]:
    """
    Return ``(key, value)`` string pairs for a diagnostics status, sorted by key.

    Parameters
    ----------
    counters : collections.Counter or dict
        Event counts by name.
    extra : dict, optional
        More values, shown first.

    Returns
    -------
    list of (str, str)
        The extra values, the counters sorted by key, then the deprecated alias of each
        renamed key present (``DEPRECATED_KEYS``, sorted by old name).

    """
    values = [(key, str(value)) for key, value in (extra or {}).items()]
    values += [(key, str(counters[key])) for key in sorted(counters)]
    present = dict(values)
    values += [(old, present[new]) for old, new in sorted(DEPRECATED_KEYS.items())
               if new in present and old not in present]
    return values


@dataclass(frozen=True)
class Status:
    """
    A diagnostics status, ROS-free: the node turns it into a ``DiagnosticStatus``.

    Attributes
    ----------
    level : str
        ``'ok'``, ``'warn'`` or ``'error'``.
    message : str
        One line of summary.
    counts : dict of str to int
        The counters.
    extra : dict
        More values, shown before the counters.
    name : str
        Suffix of the status name ('' for the component itself, else what it is about,
        such as a source topic).

    """

    level: str
    message: str
    counts: Dict[str, int]
    extra: Dict[str, Any] = field(default_factory=dict)
    name: str = ''


class Logger(Protocol):
    """What the pipeline logs through: an rclpy logger or a ``logging.Logger``."""

    def info(self, text: str, /) -> object:
        """Log an info line."""

    def warning(self, text: str, /) -> object:
        """Log a warning."""

    def error(self, text: str, /) -> object:
        """Log an error."""
