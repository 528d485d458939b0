"""ros.fast_io: the probe of rclpy internals and Periodic (the nodes: test/nodes)."""

import importlib

from landmark_ros.ros import fast_io
import pytest


def _parent_and_name(module_name, path):
    parent = importlib.import_module(module_name)
    *parents, name = path.split('.')
    for part in parents:
        parent = getattr(parent, part)
    return parent, name


@pytest.mark.parametrize('module_name, path', fast_io.INTERNALS)
def test_the_probe_names_the_internal_that_is_gone(monkeypatch, module_name, path):
    assert fast_io.missing_internal() is None
    parent, name = _parent_and_name(module_name, path)
    monkeypatch.setattr(parent, name, None)
    assert fast_io.missing_internal() == f'{module_name}.{path}'


class _Clock:

    def __init__(self):
        self.ns = 0

    def now(self):
        return self

    @property
    def nanoseconds(self):
        return self.ns


class _Node:
    """What Periodic uses of a node: a clock and timers."""

    def __init__(self):
        self.clock, self.created = _Clock(), []

    def get_clock(self):
        return self.clock

    def create_timer(self, period_s, callback):
        self.created.append(period_s)
        return period_s


def test_one_timer_runs_each_task_at_its_own_rate_over_jittered_ticks(rng):
    node, runs = _Node(), {'fast': 0, 'slow': 0}
    periodic = fast_io.Periodic(node, [
        ('fast', 0.1, lambda: runs.__setitem__('fast', runs['fast'] + 1)),
        ('slow', 0.25, lambda: runs.__setitem__('slow', runs['slow'] + 1))])
    assert node.created == [0.1]
    # 100 s of ticks every 100 ms, each up to 20 ms early or late.
    for k in range(1000):
        node.clock.ns = int((k * 0.1 + rng.uniform(-0.02, 0.02)) * 1e9)
        periodic.tick()
    assert runs['fast'] == 1000
    assert abs(runs['slow'] - 400) <= 1, runs


def test_plain_periodic_makes_one_timer_per_task():
    node = _Node()
    fast_io.Periodic(node, [('a', 0.1, print), ('b', 0.3, print)], fast=False)
    assert node.created == [0.1, 0.3]
