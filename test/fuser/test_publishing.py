"""Tests of fuser.publishing.PublicationSchedule: one timer, each output at most its rate."""

from landmark_ros.fuser.publishing import PublicationSchedule
import pytest


@pytest.mark.parametrize('publish_rate_hz, updates_rate_hz, period_s, updates_every, map_every', [
    (5.0, 10.0, 0.1, 1, 2),       # the defaults: the map with every second update
    (50.0, 10.0, 0.02, 5, 1),     # a map faster than the updates drives the tick
    (10.0, 10.0, 0.1, 1, 1),
    (3.0, 10.0, 0.1, 1, 4),       # 10 / 3 ticks: every 4th (2.5 Hz), not every 3rd (3.3 Hz)
    (0.2, 10.0, 0.1, 1, 50),
    (7.0, 0.5, 1.0 / 7.0, 14, 1),
])
def test_one_tick_at_the_faster_rate_and_each_output_at_most_its_rate(
        publish_rate_hz, updates_rate_hz, period_s, updates_every, map_every):
    schedule = PublicationSchedule(publish_rate_hz, updates_rate_hz)
    assert schedule.period_s == pytest.approx(period_s, rel=1e-12)
    assert (schedule.updates_every, schedule.map_every) == (updates_every, map_every)
    assert schedule.updates_period_s >= 1.0 / updates_rate_hz * (1 - 1e-12)
    assert schedule.map_period_s >= 1.0 / publish_rate_hz * (1 - 1e-12)
    ticks = [schedule.tick() for _ in range(700)]
    updates = [k + 1 for k, (due, _) in enumerate(ticks) if due]
    maps = [k + 1 for k, (_, due) in enumerate(ticks) if due]
    assert updates == list(range(updates_every, 701, updates_every))
    assert maps == list(range(map_every, 701, map_every))
    seconds = 700 * schedule.period_s
    assert len(updates) <= updates_rate_hz * seconds * (1 + 1e-9)
    assert len(maps) <= publish_rate_hz * seconds * (1 + 1e-9)


@pytest.mark.parametrize('rates', [(0.0, 10.0), (5.0, -1.0), (float('nan'), 1.0)])
def test_rates_must_be_positive(rates):
    with pytest.raises(ValueError, match='positive'):
        PublicationSchedule(*rates)
