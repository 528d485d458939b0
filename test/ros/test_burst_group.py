"""
Tests of ros.fast_io.BurstGroup with rclpy's own executors.

A callback that also takes what waits on the other subscriptions leaves them empty;
the group must keep the executor from dispatching them for nothing, lose and repeat
no message, leave no subscription out of a wait, and keep its callbacks exclusive
with the node's others.
"""

import threading
import time

from landmark_ros.ros.fast_io import BurstGroup, take_waiting
import pytest
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rosutil import wait_for_match
from std_msgs.msg import Int32

TOPICS = ('a', 'b', 'c')


class CountingExecutor(SingleThreadedExecutor):
    """A single-threaded executor that counts the dispatches that found no message."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.empty = 0

    def _take_subscription(self, sub):
        taken = super()._take_subscription(sub)
        self.empty += taken is None
        return taken


class Burst:
    """A node whose input callbacks take what waits on every input, as the fuser's do."""

    def __init__(self, env, burst_group=True):
        self.node = env.node('burst')
        self.group = BurstGroup(self.node) if burst_group else MutuallyExclusiveCallbackGroup()
        self.received = {topic: [] for topic in TOPICS}
        self.calls = 0
        self.subscriptions = {
            topic: self.node.create_subscription(
                Int32, topic, lambda msg, topic=topic: self.on_message(msg, topic), 100,
                callback_group=self.group)
            for topic in TOPICS}
        self.inside = None      # called in a callback, after its own message, before the takes
        self.takes = {topic: TOPICS for topic in TOPICS}    # what each callback takes

    def on_message(self, msg, topic):
        self.calls += 1
        self.received[topic].append(msg.data)
        self.received[topic] += [m.data for m in take_waiting(self.subscriptions[topic], Int32,
                                                              100)]
        if self.inside is not None:
            self.inside(topic)
        for other, subscription in self.subscriptions.items():
            if other != topic and other in self.takes[topic]:
                take = self.group.take if isinstance(self.group, BurstGroup) else take_waiting
                self.received[other] += [m.data for m in take(subscription, Int32, 100)]


def wait_until_ready(context, subscriptions, timeout=5.0):
    """Wait, without taking, until every subscription has a message (as wait_for_message)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        wait_set = _rclpy.WaitSet(len(subscriptions), 0, 0, 0, 0, 0, context.handle)
        wait_set.clear_entities()
        for subscription in subscriptions:
            wait_set.add_subscription(subscription.handle)
        wait_set.wait(10 ** 7)
        ready = wait_set.get_ready_entities('subscription')
        if all(subscription.handle.pointer in ready for subscription in subscriptions):
            return True
    return False


def spin_without_timeout(env, predicate, timeout=2.0):
    """
    Spin as ``rclpy.spin`` does (no timeout on a wait) until ``predicate()``.

    Return False if ``timeout`` passed first: the executor is then shut down, to end
    its wait.
    """
    alarm = threading.Timer(timeout, env.executor.shutdown)
    alarm.start()
    try:
        while not predicate() and alarm.is_alive():
            env.executor.spin_once()
    finally:
        alarm.cancel()
        alarm.join()
    return predicate() and not env.executor._is_shutdown


def publishers(env):
    node = env.node('talker')
    return {topic: node.create_publisher(Int32, topic, 100) for topic in TOPICS}


def setup(env, burst_group):
    env.executor = CountingExecutor(context=env.context)
    talker = publishers(env)
    burst = Burst(env, burst_group)
    for node in env.nodes:
        env.executor.add_node(node)
    assert wait_for_match(env, talker.values(), burst.subscriptions.values())
    return talker, burst


@pytest.mark.parametrize('burst_group', [True, False])
def test_no_dispatch_finds_an_emptied_subscription_and_no_message_is_lost(env, burst_group):
    talker, burst = setup(env, burst_group)
    sent = {topic: [] for topic in TOPICS}
    for round_ in range(3):
        for k, topic in enumerate(TOPICS):
            for j in range(5):
                value = 100 * round_ + 10 * k + j
                talker[topic].publish(Int32(data=value))
                sent[topic].append(value)
        # Every input ready in the executor's next wait: its first callback empties all.
        assert wait_until_ready(env.context, list(burst.subscriptions.values()))
        calls = burst.calls
        assert env.spin_until(lambda: burst.received == sent)
        # Let the executor go through the rest of what that wait found ready.
        env.spin_for(0.1)
        assert burst.calls == calls + 1
        assert burst.received == sent
        # What the group saves: each emptied input dispatched for nothing.
        assert env.executor.empty == (0 if burst_group else 2 * (round_ + 1))


def test_an_input_emptied_while_not_ready_stays_in_the_next_waits(env):
    talker, burst = setup(env, True)

    def publish_on_b_and_wait(topic):
        # b gets a message after the executor's wait that woke a: the take empties it
        # although the executor did not see it ready.
        burst.inside = None
        talker['b'].publish(Int32(data=1))
        assert wait_until_ready(env.context, [burst.subscriptions['b']])

    burst.inside = publish_on_b_and_wait
    talker['a'].publish(Int32(data=0))
    assert env.spin_until(lambda: burst.received['b'] == [1])
    assert burst.calls == 1
    # The node has no timer: only b's next message can wake the executor now.
    talker['b'].publish(Int32(data=2))
    assert spin_without_timeout(env, lambda: burst.received['b'] == [1, 2])
    assert env.executor.empty == 0


def test_an_input_emptied_after_its_dispatch_stays_in_the_next_waits(env):
    talker, burst = setup(env, True)
    burst.takes = {'a': (), 'b': (), 'c': ('b',)}

    def refill_b(topic):
        # The wait found a, b and c ready; b was dispatched already when c's callback
        # empties it again: the executor has nothing left to pass over.
        if topic == 'c':
            burst.inside = None
            talker['b'].publish(Int32(data=2))
            assert wait_until_ready(env.context, [burst.subscriptions['b']])

    for topic in TOPICS:
        talker[topic].publish(Int32(data=1))
    assert wait_until_ready(env.context, list(burst.subscriptions.values()))
    burst.inside = refill_b
    assert env.spin_until(lambda: burst.calls == 3 and burst.received['b'] == [1, 2])
    # The node has no timer: only b's next message can wake the executor now.
    talker['b'].publish(Int32(data=3))
    assert spin_without_timeout(env, lambda: burst.received['b'] == [1, 2, 3])
    assert burst.calls == 4 and env.executor.empty == 0


def test_its_callbacks_and_the_nodes_others_exclude_each_other(env):
    burst = Burst(env)
    subscription = burst.subscriptions['a']
    timer = burst.node.create_timer(3600.0, lambda: None)    # the node's default group
    default = burst.node.default_callback_group
    assert burst.group.has_entity(subscription) and default.has_entity(subscription)
    assert burst.group.can_execute(subscription) and default.can_execute(timer)
    assert burst.group.beginning_execution(subscription)
    # While an input callback runs, no other callback of the node may start, in any
    # executor (a multi-threaded one asks the groups), and the other way round.
    assert not default.can_execute(timer) and not default.beginning_execution(timer)
    assert not burst.group.can_execute(burst.subscriptions['b'])
    burst.group.ending_execution(subscription)
    assert default.beginning_execution(timer)
    assert not burst.group.can_execute(subscription)
    assert not burst.group.beginning_execution(subscription)
    default.ending_execution(timer)
    assert burst.group.can_execute(subscription)
