"""Tests of pipeline.counters: counting and throttled logging."""


from landmark_ros.pipeline import counters as diagnostics


# --- diagnostics.Counters ------------------------------------------------------------------------

class Clock:
    """A settable clock for Counters."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_counters_count_and_throttle_per_reason():
    lines, clock = [], Clock()
    counters = diagnostics.Counters(lines.append, throttle_s=5.0, clock=clock)
    counters.add('bad_row', 3, 'three bad rows')
    counters.add('late', 1)                    # counted, never logged without detail
    counters.add('nothing', 0, 'ignored')      # non-positive counts are ignored
    counters.add('nothing', -2, 'ignored')
    assert lines == ['bad_row x3: three bad rows']
    assert counters['bad_row'] == 3 and counters['late'] == 1 and counters['nothing'] == 0
    assert 'nothing' not in counters.counts
    clock.now += 1.0
    counters.add('bad_row', 2, 'suppressed')
    counters.add('other', 1, 'another kind is not throttled by the first')
    clock.now += 3.9
    counters.add('bad_row', 4, 'suppressed too')
    assert lines == ['bad_row x3: three bad rows',
                     'other x1: another kind is not throttled by the first']
    clock.now += 0.1   # 5 s after the last report
    counters.add('bad_row', 1, 'back')
    assert lines[-1] == 'bad_row x1: back (6 more since the last report)'
    clock.now += 10.0
    counters.add('bad_row', 1, 'quiet since')
    assert lines[-1] == 'bad_row x1: quiet since'
    assert counters['bad_row'] == 11
    assert diagnostics.status_values(counters.counts, {'state': 'ok'}) == [
        ('state', 'ok'), ('bad_row', '11'), ('late', '1'), ('other', '1')]


def test_counters_without_detail_do_not_reset_the_throttle():
    lines, clock = [], Clock()
    counters = diagnostics.Counters(lines.append, throttle_s=2.0, clock=clock)
    counters.add('x', 1, 'a')
    clock.now += 1.0
    counters.add('x', 5)          # no detail: not part of "more since the last report"
    clock.now += 1.0
    counters.add('x', 1, 'b')
    assert lines == ['x x1: a', 'x x1: b'] and counters['x'] == 7


def test_counters_zero_throttle_logs_every_time():
    lines, clock = [], Clock()
    counters = diagnostics.Counters(lines.append, throttle_s=0.0, clock=clock)
    for _ in range(3):
        counters.add('x', 1, 'd')
    assert lines == ['x x1: d'] * 3


def test_renamed_keys_keep_their_old_name_for_one_release():
    # A status carries each renamed key also under its old name, same value, after the
    # others; the package's own readers drop the aliases.
    values = diagnostics.status_values({'partial_gated': 3, 'fused': 2},
                                       {'queued_partial': 0})
    assert values == [('queued_partial', '0'), ('fused', '2'), ('partial_gated', '3'),
                      ('queued_views', '0'), ('views_gated', '3')]
    assert diagnostics.without_deprecated(dict(values)) == {
        'queued_partial': '0', 'fused': '2', 'partial_gated': '3'}
    # No alias without its new key, and every alias names a new key once.
    assert diagnostics.status_values({'fused': 1}) == [('fused', '1')]
    assert len(set(diagnostics.DEPRECATED_KEYS.values())) == len(diagnostics.DEPRECATED_KEYS)
    assert not set(diagnostics.DEPRECATED_KEYS) & set(diagnostics.DEPRECATED_KEYS.values())
