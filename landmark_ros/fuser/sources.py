"""
What the fuser (``fuser.fuser``) keeps per input: its queue of messages and counters.

``LandmarkMessage`` is a message as the fuser takes it (``Fuser.add_landmarks``);
``Queued`` the rows of one message once checked and queued; ``Source`` an input topic's
queue, counters and the stamp of its last message; ``shard_of_position`` the shard
that takes a row without an ID (``shard_count`` fusers, each taking its own).
"""

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Deque, NamedTuple, Optional

from landmark_ros.pipeline.scan import Scan
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Queued:
    """Rows of one message waiting in a source's queue (``Fuser.fuse_queued`` takes them)."""

    sequence: int
    ids: NDArray[np.int64]
    m: NDArray[np.float64]
    P: NDArray[np.float64]
    P_dep: NDArray[np.float64]
    stamp_ns: int
    classes: Optional[NDArray[np.int64]] = None
    scan: Optional[Scan] = None
    unlabelled: bool = False


class LandmarkMessage(NamedTuple):
    """
    One landmark message of a source, as ``Fuser.add_landmarks`` takes it.

    Attributes
    ----------
    stamp_ns : int
        The message stamp [ns].
    ids : ndarray of int, shape (N,)
        Landmark IDs (``UNKNOWN_ID`` for rows without one).
    m : ndarray, shape (N, 2)
        Positions in ``world_frame`` [m].
    P : ndarray, shape (N, 2, 2)
        Total covariances [m^2].
    P_dep : ndarray, shape (N, 2, 2)
        Their dependent parts (zeros when the source does not say).
    frame_id : str, optional
        The message's frame, checked against ``world_frame``; None skips the check.
    classes : ndarray of int, shape (N,), optional
        Landmark classes (0 when absent).
    scan : Scan, optional
        The message's robot pose terms, for the association of rows without an ID
        (without it they are associated as independent rows).

    """

    stamp_ns: int
    ids: NDArray[Any]
    m: NDArray[np.float64]
    P: NDArray[np.float64]
    P_dep: NDArray[np.float64]
    frame_id: Optional[str] = None
    classes: Optional[NDArray[Any]] = None
    scan: Optional[Scan] = None


@dataclass
class Source:
    """One input of the fuser (a robot's landmark topic): its queue and counters."""

    name: str
    queue: Deque[Queued] = field(default_factory=deque)
    counts: Counter[str] = field(default_factory=Counter)
    last_message_ns: Optional[int] = None
    optional: bool = False
    """A partial source: not stale before its first message (rb-only teams)."""


def shard_of_position(m: NDArray[np.float64], cell_m: float,
                      shard_count: int) -> NDArray[np.int64]:
    """
    Return the shard of each row without an ID, from its world position.

    Square cells of side ``cell_m``: ``(floor(x / cell_m) + 31 floor(y / cell_m))``
    modulo ``shard_count``. A non-finite position (a row the checks reject anyway)
    goes to shard 0.

    Parameters
    ----------
    m : ndarray, shape (N, 2) [m]
        Positions in the world.
    cell_m : float
        Side of a cell [m].
    shard_count : int
        Number of shards.

    Returns
    -------
    ndarray of int64, shape (N,)

    """
    m = np.asarray(m, np.float64).reshape(-1, 2)
    finite = np.isfinite(m).all(axis=1)
    cells = np.zeros((len(m), 2))
    cells[finite] = np.floor(np.clip(m[finite] / cell_m, -1e15, 1e15))
    return ((cells[:, 0].astype(np.int64) + 31 * cells[:, 1].astype(np.int64))
            % int(shard_count)).astype(np.int64)
