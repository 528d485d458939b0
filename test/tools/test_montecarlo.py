"""Monte Carlo consistency in the simulator: each method where theory says it should be."""

import io

from landmark_ros.eval import montecarlo


def test_each_method_is_as_consistent_as_theory_says():
    out = io.StringIO()
    rows = montecarlo.run(seeds=6, duration_s=10.0, out=out)
    assert len(rows) == 6, out.getvalue()
    failures = [row for row in rows if not row['ok']]
    assert not failures, out.getvalue()
    by_key = {(row['scenario'], row['fusion']): row for row in rows}
    # The product of Gaussians is exact for white noise and over-confident with biases.
    white = by_key[('white', 'independent')]
    assert abs(white['seed_mean'] - 2.0) <= white['seed_half_width']
    assert by_key[('biased', 'independent')]['seed_mean'] > 3 * white['seed_mean']
    assert all(row['landmarks'] > 50 for row in rows)
