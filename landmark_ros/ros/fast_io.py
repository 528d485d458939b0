"""
The nodes' speed code: the one module of the package that relies on rclpy internals.

One rclpy callback costs 170 to 300 us here, so the nodes handle their inputs in
batches. With the node parameter ``fast_io`` true (the default) this module:

- takes the messages already queued on a subscription from inside a callback
  (``take_waiting``: ``Subscription.handle.take_message``, the call rclpy's own
  executor makes), so that one dispatch serves a burst;
- for a set of inputs served together (the fuser's landmark inputs), passes over the
  dispatches the executor would make to find an emptied queue (``BurstGroup``: a
  callback group that learns the subscriptions a wait found ready from the executor's
  wait set, ``WaitSet.get_ready_entities`` and ``handle.pointer``, through a
  ``Waitable``'s ``is_ready`` hook);
- takes landmark clouds as bytes and reads them with the hand-written CDR reader of
  ``cloud_bytes`` (no Python message built);
- creates the inputs without QoS event handlers (each is one more entity in every
  executor wait);
- runs several periodic tasks on one timer (``Periodic``: each timer in a node costs
  every message some executor time).

With ``fast_io`` false, or when rclpy lacks an internal listed in ``INTERNALS`` (a
future release may rename or drop one), the same classes use plain rclpy: one
callback per message, rclpy's messages and default event handlers, one timer per
task; one log line says so and why. What the nodes compute is the same either way.
"""

import copy
from dataclasses import dataclass
import importlib
import time
from typing import Any, Callable, Optional, Sequence, Tuple

from landmark_ros.ros.cloud import CloudError
from landmark_ros.ros.lost import SequenceGaps
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import CallbackGroup, ReentrantCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.subscription import Subscription

SWITCH = 'fast_io'
"""Name of the node parameter that turns this module's speed code on (default true)."""

SWITCH_HELP = (f'{SWITCH} (bool, default true, read-only): batch the inputs with '
               'rclpy internals (ros/fast_io.py); false: plain rclpy subscriptions '
               'and timers')
"""The switch's line in a node's ``--help``."""

INTERNALS = (
    ('rclpy.impl.implementation_singleton', 'rclpy_implementation.Subscription.take_message'),
    ('rclpy.impl.implementation_singleton', 'rclpy_implementation.Subscription.pointer'),
    ('rclpy.impl.implementation_singleton', 'rclpy_implementation.WaitSet.get_ready_entities'),
    ('rclpy.subscription', 'Subscription.handle'),
    ('rclpy.waitable', 'Waitable.is_ready'),
    ('rclpy.waitable', 'Waitable.add_to_wait_set'),
    ('rclpy.waitable', 'NumberOfEntities'),
    ('rclpy.callback_groups', 'CallbackGroup.beginning_execution'),
    ('rclpy.callback_groups', 'CallbackGroup.ending_execution'),
    ('rclpy.node', 'Node.add_waitable'),
)
"""``(module, attribute path)`` of every rclpy internal the fast path uses."""


def missing_internal():
    """
    Return the first entry of ``INTERNALS`` this rclpy lacks, as text, or None.

    Returns
    -------
    str or None
        ``'module.attribute.path'`` of the missing internal; None when all are there.

    """
    for module_name, path in INTERNALS:
        try:
            found = importlib.import_module(module_name)
        except ImportError:
            return module_name
        for name in path.split('.'):
            found = getattr(found, name, None)
            if found is None:
                return f'{module_name}.{path}'
    return None


def declare_switch(node):
    """
    Declare the ``fast_io`` parameter on ``node``; return whether the fast path is on.

    The fast path is on when the parameter is true and every internal it uses is
    there; otherwise one log line says why the node uses plain rclpy.

    Parameters
    ----------
    node : rclpy.node.Node
        The node, before it creates its subscriptions and timers.

    Returns
    -------
    bool

    """
    wanted = node.declare_parameter(SWITCH, True, ParameterDescriptor(
        description=SWITCH_HELP, read_only=True)).value
    if not wanted:
        node.get_logger().info(f'{SWITCH} is false: plain rclpy subscriptions and timers')
        return False
    missing = missing_internal()
    if missing is not None:
        node.get_logger().warning(
            f'{SWITCH}: this rclpy has no {missing}; plain rclpy subscriptions and timers '
            'instead (slower on bursts, same results)')
        return False
    return True


