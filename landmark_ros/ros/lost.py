"""
Messages lost on the way to a subscription, from gaps in the publication sequence numbers.

Every message a DDS publisher sends carries its sequence number (``MessageInfo``'s
``publication_sequence_number``: 1, 2, 3, ... per publisher). A subscription that gets
5 after 2 lost 3 and 4 somewhere: a best-effort sample dropped, a reliable publisher's
``KEEP_LAST`` queue overwritten while the subscriber was busy, or the subscription's
own queue overflowing before the node took them. The middleware's ``message_lost``
event reports only some of these (not the subscription's own overflow); the sequence
numbers show them all, except the last messages of a stream (no later message shows
the gap).

MessageInfo does not name the publisher, so the numbers of one topic are only
compared while it has one publisher: a number that goes back starts over (a new or
restarted publisher), and the gaps of a topic with several publishers are not counted.
"""

from typing import Any, Callable, Dict, Iterable, Mapping, Optional


class SequenceGaps:
    """
    Count the messages lost per topic from the sequence numbers of those that arrived.

    Parameters
    ----------
    publisher_count : callable
        ``publisher_count(topic) -> int``: the topic's publishers now (asked only when a
        gap shows, so a graph query per gap, not per message).

    """

    def __init__(self, publisher_count: Callable[[str], int]) -> None:
        self._publisher_count = publisher_count
        self._last: Dict[str, Optional[int]] = {}

    def lost(self, topic: str, infos: Iterable[Optional[Mapping[str, Any]]]) -> int:
        """
        Return how many messages of ``topic`` went missing before those of ``infos``.

        Parameters
        ----------
        topic : str
            The subscription's topic.
        infos : iterable of MessageInfo dicts (or None)
            The messages' infos, in the order they were taken. A missing or None
            ``publication_sequence_number`` (a middleware without it) is skipped.

        Returns
        -------
        int
            The messages skipped in the sequence (0 with several publishers).

        """
        last = self._last.get(topic)
        gap = 0
        for info in infos:
            number = None if info is None else info.get('publication_sequence_number')
            if number is None:
                continue
            if last is not None and number > last + 1:
                gap += number - last - 1
            last = number
        self._last[topic] = last
        if gap and self._publisher_count(topic) == 1:
            return gap
        return 0


def describe(topic: str, count: int) -> str:
    """Return the log detail of ``count`` messages of ``topic`` lost on the way."""
    return (f'{count} {topic} messages lost on the way (a queue overflowed or a '
            "best-effort sample was dropped while a node was busy: raise this input's "
            "input_depth or the publisher's queue depth)")


def counting_gaps(on_message: Callable[[Any], None], topic: str,
                  publisher_count: Callable[[str], int],
                  on_lost: Callable[[str, int], None]) -> Callable[[Any, Any], None]:
    """
    Return a ``(msg, info)`` subscription callback that counts the gaps, then calls on.

    Parameters
    ----------
    on_message : callable
        ``on_message(msg)``: the subscription's own callback (its ``__name__`` is kept).
    topic : str
        The subscription's topic.
    publisher_count : callable
        ``publisher_count(topic) -> int`` (``Node.count_publishers``).
    on_lost : callable
        ``on_lost(topic, count)``, called before ``on_message`` when ``count`` messages
        went missing.

    """
    gaps = SequenceGaps(publisher_count)

    def callback(msg: Any, info: Any) -> None:
        lost = gaps.lost(topic, [info])
        if lost:
            on_lost(topic, lost)
        on_message(msg)
    callback.__name__ = getattr(on_message, '__name__', 'callback')
    return callback
