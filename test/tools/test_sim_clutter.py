"""The simulator's missed detections and clutter (landmarks without IDs), without ROS."""

from dataclasses import replace

from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.sim.simulation import SimConfig, Simulation
import numpy as np


def measurements(config, count=200):
    """Return the measurements of robot 0 at observations 0 .. count - 1."""
    sim = Simulation(config)
    return [sim.measure(0, j) for j in range(count)]


def test_defaults_measure_exactly_as_before():
    config = SimConfig()
    explicit = replace(config, detection_probability=1.0, clutter_rate=0.0)
    for a, b in zip(measurements(config, 50), measurements(explicit, 50)):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.z, b.z)


def test_missed_detections_and_clutter_rates():
    base = measurements(SimConfig())
    thinned = measurements(SimConfig(detection_probability=0.5, clutter_rate=2.0))
    seen = sum(len(m.ids) for m in base)
    kept = sum(int(np.count_nonzero(m.ids != UNKNOWN_ID)) for m in thinned)
    false = sum(int(np.count_nonzero(m.ids == UNKNOWN_ID)) for m in thinned)
    assert abs(kept / seen - 0.5) < 0.1
    assert abs(false / len(thinned) - 2.0) < 0.3
    config = SimConfig()
    for m in thinned:
        rows = m.z[m.ids == UNKNOWN_ID]
        assert np.all((rows[:, 0] >= config.min_range) & (rows[:, 0] <= config.max_range))
        assert np.all(np.abs(rows[:, 1]) <= 0.5 * config.fov)
        real = m.ids != UNKNOWN_ID
        assert set(m.ids[real].tolist()) <= set(Simulation(config).world.ids.tolist())
