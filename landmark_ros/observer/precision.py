"""
Precision sources: a robot's landmark messages split by the size of their dependent part.

The fuser bounds the dependent parts of one source's rows as if they were one error
(split CI within a source, ``fusion.source_sums``), so a source that mixes rows placed
from a pose known to centimetres with rows placed after a stretch of dead reckoning
keeps about the typical pose error. Split CI across sources holds for any correlation
between their dependent parts, so an observer may send each message to one of
``precision_sources`` topics by its dependent standard deviation ``s``: level
``floor(log2(s / precision_base_m))``, clipped to the levels; the tight messages then
make a tight source. It does not bound the errors split CI takes as independent that
are not (docs/slam.md, "What is not bounded", and the figures there: in the closed
loop it can make the map over-confident). Level 0 is the ``landmarks`` topic itself;
level k > 0 is ``landmarks/precision_k``.
"""

from typing import List

import numpy as np
from numpy.typing import NDArray


def dependent_stddev(P_dep: NDArray[np.float64]) -> float:
    """
    Return a message's dependent standard deviation [m] from its rows' ``P_dep`` (K, 2, 2).

    The square root of the median over the rows of the largest eigenvalue of the
    dependent part (the pose error at the sighting, placed at the landmark); K >= 1.
    """
    return float(np.sqrt(np.median(np.linalg.eigvalsh(P_dep)[:, -1])))


def precision_level(P_dep: NDArray[np.float64], sources: int, base_m: float) -> int:
    """
    Return the precision level of a message with dependent parts ``P_dep`` (K, 2, 2).

    ``floor(log2(dependent_stddev / base_m))`` clipped to ``0 .. sources - 1``; 0 when
    ``sources`` is 1 or the message has no row. ``base_m`` [m] > 0.
    """
    if sources <= 1 or not len(P_dep):
        return 0
    s = dependent_stddev(P_dep)
    level = int(np.floor(np.log2(max(s, 1e-12) / base_m)))
    return min(max(level, 0), sources - 1)


def precision_topics(topic: str, sources: int) -> List[str]:
    """
    Return the topic of each precision level for the landmark topic ``topic``.

    ``[topic, topic/precision_1, ..., topic/precision_{sources-1}]``: one source alone
    is ``topic`` itself, as without precision sources.
    """
    return [topic] + [f'{topic}/precision_{k}' for k in range(1, max(1, int(sources)))]