def take_waiting(subscription, msg_type, limit, raw=False, infos=None):
    """
    Take up to ``limit`` messages already queued on ``subscription``, without waiting.

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
    infos : list, optional
        Gets each taken message's ``MessageInfo`` dict appended.

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
            if infos is not None:
                infos.append(message_and_info[1])
    return taken


@dataclass(frozen=True)
class InputSpec:
    """
    What an ``Inputs`` subscribes to and how it batches.

    ``limit()`` is the most messages per topic one callback hands on (read at each
    callback: a parameter may change it); ``budget_s()`` the wall time after which a
    callback takes no further round of what arrived meanwhile (only with ``across``).
    ``across``: a callback also takes what waits on the set's other topics
    (``BurstGroup``). ``raw_clouds``: PointCloud2 taken as bytes and read by
    ``cloud_bytes``; a cloud it cannot read is handed on as its ``CloudError``.
    ``on_lost(topic, count)``: called with the ``count`` messages of ``topic`` that went
    missing before those just taken (``lost.SequenceGaps``); None: not watched.
    """

    msg_type: type
    topics: Sequence[str]
    qos_profile: Any
    limit: Callable[[], int]
    budget_s: Callable[[], float] = lambda: 0.0
    across: bool = False
    raw_clouds: bool = False
    qos_overriding_options: Any = None
    on_lost: Optional[Callable[[str, int], None]] = None


class Inputs:
    """
    Subscriptions to topics of one message type whose callback gets batches.

    ``on_batches(bursts)`` receives ``[(topic, messages), ...]`` (each topic once,
    messages oldest first, never empty); ``topic`` is the entry of ``spec.topics``.
    Fast: a message's callback adds what waits (``take_waiting``), across the set with
    ``spec.across``. Plain: one message per call.
    """

    def __init__(self, node, spec: InputSpec, on_batches, wrap=None, fast=True):
        self.spec, self.fast = spec, fast
        self._on_batches = on_batches
        self._raw = fast and spec.raw_clouds
        self._group = BurstGroup(node) if fast and spec.across else None
        wrap = wrap or (lambda callback: callback)
        events = SubscriptionEventCallbacks(use_default_callbacks=False) if fast else None
        self.subscriptions = {}
        self._gaps = None if spec.on_lost is None else SequenceGaps(
            lambda topic: self.subscriptions[topic].get_publisher_count())
        for topic in spec.topics:
            self.subscriptions[topic] = node.create_subscription(
                spec.msg_type, topic,
                wrap(lambda msg, info, topic=topic: self.receive(msg, topic, info)),
                copy.copy(spec.qos_profile),    # qos_overrides.<topic>.* apply to each alone
                qos_overriding_options=spec.qos_overriding_options,
                raw=self._raw, event_callbacks=events, callback_group=self._group)

    def receive(self, msg, topic, info=None):
        """Hand on ``msg`` of ``topic`` with what waits (fast) or alone (plain)."""
        if not self.fast:
            self._count_lost(topic, [info])
            self._deliver([(topic, [msg])])
            return
        limit = self.spec.limit()
        infos = [info]
        bursts = [(topic, [msg] + take_waiting(self.subscriptions[topic], self.spec.msg_type,
                                               limit - 1, self._raw, infos))]
        self._count_lost(topic, infos)
        if self._group is None:
            self._deliver(bursts)
            return
        for other in self.subscriptions:
            if other != topic:
                self._take_into(bursts, other, limit)
        taken = {name: len(messages) for name, messages in bursts}
        # Wall time (not the node's clock, which may be a paused simulation's).
        deadline = time.monotonic() + self.spec.budget_s()
        while True:
            self._deliver(bursts)
            if sum(len(messages) for _, messages in bursts) < 2:
                break       # a lone message: the inputs are not busy
            if time.monotonic() >= deadline:
                break
            bursts = []
            for name in self.subscriptions:
                room = limit - taken.get(name, 0)
                if room > 0 and self._take_into(bursts, name, room):
                    taken[name] = taken.get(name, 0) + len(bursts[-1][1])
            if not bursts:
                break

    def _take_into(self, bursts, topic, limit):
        infos = []
        waiting = self._group.take(self.subscriptions[topic], self.spec.msg_type, limit,
                                   self._raw, infos)
        if waiting:
            self._count_lost(topic, infos)
            bursts.append((topic, waiting))
        return bool(waiting)

    def _count_lost(self, topic, infos):
        if self._gaps is not None:
            lost = self._gaps.lost(topic, infos)
            if lost:
                self.spec.on_lost(topic, lost)

    def _deliver(self, bursts):
        if self._raw:
            bursts = [(topic, [_read_cloud(raw) for raw in messages])
                      for topic, messages in bursts]
        self._on_batches(bursts)


def _read_cloud(raw):
    """Return the cloud read from ``raw`` bytes, or the ``CloudError`` that refused it."""
    from landmark_ros.ros.cloud_bytes import read_cloud_bytes
    try:
        return read_cloud_bytes(raw)
    except CloudError as error:
        return error


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

    def __init__(self, node) -> None:
        super().__init__()
        self._inner = node.default_callback_group
        self._pointers = {}     # entity -> its handle's pointer (the wait set's name for it)
        self._ready = set()     # pointers ready in the last wait, not yet passed
        self._emptied = set()   # of those, the subscriptions ``take`` emptied
        node.add_waitable(_wait_watch(self))

    def add_entity(self, entity) -> None:
        """Add ``entity`` to this group and to the node's default group."""
        super().add_entity(entity)
        self._inner.add_entity(entity)
        if isinstance(entity, Subscription):     # not its QoS event handlers
            self._pointers[entity] = entity.handle.pointer

    def take(self, subscription, msg_type, limit, raw=False, infos=None):
        """
        Take what waits on another ``subscription`` of the group (``take_waiting``).

        Call it from the callback of a subscription of the group, not on that one.
        """
        taken = take_waiting(subscription, msg_type, limit, raw, infos)
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

    def waiting(self) -> None:
        """Forget the last wait's ready subscriptions: a new wait starts."""
        self._ready.clear()
        self._emptied.clear()

    def woken(self, wait_set) -> None:
        """Note the subscriptions of the group that ``wait_set`` found ready."""
        self._ready = set(wait_set.get_ready_entities('subscription'))
        self._ready.intersection_update(self._pointers.values())


