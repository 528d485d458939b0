"""Take the messages already waiting on subscriptions, to handle them in one batch."""

from rclpy.callback_groups import CallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.subscription import Subscription
from rclpy.waitable import NumberOfEntities, Waitable


def take_waiting(subscription, msg_type, limit, raw=False):
    """
    Take up to ``limit`` messages already queued on ``subscription``, without waiting.

    A node that handles a burst of messages in one callback pays the executor's
    per-message overhead (wait set, dispatch) once; the rest is taken directly,
    as rclpy's own ``wait_for_message`` does.

    Parameters
    ----------
    subscription : rclpy.subscription.Subscription
        A subscription of the calling node.
    msg_type : type
        Its message type.
    limit : int
        Most messages to take.
    raw : bool
        Take the serialized bytes (as a ``raw=True`` subscription delivers them).

    Returns
    -------
    list
        The messages (or their bytes), oldest first.

    """
    taken = []
    if limit <= 0:
        return taken
    handle = subscription.handle
    with handle:
        while len(taken) < limit:
            message_and_info = handle.take_message(msg_type, raw)
            if message_and_info is None:
                break
            taken.append(message_and_info[0])
    return taken


class BurstGroup(CallbackGroup):
    """
    Callback group of subscriptions whose callbacks also take what waits on the others.

    An executor wait returns every subscription with data; the executor then
    dispatches them one by one. When the first callback empties the queues of the
    others (``take``), each of those would still be dispatched, to find nothing: an
    empty dispatch costs the executor about as much as a message. This group
    passes over, once, each subscription that ``take`` emptied while the executor
    had it still to dispatch from the current wait (its ``can_execute`` answers
    False). Which ones are still to dispatch it learns from the wait set itself,
    through an entity-free waitable on the node whose ``is_ready`` the executor calls
    after each wait: no subscription is ever left out of a wait set. Should an
    executor not call it, nothing is passed over (the empty dispatches come back).

    Otherwise it is the node's default group (mutually exclusive): its entities are
    added to that group too, which decides when they run, so these callbacks never
    overlap the node's others, in any executor.
    """

    def __init__(self, node: Node) -> None:
        super().__init__()
        self._inner = node.default_callback_group
        self._pointers = {}     # entity -> its handle's pointer (the wait set's name for it)
        self._ready = set()     # pointers ready in the last wait, not yet passed
        self._emptied = set()   # of those, the subscriptions ``take`` emptied
        node.add_waitable(_WaitWatch(self))

    def add_entity(self, entity) -> None:
        """Add ``entity`` to this group and to the node's default group."""
        super().add_entity(entity)
        self._inner.add_entity(entity)
        if isinstance(entity, Subscription):     # not its QoS event handlers
            self._pointers[entity] = entity.handle.pointer

    def take(self, subscription, msg_type, limit, raw=False):
        """
        Take what waits on another ``subscription`` of the group (``take_waiting``).

        Call it from the callback of a subscription of the group, not on that one.
        """
        taken = take_waiting(subscription, msg_type, limit, raw)
        if taken and self._pointers.get(subscription) in self._ready:
            self._emptied.add(subscription)
        return taken

    def can_execute(self, entity) -> bool:
        """Return False for a subscription ``take`` emptied, else the default group's answer."""
        if self._ready:
            self._ready.discard(self._pointers.get(entity))     # the executor passes it now
            if entity in self._emptied:
                self._emptied.discard(entity)
                return False
        return self._inner.can_execute(entity)

    def beginning_execution(self, entity) -> bool:
        """Return the default group's permission to start ``entity``'s callback."""
        return self._inner.beginning_execution(entity)

    def ending_execution(self, entity) -> None:
        """Tell the default group that ``entity``'s callback ended."""
        self._inner.ending_execution(entity)

    def _waiting(self) -> None:
        self._ready.clear()
        self._emptied.clear()

    def _woken(self, wait_set) -> None:
        self._ready = set(wait_set.get_ready_entities('subscription'))
        self._ready.intersection_update(self._pointers.values())


class _WaitWatch(Waitable):
    """Tells a ``BurstGroup`` when a wait set is built and which subscriptions woke it."""

    def __init__(self, group: BurstGroup) -> None:
        super().__init__(ReentrantCallbackGroup())
        self._group = group

    def get_num_entities(self) -> NumberOfEntities:
        """Return no entities: it only watches."""
        return NumberOfEntities()

    def add_to_wait_set(self, wait_set) -> None:
        """Note that a new wait starts."""
        self._group._waiting()

    def is_ready(self, wait_set) -> bool:
        """Note which subscriptions of the group the wait found ready; never ready itself."""
        self._group._woken(wait_set)
        return False

    def take_data(self):
        """Never called: never ready."""
        return None

    async def execute(self, taken_data) -> None:
        """Never called: never ready."""