def _wait_watch(group: BurstGroup):
    """Return a waitable that tells ``group`` when a wait starts and what it woke."""
    from rclpy.waitable import NumberOfEntities, Waitable

    class WaitWatch(Waitable):
        """Watches the executor's wait sets for a ``BurstGroup``; never ready itself."""

        def __init__(self) -> None:
            super().__init__(ReentrantCallbackGroup())

        def get_num_entities(self) -> NumberOfEntities:
            """Return no entities: it only watches."""
            return NumberOfEntities()

        def add_to_wait_set(self, wait_set) -> None:
            """Note that a new wait starts."""
            group.waiting()

        def is_ready(self, wait_set) -> bool:
            """Note which subscriptions of the group the wait found ready."""
            group.woken(wait_set)
            return False

        def take_data(self):
            """Never called: never ready."""
            return None

        async def execute(self, taken_data) -> None:
            """Never called: never ready."""
            return None

    return WaitWatch()


Task = Tuple[str, float, Callable[[], Any]]
"""A periodic task: ``(name, period_s, callback)``."""


class Periodic:
    """
    A node's periodic tasks: on one timer at the shortest period (fast) or a timer each.

    On one timer each task keeps its own schedule (``due``): its next due time
    advances by its period from the last due time, not from the tick, so a tick a
    little early or late neither drops a run nor shifts the rest; a tick within half
    a tick period of the due time counts as on time; after a stall (or a clock jump)
    of more than a period the schedule restarts from the tick.
    """

    def __init__(self, node, tasks: Sequence[Task], wrap=None, fast=True):
        self._node, self._tasks = node, list(tasks)
        wrap = wrap or (lambda callback: callback)
        self._next_due = {}
        if fast:
            period_s = min(period for _, period, _ in self._tasks)
            self._tick_ns = int(period_s * 1e9)
            self.timers = [node.create_timer(period_s, wrap(self.tick))]
        else:
            self.timers = [node.create_timer(period, wrap(callback))
                           for _, period, callback in self._tasks]

    def tick(self):
        """Run every task due now (by the node's clock)."""
        now = self._node.get_clock().now().nanoseconds
        for name, period_s, callback in self._tasks:
            if self.due(name, period_s, now):
                callback()

    def due(self, task: str, period_s: float, now: int) -> bool:
        """Return whether ``task`` is due at ``now`` [ns]; if so, schedule its next run."""
        period = int(period_s * 1e9)
        due: Optional[int] = self._next_due.get(task)
        if due is not None and now < due - self._tick_ns // 2:
            if due - now <= period + self._tick_ns:
                return False
            due = now  # the clock jumped back
        due = now if due is None else due
        self._next_due[task] = due + period if now - due < period else now + period
        return True

    def destroy(self):
        """Destroy the timers."""
        for timer in self.timers:
            self._node.destroy_timer(timer)
        self.timers = []
